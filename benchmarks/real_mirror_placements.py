"""Real-mirror calibration with 1, 3, 5 and 14 placements of the board on the mirror: mirror normal and
projector angle errors against the ground truth (issue 18).

    python benchmarks/real_mirror_placements.py [--seeds 10] [--noise 0.05] [--counts 1 3 5 14]

Exact-geometry synthetic observations (calib.synthetic.observe, circle centroids, Gaussian noise) of the
nonoverlap-136-realmirror scenario with its 52 projector views; each placement is one image of the board
lying on the mirror at its own place and in-plane angle (the scenario's mirror_poses). Means over seeds of
the joint method's (and the paper method's) errors, worst in brackets, and the joint's own 1-sigma of the
mirror normal; a session a method fails (trust check) is counted, not averaged.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.errors import CalibrationError  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
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
          " | paper projector angle deg | failed (joint / paper)")
    for n in args.counts:
        joint, paper, failed = [], [], {"joint": 0, "paper": 0}
        for seed in range(args.seeds):
            sc = replace(get_scenario(args.scenario, seed), mirror_count=n)
            ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                                  sc.mirror_method, sc.board_thickness_mm)
            obs = observe(ss, args.noise, seed, circle_centroids=True)
            for method, rows in (("joint", joint), ("paper", paper)):
                try:
                    r = calibrate_observations(obs, method)
                except CalibrationError:
                    failed[method] += 1
                    continue
                m = compare(r, sc.ground_truth())
                rows.append([m.mirror_angle_deg, m.angle_deg]
                            + ([r.uncertainty["mirror"]["normal_deg"]] if method == "joint" else []))

        def cells(rows, cols):
            a = np.array(rows, float)
            if not len(a):
                return ["-"] * len(cols)
            return [f"{a[:, c].mean():.4f} [{a[:, c].max():.4f}]" if c < 2 else f"{a[:, c].mean():.4f}" for c in cols]

        print(" | ".join([str(n)] + [cells(joint, [0])[0], cells(joint, [2])[0], cells(joint, [1])[0]]
                         + cells(paper, [0, 1]) + [f"{failed['joint']} / {failed['paper']}"]), flush=True)

if __name__ == "__main__":
    main()
