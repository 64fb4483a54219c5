"""Shared fixtures for the calibration-stage tests: synthetic sessions and their observations, cached
per process (building a session is deterministic and takes ~0.2 s)."""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import cv2
import numpy as np

from calib.models.observations import SessionObservations
from calib.quality.metrics import compare
from calib.synthetic import make_direct_rig, make_rig, make_session, observe


@lru_cache(maxsize=16)
def session(rig: str = "136", mirror_method: str = "real-virtual", per_position: int = 4, seed: int = 0,
            thickness_mm: float = 3.0):
    """rig: '90', '136', '180' (mirrored) or 'direct'."""
    r = make_direct_rig() if rig == "direct" else make_rig(float(rig))
    return make_session(r, mirror_method=None if rig == "direct" else mirror_method, per_position=per_position,
                        seed=seed, thickness_mm=thickness_mm)


@lru_cache(maxsize=32)
def observations(rig: str = "136", noise_px: float = 0.0, noise_seed: int = 0, mirror_method: str = "real-virtual",
                 per_position: int = 4, seed: int = 0, thickness_mm: float = 3.0) -> SessionObservations:
    return observe(session(rig, mirror_method, per_position, seed, thickness_mm), noise_px, noise_seed)


@lru_cache(maxsize=8)
def placements_observations(scenario: str, seed: int, placements: int, noise_px: float) -> SessionObservations:
    """A scenario's mirror views and its first `placements` projector placements in the structured step's
    order (calib.models.structured_light.placement_order), observed with `noise_px` of noise (circle
    centroids, noise seed `seed`)."""
    from calib.models.structured_light import placement_order
    from calib.synthetic import SyntheticSession
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario(scenario, seed)
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    poses = [(p, by_slot[p][k]) for p, k in placement_order(sc.pattern.positions, 4)[:placements]]
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, poses, sc.mirror_poses, sc.mirror_method,
                          sc.board_thickness_mm)
    return observe(ss, noise_px, seed, circle_centroids=True)


def metrics(result, rig: str = "136", mirror_method: str = "real-virtual", per_position: int = 4, seed: int = 0):
    return compare(result, session(rig, mirror_method, per_position, seed).rig.ground_truth())


def replace_obs(obs: SessionObservations, **changes) -> SessionObservations:
    return dataclasses.replace(obs, **changes)


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


# ---- a ray-cast renderer of synthetic sessions (for end-to-end tests through detection) -------------
# Every camera (super-)pixel's ray is traced into the scene of calib.synthetic: the mirror rectangle, the
# board (ChArUco area, white border, blank region) and the projector's light. Exact with both lens
# distortions; 2x2 supersampling then INTER_AREA for anti-aliased edges. A board seen through the
# mirror is found by intersecting the camera ray with the reflected board S T (behind the mirror).

AMBIENT, LIGHT, BACKGROUND = 0.55, 0.45, 40.0


@lru_cache(maxsize=2)
def _camera_rays(camera_key, k: int):
    camera = _CAMERAS[camera_key]
    ys, xs = np.mgrid[0 : camera.height * k, 0 : camera.width * k]
    uv = np.column_stack([(xs.ravel() + 0.5) / k - 0.5, (ys.ravel() + 0.5) / k - 0.5])
    return camera.rays(uv)


_CAMERAS: dict = {}


def _rays(camera, k):
    key = (camera.width, camera.height, tuple(np.round(camera.K.ravel(), 9)), tuple(np.round(camera.dist, 12)))
    _CAMERAS[key] = camera
    return _camera_rays(key, k)


def _plane_hit(rays, T):
    """Ray parameter t and board-frame hit points of camera rays with the z = 0 plane of T (cam<-board;
    T may be improper, e.g. a reflected board)."""
    Ti = np.linalg.inv(T)
    o = Ti[:3, 3]
    d = rays @ Ti[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[:, 2]
    X = o + t[:, None] * d
    return t, X


def _texture(spec, px_per_unit: float):
    img = spec.render(px_per_unit).astype(np.float32) / 255.0
    return np.clip(img, 0.04, 0.96)


def _sample(img, x, y, border):
    """Bilinear samples of `img` at (x, y) pixel coordinates (cv2.remap wants maps < 32767 rows)."""
    n = len(x)
    cols = 2048
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=border,
                    borderValue=0)
    return out.ravel()[:n]


def _albedo(X, spec, outline, tex, s):
    """Albedo at board points X (N, 3) of a board whose printed ChArUco area is `spec` (texture `tex`
    at `s` px per unit) inside `outline` (x0, y0, x1, y1); NaN outside the board."""
    x0, y0, x1, y1 = outline
    inside = (X[:, 0] >= x0) & (X[:, 0] <= x1) & (X[:, 1] >= y0) & (X[:, 1] <= y1)
    a = np.full(len(X), np.nan, np.float32)
    a[inside] = 0.96
    w, h = spec.size
    ch = inside & (X[:, 0] >= 0) & (X[:, 0] <= w) & (X[:, 1] >= 0) & (X[:, 1] <= h)
    if ch.any():
        a[ch] = _sample(tex, X[ch, 0] * s - 0.5, X[ch, 1] * s - 0.5, cv2.BORDER_REPLICATE)
    return a


