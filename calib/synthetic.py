"""Synthetic rigs with exact ground truth, and the observations they produce (no images).

Used by tests and benchmarks of every calibration stage, and by the simulated rig (drivers.sim), which
renders images of the same scenes. Lengths are in millimetres.

A mirrored rig (camera frame = world frame): the camera looks along +z at a mirror centred at
(0, 0, mirror_distance_mm). The projector's optical axis is rotated by `angle_deg` about the camera's y
axis (90, 136, 180: fields of view that do not overlap). The board, lit by the projector, is where the
camera's central ray lands after reflection, outside the camera's direct view.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import (
    STEP_REAL_MIRROR,
    STEP_REAL_VIRTUAL,
    VIEW_DIRECT,
    VIEW_MIRROR,
    BoardObservation,
    MirrorView,
    ProjectorView,
    SessionObservations,
)
from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult, MirrorPlane
from calib.transforms import invert_T, make_T, rays_to_board_plane, rotation_about, transform_points
from calib.models.vocab import LengthUnit, MirrorMethod, PatternKind


def d455_camera() -> CameraModel:
    """A RealSense D455-like colour camera: 1280x800, ~90 deg horizontal field of view."""
    return CameraModel(1280, 800, [[642.5, 0, 637.3], [0, 641.8, 402.6], [0, 0, 1]],
                       [-0.054, 0.062, 0.0006, -0.0004, -0.019])


def portable_projector(width: int = 1920, height: int = 1080) -> CameraModel:
    """A portable projector: throw ratio ~1.2, principal point shifted towards the bottom edge."""
    f = 1.2 * width
    return CameraModel(width, height, [[f, 0, (width - 1) / 2 + 0.012 * width], [0, f * 1.002, 0.93 * height],
                                       [0, 0, 1]], [0.021, -0.035, 0.0, 0.0, 0.0])


@dataclass(frozen=True, eq=False)
class BoardLayout:
    """A physical board: a ChArUco area (board frame origin at its top-left outer corner) and a blank
    region beside it, to the right, where the projected pattern lands (the paper's Fig. 8)."""

    charuco: CharucoSpec
    blank_width: float = 320.0
    gap: float = 20.0

    @property
    def blank_rect(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the blank region in board coordinates."""
        w, h = self.charuco.size
        x0 = w + self.gap
        return (x0, 0.0, x0 + self.blank_width, h)

    @property
    def blank_centre(self) -> np.ndarray:
        x0, y0, x1, y1 = self.blank_rect
        return np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])

    @property
    def outline(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the whole board, with a white border of half a square."""
        m = self.charuco.square_length / 2
        x0, y0, x1, y1 = self.blank_rect
        return (-m, -m, x1 + m, y1 + m)


@dataclass(frozen=True, eq=False)
class MirrorRect:
    """A finite planar mirror: centre, two in-plane unit axes, and its size (mm)."""

    centre: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size: tuple[float, float]

    def contains(self, X: np.ndarray) -> np.ndarray:
        D = np.asarray(X, float).reshape(-1, 3) - self.centre
        return (np.abs(D @ self.axis_u) <= self.size[0] / 2) & (np.abs(D @ self.axis_v) <= self.size[1] / 2)


@dataclass(frozen=True, eq=False)
class SyntheticRig:
    camera: CameraModel
    projector: CameraModel
    T_cam_proj: np.ndarray
    mirror: MirrorPlane | None
    mirror_rect: MirrorRect | None
    board_target: np.ndarray  # camera-frame point the projector-calibration poses are centred on
    projector_distance_mm: float
    angle_deg: float
    units: str = LengthUnit.MM

    @property
    def view(self) -> str:
        return VIEW_DIRECT if self.mirror is None else VIEW_MIRROR

    def ground_truth(self) -> CalibrationResult:
        return CalibrationResult(self.camera, self.projector, self.T_cam_proj, self.mirror, self.units,
                                 method="ground-truth")

    def S(self) -> np.ndarray:
        return np.eye(4) if self.mirror is None else self.mirror.reflection()


def make_rig(angle_deg: float = 136.0, camera: CameraModel | None = None, projector: CameraModel | None = None,
             mirror_distance_mm: float = 350.0, board_distance_mm: float = 750.0,
             projector_distance_mm: float = 950.0, mirror_size_mm=(620.0, 420.0),
             elevation_deg: float = 0.0) -> SyntheticRig:
    """A non-overlapping rig seen through a mirror (see the module docstring). `elevation_deg` turns the
    reflected central ray upwards (-y), so the boards are held higher than the camera: a projector with
    a strong lens shift, projecting upwards, then sits beside the camera instead of below it."""
    camera = camera or d455_camera()
    projector = projector or portable_projector()
    M = np.array([0.0, 0.0, mirror_distance_mm])
    phi = np.radians(60.0 + angle_deg / 2.0)
    e = np.radians(elevation_deg)
    r = np.array([np.sin(phi) * np.cos(e), -np.sin(e), np.cos(phi) * np.cos(e)])  # reflected central ray
    n = np.array([0.0, 0.0, 1.0]) - r
    n /= np.linalg.norm(n)
    n = -n if n @ (-M) < 0 else n  # towards the camera
    mirror = MirrorPlane(n, -n @ M)
    u = np.cross([0.0, 1.0, 0.0], n)
    u /= np.linalg.norm(u)
    rect = MirrorRect(M, u, np.cross(n, u), tuple(mirror_size_mm))
    B = M + board_distance_mm * r
    T_cam_proj = _place_projector(projector, B, angle_deg, projector_distance_mm)
    return SyntheticRig(camera, projector, T_cam_proj, mirror, rect, B, projector_distance_mm, angle_deg)


def make_direct_rig(camera: CameraModel | None = None, projector: CameraModel | None = None,
                    board_distance_mm: float = 1000.0, baseline_mm: float = 250.0) -> SyntheticRig:
    """The paper's control: camera and projector side by side, both seeing the board, no mirror."""
    camera = camera or d455_camera()
    projector = projector or portable_projector()
    B = np.array([0.0, 0.0, board_distance_mm])
    P = np.array([baseline_mm, 0.0, 0.0])
    ang = np.degrees(np.arctan2(-baseline_mm, board_distance_mm))
    T = _place_projector(projector, B, ang, np.linalg.norm(B - P))
    return SyntheticRig(camera, projector, T, None, None, B, float(np.linalg.norm(B - P)), 0.0)


def _place_projector(projector: CameraModel, target, yaw_deg: float, distance_mm: float) -> np.ndarray:
    R = rotation_about([0, 1, 0], yaw_deg) @ rotation_about([1, 0, 0], 4.0)
    centre_ray = projector.rays(np.array([[(projector.width - 1) / 2, (projector.height - 1) / 2]]))[0]
    P = np.asarray(target, float) - distance_mm * (R @ centre_ray)
    return make_T(R, P)


# ---- board poses ---------------------------------------------------------------------------------
def _frame_from_normal(face_out: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    z = -face_out / np.linalg.norm(face_out)
    x = x_hint - (x_hint @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _tilted(R: np.ndarray, rng, max_tilt_deg: float, min_tilt_deg: float = 0.0) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    axis = R[:, 0] * np.cos(a) + R[:, 1] * np.sin(a)
    return rotation_about(axis, rng.uniform(min_tilt_deg, max_tilt_deg)) @ R


def projector_poses(rig: SyntheticRig, layout: BoardLayout, pattern: PatternSpec, per_position: int = 4,
                    seed: int = 0, max_tilt_deg: float = 28.0) -> list[tuple[int, np.ndarray]]:
    """Board poses meeting the paper's protocol: for every pattern position, `per_position` poses that
    put the pattern on the board's blank region, tilted like a person would. [(position, T_cam_board)]."""
    rng = np.random.default_rng(seed)
    poses = []
    for pos in range(pattern.positions):
        for k in range(per_position):
            poses.append((pos, projector_pose(rig, layout, pattern, pos, rng, max_tilt_deg)))
    return poses


def projector_pose(rig: SyntheticRig, layout: BoardLayout, pattern: PatternSpec, position: int,
                   rng: np.random.Generator, max_tilt_deg: float = 28.0) -> np.ndarray:
    """One board pose (T_cam_board) for pattern `position`, drawn with `rng` (see projector_poses)."""
    proj, T_cp = rig.projector, rig.T_cam_proj
    P = T_cp[:3, 3]
    V = transform_points(rig.S(), np.zeros((1, 3)))[0]  # (virtual) camera centre
    q = pattern.points_px(proj.width, proj.height, position)
    ray = T_cp[:3, :3] @ proj.rays(q.mean(axis=0, keepdims=True))[0]
    for attempt in range(400):
        D = rig.projector_distance_mm * rng.uniform(0.85, 1.15)
        C = P + D * ray
        to_p = (P - C) / np.linalg.norm(P - C)
        to_v = (V - C) / np.linalg.norm(V - C)
        face = to_p + to_v
        R = _frame_from_normal(face, T_cp[:3, 0])
        R = _tilted(R, rng, max_tilt_deg, min_tilt_deg=8.0 if attempt < 200 else 0.0)
        # a person keeps the printed part in view: near the edges of the projector's field of
        # view the board is held turned by 180 degrees, the printed part towards the centre
        flip = 180.0 if (attempt % 2 == 1) else 0.0
        inplane = rotation_about(R[:, 2], rng.uniform(-10, 10) + flip)
        R = inplane @ R
        T = make_T(R, C - R @ layout.blank_centre)
        T[:3, 3] += R @ np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 0])
        if projector_pose_ok(rig, layout, pattern, position, T):
            return T
    raise RuntimeError(f"no valid board pose found for pattern position {position}")


def projector_pose_ok(rig, layout, pattern, pos, T_cam_board) -> bool:
    """Whether a board at T_cam_board is a valid placement for pattern position `pos`: the board's
    corners and the pattern (inside the blank area, with a margin) seen by the camera."""
    corners = transform_points(T_cam_board, layout.charuco.corner_points())
    if not _visible(rig, corners, T_cam_board):
        return False
    q = pattern.points_px(rig.projector.width, rig.projector.height, pos)
    Xb = projector_points_on_board(rig, T_cam_board, q)
    x0, y0, x1, y1 = layout.blank_rect
    m = pattern.spacing_px * 0.0 + 15.0
    if not (np.all(Xb[:, 0] > x0 + m) and np.all(Xb[:, 0] < x1 - m) and np.all(Xb[:, 1] > y0 + m)
            and np.all(Xb[:, 1] < y1 - m)):
        return False
    Xc = transform_points(T_cam_board, Xb)
    return _visible(rig, Xc, T_cam_board)


def held_pose(rig, layout, pattern, pos: int, T_cam_board: np.ndarray, deg: float, mm: float,
              rng: np.random.Generator, tries: int = 50) -> np.ndarray:
    """The pose a person holds when shown T_cam_board (an outline to follow): off by a rotation of `deg`
    degrees (1-sigma, about a random axis through the board's blank centre) and a shift of `mm` (1-sigma
    per axis), redrawn until it is a valid placement for pattern position `pos` (projector_pose_ok);
    T_cam_board itself when no draw is, or when both are 0."""
    T = np.asarray(T_cam_board, float)
    if deg == 0 and mm == 0:
        return T.copy()
    c = T[:3, :3] @ layout.blank_centre + T[:3, 3]
    for _ in range(tries):
        axis = rng.normal(size=3)
        R = rotation_about(axis / np.linalg.norm(axis), rng.normal(0.0, deg))
        H = make_T(R @ T[:3, :3], R @ (T[:3, 3] - c) + c + rng.normal(0.0, mm, 3))
        if projector_pose_ok(rig, layout, pattern, pos, H):
            return H
    return T.copy()


def _visible(rig: SyntheticRig, X_cam: np.ndarray, T_cam_board: np.ndarray, max_oblique_deg: float = 65.0) -> bool:
    """All points imaged inside the camera (through the mirror rectangle when there is one), with
    the board's face towards the (virtual) camera at an angle below `max_oblique_deg`."""
    S = rig.S()
    Xs = transform_points(S, X_cam)
    uv = rig.camera.project(Xs)
    if not np.all(rig.camera.in_image(uv, margin_px=8)):
        return False
    face_out = -T_cam_board[:3, 2]
    centre = X_cam.mean(axis=0)
    V = transform_points(S, np.zeros((1, 3)))[0]
    to_v = (V - centre) / np.linalg.norm(V - centre)
    if face_out @ to_v < np.cos(np.radians(max_oblique_deg)):
        return False
    if rig.mirror is not None:
        n, d = rig.mirror.normal, rig.mirror.d
        t = -d / (Xs @ n)  # camera ray to the virtual point meets the mirror at t * Xs
        if np.any(t <= 0) or np.any(t >= 1):
            return False
        if not np.all(rig.mirror_rect.contains(t[:, None] * Xs)):
            return False
        if np.any(rig.mirror.signed_distance(X_cam) <= 0):
            return False
    return True


def projector_points_on_board(rig: SyntheticRig, T_cam_board: np.ndarray, q_px: np.ndarray) -> np.ndarray:
    """Board-frame (z = 0) points lit by projector pixels `q_px` (exact, with projector distortion)."""
    return rays_to_board_plane(invert_T(T_cam_board) @ rig.T_cam_proj, rig.projector.rays(q_px))[0]


#: draws of a mirror placement before giving up, and before giving up when none was valid yet (over the
#: random rigs' family the first valid pose comes within 2500 draws whenever one comes at all)
MIRROR_POSE_TRIES = 20000
FIRST_MIRROR_POSE_WITHIN = 3000


def mirror_poses(rig: SyntheticRig, board: CharucoSpec, method: str, count: int = 7, seed: int = 0,
                 thickness_mm: float = 3.0) -> list[np.ndarray]:
    """T_cam_board of mirror-calibration placements. real-virtual: board between camera and mirror,
    seen directly and in the mirror, unoccluded; real-mirror: board lying on the mirror."""
    if rig.mirror is None:
        raise ValueError("a direct rig has no mirror to calibrate")
    rng = np.random.default_rng(seed)
    n, d = rig.mirror.normal, rig.mirror.d
    V = transform_points(rig.S(), np.zeros((1, 3)))[0]
    w, h = board.size
    centre_b = np.array([w / 2, h / 2, 0.0])
    poses = []
    for k in range(MIRROR_POSE_TRIES):
        if len(poses) == count:
            break
        if not poses and k == FIRST_MIRROR_POSE_WITHIN:
            break  # no valid pose in this many draws: the rig leaves none worth searching for
        if method == STEP_REAL_MIRROR or method == MirrorMethod.REAL_MIRROR:
            rect = rig.mirror_rect
            c = rect.centre + rect.axis_u * rng.uniform(-0.25, 0.25) * rect.size[0] \
                + rect.axis_v * rng.uniform(-0.25, 0.25) * rect.size[1] + n * thickness_mm
            R = _frame_from_normal(n, np.array([1.0, 0, 0]))
            R = rotation_about(R[:, 2], rng.uniform(-35, 35)) @ R
            T = make_T(R, c - R @ centre_b)
            if _real_mirror_ok(rig, board, T):
                poses.append(T)
            continue
        # real-virtual
        uv0 = np.array([[rng.uniform(0.15, 0.85) * rig.camera.width, rng.uniform(0.15, 0.85) * rig.camera.height]])
        ray = rig.camera.rays(uv0)[0]
        t_mirror = -d / (ray @ n)
        c = ray * t_mirror * rng.uniform(0.35, 0.75)
        face = rng.uniform(0.3, 1.0) * (-c / np.linalg.norm(c)) + rng.uniform(0.3, 1.0) * (V - c) / np.linalg.norm(V - c)
        R = _frame_from_normal(face, np.array([1.0, 0, 0]))
        R = _tilted(R, rng, 20.0)
        R = rotation_about(R[:, 2], rng.uniform(-30, 30)) @ R
        T = make_T(R, c - R @ centre_b)
        if _real_virtual_ok(rig, board, T):
            poses.append(T)
    if len(poses) < count:
        raise RuntimeError(f"found only {len(poses)} of {count} {method} mirror poses for this rig")
    return poses


def _real_mirror_ok(rig, board, T) -> bool:
    """A board lying on the mirror: its outline inside the mirror rectangle, its corners in the image."""
    w, h = board.size
    rect = rig.mirror_rect
    outline = transform_points(T, np.array([[0, 0, 0], [w, 0, 0], [0, h, 0], [w, h, 0]], float))
    D = outline - rect.centre
    inside = np.all(np.abs(D @ rect.axis_u) < rect.size[0] / 2) and np.all(np.abs(D @ rect.axis_v) < rect.size[1] / 2)
    return bool(inside and np.all(rig.camera.in_image(rig.camera.project(transform_points(T, board.corner_points())), 10)))


def held_mirror_pose(rig, board: CharucoSpec, method: str, T_cam_board: np.ndarray, deg: float, mm: float,
                     rng: np.random.Generator, thickness_mm: float = 3.0, tries: int = 50) -> np.ndarray:
    """The mirror-step pose a person holds when shown T_cam_board: as held_pose, about the board's
    centre, redrawn until valid for `method`. A board laid on the mirror (real-mirror) lies on the rig's
    own mirror, `thickness_mm` above it, whatever plane the pose shown was drawn on (an estimate of it):
    it turns about the mirror's normal and slides along it only."""
    T = np.asarray(T_cam_board, float).copy()
    w, h = board.size
    c = transform_points(T, np.array([[w / 2, h / 2, 0.0]]))[0]
    flat = method == STEP_REAL_MIRROR or method == MirrorMethod.REAL_MIRROR
    if flat:  # onto the true mirror: the face parallel to it, at the board's thickness
        n = np.asarray(rig.mirror.normal, float)
        z = T[:3, 2]
        axis = np.cross(z, -n)
        if np.linalg.norm(axis) > 1e-12:
            ang = np.degrees(np.arctan2(np.linalg.norm(axis), z @ -n))
            T[:3, :3] = rotation_about(axis, ang) @ T[:3, :3]
        c_on = c - (float(rig.mirror.signed_distance(c[None])[0]) - thickness_mm) * n
        T[:3, 3] = c_on - T[:3, :3] @ np.array([w / 2, h / 2, 0.0])
        c = c_on
    if deg == 0 and mm == 0:
        return T
    for _ in range(tries):
        if flat:
            R = rotation_about(T[:3, 2], rng.normal(0.0, deg))
            shift = T[:3, :2] @ rng.normal(0.0, mm, 2)
        else:
            axis = rng.normal(size=3)
            R = rotation_about(axis / np.linalg.norm(axis), rng.normal(0.0, deg))
            shift = rng.normal(0.0, mm, 3)
        H = make_T(R @ T[:3, :3], R @ (T[:3, 3] - c) + c + shift)
        if (_real_mirror_ok if flat else _real_virtual_ok)(rig, board, H):
            return H
    return T


def _real_virtual_ok(rig, board, T) -> bool:
    X = transform_points(T, board.corner_points())
    cam = rig.camera
    if not np.all(cam.in_image(cam.project(X), 10)):
        return False
    face_out = -T[:3, 2]
    c = X.mean(axis=0)
    if face_out @ (-c / np.linalg.norm(c)) < np.cos(np.radians(65)):
        return False
    if not _visible(rig, X, T):
        return False
    # the real board must not hide its own reflection: camera ray to each virtual corner vs board plane
    Xs = transform_points(rig.S(), X)
    T_b_c = invert_T(T)
    o = T_b_c[:3, 3]
    dirs = Xs @ T_b_c[:3, :3].T
    t = -o[2] / dirs[:, 2]
    hit = o + t[:, None] * dirs
    w, h = board.size
    blocked = (t > 0) & (t < 1) & (hit[:, 0] > -20) & (hit[:, 0] < w + 20) & (hit[:, 1] > -20) & (hit[:, 1] < h + 20)
    return not np.any(blocked)


# ---- observations --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SyntheticSession:
    rig: SyntheticRig
    layout: BoardLayout
    mirror_board: CharucoSpec | None
    pattern: PatternSpec
    projector_T_cam_board: list
    mirror_T_cam_board: list
    mirror_method: str | None
    board_thickness_mm: float = 0.0
    extras: dict = field(default_factory=dict)


def make_session(rig: SyntheticRig, layout: BoardLayout | None = None, pattern: PatternSpec | None = None,
                 mirror_board: CharucoSpec | None = None, mirror_method: str | None = MirrorMethod.REAL_VIRTUAL,
                 per_position: int = 4, mirror_count: int = 7, thickness_mm: float = 3.0,
                 seed: int = 0) -> SyntheticSession:
    layout = layout or BoardLayout(CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0, LengthUnit.MM))
    pattern = pattern or PatternSpec.default_for(rig.projector.width, rig.projector.height)
    poses = projector_poses(rig, layout, pattern, per_position, seed)
    mposes, method = [], None
    if rig.mirror is not None and mirror_method is not None:
        mirror_board = mirror_board or CharucoSpec(8, 6, "DICT_5X5_50", 22.0, 11.0, LengthUnit.MM)
        method = mirror_method
        mposes = mirror_poses(rig, mirror_board, method, mirror_count, seed + 1, thickness_mm)
    return SyntheticSession(rig, layout, mirror_board, pattern, poses, mposes, method,
                            thickness_mm if method == MirrorMethod.REAL_MIRROR else 0.0)


def observe(ss: SyntheticSession, noise_px: float = 0.0, seed: int = 0,
            circle_centroids: bool = False) -> SessionObservations:
    """Exact (or Gaussian-noised) observations of a synthetic session, as detection would report them.

    circle_centroids: report each projected circle (of a circle pattern) where a blob detector sees it,
    at the area centroid of its image (its boundary mapped point by point through the exact model),
    instead of at the image of its centre; the two differ by the perspective bias (docs/GEOMETRY.md)."""
    rng = np.random.default_rng(seed)
    rig, cam = ss.rig, ss.rig.camera
    S = rig.S()
    mirrored = rig.mirror is not None

    def noisy(uv):
        return uv + rng.normal(0, noise_px, uv.shape) if noise_px > 0 else uv

    pviews = []
    board = ss.layout.charuco
    for i, (pos, T) in enumerate(ss.projector_T_cam_board):
        X = transform_points(S @ T, board.corner_points())
        obs = BoardObservation(np.arange(board.n_corners), noisy(cam.project(X)), mirrored)
        q = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)
        Xb = projector_points_on_board(rig, T, q)
        uv = cam.project(transform_points(S @ T, Xb))
        if circle_centroids and ss.pattern.kind == PatternKind.CIRCLES:
            uv = imaged_circle_centroids(rig, T, q, ss.pattern.radius_px)
        pviews.append(ProjectorView(f"p{i:04d}", obs, noisy(uv), q, pos))
    mviews = []
    for i, T in enumerate(ss.mirror_T_cam_board):
        Xc = transform_points(T, ss.mirror_board.corner_points())
        ids = np.arange(ss.mirror_board.n_corners)
        real = BoardObservation(ids, noisy(cam.project(Xc)), False)
        if ss.mirror_method == MirrorMethod.REAL_VIRTUAL:
            virt = BoardObservation(ids, noisy(cam.project(transform_points(S, Xc))), True)
            mviews.append(MirrorView(f"mrv{i:04d}", STEP_REAL_VIRTUAL, real, virt))
        else:
            mviews.append(MirrorView(f"mrm{i:04d}", STEP_REAL_MIRROR, real, None))
    return SessionObservations(
        camera_size=cam.size, projector_size=rig.projector.size, view=rig.view, projector_board=board,
        pattern=ss.pattern, projector_views=tuple(pviews), mirror_board=ss.mirror_board,
        mirror_views=tuple(mviews), board_thickness=ss.board_thickness_mm,
    )


