"""The quality gate's reference numbers and what a thin session gives (docs/CALIBRATION.md, "Quality gate").

For every simulator scenario and a few seeds: exact-geometry observations (calib.synthetic, blob-centroid
bias, Gaussian pixel noise) of the full session (52 projector + 14 mirror views, or the scenario's plan)
and of two thin sessions as the panel's shortest path (3 mirror + 6 projector views): "spread", the 6
projector views spread evenly over the plan, and "first", its first 6. Each is calibrated with the joint
method; prints (each 1-sigma scaled to 0.3 px of noise, as the gate compares them) the worst full-session value of every quality metric next to calib.quality.trust.QualityThresholds,
the thin sessions' metrics, their errors against the scenario's truth, and the quality codes of each run
(every full session should have none, every thin one some).

    python benchmarks/quality_gate.py [--seeds 3] [--noise 0.3] [--scenarios a,b]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.quality.trust import QualityThresholds, check_calibration  # noqa: E402
from calib.synthetic import SyntheticSession, observe  # noqa: E402
from drivers.sim.scenarios import get_scenario, scenario_names  # noqa: E402

#: the quality gate's metrics: each 1-sigma scaled to 0.3 px of noise (calib.quality.trust.check_quality)
METRICS = ("quality.t_mm", "quality.rot_deg", "quality.camera_intrinsics_px", "quality.projector_intrinsics_px",
           "quality.mirror_normal_deg", "quality.projection_camera_max_px", "quality.projection_projector_max_px")


def thin(obs, kind: str, projector: int = 6, mirror: int = 3):
    """The observations cut to `mirror` mirror and `projector` projector views ("spread" or "first")."""
    pv = obs.projector_views
    idx = (sorted({round(i * (len(pv) - 1) / (projector - 1)) for i in range(projector)}) if kind == "spread"
           else list(range(projector)))
    return dataclasses.replace(obs, projector_views=tuple(pv[i] for i in idx), mirror_views=obs.mirror_views[:mirror])


def run(name: str, seed: int, noise_px: float, kind: str):
    sc = get_scenario(name, seed)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                          sc.mirror_method, sc.board_thickness_mm)
    obs = observe(ss, noise_px, seed, circle_centroids=True)
    if kind != "full":
        obs = thin(obs, kind)
    res = calibrate_observations(obs, "joint", trust=None)
    rep = check_calibration(res)
    return rep, compare(res, sc.ground_truth())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--scenarios", default=",".join(scenario_names()))
    args = ap.parse_args()
    names = args.scenarios.split(",")
    worst: dict = {}
    print(f"joint method, noise {args.noise} px, {len(names)} scenarios x {args.seeds} seeds")
    print("| scenario (seed) | session | 1-sigma t mm / rot deg | cam / proj intrinsics px | mirror deg | "
          "projection max cam / proj px | joint RMS px | vs truth: distance mm, angle deg, CamK px, ProjK px | trust | quality codes |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        for seed in range(args.seeds):
            for kind in ("full", "spread", "first"):
                try:
                    rep, mt = run(name, seed, args.noise, kind)
                except Exception as e:  # a thin session may not even calibrate: say so and go on
                    print(f"| {name} ({seed}) | {kind} | failed: {type(e).__name__}: {str(e)[:80]} |")
                    continue
                m = rep.metrics
                g = lambda k: m.get(k, float("nan"))  # noqa: E731
                if kind == "full":
                    for k in METRICS:
                        if k in m and (k not in worst or m[k] > worst[k][0]):
                            worst[k] = (m[k], name, seed)
                print(f"| {name} ({seed}) | {kind} | {g('quality.t_mm'):.3g} / {g('quality.rot_deg'):.3g} | "
                      f"{g('quality.camera_intrinsics_px'):.3g} / {g('quality.projector_intrinsics_px'):.3g} | "
                      f"{g('quality.mirror_normal_deg'):.3g} | {g('quality.projection_camera_max_px'):.3g} / "
                      f"{g('quality.projection_projector_max_px'):.3g} | {g('rms.joint'):.3g} | {mt.distance:.3f}, {mt.angle_deg:.4f}, "
                      f"{mt.cam_k_px:.3f}, {mt.proj_k_px:.3f} | {'pass' if rep.passed else ','.join(rep.codes)} | "
                      f"{', '.join(c.removeprefix('quality_') for c in rep.quality_codes) or '-'} |", flush=True)
    th = dataclasses.asdict(QualityThresholds())
    print("\n| metric | worst full session | scenario (seed) |\n|---|---|---|")
    for k in METRICS:
        if k in worst:
            v, name, seed = worst[k]
            print(f"| {k} | {v:.4g} | {name} ({seed}) |")
    print("\nquality limits:", ", ".join(f"{k} {v:g}" for k, v in th.items()))


if __name__ == "__main__":
    main()
