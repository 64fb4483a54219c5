"""The simplest correct renderer of detection test images (until drivers/sim renders real scenes).

A physical board = the printed ChArUco area (board frame origin at its top-left outer corner) with a
white border and a blank white region to its right where the projector's pattern lands. A camera sees
it through a plane-to-image homography H_img_board (board units -> camera pixels, pixel (0, 0) the
centre of the top-left pixel). A mirrored view uses a homography that includes a reflection: the board
appears left-handed, as through a mirror.

Rendering is supersampled: the scene is warped into a k-times larger image whose pixel X covers camera
x = (X + 0.5) / k - 0.5, then box-filtered down (INTER_AREA), so edges are anti-aliased and every pixel
is the average of the scene over its footprint. Projected circles are rasterised analytically (each
supersample's projector coordinate tested against each circle), so a blob's intensity centroid is the
centre of the imaged conic (H^-T C H^-1), the ground truth for detection of the blob.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.models.boards import CharucoSpec
from calib.models.pattern import PatternSpec

#: horizontal flip of a W-wide image as a pixel homography: x -> (W - 1) - x
def flip_H(width: int) -> np.ndarray:
    return np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def apply_H(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.asarray(pts, float).reshape(-1, 2)
    q = np.column_stack([p, np.ones(len(p))]) @ np.asarray(H, float).T
    return q[:, :2] / q[:, 2:3]


def homography_from_pose(K: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """Board plane (z = 0) -> pixels of a distortion-free camera K; T may be improper (a mirror view)."""
    T = np.asarray(T_cam_board, float)
    return np.asarray(K, float) @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])


def board_homography(width: int, height: int, spec: CharucoSpec, centre=None, scale_px: float | None = None,
                     angle_deg: float = 0.0, tilt: tuple[float, float] = (0.0, 0.0), mirrored: bool = False,
                     blank_width: float | None = None) -> np.ndarray:
    """A simple board -> image homography: the whole board (ChArUco + blank region) centred at `centre`
    with ~`scale_px` pixels per board unit, rotated by `angle_deg`, with perspective `tilt` (g, h terms,
    per board unit). `mirrored` composes the image flip (a mirror view of the same scene)."""
    bw = spec.size[0] + (blank_width if blank_width is not None else 0.8 * spec.size[0]) + spec.square_length * 0.5
    bh = spec.size[1]
    if scale_px is None:
        scale_px = 0.55 * width / bw
    if centre is None:
        centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    C = np.array([[1, 0, -bw / 2], [0, 1, -bh / 2], [0, 0, 1]], float)
    P = np.array([[1, 0, 0], [0, 1, 0], [tilt[0] / bw, tilt[1] / bh, 1]], float)
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    S = np.diag([scale_px, scale_px, 1.0])
    Tr = np.array([[1, 0, centre[0]], [0, 1, centre[1]], [0, 0, 1]], float)
    H = Tr @ S @ R @ P @ C
    if mirrored:
        H = flip_H(width) @ H
    return H


@dataclass
class Scene:
    """What a test image shows, with its ground truth."""

    image: np.ndarray
    corners_px: np.ndarray  # (n_corners, 2) every ChArUco corner, by id (may fall outside the image)
    pattern_px: np.ndarray | None = None  # (N, 2) imaged-conic centres (circles) / corners (chessboard)
    pattern_point_px: np.ndarray | None = None  # (N, 2) images of the projector points themselves


def board_texture(spec: CharucoSpec, px_per_unit: float, blank_width: float, border: float, legacy: bool = False):
    """(texture uint8, A) where A maps texture pixels to board coordinates. `legacy`: the layout OpenCV
    < 4.6 printed for boards with an even number of rows."""
    s = px_per_unit
    if legacy:
        b = cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_length, spec.marker_length,
                                   spec.cv_board().getDictionary())
        b.setLegacyPattern(True)
        size = (int(round(spec.size[0] * s)), int(round(spec.size[1] * s)))
        tex_charuco = b.generateImage(size, marginSize=0, borderBits=1)
    else:
        tex_charuco = spec.render(s)
    b = int(round(border * s))
    bw = int(round(blank_width * s))
    h, w = tex_charuco.shape
    tex = np.full((h + 2 * b, w + 2 * b + bw + b), 255, np.uint8)
    tex[b : b + h, b : b + w] = tex_charuco
    # texture pixel (u, v) centre is board ((u + 0.5 - b) / s, (v + 0.5 - b) / s)
    A = np.array([[1 / s, 0, (0.5 - b) / s], [0, 1 / s, (0.5 - b) / s], [0, 0, 1]])
    return tex, A


def _super(H_img_x: np.ndarray, k: int) -> np.ndarray:
    D = np.array([[k, 0, (k - 1) / 2.0], [0, k, (k - 1) / 2.0], [0, 0, 1]], float)
    return D @ H_img_x


def render_board_scene(width: int, height: int, spec: CharucoSpec, H_img_board: np.ndarray,
                       pattern: PatternSpec | None = None, H_board_proj: np.ndarray | None = None,
                       proj_size=(1920, 1080), position: int = 0, supersample: int = 4,
                       blank_width: float | None = None, noise_px: float = 0.0, seed: int = 0,
                       ambient: float = 0.35, background: float = 0.12, colour: bool = False,
                       extra_light: np.ndarray | None = None, legacy: bool = False) -> Scene:
    """Render a camera image of the board lit by the projector showing `pattern` at `position`.

    Camera intensity = albedo * (ambient + (1 - ambient) * projector light), albedo from the board's
    texture (white paper 0.92, black ink 0.06); background outside the board. `H_board_proj` maps
    projector pixels to board coordinates (None: no pattern)."""
    k = supersample
    blank = blank_width if blank_width is not None else 0.8 * spec.size[0]
    border = spec.square_length * 0.25
    img_per_unit = _scale_of(H_img_board, spec)
    s = max(2.0, np.ceil(1.5 * k * img_per_unit))
    # integer number of texture pixels per square
    s = np.ceil(s * spec.square_length) / spec.square_length
    tex, A = board_texture(spec, s, blank, border, legacy)
    albedo_tex = (0.06 + (0.92 - 0.06) * tex.astype(np.float32) / 255.0)
    Hs = _super(H_img_board @ A, k)
    W2, H2 = width * k, height * k
    albedo = cv2.warpPerspective(albedo_tex, Hs, (W2, H2), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=-1.0)
    outside = albedo < 0
    light = np.full((H2, W2), ambient, np.float32)
    pattern_px = pattern_point_px = None
    if pattern is not None and H_board_proj is not None:
        H_img_proj = H_img_board @ H_board_proj
        lit = _render_projection(pattern, proj_size, position, _super(H_img_proj, k), (W2, H2))
        light += (1.0 - ambient) * lit
        q = pattern.points_px(proj_size[0], proj_size[1], position)
        pattern_point_px = apply_H(H_img_proj, q)
        if pattern.kind == "circles":
            pattern_px = np.array([conic_centre(H_img_proj, c, pattern.radius_px) for c in q])
        else:
            pattern_px = pattern_point_px.copy()
    if extra_light is not None:
        light += cv2.resize(extra_light.astype(np.float32), (W2, H2), interpolation=cv2.INTER_NEAREST)
    img = albedo * light
    img[outside] = background
    img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA) * 255.0
    if noise_px > 0:
        img = img + np.random.default_rng(seed).normal(0, noise_px, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    if colour:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    corners = apply_H(H_img_board, spec.corner_points()[:, :2])
    return Scene(img, corners, pattern_px, pattern_point_px)


def _scale_of(H: np.ndarray, spec: CharucoSpec) -> float:
    """Largest pixels-per-board-unit of H over the board's ChArUco area."""
    w, h = spec.size
    pts = np.array([[0, 0], [w, 0], [0, h], [w, h]], float)
    d = 1e-3 * spec.square_length
    s = 0.0
    for p in pts:
        a = apply_H(H, np.array([p, p + [d, 0], p + [0, d]]))
        s = max(s, np.linalg.norm(a[1] - a[0]) / d, np.linalg.norm(a[2] - a[0]) / d)
    return s


