"""Photometric realism (issue 18): what each effect of the renderer does to the projected-circle centres,
to the calibration and to the epipolar verification.

    python benchmarks/photometric.py [--seeds 2] [--scenario nonoverlap-136] [--effects ...] [--no-calib]
    python benchmarks/photometric.py --corners --seeds 6 --effects none "camera gamma" "all (default)"

For each effect alone (added to a photometrically neutral renderer: linear projector and camera, no
black level, no defocus, no vignetting), all together (the scenario's default) and none:

- circle centres: the scenario's 13 pattern positions (one board pose each) per seed, rendered at session
  quality without noise (blur and 8-bit quantisation kept), detected by calib.detection.detect as a session is;
  each detected centre against the true projection of the circle's centre (`centre`), against the
  area centroid of the circle's exact image (`conic`: what the joint method's conic model predicts),
  and against the same circle detected in the neutral image (`shift`: the effect alone);
- calibration: full sessions rendered with noise (simulate, detect, joint method), errors against the
  ground truth: distance mm, angle deg, projector K px (mean over seeds);
- verification: `app.verification.verify` with the ground truth at the scenario's verification pose:
  the mean distance in projector px, and the stroke's measured scale (camera px per projector px)
  relative to the neutral renderer's, mean and worst |ratio - 1| over the checked pixels.

Every calibrated effect but `none` is also compared with `none` seed by seed (the same poses and noise
draws): the mean paired ProjK difference and its standard error.

`--corners` measures the ChArUco corners instead: small live-quality sessions (26 projector + 4 mirror
views, as --small-live), detected with and without the recorded response, each corner against its true
projection: mean / max distance, the mean error vector (a systematic shift), its mean radial part about
the view's corners' centre (a scale), and the distance to the same corner with the linear camera.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.detection.detect import detect_board, detect_pattern  # noqa: E402
from calib.detection.response import CameraResponse  # noqa: E402
from calib.models.observations import VIEW_MIRROR  # noqa: E402
from calib.synthetic import imaged_circle_centroids, projector_points_on_board  # noqa: E402
from calib.transforms import transform_points  # noqa: E402
from drivers.sim.render import PlacedBoard, Renderer, SceneState  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402

#: effect name -> the RenderSettings fields it takes from the scenario's default (realistic) settings
EFFECTS = {
    "none": (),
    "projector gamma": ("projector_gamma",),
    "camera gamma": ("camera_gamma",),
    "projector black level": ("projector_black_level",),
    "projector defocus": ("projector_aperture_mm", "projector_focus_mm"),
    "vignetting": ("vignetting_corner",),
    "ambient x2": (),
    "all (default)": ("projector_gamma", "camera_gamma", "projector_black_level", "projector_aperture_mm",
                      "projector_focus_mm", "vignetting_corner"),
}

#: calibrated by default: the effects that move circle centres measurably, none and all
CALIB_EFFECTS = ("none", "projector gamma", "camera gamma", "projector defocus", "vignetting", "all (default)")


def settings_for(scenario, effect: str):
    full = scenario.render
    st = full.photometrically_neutral()
    st = replace(st, **{f: getattr(full, f) for f in EFFECTS[effect]})
    if effect == "ambient x2":  # twice the room light for the projector's, at the same brightness
        # (as the camera's exposure would keep it: the lit board is not saturated)
        st = replace(st, ambient=2 * full.ambient * 2 / 3, projector_gain=full.projector_gain * 2 / 3)
    return st


def circle_truth(sc, T, pts_px) -> tuple[np.ndarray, np.ndarray]:
    """(projections of the circle centres, area centroids of the circles' exact images), camera px."""
    rig = sc.rig
    S = rig.S() if rig.mirror is not None else np.eye(4)
    Xb = projector_points_on_board(rig, T, pts_px)
    centre = rig.camera.project(transform_points(S @ T, Xb))
    conic = imaged_circle_centroids(rig, T, pts_px, sc.pattern.radius_px, n_boundary=360)
    return centre, conic


def circle_bias(scenario_name: str, seeds: int, effects, quality: str = "session", response: bool = True) -> dict:
    """effect -> {'centre': errors, 'conic': errors, 'shift': errors vs the neutral detection} (px arrays).
    `response`: the detector knows the camera's tone curve, as a session that records it (the simulated
    rig's do: calib.detection.response)."""
    out = {e: {"centre": [], "conic": [], "shift": [], "failed": 0} for e in effects}
    for seed in range(seeds):
        sc = get_scenario(scenario_name, seed)
        rig = sc.rig
        W, H = rig.projector.size
        mirrored = sc.view == VIEW_MIRROR
        ss = 1 if quality == "live" else 3
        renderers = {e: Renderer(rig.camera, rig.projector, rig.T_cam_proj, rig.mirror, rig.mirror_rect,
                                 replace(settings_for(sc, e).without_noise(), supersample=ss))
                     for e in set(effects) | {"none"}}
        poses = sc.projector_poses[:: sc.per_position]  # one pose per pattern position
        for pos, T in poses:
            img_p, pts = sc.pattern.render(W, H, pos)
            centre, conic = circle_truth(sc, T, pts)
            state = SceneState((PlacedBoard(sc.layout, T),), img_p)
            found = {}
            for e in set(effects) | {"none"}:
                img = renderers[e].render(state)
                board = detect_board(img, sc.projector_board, mirrored)
                det = None
                if not hasattr(board, "reason"):
                    gamma = float(renderers[e].settings.camera_gamma)
                    det = detect_pattern(img, sc.pattern, mirrored, board, sc.projector_board,
                                         CameraResponse("bt709", gamma) if response else None)
                found[e] = None if det is None or hasattr(det, "reason") else np.asarray(det, float)
            for e in effects:
                d = found[e]
                if d is None:
                    out[e]["failed"] += 1
                    continue
                out[e]["centre"].append(np.linalg.norm(d - centre, axis=1))
                out[e]["conic"].append(np.linalg.norm(d - conic, axis=1))
                if found["none"] is not None:
                    out[e]["shift"].append(np.linalg.norm(d - found["none"], axis=1))
    for e in effects:
        for k in ("centre", "conic", "shift"):
            out[e][k] = np.concatenate(out[e][k]) if out[e][k] else np.array([np.nan])
    return out


def calibration_errors(scenario_name: str, seeds: int, effects, workers: int = 2, log=print, small_live: bool = False,
                       response: bool = True) -> dict:
    """effect -> list of (distance mm, angle deg, projector K px) per seed (None for a failed session).
    `small_live`: 26 projector + 4 mirror views rendered at live quality (as the station captures;
    tests/test_import_procamcalib.py's session) instead of the scenario's session at session quality.
    `response`: the session records the camera's tone curve (as `procam simulate` does), else it is
    removed from the manifest before detection (the detector as it was without it)."""
    from app.commands.simulate import simulate_session
    from calib.detection.detect import detect_session
    from calib.errors import ProcamError
    from calib.formats.session import SessionStore
    from calib.pipeline import calibrate_observations
    from calib.quality.metrics import compare

    out = {e: [] for e in effects}
    with tempfile.TemporaryDirectory(prefix="procam-photometric-") as tmp:
        for seed in range(seeds):  # seed by seed: a run stopped early still has every effect of its seeds
            for e in effects:
                sc = get_scenario(scenario_name, seed)
                sc = replace(sc, render=settings_for(sc, e))
                if small_live:
                    sc = replace(sc, per_position=2, mirror_count=4)
                folder = Path(tmp) / f"{e.replace(' ', '_')}-{seed}"
                t0 = time.perf_counter()
                simulate_session(sc, folder, quality="live" if small_live else "session", workers=workers, force=True,
                                 progress=False)
                store = SessionStore.open(folder)
                if not response:
                    rig = store.manifest.rig
                    store.update(rig=replace(rig, camera_settings={k: v for k, v in rig.camera_settings.items()
                                                                   if k != "response"}))
                obs = detect_session(SessionStore.open(folder), workers, cache="refresh")
                try:
                    res = calibrate_observations(obs, "joint")
                except ProcamError as err:
                    log(f"  {e}, seed {seed}: calibration FAILED: {err}")
                    out[e].append(None)
                    continue
                m = compare(res, sc.ground_truth())
                out[e].append((m.distance, m.angle_deg, m.proj_k_px))
                log(f"  {e}, seed {seed}: {m.distance:.3f} mm, {m.angle_deg:.4f} deg, ProjK {m.proj_k_px:.3f} px, "
                    f"CamK {m.cam_k_px:.3f} px "
                    f"({len(obs.skipped)} skipped; {time.perf_counter() - t0:.0f} s)")
    return out


def corner_errors(scenario_name: str, seeds: int, effects, noise: bool, log=print) -> dict:
    """(effect, response used, board kind) -> list of (ids, detected px, true px) per view; board kind
    "projector" (projector-step boards) or "mirror" (the real and virtual boards of the mirror step).
    Small live-quality sessions, rendered with or without the sensor's noise (blur and 8 bits kept)."""
    import cv2

    from app.commands.simulate import simulate_session
    from calib.detection import detect as D
    from calib.detection.response import recorded_response
    from calib.formats.session import SessionStore
    from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL
    from drivers.sim.scene_file import expected_points

    out: dict = {}
    with tempfile.TemporaryDirectory(prefix="procam-corners-") as tmp:
        for seed in range(seeds):
            for e in effects:
                sc = get_scenario(scenario_name, seed)
                st = settings_for(sc, e)
                if not noise:
                    st = replace(st, read_noise_dn=0.0, electrons_per_dn=0.0)
                sc = replace(sc, render=st, per_position=2, mirror_count=4)
                folder = Path(tmp) / f"{e.replace(' ', '_')}-{seed}"
                simulate_session(sc, folder, quality="live", workers=2, force=True, progress=False)
                store = SessionStore.open(folder)
                m = store.manifest
                truth = expected_points(folder)
                mirrored = m.rig.view == VIEW_MIRROR
                mboard = m.mirror_board or m.projector_board
                for use in (False, True):
                    resp = recorded_response(m.rig.camera_settings) if use else None
                    for c in m.captures:
                        gray = cv2.imread(str(store.image_path(c)), cv2.IMREAD_GRAYSCALE)
                        t = truth[c.id]
                        if c.step == STEP_PROJECTOR:
                            found = [(D.detect_board(gray, m.projector_board, mirrored, response=resp),
                                      t.board_px, "projector")]
                        else:
                            fn = D.detect_real_virtual if c.step == STEP_REAL_VIRTUAL else D.detect_real_mirror
                            mv = fn(gray, mboard, c.id, response=resp)
                            found = [] if isinstance(mv, D.DetectionFailure) else \
                                [(mv.real, t.board_px, "mirror"), (mv.virtual, t.virtual_px, "mirror")]
                        for j, (b, px, kind) in enumerate(found):
                            if b is not None and not isinstance(b, D.DetectionFailure):
                                out.setdefault((e, use, kind), {})[(seed, c.id, j)] = (b.ids, b.corners_px, px[b.ids])
                out["image centre"] = (np.asarray(m.rig.camera_size, float) - 1.0) / 2.0
                log(f"  corners: {e}, seed {seed}")
    return out


def _corner_table(errs: dict, effects) -> None:
    print("| camera | detector | boards | corners | vs truth px, mean / max | mean error vector px | radial px "
          "| towards the image centre px | vs linear camera px, mean / max |")
    print("|---|---|---|---|---|---|---|---|---|")
    c0 = errs.get("image centre", np.zeros(2))
    for kind in ("projector", "mirror"):
        for e in effects:
            for use in (False, True):
                views = errs.get((e, use, kind), {})
                ref = errs.get(("none", False, kind), {})
                if not views or (e == "none" and use):  # a linear camera's response changes nothing
                    continue
                d, rad, inward, shift = [], [], [], []
                for key, (ids, det, tru) in views.items():
                    err = det - tru
                    u = tru - tru.mean(axis=0)
                    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
                    d.append(err)
                    rad.append((err * u).sum(axis=1))
                    v = c0 - tru
                    inward.append((err * v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)).sum(axis=1))
                    if key in ref and e != "none":
                        _, ia, ib = np.intersect1d(ids, ref[key][0], return_indices=True)
                        shift.append(np.linalg.norm(det[ia] - ref[key][1][ib], axis=1))
                d, rad, inward = np.concatenate(d), np.concatenate(rad), np.concatenate(inward)
                n = np.linalg.norm(d, axis=1)
                vs_linear = "- / -"
                if shift:
                    sh = np.concatenate(shift)
                    vs_linear = f"{sh.mean():.4f} / {sh.max():.3f}"
                print(f"| {e} | {'response' if use else 'encoded levels'} | {kind} | {len(d)} "
                      f"| {n.mean():.4f} / {n.max():.3f} | ({d[:, 0].mean():+.4f}, {d[:, 1].mean():+.4f}) "
                      f"| {rad.mean():+.4f} | {inward.mean():+.4f} | {vs_linear} |")


