"""The wide-angle corner-poor camera (scenario wideangle-realmirror, issue 18): camera distortion error over
the image and the coverage of the reported projection uncertainty, per seed; and the k3 shrinkage's effect
on other scenarios.

    python benchmarks/wide_angle.py [--seeds 10] [--noise 0.05] [--scenario wideangle-realmirror]
    python benchmarks/wide_angle.py --sessions DIR    # rendered sessions (procam bench accuracy --keep DIR)
    python benchmarks/wide_angle.py --other nonoverlap-136,direct --seeds 10

Observations are exact-geometry synthetic ones (calib.synthetic.observe: circle centroids, Gaussian noise
of --noise px), or, with --sessions, detected in every rendered session folder under DIR (its
ground_truth.json is the truth). Columns (px): the distortion error over the image (mean distance between
where the estimated and the true distortion put the same ray, both with the true K) of the joint method
with the coverage criterion's keep-or-drop rule for k3 (joint-margin: shrinkage=False), with the k3
shrinkage prior instead (joint-shrink: shrinkage=True), without the coverage criterion (joint-bic), the
paper method, and OpenCV's calibrateCamera of the same board views with 5 coefficients (cv-5) and with
k3 fixed at 0 (cv-k3fix); the camera model the two coverage variants chose; and, for the default variant,
the fraction of the 16x10 grid where the joint's actual projection error (estimated vs true intrinsics on
the true rays, its best-fitting rotation removed, as the grid is defined) is within 1 sigma and within
2.15 sigma (the radius holding >= 90% of a 2D Gaussian whose worst direction is sigma), and the same for
the distortion-only error.

--other: per scenario, the means over the seeds of every metric (camera and projector distortion error
over the image, projector position and angle, K errors, mirror normal) with the shrinkage off and on, and
the number of sessions whose chosen models differ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.errors import UntrustedCalibration  # noqa: E402
from calib.joint.method import JointOptions  # noqa: E402
from calib.paper.camera import calibrate_camera  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality import projection_uncertainty as PU  # noqa: E402
from calib.quality.metrics import compare, distortion_error_over_image  # noqa: E402
from calib.synthetic import SyntheticSession, observe  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402

K90 = 2.146  # sqrt(-2 ln 0.1)


def scenario_observations(name: str, seed: int, noise_px: float):
    sc = get_scenario(name, seed)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                          sc.mirror_method, sc.board_thickness_mm)
    return sc, observe(ss, noise_px, seed, circle_centroids=True)


def coverage(result, true):
    """(fraction within 1 sigma, within K90 sigma) of the projection error and of the distortion-only error."""
    g = result.projection_uncertainty["camera"]
    X, Y = np.meshgrid(g["x_px"], g["y_px"])
    uv = np.column_stack([X.ravel(), Y.ravel()])
    sig = np.asarray(g["sigma_px"], float).ravel()
    rays = true.rays(uv)
    e_full = result.camera.project(rays) - true.project(rays)
    R = PU.rotation_jacobian(true, uv).reshape(-1, 3)
    ok = np.all(np.isfinite(e_full), axis=1)
    e = e_full.reshape(-1)
    okr = np.repeat(ok, 2)
    w = np.linalg.lstsq(R[okr], e[okr], rcond=None)[0]
    e_rot = np.linalg.norm((e - R @ w).reshape(-1, 2), axis=1)
    e_dist = np.linalg.norm(true.with_params(dist=result.camera.dist).project(rays) - true.project(rays), axis=1)
    out = []
    for err in (e_rot, e_dist):
        err = np.where(np.isfinite(err), err, np.inf)
        out += [float(np.mean(err <= sig)), float(np.mean(err <= K90 * sig))]
    return out


JOINT_VARIANTS = (("joint-margin", {"shrinkage": False}), ("joint-shrink", {"shrinkage": True}),
                  ("joint-bic", {"coverage": False}))


def _joint(obs, opts):
    try:
        return calibrate_observations(obs, "joint", method_options=opts)
    except UntrustedCalibration:
        return None


def wide_angle_table(sessions) -> None:
    """The per-session table of the wide-angle scenario (see the module docstring)."""
    default = "joint-shrink" if JointOptions().shrinkage else "joint-margin"
    cols = ["seed"] + [n for n, _ in JOINT_VARIANTS] + ["paper", "cv-5", "cv-k3fix", "model margin/shrink",
                                                        "proj<=1s", "proj<=2.15s", "dist<=1s", "dist<=2.15s"]
    print(f"coverage columns: {default} (the default)")
    print(" | ".join(cols))
    rows = []
    for seed, true, obs in sessions:
        res = {name: _joint(obs, opts) for name, opts in JOINT_VARIANTS}
        try:
            res["paper"] = calibrate_observations(obs, "paper")
        except UntrustedCalibration:
            res["paper"] = None
        errs = [distortion_error_over_image(r.camera, true) if r is not None else np.nan for r in res.values()]
        cv5 = distortion_error_over_image(calibrate_camera(obs).camera, true)
        cvk = distortion_error_over_image(calibrate_camera(obs, fix_k3=True).camera, true)
        models = "/".join(res[n].diagnostics["model_selection"]["camera"]["chosen"] if res[n] is not None
                          else "untrusted" for n in ("joint-margin", "joint-shrink"))
        rj = res[default]
        cov = coverage(rj, true) if rj is not None else [np.nan] * 4
        row = errs + [cv5, cvk] + cov
        rows.append(row)
        print(" | ".join([str(seed)] + [f"{v:.3f}" for v in row[:6]] + [models] + [f"{v:.2f}" for v in cov]),
              flush=True)
    a = np.array(rows, float)
    for name, fn in (("mean", np.nanmean), ("median", np.nanmedian)):
        print(" | ".join([name] + [f"{v:.3f}" for v in fn(a[:, :6], axis=0)] + ["-"]
                         + [f"{v:.2f}" for v in fn(a[:, 6:], axis=0)]))
    for j, (name, _) in enumerate(JOINT_VARIANTS):
        print(f"{name} <= cv-k3fix on {int(np.sum(a[:, j] <= a[:, 5]))} of {len(a)} seeds")


def other_scenarios(names, seeds: int, noise_px: float) -> None:
    """Every metric of the joint method with the k3 shrinkage off and on, over synthetic sessions of other
    scenarios: means over the seeds, and how many sessions changed their chosen models."""
    print(f"synthetic observations, noise {noise_px} px, seeds 0-{seeds - 1}; means (CamD/ProjD img: distortion "
          "error over the image, px; Dist in mm)")
    print("scenario | variant | models changed | CamD img | ProjD img | Dist | Ang deg | ProjK px | CamK px | Mir deg")
    for name in names:
        vals = {v: [] for v in ("joint-margin", "joint-shrink")}
        changed = 0
        for seed in range(seeds):
            sc, obs = scenario_observations(name, seed, noise_px)
            gt = sc.rig.ground_truth()
            chosen = []
            for variant, opts in JOINT_VARIANTS[:2]:
                r = _joint(obs, opts)
                if r is None:
                    vals[variant].append([np.nan] * 7)
                    chosen.append(None)
                    continue
                m = compare(r, gt)
                vals[variant].append([distortion_error_over_image(r.camera, gt.camera),
                                      distortion_error_over_image(r.projector, gt.projector), m.distance,
                                      m.angle_deg, m.proj_k_px, m.cam_k_px,
                                      np.nan if m.mirror_angle_deg is None else m.mirror_angle_deg])
                ms = r.diagnostics["model_selection"]
                chosen.append((ms["camera"]["chosen"], ms["projector"]["chosen"]))
            changed += chosen[0] != chosen[1]
        for variant, rows in vals.items():
            a = np.nanmean(np.array(rows, float), axis=0)
            print(" | ".join([name, variant, str(changed) if variant == "joint-shrink" else "-"]
                             + [f"{v:.4f}" if i < 2 else f"{v:.3f}" for i, v in enumerate(a)]), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--scenario", default="wideangle-realmirror")
    ap.add_argument("--sessions", default=None, help="calibrate the rendered session folders under this folder")
    ap.add_argument("--other", default=None, help="comma-separated scenarios: every metric with the k3 shrinkage "
                                                  "off and on (synthetic, --seeds seeds)")
    args = ap.parse_args()
    if args.other:
        other_scenarios([n.strip() for n in args.other.split(",") if n.strip()], args.seeds, args.noise)
        return
    if args.sessions:
        from calib.detection.detect import detect_session
        from calib.formats.session import SessionStore
        from calib.models.result import CalibrationResult

        folders = sorted(f for f in Path(args.sessions).iterdir() if (f / "session.json").exists())
        print(f"rendered sessions under {args.sessions}; distortion error over the image (px)")

        def sessions():
            for f in folders:
                gt = CalibrationResult.load_json(f / "ground_truth.json")
                yield f.name, gt.camera, detect_session(SessionStore.open(f), 1, cache="use")
    else:
        print(f"{args.scenario}, synthetic observations, noise {args.noise} px; distortion error over the image (px)")

        def sessions():
            for seed in range(args.seeds):
                sc, obs = scenario_observations(args.scenario, seed, args.noise)
                yield str(seed), sc.rig.camera, obs
    wide_angle_table(sessions())


if __name__ == "__main__":
    main()
