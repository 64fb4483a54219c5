"""Real-mirror calibration with 1, 3, 5 and 14 placements of the board on the mirror: mirror normal and
projector angle errors against the ground truth (issue 18).

    python benchmarks/real_mirror_placements.py [--seeds 10] [--noise 0.05] [--counts 1 3 5 14]

Exact-geometry synthetic observations (calib.synthetic.observe, circle centroids, Gaussian noise) of the
nonoverlap-136-realmirror scenario with its 52 projector views; each placement is one image of the board
lying on the mirror at its own place and in-plane angle (the scenario's mirror_poses). Means over seeds of
the joint method's (and the paper method's) errors, and the joint's own 1-sigma of the mirror normal.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.errors import CalibrationError  # noqa: E402
from calib.metrics import compare  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.synthetic import SyntheticSession, observe  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 3, 5, 14])
    ap.add_argument("--scenario", default="nonoverlap-136-realmirror")
    args = ap.parse_args()
    print(f"{args.scenario}, synthetic observations, noise {args.noise} px, {args.seeds} seeds (means; worst in brackets)")
    print("placements | joint mirror normal deg | joint 1-sigma deg | joint projector angle deg | paper mirror normal deg"
          " | paper projector angle deg | failed")
    for n in args.counts:
        rows, failed = [], 0
        for seed in range(args.seeds):
            sc = replace(get_scenario(args.scenario, seed), mirror_count=n)
            ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                                  sc.mirror_method, sc.board_thickness_mm)
            obs = observe(ss, args.noise, seed, circle_centroids=True)
            try:
                rj = calibrate_observations(obs, "joint")
                rp = calibrate_observations(obs, "paper")
            except CalibrationError:
                failed += 1
                continue
            mj, mp = compare(rj, sc.ground_truth()), compare(rp, sc.ground_truth())
            rows.append([mj.mirror_angle_deg, rj.uncertainty["mirror"]["normal_deg"], mj.angle_deg,
                         mp.mirror_angle_deg, mp.angle_deg])
        a = np.array(rows, float)
        cells = [f"{m:.4f} [{w:.4f}]" for m, w in zip(a.mean(axis=0), a.max(axis=0))] if len(a) else ["-"] * 5
        print(" | ".join([str(n)] + cells + [str(failed)]), flush=True)


if __name__ == "__main__":
    main()
