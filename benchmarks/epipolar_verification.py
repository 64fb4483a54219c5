"""Epipolar verification: what the check measures for correct and wrong calibrations.

    python benchmarks/epipolar_verification.py [--quick] [--session DIR]

Prints three tables (numbers quoted in docs/VERIFICATION.md):

A. The real procedure (app.verification.verify, 4x3 grid) on the rendered simulated rigs: the ground
   truth and deliberately perturbed calibrations (0.5 deg rotations of T_cam_proj about the projector's
   axes, 5 px shifts of the projector's principal point), mean / worst distance in camera and projector
   pixels and the verdict at the default threshold; each with the frames read as light through the
   camera's response (`light`, what the station and `procam verify` do) and as the camera's encoded
   levels (`levels`, before the response was used). `--repeats N`: N checks each (the rig's noise
   moves the numbers from one check to the next): mean of the means, largest worst.
B. Calibrations as the pipeline estimates them from observations with Gaussian detection noise
   (calib.synthetic + calib.pipeline, 136 deg rig), measured by an ideal detector (exact geometry: the
   estimated curve drawn on the true board, seen by the true camera), over the blank region of 13
   board poses: how far honest calibrations are from the threshold.
C. Rotations of 0.5 deg about axes in the projector's image plane, every 15 deg (ideal detector,
   verification pose): the direction the epipolar check is blind to.
D. The stroke's scale (camera px per projector px, from its cross-section) under the projector's and the
   camera's gamma, with and without the camera's response, against the photometrically neutral
   renderer's at the same pixels (session quality, 136 deg rig, ground truth; noise-free, then with the
   scenario's noise as benchmarks/photometric.py renders it).
With --session DIR (a `procam simulate` session calibrated with `procam calibrate`), also the
`procam calibrate` result of that session through the real procedure.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.verification import DEFAULT_THRESHOLD_PX, perturbed, verify  # noqa: E402
from calib.epipolar import camera_ray, distance_to_polyline, epipolar_curve  # noqa: E402
from calib.transforms import invert_T, transform_points  # noqa: E402

PERTURBATIONS = [
    ("ground truth", {}),
    ("rot 0.5 deg about proj x", dict(rotation_deg=0.5, axis=(1, 0, 0))),
    ("rot 0.5 deg about proj y", dict(rotation_deg=0.5, axis=(0, 1, 0))),
    ("rot 0.5 deg about proj z", dict(rotation_deg=0.5, axis=(0, 0, 1))),
    ("cx + 5 px", dict(principal_shift_px=(5.0, 0.0))),
    ("cy + 5 px", dict(principal_shift_px=(0.0, 5.0))),
]


def _fmt(v, w=7):
    return f"{v:{w}.2f}" if v is not None else f"{'-':>{w}}"


def table_a(scenarios, grid, perturbations=PERTURBATIONS, reads=("light", "levels"), repeats=1):
    from calib.detection.response import parse_response
    from drivers.settle import apply_timing
    from drivers.sim.rig import open_sim_rig

    print(f"A. verify() on the rendered simulated rigs, grid {grid[0]}x{grid[1]}, threshold "
          f"{DEFAULT_THRESHOLD_PX:g} projector px (mean; worst <= 2x); {repeats} check(s) each")
    print(f"{'scenario':<16} {'calibration':<26} {'frames':<6} {'cam mean':>8} {'cam worst':>9} {'proj mean':>9} "
          f"{'proj worst':>10} {'measured':>8}  verdict")
    for name in scenarios:
        rig = open_sim_rig(name, seed=0, quality="live")
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)
        apply_timing(rig.camera, rig.projector)  # exposure and latency, as the station's rig check
        response = parse_response(rig.camera.response())  # what the rig check records
        gt = rig.ground_truth()
        for label, kw in perturbations:
            res = perturbed(gt, **kw) if kw else gt
            for read in reads:
                reps = [verify(rig.camera, rig.projector, rig.operator, res, grid=grid,
                               response=response if read == "light" else None) for _ in range(repeats)]

                def agg(key, f):
                    v = [getattr(r, key) for r in reps]
                    return None if any(x is None for x in v) else float(f(v))

                rep = reps[0]
                print(f"{name:<16} {label:<26} {read:<6} {_fmt(agg('mean_px', np.mean), 8)} "
                      f"{_fmt(agg('worst_px', np.max), 9)} {_fmt(agg('mean_proj_px', np.mean), 9)} "
                      f"{_fmt(agg('worst_proj_px', np.max), 10)} {min(r.n_measured for r in reps):>4}/{len(rep.checks):<3}  "
                      f"{'/'.join(sorted({'PASS' if r.passed else 'FAIL' for r in reps}))}", flush=True)
        rig.close()
    print()


def table_d(grid, effects=("projector_gamma", "camera_gamma", "all"), noise: bool = False):
    """The stroke's scale vs the neutral renderer's at the same pixels, per effect, levels and light;
    `noise`: the scenario's read and shot noise kept (else noise-free frames)."""
    from dataclasses import replace

    from calib.detection.response import parse_response
    from drivers.sim.rig import open_sim_rig
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", 0)
    full = sc.render
    neutral = full.photometrically_neutral()

    def run(settings, pixels, response):
        rig = open_sim_rig("nonoverlap-136", 0, quality="session", ideal=True, latency_ms=0.0,
                           **(settings if noise else settings.without_noise()).to_dict())
        try:
            rig.camera.start()
            rig.operator.request_pose("verification", None, 0)
            r = parse_response(rig.camera.response()) if response else None
            return verify(rig.camera, rig.projector, None, rig.ground_truth(), grid=grid, pixels=pixels, response=r)
        finally:
            rig.close()

    base = run(neutral, None, False)
    pixels = [c.pixel for c in base.checks]
    ref = np.array([c.scale or np.nan for c in base.checks])
    print(f"D. stroke scale vs the neutral renderer ({'with noise' if noise else 'noise-free'}, session quality, "
          f"136 deg rig, ground truth, "
          f"{len(pixels)} pixels); neutral: mean {base.mean_proj_px:.3f} projector px")
    print(f"{'effect':<18} {'frames':<6} {'scale vs neutral mean %':>23} {'worst %':>8} {'proj mean':>9} {'proj worst':>10}")
    for e in effects:
        st = full if e == "all" else replace(neutral, **{e: getattr(full, e)})
        for read in ("levels", "light"):
            rep = run(st, pixels, read == "light")
            sc_ = np.array([c.scale or np.nan for c in rep.checks])
            dev = 100.0 * np.abs(sc_ / ref - 1.0)
            print(f"{e:<18} {read:<6} {np.nanmean(dev):23.2f} {np.nanmax(dev):8.2f} {_fmt(rep.mean_proj_px, 9)} "
                  f"{_fmt(rep.worst_proj_px, 10)}", flush=True)
    print()