def paired_projk(calib: dict) -> dict:
    """effect -> (mean ProjK difference to `none` px, its standard error, seeds) over the seeds where both
    calibrated (the same poses and noise draws: the seeds' own spread cancels)."""
    out = {}
    base = calib.get("none", [])
    for e, runs in calib.items():
        if e == "none":
            continue
        diff = np.array([r[2] - b[2] for r, b in zip(runs, base) if r is not None and b is not None])
        if len(diff) >= 2:
            out[e] = (float(diff.mean()), float(diff.std(ddof=1) / np.sqrt(len(diff))), len(diff))
    return out


def verification(scenario_name: str, effects) -> dict:
    """effect -> (mean distance proj px, per-pixel scales {pixel: scale}), ground truth, seed 0."""
    from app.verification import verify
    from drivers.sim.rig import open_sim_rig

    out = {}
    for e in effects:
        sc = get_scenario(scenario_name, 0)
        rig = open_sim_rig(scenario_name, 0, quality="session", ideal=True, **settings_for(sc, e).to_dict())
        try:
            rig.camera.start()
            rep = verify(rig.camera, rig.projector, rig.operator, rig.ground_truth())
        finally:
            rig.close()
        scales = {tuple(np.round(c.pixel, 1)): c.scale for c in rep.checks if c.scale}
        out[e] = (rep.mean_proj_px, scales)
    return out