def _render_projection(pattern: PatternSpec, proj_size, position: int, H_super_proj: np.ndarray, size) -> np.ndarray:
    """Projector light (0..1) in the supersampled camera image."""
    W2, H2 = size
    pw, ph = proj_size
    if pattern.kind == "chessboard":
        img, _ = pattern.render(pw, ph, position)
        # squares lie on projector pixel boundaries: nearest sampling at supersample density is exact
        return cv2.warpPerspective(img.astype(np.float32) / 255.0, H_super_proj, (W2, H2), flags=cv2.INTER_NEAREST,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    out = np.zeros((H2, W2), np.float32)
    Hinv = np.linalg.inv(H_super_proj)
    r = pattern.radius_px
    for c in pattern.points_px(pw, ph, position):
        box = np.array([[c[0] - r, c[1] - r], [c[0] + r, c[1] - r], [c[0] + r, c[1] + r], [c[0] - r, c[1] + r]])
        b = apply_H(H_super_proj, box)
        x0, y0 = np.floor(b.min(axis=0)).astype(int) - 1
        x1, y1 = np.ceil(b.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W2), min(y1, H2)
        if x0 >= x1 or y0 >= y1:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1]
        q = apply_H(Hinv, np.column_stack([xs.ravel(), ys.ravel()]).astype(float))
        inside = ((q[:, 0] - c[0]) ** 2 + (q[:, 1] - c[1]) ** 2 <= r * r).reshape(ys.shape)
        out[y0:y1, x0:x1] = np.maximum(out[y0:y1, x0:x1], inside.astype(np.float32))
    return out


