"""What the panel's 3D view shows, computed from the session and (once there is one) its calibration:
the camera, the mirror plane, the virtual camera, the captured board poses, the projector frustum and
its rays. Pure computation, in camera coordinates and board units; the panel scales to metres.

Before calibration the camera model is approximate (the device's, or a 90 deg guess) and the mirror is
unknown: boards seen through the mirror are drawn where the camera sees them, as virtual images behind
the mirror. Once calibrated they are reflected to where they physically were.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from calib.formats.session import Capture, SessionManifest
from calib.models.boards import MM_PER_UNIT
from calib.models.camera import CameraModel
from calib.models.observations import STEP_PROJECTOR, VIEW_MIRROR
from calib.models.result import CalibrationResult
from calib.transforms import FLIP_X, transform_points

UNIT_TO_M = {u: mm / 1000.0 for u, mm in MM_PER_UNIT.items()}


@dataclass(frozen=True, eq=False)
class Device:
    T_cam_dev: np.ndarray  # proper rigid transform (camera frame <- device)
    fov_v_rad: float
    aspect: float


@dataclass(frozen=True, eq=False)
class SceneBoard:
    """A captured board as the 3D view draws it: its pose and outline in the camera frame."""

    capture_id: str
    step: str
    T_cam_board: np.ndarray
    outline: np.ndarray  # (4, 3) corners of the printed ChArUco area, camera frame
    virtual: bool  # True: the board's image behind the mirror (mirror not known yet)


@dataclass(frozen=True, eq=False)
class RigScene:
    units: str
    camera: Device
    virtual_camera: Device | None = None
    mirror_quad: np.ndarray | None = None  # (4, 3)
    projector: Device | None = None
    boards: tuple[SceneBoard, ...] = ()
    rays: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))  # (N, 2, 3) projector rays

    @property
    def to_m(self) -> float:
        return UNIT_TO_M.get(self.units, 1e-3)


def device(model: CameraModel, T: np.ndarray) -> Device:
    return Device(np.asarray(T, float), float(2 * np.arctan2(model.height / 2.0, model.fy)),
                  float(model.width / model.height))


def capture_corners(cap: Capture) -> tuple[np.ndarray, np.ndarray] | None:
    """(ids, pixels) of the board corners the station detected when it took the capture."""
    ids, px = cap.meta.get("board_ids"), cap.meta.get("board_px")
    if ids is None or px is None:
        return None
    ids = np.asarray(ids, int).reshape(-1)
    px = np.asarray(px, float).reshape(-1, 2)
    if len(ids) != len(px) or len(ids) < 4:
        return None
    return ids, px


def solve_board(model: CameraModel, obj: np.ndarray, px: np.ndarray, mirrored: bool) -> np.ndarray | None:
    """T of the board from its corners: T_cam_board (direct) or T_V'_board (mirrored: flipped view)."""
    cam, pts = (model.flipped(), model.flip_points(px)) if mirrored else (model, px)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), pts.astype(np.float64), np.asarray(cam.K),
                                      np.asarray(cam.dist), flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return None
    if not ok:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = np.asarray(tvec, float).reshape(3)
    return T


def mirror_quad(model: CameraModel, S_normal: np.ndarray, d: float, shrink: float = 0.9) -> np.ndarray | None:
    """Where the camera's view (its image corners, shrunk a little) meets the mirror plane."""
    W, H = model.size
    cx, cy = (W - 1) / 2, (H - 1) / 2
    uv = np.array([[cx + s * shrink * (W / 2), cy + t * shrink * (H / 2)] for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    rays = model.rays(uv)
    den = rays @ S_normal
    if np.any(np.abs(den) < 1e-9):
        return None
    t = -d / den
    if np.any(t <= 0):
        return None
    return rays * t[:, None]


def rig_scene(manifest: SessionManifest, result: CalibrationResult | None, approx_camera: CameraModel) -> RigScene:
    units = manifest.units
    model = result.camera if result is not None else approx_camera
    scene_kw = {"units": units, "camera": device(model, np.eye(4))}
    S = None
    if result is not None and result.mirror is not None:
        S = result.mirror.reflection()
        T_v = S @ FLIP_X  # the virtual camera, made proper by the flip of its image
        scene_kw["virtual_camera"] = device(model, T_v)
        scene_kw["mirror_quad"] = mirror_quad(model, result.mirror.normal, result.mirror.d)
    if result is not None:
        scene_kw["projector"] = device(result.projector, result.T_cam_proj)
    mirrored_rig = manifest.rig.view == VIEW_MIRROR
    boards, rays = [], []
    for cap in manifest.captures:
        det = capture_corners(cap)
        if det is None:
            continue
        spec = manifest.projector_board if cap.step == STEP_PROJECTOR else (manifest.mirror_board or manifest.projector_board)
        ids, px = det
        keep = (ids >= 0) & (ids < spec.n_corners)
        ids, px = ids[keep], px[keep]
        if len(ids) < 4:
            continue
        mirrored = mirrored_rig and cap.step == STEP_PROJECTOR
        T = solve_board(model, spec.corner_points()[ids], px, mirrored)
        if T is None:
            continue
        virtual = False
        if mirrored:
            if S is not None:
                T = S @ FLIP_X @ T
            else:
                T = FLIP_X @ T  # the board's image in the mirror, where the camera sees it
                virtual = True
        w, h = spec.size
        outline = transform_points(T, np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float))
        boards.append(SceneBoard(cap.id, cap.step, T, outline, virtual))
        if result is not None and cap.step == STEP_PROJECTOR and not virtual and cap.pattern_points_px is not None:
            q = np.asarray(cap.pattern_points_px, float).mean(axis=0, keepdims=True)
            o = result.T_cam_proj[:3, 3]
            dvec = result.T_cam_proj[:3, :3] @ result.projector.rays(q)[0]
            n, p0 = T[:3, 2], T[:3, 3]
            den = dvec @ n
            if abs(den) > 1e-9:
                t = ((p0 - o) @ n) / den
                if t > 0:
                    rays.append([o, o + t * dvec])
    scene_kw["boards"] = tuple(boards)
    scene_kw["rays"] = np.array(rays, float).reshape(-1, 2, 3)
    return RigScene(**scene_kw)
