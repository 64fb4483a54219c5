"""The trust check's metrics on simulated full sessions (docs/CALIBRATION.md, "Trust check").

For every simulator scenario and a few seeds: exact-geometry observations of the scenario's full session
(calib.synthetic, no rendering: circle centroids as a blob detector sees them, Gaussian pixel noise),
calibrated with both methods; prints the largest value of each trust metric over the runs, next to the
limit of calib.quality.trust.TrustThresholds, and every run that the check rejects (there should be none).

    python benchmarks/trust_thresholds.py [--seeds 3] [--noise 0.3]
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import asdict

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.trust import TrustThresholds, check_calibration  # noqa: E402
from calib.synthetic import SyntheticSession, observe  # noqa: E402
from drivers.sim.scenarios import get_scenario, scenario_names  # noqa: E402


def scenario_observations(name: str, seed: int, noise_px: float):
    sc = get_scenario(name, seed)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                          sc.mirror_method, sc.board_thickness_mm)
    return observe(ss, noise_px, seed, circle_centroids=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--noise", type=float, default=0.3)
    args = ap.parse_args()
    worst: dict = {}
    rejected = []
    for name in scenario_names():
        for seed in range(args.seeds):
            obs = scenario_observations(name, seed, args.noise)
            for method in ("paper", "joint"):
                res = calibrate_observations(obs, method, trust=None)
                rep = check_calibration(res)
                if not rep.passed:
                    rejected.append((name, seed, method, rep.codes))
                for k, v in rep.metrics.items():
                    if isinstance(v, (int, float)) and v is not None:
                        key = (method, k)
                        if key not in worst or abs(v) > abs(worst[key][0]):
                            worst[key] = (v, name, seed)
    th = asdict(TrustThresholds())
    print(f"worst trust metrics over {len(scenario_names())} scenarios x {args.seeds} seeds, noise {args.noise} px")
    print("| method | metric | worst | scenario (seed) |")
    print("|---|---|---|---|")
    for (method, k), (v, name, seed) in sorted(worst.items()):
        print(f"| {method} | {k} | {v:.4g} | {name} ({seed}) |")
    print("\nlimits:", ", ".join(f"{k} {v:g}" for k, v in th.items()))
    print("rejected runs:", rejected if rejected else "none")


if __name__ == "__main__":
    main()