def render_capture(ss, step: str, index: int, k: int = 2) -> np.ndarray:
    """8-bit grayscale camera image of capture `index` of `step` ("projector", "mirror")."""
    from calib.transforms import transform_points

    rig, cam = ss.rig, ss.rig.camera
    W, H = cam.width, cam.height
    S = rig.S()
    if step == "projector":
        spec = ss.layout.charuco
        outline = ss.layout.outline
        pos, T = ss.projector_T_cam_board[index]
        through_mirror = rig.mirror is not None
        proj_img, _ = ss.pattern.render(rig.projector.width, rig.projector.height, pos)
        proj_img = proj_img.astype(np.float32) / 255.0
    else:
        spec = ss.mirror_board
        m = spec.square_length / 2
        outline = (-m, -m, spec.size[0] + m, spec.size[1] + m)
        T = ss.mirror_T_cam_board[index]
        through_mirror = ss.mirror_method == "real-virtual"
        proj_img = None
    # trace only the rays of the image region the board (and its reflection) can cover
    x0, y0, x1, y1 = outline
    gx, gy = np.meshgrid(np.linspace(x0, x1, 9), np.linspace(y0, y1, 9))
    Xo = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    uv = [cam.project(transform_points(T, Xo))]
    if through_mirror:
        uv.append(cam.project(transform_points(S @ T, Xo)))
    uv = np.concatenate(uv)
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv):
        c0 = int(np.clip(np.floor(uv[:, 0].min()) - 12, 0, W))
        c1 = int(np.clip(np.ceil(uv[:, 0].max()) + 12, 0, W))
        r0 = int(np.clip(np.floor(uv[:, 1].min()) - 12, 0, H))
        r1 = int(np.clip(np.ceil(uv[:, 1].max()) + 12, 0, H))
    else:
        c0, c1, r0, r1 = 0, 0, 0, 0
    out = np.full((H, W), BACKGROUND, np.float32)
    if c1 <= c0 or r1 <= r0:
        return out.astype(np.uint8)
    rays = _rays(cam, k).reshape(H * k, W * k, 3)[r0 * k : r1 * k, c0 * k : c1 * k].reshape(-1, 3)
    img = np.full(len(rays), BACKGROUND, np.float32)
    mirror_t = None
    if rig.mirror is not None:
        n, d = rig.mirror.normal, rig.mirror.d
        with np.errstate(divide="ignore", invalid="ignore"):
            mirror_t = -d / (rays @ n)
        on = (mirror_t > 0) & rig.mirror_rect.contains(rays * mirror_t[:, None])
        mirror_t = np.where(on, mirror_t, np.inf)
    s = max(4.0, 160.0 / spec.square_length)
    tex = _texture(spec, s)
    t, X = _plane_hit(rays, T)
    a = _albedo(X, spec, outline, tex, s)
    hit = np.isfinite(a) & (t > 0)
    if mirror_t is not None:
        hit &= t < mirror_t
    img[hit] = _shade(a[hit], X[hit], T, rig, proj_img)
    if through_mirror and mirror_t is not None:
        tv, Xv = _plane_hit(rays, S @ T)
        av = _albedo(Xv, spec, outline, tex, s)
        hv = np.isfinite(av) & np.isfinite(mirror_t) & (tv > mirror_t) & ~hit
        img[hv] = _shade(av[hv], Xv[hv], T, rig, proj_img)
    big = img.reshape((r1 - r0) * k, (c1 - c0) * k)
    out[r0:r1, c0:c1] = cv2.resize(big, (c1 - c0, r1 - r0), interpolation=cv2.INTER_AREA) if k > 1 else big
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def _shade(albedo, Xb, T_cam_board, rig, proj_img):
    light = np.full(len(albedo), AMBIENT, np.float32)
    if proj_img is not None and len(Xb):
        from calib.transforms import invert_T, transform_points

        Xp = transform_points(invert_T(rig.T_cam_proj) @ T_cam_board, Xb)
        q = rig.projector.project(Xp).astype(np.float32)
        ok = np.isfinite(q).all(axis=1)
        p = np.zeros(len(Xb), np.float32)
        if ok.any():
            p[ok] = _sample(proj_img, q[ok, 0], q[ok, 1], cv2.BORDER_CONSTANT)
        light = light + LIGHT * p
    return 255.0 * albedo * light


def write_session(folder, ss, k: int = 2, projector_indices=None, mirror_indices=None):
    """Render a synthetic session into a session folder (SessionStore) and return the store."""
    from calib.formats.session import RigInfo, SessionManifest, SessionStore

    rig = ss.rig
    manifest = SessionManifest(
        rig=RigInfo(rig.camera.size, rig.projector.size, rig.view, driver="test-render"),
        projector_board=ss.layout.charuco, pattern=ss.pattern, mirror_board=ss.mirror_board,
        mirror_method=ss.mirror_method, board_thickness=float(ss.board_thickness_mm))
    store = SessionStore.create(folder, manifest)
    pidx = range(len(ss.projector_T_cam_board)) if projector_indices is None else projector_indices
    for i in pidx:
        pos, _ = ss.projector_T_cam_board[i]
        q = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)
        store.add_capture("projector", render_capture(ss, "projector", i, k), pos, q)
    if ss.mirror_method is not None:
        step = "mirror-real-virtual" if ss.mirror_method == "real-virtual" else "mirror-real-mirror"
        midx = range(len(ss.mirror_T_cam_board)) if mirror_indices is None else mirror_indices
        for i in midx:
            store.add_capture(step, render_capture(ss, "mirror", i, k))
    return store
