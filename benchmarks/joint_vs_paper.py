"""Joint refinement vs the paper's sequential method on synthetic sessions, side by side.

For every rig (90, 136, 180 degrees through a mirror, and the direct control) and several noise draws,
the same observations are calibrated by the paper's pipeline and by the joint refinement (started from
it), and the paper's metrics (calib.quality.metrics.compare) are averaged over the seeds. The observations are
what a detector reports: Gaussian noise on every point and, by default, projected circles at the area
centroids of their images (calib.synthetic.observe(circle_centroids=True)).

    python benchmarks/joint_vs_paper.py [--noise 0.05] [--seeds 5] [--rigs 90 136 180 direct]
                                        [--mirror-method real-virtual] [--point-observations]

Prints one table per rig (paper | joint | joint/paper), the issue's targets with pass/fail, the
joint's mean 1-sigma for the extrinsics, and the time of each stage.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.joint.method import JointOptions, refine_joint  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.synthetic import make_direct_rig, make_rig, make_session, observe  # noqa: E402

METRICS = [  # (PaperMetrics field, label, unit, format)
    ("cam_k_px", "CamK", "px", "{:.3f}"),
    ("cam_d", "CamD", "", "{:.5f}"),
    ("proj_k_px", "ProjK", "px", "{:.3f}"),
    ("proj_d", "ProjD", "", "{:.5f}"),
    ("distance", "Distance", "mm", "{:.3f}"),
    ("angle_deg", "Angle", "deg", "{:.4f}"),
    ("mirror_angle_deg", "Mirror angle", "deg", "{:.4f}"),
    ("mirror_offset", "Mirror offset", "mm", "{:.3f}"),
]
TARGETS = {"proj_k_px": 1.0, "distance": 0.5, "angle_deg": 0.05, "mirror_angle_deg": 0.05}


def run_rig(rig_name: str, seeds: int, noise: float, centroids: bool, mirror_method: str, per_position: int):
    rig = make_direct_rig() if rig_name == "direct" else make_rig(float(rig_name))
    ss = make_session(rig, mirror_method=None if rig_name == "direct" else mirror_method, per_position=per_position)
    gt = rig.ground_truth()
    rows = {"paper": [], "joint": []}
    rms = {"paper": [], "joint": []}
    sig, times, models = [], [], []
    for seed in range(seeds):
        obs = observe(ss, noise, seed, circle_centroids=centroids)
        t0 = time.perf_counter()
        p = calibrate_observations(obs, "paper")
        t_paper = time.perf_counter() - t0
        j = refine_joint(obs, p, JointOptions())
        for name, res in (("paper", p), ("joint", j)):
            m = compare(res, gt)
            rows[name].append([np.nan if getattr(m, k) is None else float(getattr(m, k)) for k, *_ in METRICS])
        rms["paper"].append(p.rms.get("projector", np.nan))
        rms["joint"].append(j.rms["joint"])
        u = j.uncertainty
        sig.append([u["T_cam_proj"]["t_total"], u["T_cam_proj"]["rot_total_deg"], u["projector"]["fx"],
                    np.nan if u["mirror"] is None else u["mirror"]["normal_deg"]])
        tj = {k: v for k, v in j.diagnostics["timing_s"].items() if k.startswith("joint.")}
        times.append(dict(tj, paper=t_paper))
        models.append(f"{j.diagnostics['camera_model']}/{j.diagnostics['projector_model']}")
    return ({k: np.nanmean(np.array(v), axis=0) for k, v in rows.items()},
            {k: float(np.nanmean(v)) for k, v in rms.items()}, np.nanmean(np.array(sig), axis=0), times, models,
            len(obs.projector_views), len(obs.mirror_views))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", nargs="+", default=["90", "136", "180", "direct"])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--noise", type=float, default=0.05, help="pixel noise sigma (default 0.05, about what "
                    "the simulator's rendered sessions give after detection)")
    ap.add_argument("--mirror-method", default="real-virtual", choices=("real-virtual", "real-mirror"))
    ap.add_argument("--per-position", type=int, default=4, help="board poses per pattern position (4: 52 views)")
    ap.add_argument("--point-observations", action="store_true",
                    help="pattern points at the images of the circle centres (no perspective bias)")
    args = ap.parse_args(argv)
    centroids = not args.point_observations
    print(f"joint vs paper: {args.seeds} seed(s), noise {args.noise} px, "
          f"{'circle centroids' if centroids else 'point'} observations, mirror {args.mirror_method}")
    all_ok = True
    for rig_name in args.rigs:
        means, rms, sig, times, models, nv, nm = run_rig(rig_name, args.seeds, args.noise, centroids,
                                                         args.mirror_method, args.per_position)
        print(f"\nrig {rig_name}: {nv} projector views, {nm} mirror views; joint models (camera/projector): "
              f"{', '.join(sorted(set(models)))}")
        print(f"  {'metric':<14} {'paper':>10} {'joint':>10} {'joint/paper':>12}  target")
        for i, (key, label, unit, fmt) in enumerate(METRICS):
            a, b = means["paper"][i], means["joint"][i]
            if np.isnan(a) and np.isnan(b):
                continue
            ratio = b / a if a > 0 else np.nan
            tgt = TARGETS.get(key)
            mark = ""
            if tgt is not None:
                ok = b <= tgt
                all_ok &= ok
                mark = f"<= {tgt:g} {'ok' if ok else 'MISSED'}"
            better = "" if b < a else "  (paper better)"
            all_ok &= b < a
            print(f"  {label + (' ' + unit if unit else ''):<14} {fmt.format(a):>10} {fmt.format(b):>10} "
                  f"{ratio:>12.2f}  {mark}{better}")
        print(f"  {'RMS px':<14} {rms['paper']:>10.4f} {rms['joint']:>10.4f}   (paper: projector stage; joint: all points)")
        print(f"  joint 1-sigma (mean): position {sig[0]:.3f} mm, rotation {sig[1]:.4f} deg, projector fx "
              f"{sig[2]:.3f} px" + ("" if np.isnan(sig[3]) else f", mirror normal {sig[3]:.4f} deg"))
        keys = ["paper"] + [k for k in times[0] if k != "paper"]
        print("  time s (mean): " + ", ".join(f"{k} {np.mean([t.get(k, 0) for t in times]):.2f}" for k in keys))
    print(f"\n{'all targets met and joint better on every metric' if all_ok else 'some target missed (see above)'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
