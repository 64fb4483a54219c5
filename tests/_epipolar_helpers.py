"""Test helpers for the epipolar verification: synthetic camera frames of a projected stripe.

`stripe_frames` makes the three frames the verification captures (curve on, projector black, projector
white) of a flat scene: a board region with a checkerboard albedo (white/black squares, like the
printed ChArUco area) lit by the projector, ambient light, and Gaussian noise. The stripe's profile
across its centre line is a box of `width_px` blurred by a Gaussian of `blur_px`: symmetric, so its
true centre line is the given polyline exactly.
"""

from __future__ import annotations

import math

import numpy as np

from calib.epipolar import distance_to_polyline


def _erf(x):
    return np.vectorize(math.erf, otypes=[float])(x)


def stripe_profile(d, width_px, blur_px):
    a = (width_px / 2 - d) / (math.sqrt(2) * blur_px)
    b = (width_px / 2 + d) / (math.sqrt(2) * blur_px)
    return 0.5 * (_erf(a) + _erf(b))


def stripe_coverage(size, polyline, width_px=3.0, blur_px=0.8):
    w, h = size
    poly = np.asarray(polyline, float)
    cover = np.zeros((h, w))
    pad = width_px / 2 + 5 * blur_px + 2
    x0, y0 = np.floor(poly.min(axis=0) - pad).astype(int)
    x1, y1 = np.ceil(poly.max(axis=0) + pad).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    if x1 < x0 or y1 < y0:
        return cover
    yy, xx = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
    P = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    d = distance_to_polyline(P, poly).distance
    prof = np.zeros(len(P))
    near = d < pad
    prof[near] = stripe_profile(d[near], width_px, blur_px)
    cover[y0 : y1 + 1, x0 : x1 + 1] = prof.reshape(yy.shape)
    return cover


def checker_albedo(size, cell_px=40, angle_deg=20.0, white=0.85, black=0.04, region=None):
    """A rotated checkerboard albedo; outside `region` (x0, y0, x1, y1) a uniform grey wall."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    u, v = c * xx + s * yy, -s * xx + c * yy
    alb = np.where((np.floor(u / cell_px) + np.floor(v / cell_px)) % 2 == 0, white, black)
    if region is not None:
        x0, y0, x1, y1 = region
        inside = (xx >= x0) & (xx <= x1) & (yy >= y0) & (yy <= y1)
        alb = np.where(inside, alb, 0.3)
    return alb


def stripe_frames(size=(640, 400), polyline=None, width_px=3.0, blur_px=0.8, albedo=None, ambient=50.0,
                  gain=170.0, noise_dn=1.0, lit=None, seed=0):
    """(on, off, white) uint8 BGR frames. `lit`: bool mask of where the projector's light lands
    (default: everywhere)."""
    rng = np.random.default_rng(seed)
    w, h = size
    alb = np.full((h, w), 0.85) if albedo is None else albedo
    light = np.ones((h, w)) if lit is None else np.asarray(lit, float)
    cover = stripe_coverage(size, polyline, width_px, blur_px) if polyline is not None else np.zeros((h, w))

    def frame(proj):
        img = alb * (ambient + gain * proj * light) + rng.normal(0, noise_dn, (h, w))
        img = np.clip(np.round(img), 0, 255).astype(np.uint8)
        return np.repeat(img[:, :, None], 3, axis=2)

    return frame(cover), frame(np.zeros((h, w))), frame(np.ones((h, w)))


def make_sim_session(folder, scenario: str = "nonoverlap-136", seed: int = 0, calibration=None, driver: str = "sim"):
    """A session folder as a simulated station session leaves it, without captures: session.json whose
    rig names the simulated scenario, plus `calibration` (a CalibrationResult) as calibration.json."""
    from calib.formats.session import RigInfo, SessionManifest, SessionStore
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario(scenario, seed)
    settings = {"driver": driver, "scenario": scenario, "seed": seed} if driver == "sim" else {}
    manifest = SessionManifest(
        rig=RigInfo(sc.rig.camera.size, sc.rig.projector.size, sc.rig.view, settings, driver),
        projector_board=sc.projector_board, pattern=sc.pattern,
        mirror_board=sc.mirror_board if sc.mirror_method else None, mirror_method=sc.mirror_method,
        state={"simulated": True, "scenario": scenario, "seed": seed} if driver == "sim" else {},
    )
    SessionStore.create(folder, manifest)
    if calibration is not None:
        calibration.save_json(folder / "calibration.json")
    return sc