def _fmt(v, f="{:.3f}"):
    return "-" if v is None or not np.isfinite(v) else f.format(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nonoverlap-136")
    ap.add_argument("--seeds", type=int, default=2, help="seeds for the circle centres and the calibration")
    ap.add_argument("--effects", nargs="+", default=list(EFFECTS), choices=list(EFFECTS))
    ap.add_argument("--calib-effects", nargs="+", default=list(CALIB_EFFECTS), choices=list(EFFECTS),
                    help="effects whose sessions are calibrated (the slow part: one session per effect and seed)")
    ap.add_argument("--no-calib", action="store_true", help="skip the calibration of rendered sessions")
    ap.add_argument("--no-verify", action="store_true", help="skip the epipolar verification")
    ap.add_argument("--quality", choices=("session", "live"), default="session",
                    help="render quality of the circle-centre part (live: 1 sample per pixel, as the station captures)")
    ap.add_argument("--small-live", action="store_true",
                    help="calibrate small live-quality sessions (26 projector + 4 mirror views) instead of full ones")
    ap.add_argument("--no-response", action="store_true",
                    help="the detector without the camera's recorded tone curve (centroids and corners on encoded "
                         "levels)")
    ap.add_argument("--no-centres", action="store_true", help="skip the circle-centre part")
    ap.add_argument("--corners", action="store_true",
                    help="only the ChArUco corners of small live-quality sessions, with and without the response")
    ap.add_argument("--noise", action="store_true", help="--corners: with the sensor's noise (default noise-free)")
    ap.add_argument("--encoded-corners", action="store_true",
                    help="refine ChArUco corners on the encoded levels even with the response (the detector before "
                         "2026-12-02; circle centroids still linearised)")
    a = ap.parse_args()
    if a.encoded_corners:
        from calib.detection import charuco

        charuco._refinement_image = lambda img, response: img  # a before/after measurement only
    effects = list(dict.fromkeys(a.effects))
    if a.corners:
        t0 = time.perf_counter()
        errs = corner_errors(a.scenario, a.seeds, list(dict.fromkeys(["none"] + effects)), a.noise)
        print(f"corners ({'with' if a.noise else 'without'} noise): {time.perf_counter() - t0:.0f} s\n")
        _corner_table(errs, list(dict.fromkeys(["none"] + effects)))
        return
    sc = get_scenario(a.scenario)
    st = sc.render
    print(f"{a.scenario}, seeds 0-{a.seeds - 1}; defaults: projector gamma {st.projector_gamma}, black level "
          f"{st.projector_black_level}, aperture {st.projector_aperture_mm} mm focused at {st.projector_focus_mm} mm, "
          f"vignetting {st.vignetting_corner} at the corners, camera gamma {st.camera_gamma}, ambient {st.ambient}")
    t0 = time.perf_counter()
    bias = {e: {"centre": np.array([np.nan]), "conic": np.array([np.nan]), "shift": np.array([np.nan]), "failed": 0}
            for e in effects}
    if not a.no_centres:
        bias = circle_bias(a.scenario, a.seeds, effects, a.quality, not a.no_response)
        print(f"circle centres ({a.quality} quality): {time.perf_counter() - t0:.0f} s", flush=True)
    calib = {}
    if not a.no_calib:
        t0 = time.perf_counter()
        calib = calibration_errors(a.scenario, a.seeds, [e for e in a.calib_effects if e in effects],
                                   small_live=a.small_live, response=not a.no_response,
                                   log=lambda line: print(line, flush=True))
        print(f"calibration: {time.perf_counter() - t0:.0f} s", flush=True)
    ver = {}
    if not a.no_verify:
        t0 = time.perf_counter()
        ver = verification(a.scenario, list(dict.fromkeys(["none"] + effects)))
        print(f"verification: {time.perf_counter() - t0:.0f} s", flush=True)

    print()
    print("| effect | centre bias px mean / max | vs conic centroid px mean / max | shift vs none px mean / max "
          "| distance mm | angle deg | ProjK px | verification proj px | stroke scale vs none mean / worst % |")
    print("|---|---|---|---|---|---|---|---|---|")
    for e in effects:
        b = bias[e]
        cells = [e]
        for k in ("centre", "conic", "shift"):
            cells.append(f"{_fmt(np.nanmean(b[k]))} / {_fmt(np.nanmax(b[k]))}")
        if b["failed"]:
            cells[-1] += f" ({b['failed']} views not detected)"
        runs = [r for r in calib.get(e, []) if r is not None]
        if runs:
            m = np.mean(np.array(runs), axis=0)
            cells += [_fmt(m[0]), _fmt(m[1], "{:.4f}"), _fmt(m[2])]
            if len(runs) < len(calib[e]):
                cells[-1] += f" ({len(calib[e]) - len(runs)} failed)"
        else:
            cells += ["-", "-", "-"]
        if e in ver:
            mean_proj, scales = ver[e]
            ref = ver["none"][1]
            ratios = []
            for p, sc_p in scales.items():  # the neutral check at the nearest pixel (the grids differ a little)
                q = min(ref, key=lambda r: np.hypot(r[0] - p[0], r[1] - p[1]), default=None)
                if q is not None and np.hypot(q[0] - p[0], q[1] - p[1]) < 15.0:
                    ratios.append(sc_p / ref[q] - 1.0)
            ratios = np.array(ratios)
            cells.append(_fmt(mean_proj))
            cells.append(f"{_fmt(100 * np.abs(ratios).mean(), '{:.1f}')} / {_fmt(100 * np.abs(ratios).max(), '{:.1f}')}"
                         if len(ratios) else "-")
        else:
            cells += ["-", "-"]
        print("| " + " | ".join(cells) + " |")
    paired = paired_projk(calib)
    if paired:
        print()
        for e, (mean, se, n) in paired.items():
            print(f"ProjK {e} minus none, paired over {n} seeds: {mean:+.3f} +- {se:.3f} px (standard error)")


if __name__ == "__main__":
    main()
