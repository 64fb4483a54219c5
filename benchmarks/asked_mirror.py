"""Asking for the mirror step's board poses against the plan's order: how many mirror placements a
session stopping on confidence takes, and how accurate it is then.

    python benchmarks/asked_mirror.py [--scenarios nonoverlap-136 nonoverlap-90 nonoverlap-136-realmirror]
                                      [--seeds 10] [--first 5] [--most 14] [--noise 0.05] [--follow 3 10]

Exact-geometry synthetic observations (calib.synthetic.observe, circle centroids, Gaussian noise) of each
scenario: 6 projector placements in the plan's order with a pattern twice as dense (a stand-in for the
structured step, as benchmarks/next_pose.py), and the mirror step's first `--first` placements of the
scenario's own mirror poses. Then, as a station stopping on confidence does after its projector step,
one mirror placement at a time until the mirror normal's 1-sigma meets its target
(calib.quality.confidence) or `--most` mirror placements are taken: "order" takes the scenario's next
mirror pose (the plan's), "asked" the one calib.asked_pose chooses (12 candidates drawn through the
calibration so far with calib.asked_pose.mirror_candidates, inside the part of the mirror seen so far,
ranked by their predicted mirror-normal 1-sigma), held by the operator off by `--follow` DEG MM
(1-sigma; calib.synthetic.held_mirror_pose). Means over seeds of the mirror placements taken and of the
errors against the ground truth; in brackets, the seeds where "asked" beats "order".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.asked_pose import ask_pose, mirror_candidates, mirror_seen  # noqa: E402
from calib.errors import ProcamError  # noqa: E402
from calib.models.structured_light import placement_order  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.confidence import confidence_of  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.synthetic import SyntheticSession, held_mirror_pose, observe  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from next_pose import dense  # noqa: E402

METRICS = (("mirror_placements", "mirror placements"), ("distance", "distance mm"), ("angle_deg", "angle deg"),
           ("proj_k_px", "ProjK px"), ("cam_k_px", "CamK px"), ("mirror_angle_deg", "mirror deg"))
CANDIDATES = 12


def _observe(sc, projector, mirror, noise, seed):
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, projector, mirror, sc.mirror_method,
                          sc.board_thickness_mm)
    return observe(ss, noise, seed, circle_centroids=True)


def run(sc, arm: str, first: int, most: int, noise: float, seed: int, follow: tuple[float, float]):
    """(metrics, mirror placements, seconds per choice, confident)."""
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    projector = [(p, by_slot[p][k]) for p, k in placement_order(13, 4)[:6]]
    mirror = list(sc.mirror_poses[:first])
    spent = []
    step = sc.mirror_method
    while True:
        obs = _observe(sc, projector, mirror, noise, seed)
        est = calibrate_observations(obs, "joint")
        confident = confidence_of(est, step).all_met
        if confident or len(mirror) >= most:
            break
        if arm == "order":
            mirror.append(sc.mirror_poses[len(mirror)])
            continue
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed * 7919 + len(mirror))
        asked = ask_pose(obs, est, mirror_candidates(obs, est, CANDIDATES, rng, mirror_seen(obs, est)), step)
        spent.append(time.perf_counter() - t0)
        if asked is None:
            raise RuntimeError("no mirror pose could be predicted")
        mirror.append(held_mirror_pose(sc.rig, sc.mirror_board, step, asked.candidate.T_cam_board, follow[0],
                                       follow[1], rng, sc.board_thickness_mm))
    m = compare(est, sc.ground_truth())
    return {k: getattr(m, k) for k, _ in METRICS[1:]} | {"mirror_placements": len(mirror)}, \
        (float(np.mean(spent)) if spent else None), confident


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["nonoverlap-136", "nonoverlap-90", "nonoverlap-136-realmirror"])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=5)
    ap.add_argument("--most", type=int, default=14)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--follow", type=float, nargs=2, default=[3.0, 10.0], metavar=("DEG", "MM"))
    args = ap.parse_args()
    print(f"6 projector placements (pattern density 2), mirror placements from {args.first} until confident "
          f"(at most {args.most}), noise {args.noise} px, asked poses held to {args.follow[0]} deg / "
          f"{args.follow[1]} mm, {args.seeds} seeds; means (in brackets: the seeds where asked beats order)")
    print("| scenario | arm | " + " | ".join(label for _, label in METRICS) + " | confident | s per choice |")
    print("|---|---|" + "---|" * (len(METRICS) + 2))
    for name in args.scenarios:
        rows = {}
        for arm in ("order", "asked"):
            vals = []
            for seed in range(args.seeds):
                sc = dense(get_scenario(name, seed), 2)
                try:
                    vals.append(run(sc, arm, args.first, args.most, args.noise, seed, tuple(args.follow)))
                except (ProcamError, RuntimeError) as e:
                    print(f"  {name} seed {seed} {arm}: failed ({str(e).splitlines()[0]})", file=sys.stderr)
                    vals.append(None)
            rows[arm] = vals
        for arm, vals in rows.items():
            cells = []
            for k, _ in METRICS:
                xs = [v[0][k] for v in vals if v is not None and v[0][k] is not None]
                cell = f"{np.mean(xs):.3f}" if xs and k != "mirror_placements" else (f"{np.mean(xs):.1f}" if xs else "-")
                if arm == "asked":
                    wins = sum(1 for a, b in zip(vals, rows["order"]) if a and b and a[0][k] is not None and a[0][k] < b[0][k])
                    cell += f" ({wins})"
                cells.append(cell)
            cells.append(f"{sum(1 for v in vals if v and v[2])}/{len(vals)}")
            spent = [v[1] for v in vals if v is not None and v[1] is not None]
            cells.append(f"{np.mean(spent):.1f}" if spent else "-")
            print(f"| {name} | {arm} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
