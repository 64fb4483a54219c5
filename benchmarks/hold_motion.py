"""How a board held by hand, on a stand or lying still moves over a mirror placement's frames, what the
motion check (calib.detection.structured_view.board_motion_px) reads, and what the mean of the frames
gains over one frame.

    python3 benchmarks/hold_motion.py [--scenario nonoverlap-136] [--seeds 2] [--frames 8]

For each hold (drivers/sim/hold.py) and seed: the scenario's 14 real-virtual mirror placements on the
hardware-like simulated rig (live quality, simulated time), `--frames` consecutive frames each after 3
frames of settling. Printed per hold: the board's true motion between the first and the last frame (the
largest corner displacement, px), the check's error against it, the share of placements the station
would refuse (a structured sequence: more than MAX_MOTION_PX; a mirror placement's mean:
MAX_MEAN_MOTION_PX), and the ChArUco corners' RMS error against the truth of one frame and of the mean
image (against the mean of the frames' true corners), direct and mirrored views. Then the hand-held
placements by how far the board truly moved: whether the mean image of a moving board is still as good.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.station.mirror_frames import MAX_MEAN_MOTION_PX  # noqa: E402
from calib.detection import detect as D  # noqa: E402
from calib.detection.structured_view import MAX_MOTION_PX, board_motion_px  # noqa: E402
from calib.transforms import transform_points  # noqa: E402
from drivers.clock import SimClock  # noqa: E402
from drivers.sim.hold import Hold  # noqa: E402
from drivers.sim.rig import SimRig  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402


def _rms(view, truth) -> float:
    d = np.asarray(view.corners_px) - truth[np.asarray(view.ids)]
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))


def placements(scenario: str, seed: int, hold: Hold, frames: int) -> list[tuple]:
    """(true motion, check's reading, rms real 1 frame, rms virtual 1 frame, rms real mean, rms virtual mean)
    per detected placement."""
    sc = get_scenario(scenario, seed)
    rig = SimRig(sc, "live", clock=SimClock(realtime=False), hold=hold.value)
    cam, spec, S = sc.rig.camera, sc.mirror_board, sc.rig.S()
    X = spec.corner_points()
    rig.camera.start()
    rows, last = [], None
    for k in range(len(sc.mirror_poses)):
        rig.operator.request_pose("mirror-real-virtual", None, k)
        got = []
        for _ in range(3 + frames):
            f = rig.camera.get_frame(newer_than=last)
            last = f.frame_number
            got.append(f)
        got = got[3:]
        truth = []
        for f in got:
            Xc = transform_points(np.array(f.meta["T_cam_board"]), X)
            truth.append((cam.project(Xc), cam.project(transform_points(S, Xc))))
        first = D.detect_real_virtual(got[0].image, spec)
        final = D.detect_real_virtual(got[-1].image, spec)
        mean = np.clip(np.rint(np.mean([f.image.astype(np.float64) for f in got], axis=0)), 0, 255).astype(np.uint8)
        averaged = D.detect_real_virtual(mean, spec)
        if any(isinstance(v, D.DetectionFailure) for v in (first, final, averaged)):
            continue
        true = float(np.hypot(*(truth[-1][0] - truth[0][0]).T).max())
        tr = np.mean([t[0] for t in truth], axis=0)
        tv = np.mean([t[1] for t in truth], axis=0)
        rows.append((true, board_motion_px(first.real, final.real), _rms(first.real, truth[0][0]),
                     _rms(first.virtual, truth[0][1]), _rms(averaged.real, tr), _rms(averaged.virtual, tv)))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nonoverlap-136")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=8)
    args = ap.parse_args()
    print(f"{args.scenario}, {args.seeds} seed(s), {args.frames} frames per placement, live quality\n")
    print("| hold | placements | true motion px, median (90th pct) | check's error px, median (largest) | "
          f"refused at {MAX_MOTION_PX} px / {MAX_MEAN_MOTION_PX} px | corners 1 frame px, direct / mirrored | "
          "corners mean image px, direct / mirrored |")
    print("|---|---|---|---|---|---|---|")
    for hold in (Hold.STILL, Hold.STAND, Hold.HAND):
        a = np.array([r for s in range(args.seeds) for r in placements(args.scenario, s, hold, args.frames)])
        err = np.abs(a[:, 1] - a[:, 0])
        rms = np.sqrt((a[:, 2:] ** 2).mean(axis=0))
        print(f"| {hold.value} | {len(a)} | {np.median(a[:, 0]):.2f} ({np.percentile(a[:, 0], 90):.2f}) | "
              f"{np.median(err):.3f} ({err.max():.3f}) | {int((a[:, 1] > MAX_MOTION_PX).sum())} / "
              f"{int((a[:, 1] > MAX_MEAN_MOTION_PX).sum())} of {len(a)} | "
              f"{rms[0]:.3f} / {rms[1]:.3f} | {rms[2]:.3f} / {rms[3]:.3f} |", flush=True)
        if hold is Hold.HAND:
            hand = a
    print("\nhand-held placements by the board's true motion over the frames:\n")
    print("| true motion px | placements | corners 1 frame px, direct / mirrored | corners mean image px, direct / mirrored |")
    print("|---|---|---|---|")
    for lo, hi in ((0.0, 1.0), (1.0, 2.0), (2.0, np.inf)):
        sel = hand[(hand[:, 0] >= lo) & (hand[:, 0] < hi)]
        if len(sel):
            rms = np.sqrt((sel[:, 2:] ** 2).mean(axis=0))
            label = f"{lo:g}-{hi:g}" if np.isfinite(hi) else f"over {lo:g}"
            print(f"| {label} | {len(sel)} | {rms[0]:.3f} / {rms[1]:.3f} | {rms[2]:.3f} / {rms[3]:.3f} |")


if __name__ == "__main__":
    main()
