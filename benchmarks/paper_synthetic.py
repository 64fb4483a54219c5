"""The paper's metrics (Vanherck et al. 2025, Sect. 5.2) of a calibration method on synthetic
observations (calib.synthetic: exact correspondences plus Gaussian pixel noise on every ChArUco corner
and pattern point), per rig, averaged over several seeds; with the paper's headline for comparison.

    python benchmarks/paper_synthetic.py                       # paper method, noise 0.2 px, 5 seeds
    python benchmarks/paper_synthetic.py --noise 0.05 0.1 0.2 --seeds 10
    python benchmarks/paper_synthetic.py --method joint        # any registered method
    python benchmarks/paper_synthetic.py --mirror-method real-mirror

Each seed draws new board poses (session seed) and new noise. Lengths in mm. Prints mean (and
standard deviation) per metric; the camera is estimated from the session's own images.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.pipeline import METHODS, calibrate_observations  # noqa: E402
from calib.quality.metrics import PAPER_HEADLINE, compare  # noqa: E402
from calib.synthetic import make_direct_rig, make_rig, make_session, observe  # noqa: E402

COLUMNS = [("CamK", "cam_k_px", 2), ("CamD", "cam_d", 4), ("ProjK", "proj_k_px", 2), ("ProjD", "proj_d", 4),
           ("Dist", "distance", 2), ("Angle", "angle_deg", 3), ("MirAng", "mirror_angle_deg", 3),
           ("MirOff", "mirror_offset", 3), ("CamRMS", "cam_rms_px", 3), ("ProjRMS", "proj_rms_px", 3),
           ("StRMS", "stereo_rms_px", 3)]


def run(rig_name: str, noise: float, seeds: int, method: str, mirror_method: str, per_position: int,
        camera_known: bool):
    rows, times = [], []
    for seed in range(seeds):
        rig = make_direct_rig() if rig_name == "direct" else make_rig(float(rig_name))
        ss = make_session(rig, mirror_method=None if rig_name == "direct" else mirror_method,
                          per_position=per_position, seed=seed)
        obs = observe(ss, noise, seed=1000 + seed)
        t0 = time.perf_counter()
        result = calibrate_observations(obs, method, rig.camera if camera_known else None)
        times.append(time.perf_counter() - t0)
        rows.append(compare(result, rig.ground_truth()))
    return rows, times


def fmt(values, digits):
    vals = [v for v in values if v is not None]
    if not vals:
        return "-"
    m = float(np.mean(vals))
    if len(vals) == 1:
        return f"{m:.{digits}f}"
    return f"{m:.{digits}f}±{float(np.std(vals)):.{digits}f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--method", default="paper", help=f"calibration method ({', '.join(sorted(METHODS))})")
    p.add_argument("--noise", type=float, nargs="+", default=[0.2], help="pixel noise sigma(s) per axis")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--rigs", nargs="+", default=["90", "136", "180", "direct"])
    p.add_argument("--mirror-method", default="real-virtual", choices=("real-virtual", "real-mirror"))
    p.add_argument("--per-position", type=int, default=4, help="board poses per pattern position (paper: 4)")
    p.add_argument("--camera-known", action="store_true", help="give the true camera (skip its calibration)")
    args = p.parse_args(argv)

    print(f"method {args.method}, {args.mirror_method} mirror calibration, {args.per_position} poses x 13 positions, "
          f"{args.seeds} seeds, camera {'known' if args.camera_known else 'estimated'}; mean±std, lengths in mm")
    header = ["rig", "noise"] + [c[0] for c in COLUMNS] + ["time_s"]
    table = []
    for noise in args.noise:
        for rig in args.rigs:
            rows, times = run(rig, noise, args.seeds, args.method, args.mirror_method, args.per_position,
                              args.camera_known)
            table.append([rig, f"{noise:g}"] + [fmt([getattr(r, attr) for r in rows], d) for _, attr, d in COLUMNS]
                         + [f"{np.mean(times):.2f}"])
    h = PAPER_HEADLINE
    table.append(["paper", "-", "-", "-", f"{h['proj_k_px']}", f"{h['proj_d']}", f"{h['distance']}", f"{h['angle_deg']}",
                  f"{h['mirror_angle_deg']}", f"{h['mirror_offset']}", "-", "-", "-", "-"])
    widths = [max(len(str(r[i])) for r in table + [header]) for i in range(len(header))]
    print("  ".join(f"{c:>{w}}" for c, w in zip(header, widths)))
    for r in table:
        print("  ".join(f"{c:>{w}}" for c, w in zip(r, widths)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