def conic_centre(H: np.ndarray, centre, radius: float) -> np.ndarray:
    """Centre of the image, under homography H, of the circle (centre, radius): H^-T C H^-1."""
    cx, cy = centre
    C = np.array([[1, 0, -cx], [0, 1, -cy], [-cx, -cy, cx * cx + cy * cy - radius * radius]], float)
    Hi = np.linalg.inv(H)
    Q = Hi.T @ C @ Hi
    return np.linalg.solve(Q[:2, :2], -Q[:2, 2])


def blank_region_proj_homography(spec: CharucoSpec, pattern: PatternSpec, proj_size, position: int,
                                 blank_width: float | None = None, fill: float = 0.7,
                                 angle_deg: float = 0.0, tilt=(0.0, 0.0)) -> np.ndarray:
    """H_board_proj that lands the pattern at `position` in the middle of the blank region, filling
    `fill` of its height, with an optional rotation and perspective (a projector seen obliquely)."""
    blank = blank_width if blank_width is not None else 0.8 * spec.size[0]
    q = pattern.points_px(proj_size[0], proj_size[1], position)
    qc = (q.min(axis=0) + q.max(axis=0)) / 2
    ext = q.max(axis=0) - q.min(axis=0) + 2 * max(pattern.radius_px, pattern.spacing_px if pattern.kind != "circles" else 0)
    scale = min(fill * spec.size[1] / ext[1], fill * blank / ext[0])
    target = np.array([spec.size[0] + spec.square_length * 0.25 + blank / 2, spec.size[1] / 2])
    a = np.radians(angle_deg)
    M = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    P = np.array([[1, 0, 0], [0, 1, 0], [tilt[0] / ext[0], tilt[1] / ext[1], 1]], float)
    C = np.array([[1, 0, -qc[0]], [0, 1, -qc[1]], [0, 0, 1]], float)
    H = P @ M @ np.diag([scale, scale, 1.0]) @ C
    # keep the pattern centre where it was meant to be after the perspective term
    c = apply_H(H, qc[None])[0]
    return np.array([[1, 0, target[0] - c[0]], [0, 1, target[1] - c[1]], [0, 0, 1]]) @ H


def synthetic_homographies(ss, index: int):
    """(H_img_board, H_board_proj, position) of projector capture `index` of a calib.synthetic session,
    for distortion-free camera and projector (homographies cannot carry lens distortion). For a mirrored
    rig H_img_board contains the reflection S: the board is imaged left-handed, as through the mirror."""
    from calib.transforms import invert_T

    rig = ss.rig
    pos, T = ss.projector_T_cam_board[index]
    H_img_board = homography_from_pose(rig.camera.K, rig.S() @ T)
    T_proj_board = invert_T(rig.T_cam_proj) @ T
    H_proj_board = homography_from_pose(rig.projector.K, T_proj_board)
    return H_img_board, np.linalg.inv(H_proj_board), pos


def pinhole_rig(angle_deg: float = 136.0):
    """calib.synthetic.make_rig with distortion-free camera and projector (so homographies are exact)."""
    from calib.synthetic import d455_camera, make_rig, portable_projector

    cam, proj = d455_camera(), portable_projector()
    return make_rig(angle_deg, camera=cam.with_params(dist=np.zeros(5)), projector=proj.with_params(dist=np.zeros(5)))
