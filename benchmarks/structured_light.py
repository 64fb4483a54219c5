"""Structured light vs the circle grid at equal projector placements (issue 23): decoding and calibration
accuracy against the simulator's ground truth.

    python benchmarks/structured_light.py [--scenarios nonoverlap-136 direct] [--seeds 3] [--placements 5]
        [--quality live|session] [--arms circles sl-grid sl-corners sl-both sl-gray-grid] [--methods paper joint]
        [--half-window PX] [--grid-step PX]

Per scenario and seed: `--placements` board poses of the scenario's protocol (the first pose of pattern
positions 0, 2, 4, 6, 8: the projector image's four corners and its centre, then the other positions).
At each pose, per arm, the camera images are rendered with the scenario's photometric effects and
detected as a session would be (the camera's recorded tone curve given to the detector):
  circles       today's step: the circle grid at that position (calib.detection.detect);
  sl-grid       the structured-light sequence (32 px period, 8 phase steps: 47 frames), its projector points
                on a lattice over the board's decoded white area (calib.detection.structured_view);
  sl-corners    the same sequence, projector points at the ChArUco corners;
  sl-both       both sets of points;
  sl-gray-grid  Gray code alone down to 1-pixel stripes (47 frames too), lattice points;
  sl-grid-4steps  4 phase steps instead of 8 (39 frames); sl-grid-64px  a 64 px period (43 frames);
  sl-grid-unweighted  sl-grid's points without their own sigmas (every point weighed alike, as before
                the joint took each point's sigma: ProjectorView.pattern_sigma_px).
The mirror-calibration views are the same for every arm: the scenario's 14 mirror placements as exact
synthetic observations with 0.1 px Gaussian noise (calib.synthetic.observe), so that the arms differ by
their projector step only. Then the paper and joint methods, and the errors against the truth.

Printed: the structured-light projector points' errors against the renderer's exact projector pixels
(RMS and 99th percentile, px, with the fits' median 1-sigma, and the RMS error of the points whose fit
sigma is in its lowest and highest quartile), then per scenario, arm and method the means
over seeds of distance (mm), angle (deg), ProjK and CamK (px), projector and camera distortion over the
image (px) and the mirror normal (deg); `fail` counts seeds whose calibration raised.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.detection.detect import detect_board, detect_pattern  # noqa: E402
from calib.detection.response import CameraResponse  # noqa: E402
from calib.detection.structured_view import BoardPoints, detect_structured_view  # noqa: E402
from calib.errors import ProcamError  # noqa: E402
from calib.joint.method import calibrate_joint  # noqa: E402
from calib.models.observations import ProjectorView, SessionObservations  # noqa: E402
from calib.models.structured_light import StructuredLightSpec  # noqa: E402
from calib.paper.method import calibrate_paper  # noqa: E402
from calib.quality.metrics import compare, distortion_error_over_image  # noqa: E402
from calib.synthetic import SyntheticSession, observe  # noqa: E402
from drivers.sim.render import PlacedBoard, Renderer, SceneState  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402
from drivers.sim.structured import placement_poses, render_sequence, true_projector_px  # noqa: E402

ARMS = {
    "circles": None,
    "sl-grid": (StructuredLightSpec(32, 8), BoardPoints.BLANK_GRID),
    "sl-corners": (StructuredLightSpec(32, 8), BoardPoints.CORNERS),
    "sl-both": (StructuredLightSpec(32, 8), BoardPoints.BOTH),
    "sl-gray-grid": (StructuredLightSpec(32, 0), BoardPoints.BLANK_GRID),
    "sl-grid-4steps": (StructuredLightSpec(32, 4), BoardPoints.BLANK_GRID),
    "sl-grid-64px": (StructuredLightSpec(64, 8), BoardPoints.BLANK_GRID),
    "sl-grid-unweighted": (StructuredLightSpec(32, 8), BoardPoints.BLANK_GRID),
}
#: arms whose views drop the points' own sigmas
UNWEIGHTED = {"sl-grid-unweighted"}

def placements(sc, n: int) -> list[tuple[int, np.ndarray]]:
    poses = sc.projector_poses
    return [poses[p * sc.per_position + k] for p, k in placement_poses(sc, n)]


def mirror_views(sc, seed: int):
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, [], sc.mirror_poses, sc.mirror_method,
                          sc.board_thickness_mm)
    return observe(ss, 0.1, seed + 1000).mirror_views


def projector_views(sc, R, arm: str, poses, seed: int, response, stats: dict, window: dict, renders: dict):
    P = sc.rig.projector
    mirrored = sc.rig.mirror is not None
    out = []
    for i, (pos, T) in enumerate(poses):
        rng = np.random.default_rng([seed, 23, i])
        cid = f"p{i:04d}"
        if arm == "circles":
            img_p, q = sc.pattern.render(P.width, P.height, pos)
            img = R.render(SceneState((PlacedBoard(sc.layout, T),), img_p), rng)
            board = detect_board(img, sc.projector_board, mirrored, response=response)
            if not board:
                continue
            uv = detect_pattern(img, sc.pattern, mirrored, board, sc.projector_board, response)
            if not isinstance(uv, np.ndarray):
                continue
            out.append(ProjectorView(cid, board, uv, q, pos))
            continue
        spec, pts = ARMS[arm]
        if (spec, i) not in renders:  # the arms of one sequence share its images (the same noise draws)
            renders[(spec, i)] = render_sequence(R, sc.layout, T, spec, rng)
        imgs = renders[(spec, i)]
        sv = detect_structured_view(imgs, spec, sc.projector_board, (P.width, P.height), mirrored, cid, pts,
                                    response=response, **window)
        if not sv:
            stats.setdefault("failed", []).append(sv.reason)
            continue
        qt = true_projector_px(R, sc.layout, T, sv.view.pattern_cam_px)
        stats.setdefault("err", []).append(np.hypot(*(np.asarray(sv.view.pattern_proj_px) - qt).T))
        stats.setdefault("sigma", []).append(sv.points.sigma_px)
        out.append(replace(sv.view, pattern_sigma_px=None) if arm in UNWEIGHTED else sv.view)
    return out


def run(args) -> None:
    methods = {"paper": calibrate_paper, "joint": calibrate_joint}
    window = {k: v for k, v in (("half_window_px", args.half_window), ("grid_step_px", args.grid_step)) if v is not None}
    for name in args.scenarios:
        rows: dict = {}
        pstats: dict = {}
        t0 = time.process_time()
        for seed in range(args.seeds):
            sc = get_scenario(name, seed)
            st = replace(sc.render, supersample=1 if args.quality == "live" else 3)
            r = sc.rig
            R = Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, st)
            response = CameraResponse("bt709", float(st.camera_gamma)) if st.camera_gamma != 1.0 else None
            poses = placements(sc, args.placements)
            mviews = mirror_views(sc, seed) if sc.mirror_method else ()
            truth = sc.ground_truth()
            renders: dict = {}
            for arm in args.arms:
                stats = pstats.setdefault(arm, {})
                views = projector_views(sc, R, arm, poses, seed, response, stats, window, renders)
                obs = SessionObservations(r.camera.size, r.projector.size, r.view, sc.projector_board, sc.pattern,
                                          tuple(views), sc.mirror_board, tuple(mviews), sc.board_thickness_mm)
                for m in args.methods:
                    key = (arm, m)
                    rec = rows.setdefault(key, {"n_views": [], "metrics": [], "fail": 0})
                    rec["n_views"].append(len(views))
                    try:
                        kw = {"pattern_model": "point"} if (m == "joint" and arm != "circles") else {}
                        res = methods[m](obs, **kw)
                    except ProcamError as e:
                        rec["fail"] += 1
                        print(f"  {name} seed {seed} {arm} {m}: {str(e)[:120]}", file=sys.stderr)
                        continue
                    pm = compare(res, truth)
                    rec["metrics"].append((pm.distance, pm.angle_deg, pm.proj_k_px, pm.cam_k_px,
                                           distortion_error_over_image(res.projector, truth.projector),
                                           distortion_error_over_image(res.camera, truth.camera),
                                           pm.mirror_angle_deg if pm.mirror_angle_deg is not None else float("nan")))
        print(f"\n## {name}: {args.placements} projector placements, {args.seeds} seeds, {args.quality} quality "
              f"({time.process_time() - t0:.0f} s CPU)\n")
        print("| arm | frames | points per view | point error RMS px | p99 px | fit sigma median px | error RMS, "
              "points of the lowest / highest sigma quartile px | failed views |")
        print("|---|---|---|---|---|---|---|---|")
        for arm in args.arms:
            s = pstats.get(arm, {})
            if arm == "circles" or not s.get("err"):
                continue
            e = np.concatenate(s["err"])
            sg = np.concatenate(s["sigma"])
            n_frames = len(ARMS[arm][0].frames(*get_scenario(name).rig.projector.size))
            lo, hi = np.percentile(sg, [25, 75])  # does a point's own sigma say how large its error is?
            q = f"{np.sqrt(np.mean(e[sg <= lo] ** 2)):.3f} / {np.sqrt(np.mean(e[sg >= hi] ** 2)):.3f}"
            print(f"| {arm} | {n_frames} | {len(e) / len(s['err']):.0f} | {np.sqrt(np.mean(e ** 2)):.3f} | "
                  f"{np.percentile(e, 99):.3f} | {np.median(sg):.3f} | {q} | {len(s.get('failed', []))} |")
        print()
        print("| arm | method | views | distance mm | angle deg | ProjK px | CamK px | proj dist px | cam dist px "
              "| mirror deg | fail |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for (arm, m), rec in rows.items():
            if rec["metrics"]:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # no mirror on a direct rig: NaN, shown as nan
                    mean = np.nanmean(np.array(rec["metrics"]), axis=0)
                cells = " | ".join(f"{v:.3f}" if i != 1 else f"{v:.4f}" for i, v in enumerate(mean))
            else:
                cells = " | ".join(["-"] * 7)
            print(f"| {arm} | {m} | {np.mean(rec['n_views']):.1f} | {cells} | {rec['fail']} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["nonoverlap-136", "direct"])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--placements", type=int, default=5)
    ap.add_argument("--quality", choices=("live", "session"), default="live")
    ap.add_argument("--arms", nargs="+", choices=tuple(ARMS), default=["circles", "sl-grid", "sl-corners", "sl-both"])
    ap.add_argument("--methods", nargs="+", choices=("paper", "joint"), default=["paper", "joint"])
    ap.add_argument("--half-window", type=int, default=None, help="local homography half window, camera px")
    ap.add_argument("--grid-step", type=int, default=None, help="lattice step of sl-grid points, camera px")
    run(ap.parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