def imaged_circle_centroids(rig: SyntheticRig, T_cam_board: np.ndarray, q_px: np.ndarray, radius_px: float,
                            n_boundary: int = 256) -> np.ndarray:
    """(N, 2) area centroids, in the camera image, of circles of `radius_px` drawn by the projector
    around `q_px` on the board at T_cam_board (seen through the mirror when the rig has one)."""
    q = np.asarray(q_px, float).reshape(-1, 2)
    th = 2.0 * np.pi * np.arange(n_boundary) / n_boundary
    ring = radius_px * np.column_stack([np.cos(th), np.sin(th)])
    B = (q[:, None, :] + ring[None]).reshape(-1, 2)
    Xb = projector_points_on_board(rig, T_cam_board, B)
    uv = rig.camera.project(transform_points(rig.S() @ T_cam_board, Xb)).reshape(len(q), n_boundary, 2)
    x, y = uv[..., 0], uv[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    c = x * y1 - x1 * y
    a6 = 3.0 * c.sum(axis=1)
    return np.column_stack([((x + x1) * c).sum(axis=1) / a6, ((y + y1) * c).sum(axis=1) / a6])


# ---- a family of random, physically valid rigs (the trust check's property test) ----------------------
_CAMERA_SIZES = ((640, 480), (1280, 720), (1280, 800), (1920, 1080), (2448, 2048))
_PROJECTOR_SIZES = ((1280, 800), (1920, 1080), (1024, 768), (3840, 2160))


def random_session(seed: int, per_position: int = 1, mirror_count: int = 6) -> SyntheticSession:
    """A random rig of the family valid rigs are drawn from, with a session on it: a direct rig (camera
    and projector side by side, 0-60 deg between their axes, 5 cm to 3 m apart) or a mirrored one (60-180
    deg); cameras from 35 to 110 deg of horizontal field of view with distortion that does not fold the
    image; projectors from short throw (0.3) to long (2.2), lens shift up to 15% of the image beyond the
    bottom edge; boards of 20-80 mm squares held as close as the projector's throw puts the pattern on
    their blank area, tilted up to 20-45 deg. Deterministic in `seed`; a draw for which no session is
    possible (no board pose lights the blank area, no mirror placement seen twice) is drawn again."""
    from calib.quality.trust import radial_fold_fraction

    rng = np.random.default_rng([seed, 7707])
    for _ in range(200):
        cw, ch = _CAMERA_SIZES[rng.integers(len(_CAMERA_SIZES))]
        hfov = rng.uniform(35.0, 110.0)
        fx = (cw / 2) / np.tan(np.radians(hfov) / 2)
        k1 = rng.uniform(-0.25, 0.1) * (1.0 if hfov > 60 else 0.5)
        cam = CameraModel(cw, ch, [[fx, 0, (cw - 1) / 2 + rng.uniform(-0.03, 0.03) * cw],
                                   [0, fx * rng.uniform(0.997, 1.003), (ch - 1) / 2 + rng.uniform(-0.03, 0.03) * ch],
                                   [0, 0, 1]],
                          [k1, rng.uniform(-0.03, 0.08), rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), 0.0])
        pw, ph = _PROJECTOR_SIZES[rng.integers(len(_PROJECTOR_SIZES))]
        throw = rng.choice([rng.uniform(0.3, 0.6), rng.uniform(0.6, 2.2)])  # short-throw projectors too
        pf = throw * pw
        proj = CameraModel(pw, ph, [[pf, 0, (pw - 1) / 2 + rng.uniform(-0.05, 0.05) * pw],
                                    [0, pf * rng.uniform(0.998, 1.002), ph * rng.uniform(0.5, 1.15)], [0, 0, 1]],
                           [rng.uniform(-0.08, 0.08), rng.uniform(-0.05, 0.05), 0.0, 0.0, 0.0])
        if radial_fold_fraction(cam) is not None or radial_fold_fraction(proj) is not None:
            continue
        pattern = PatternSpec.default_for(pw, ph)
        extent_px = float(np.ptp(pattern.points_px(pw, ph, 0), axis=0).max()) + 2 * pattern.radius_px
        square = rng.uniform(20.0, 80.0)
        board = CharucoSpec(8, 6, "DICT_5X5_50", square, 0.5 * square, LengthUnit.MM)
        # the pattern covers about half the board's height at the board's distance from the projector
        D = rng.uniform(0.35, 0.6) * 6 * square * pf / extent_px
        layout = BoardLayout(board, blank_width=max(6 * square, 1.2 * D * extent_px / pf), gap=0.4 * square)
        try:
            if rng.uniform() < 0.35:
                # side by side: the board as far from the camera as from the projector, give or take
                a = np.radians(rng.uniform(0.5, 60.0))
                baseline = float(np.clip(D * np.sin(a), 50.0, 3000.0))
                dist_cam = float(np.sqrt(max(D * D - baseline * baseline, (0.3 * D) ** 2)))
                angle = float(np.degrees(np.arctan2(baseline, dist_cam)))
                rig = make_direct_rig(cam, proj, board_distance_mm=float(dist_cam), baseline_mm=baseline)
                mirror_board = None
            else:
                angle = rng.uniform(60.0, 180.0)
                mirror_d = rng.uniform(200.0, 900.0)
                rig = make_rig(angle, cam, proj, mirror_distance_mm=mirror_d,
                               board_distance_mm=rng.uniform(250.0, 1500.0), projector_distance_mm=float(D),
                               mirror_size_mm=(rng.uniform(400, 900), rng.uniform(300, 600)))
                ms = rng.uniform(12.0, 30.0)
                mirror_board = CharucoSpec(8, 6, "DICT_5X5_50", ms, 0.5 * ms, LengthUnit.MM)
            poses = projector_poses(rig, layout, pattern, per_position, int(rng.integers(1 << 30)),
                                    max_tilt_deg=float(rng.uniform(20.0, 45.0)))
            mposes, method = [], None
            if rig.mirror is not None:
                method = MirrorMethod.REAL_VIRTUAL if rng.uniform() < 0.7 else MirrorMethod.REAL_MIRROR
                mposes = mirror_poses(rig, mirror_board, method, mirror_count, int(rng.integers(1 << 30)), 3.0)
        except RuntimeError:
            continue
        return SyntheticSession(rig, layout, mirror_board, pattern, poses, mposes, method,
                                3.0 if method == MirrorMethod.REAL_MIRROR else 0.0,
                                extras={"seed": seed, "hfov_deg": float(hfov), "throw": float(throw),
                                        "angle_deg": float(angle),
                                        "baseline_mm": float(np.linalg.norm(rig.T_cam_proj[:3, 3]))})
    raise RuntimeError(f"no valid rig drawn for seed {seed}")