def ideal_distance(true, est, T_cam_board, u):
    """(camera px, projector px) a perfect detector measures at camera pixel u with the board at
    T_cam_board: the estimated curve drawn, lit by the true projector, seen by the true camera; and the
    true projector pixel of the board point u sees vs the estimated curve. NaN when unmeasurable."""
    q = epipolar_curve(est, u)
    if len(q) < 2:
        return np.nan, np.nan
    T_bp = invert_T(T_cam_board) @ true.T_cam_proj
    r = true.projector.rays(q) @ T_bp[:3, :3].T
    o = T_bp[:3, 3]
    Xb = o + (-o[2] / r[:, 2])[:, None] * r
    S = np.eye(4) if true.mirror is None else true.mirror.reflection()
    c = true.camera.project(transform_points(S @ T_cam_board, Xb))
    c = c[np.isfinite(c).all(axis=1)]
    ray = camera_ray(true, u)
    n, p0 = T_cam_board[:3, 2], T_cam_board[:3, 3]
    X = ray.origin + (n @ (p0 - ray.origin)) / (n @ ray.direction) * ray.direction
    qt = true.projector.project(transform_points(invert_T(true.T_cam_proj), X[None]))
    if len(c) < 2 or not true.projector.in_image(qt, 5)[0]:
        return np.nan, np.nan
    d = distance_to_polyline(u, c)
    if not d.interior[0]:
        return np.nan, np.nan
    return d.distance[0], distance_to_polyline(qt, q).distance[0]


def _board_pixels(rig, T, rect, cols=3, rows=3):
    """Camera pixels of a cols x rows grid of board points (cell centres) inside `rect` (board frame)."""
    x0, y0, x1, y1 = rect
    xs = x0 + (np.arange(cols) + 0.5) * (x1 - x0) / cols
    ys = y0 + (np.arange(rows) + 0.5) * (y1 - y0) / rows
    gx, gy = np.meshgrid(xs, ys)
    Xb = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    return rig.camera.project(transform_points(rig.S() @ T, Xb))


def table_b(noises, seeds, n_poses=5):
    from calib.errors import CalibrationError
    from calib.pipeline import calibrate_observations
    from calib.synthetic import make_session, observe
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", 0)
    rig, true = sc.rig, sc.ground_truth()
    poses = [sc.verification_pose_for(k) for k in range(n_poses)]
    x0, y0, _, y1 = sc.layout.outline
    rect = (x0, y0, sc.layout.blank_rect[2], y1)
    print(f"B. pipeline calibrations from noisy observations (136 deg rig, paper method), ideal detector, "
          f"{n_poses} verification poses x 4x3 pixels over the board")
    print(f"{'noise px':>8} {'seed':>4} {'cam mean':>8} {'cam worst':>9} {'proj mean':>9} {'proj worst':>10}  verdict")
    ss = make_session(rig, sc.layout, sc.pattern, per_position=4, seed=0)
    for noise in noises:
        for seed in seeds:
            try:
                est = calibrate_observations(observe(ss, noise_px=noise, seed=seed), method="paper")
            except CalibrationError as e:
                print(f"{noise:>8.2f} {seed:>4}  calibration failed: {e}")
                continue
            rows = []
            for T in poses:
                us = _board_pixels(rig, T, rect, 4, 3)
                for u in us:
                    rows.append(ideal_distance(true, est, T, u))
            d = np.array(rows)
            d = d[np.isfinite(d).all(axis=1)]
            mp, wp = d[:, 1].mean(), d[:, 1].max()
            verdict = "PASS" if mp <= DEFAULT_THRESHOLD_PX and wp <= 2 * DEFAULT_THRESHOLD_PX else "FAIL"
            print(f"{noise:>8.2f} {seed:>4} {d[:, 0].mean():8.3f} {d[:, 0].max():9.3f} {mp:9.3f} {wp:10.3f}  {verdict}"
                  f"   ({len(d)} pixels)")
    print()


def table_c(step_deg=15):
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", 0)
    true = sc.ground_truth()
    T = sc.verification_pose
    print("C. 0.5 deg rotations about axes in the projector's image plane (ideal detector, 136 deg verification "
          "pose, 3x3 blank-region pixels)")
    print(f"{'axis angle':>10} {'cam mean':>8} {'proj mean':>9} {'proj worst':>10}")
    us = _board_pixels(sc.rig, T, sc.layout.blank_rect)
    for a in range(0, 180, step_deg):
        axis = (np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0)
        est = perturbed(true, 0.5, axis)
        d = np.array([ideal_distance(true, est, T, u) for u in us])
        d = d[np.isfinite(d).all(axis=1)]
        print(f"{a:>9}d {d[:, 0].mean():8.3f} {d[:, 1].mean():9.3f} {d[:, 1].max():10.3f}")
    print()


def session_row(folder, grid):
    from calib.formats.session import SessionStore
    from calib.models.result import CalibrationResult
    from drivers.sim.rig import open_sim_rig

    man = SessionStore.open(folder).manifest
    st = man.rig.camera_settings
    from drivers.settle import apply_timing

    rig = open_sim_rig(st.get("scenario", "nonoverlap-136"), seed=int(st.get("seed", 0)), quality="live")
    rig.camera.start()
    rig.operator.request_pose("verification", None, 0)
    apply_timing(rig.camera, rig.projector, st)
    res = CalibrationResult.load_json(Path(folder) / "calibration.json")
    from calib.detection.response import parse_response, recorded_response

    response = recorded_response(st) or parse_response(rig.camera.response())  # as `procam verify` does
    for read, r in (("light", response), ("levels", None)):
        rep = verify(rig.camera, rig.projector, rig.operator, res, grid=grid, response=r)
        print(f"procam calibrate result of {folder} ({read}): {rep.summary()}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one scenario, fewer seeds")
    ap.add_argument("--session", default=None, help="a simulated, calibrated session to verify too")
    ap.add_argument("--tables", default="ABCD", help="which tables to print (default ABCD)")
    ap.add_argument("--ground-truth-only", action="store_true", help="table A: the ground truth rows only")
    ap.add_argument("--repeats", type=int, default=1, help="table A: checks per row (default 1)")
    ap.add_argument("--scenarios", nargs="+", default=None, help="table A: these scenarios")
    a = ap.parse_args(argv)
    t0 = time.time()
    grid = (4, 3)
    if "A" in a.tables:
        names = a.scenarios or (["nonoverlap-136"] if a.quick else
                                ["nonoverlap-136", "nonoverlap-90", "nonoverlap-180", "direct"])
        table_a(names, grid, PERTURBATIONS[:1] if a.ground_truth_only else PERTURBATIONS, repeats=a.repeats)
    if "B" in a.tables:
        table_b([0.1, 0.2, 0.3, 0.5, 1.0], [1] if a.quick else [1, 2, 3])
    if "C" in a.tables:
        table_c()
    if "D" in a.tables:
        table_d(grid)
        table_d(grid, noise=True)
    if a.session:
        session_row(a.session, grid)
    print(f"({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
