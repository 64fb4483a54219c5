"""Detection stage: ChArUco boards and projected patterns in camera images -> SessionObservations.

Entry function: `detect_session(store)`. Everything else is a pure function on numpy images.

Mirrored views (seen through the mirror) are detected in the horizontally flipped image and the points
are mapped back with x -> (W - 1) - x, so every returned pixel coordinate is in the ORIGINAL image
(pixel (0, 0) = centre of the top-left pixel). A failed detection is a `DetectionFailure` value with a
reason a person can read, never an exception.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from calib.boards import CharucoSpec
from calib.observations import (
    STEP_PROJECTOR,
    STEP_REAL_MIRROR,
    STEP_REAL_VIRTUAL,
    VIEW_MIRROR,
    BoardObservation,
    MirrorView,
    ProjectorView,
    SessionObservations,
    Skipped,
)
from calib.pattern import PatternSpec


@dataclass(frozen=True)
class DetectionFailure:
    """Why a detection failed, in plain words ("board not found", "pattern partial: 30 of 36 points")."""

    reason: str

    def __bool__(self) -> bool:  # a failure is falsy, so `if result:` reads naturally
        return False


# ---- helpers ---------------------------------------------------------------------------------------
def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.ndim != 2:
        raise ValueError(f"expected a grayscale or BGR image, got shape {np.shape(image)}")
    if img.dtype != np.uint8:
        if img.dtype == np.uint16:
            img = (img >> 8).astype(np.uint8)
        else:
            img = np.clip(img, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def _flip_x(pts: np.ndarray, width: int) -> np.ndarray:
    """x -> (W - 1) - x: the map between an image and its cv2.flip(img, 1)."""
    out = np.array(pts, float).reshape(-1, 2)
    out[:, 0] = (width - 1) - out[:, 0]
    return out


@lru_cache(maxsize=16)
def _charuco_detector(spec: CharucoSpec) -> cv2.aruco.CharucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # ChArUco corners are refined anyway
    cparams = cv2.aruco.CharucoParameters()
    cparams.tryRefineMarkers = True
    return cv2.aruco.CharucoDetector(spec.cv_board(), cparams, params)


# ---- the board ---------------------------------------------------------------------------------------
def detect_board(image: np.ndarray, spec: CharucoSpec, mirrored: bool, min_corners: int = 6):
    """ChArUco corners of `spec` in `image` (gray or BGR) -> BoardObservation | DetectionFailure.

    `mirrored`: the board is seen through the mirror; detect in the flipped image and map back."""
    gray = _gray(image)
    return _detect_board_gray(gray, spec, mirrored, min_corners)


def _detect_board_gray(gray: np.ndarray, spec: CharucoSpec, mirrored: bool, min_corners: int = 6):
    img = cv2.flip(gray, 1) if mirrored else gray
    corners, ids, marker_corners, marker_ids = _charuco_detector(spec).detectBoard(img)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    n = 0 if ids is None else len(ids)
    if n == 0 and n_markers == 0:
        return DetectionFailure("board not found")
    if n < min_corners:
        return DetectionFailure(f"only {n} ChArUco corners (need {min_corners})")
    corners = np.asarray(corners, float).reshape(-1, 2)
    ids = np.asarray(ids, int).reshape(-1)
    if mirrored:
        corners = _flip_x(corners, gray.shape[1])
    order = np.argsort(ids)
    return BoardObservation(ids[order], corners[order], mirrored)


def _board_homography(obs: BoardObservation, spec: CharucoSpec, width: int, flip: bool):
    """Homography board (x, y) -> pixels of the detection frame (flipped when `flip`), or None."""
    if obs is None or len(obs.ids) < 4:
        return None
    src = spec.corner_points()[obs.ids, :2]
    dst = _flip_x(obs.corners_px, width) if flip else np.asarray(obs.corners_px, float)
    H, _ = cv2.findHomography(src, dst, 0)
    return H


def _mask_board(gray: np.ndarray, H: np.ndarray, spec: CharucoSpec, fill: int) -> np.ndarray:
    """Paint the printed ChArUco area (plus a quarter square) with `fill`, so that its squares cannot be
    taken for pattern features."""
    w, h = spec.size
    m = spec.square_length * 0.25
    quad = np.array([[-m, -m], [w + m, -m], [w + m, h + m], [-m, h + m]], float)
    px = cv2.perspectiveTransform(quad.reshape(-1, 1, 2), H).reshape(-1, 2)
    if not np.all(np.isfinite(px)):
        return gray
    out = gray.copy()
    cv2.fillConvexPoly(out, np.round(px * 16).astype(np.int32), int(fill), cv2.LINE_8, 4)
    return out


# ---- the projected pattern ------------------------------------------------------------------------------
def _blob_params(min_area: float = 6.0, max_area: float = 4.0e4) -> cv2.SimpleBlobDetector_Params:
    p = cv2.SimpleBlobDetector_Params()
    p.blobColor = 255
    p.filterByColor = True
    p.minThreshold = 30
    p.maxThreshold = 230
    p.thresholdStep = 20
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 3
    p.filterByArea = True
    p.minArea = min_area
    p.maxArea = max_area
    p.filterByCircularity = True
    p.minCircularity = 0.5
    p.filterByInertia = True
    p.minInertiaRatio = 0.15
    p.filterByConvexity = True
    p.minConvexity = 0.8
    return p


@lru_cache(maxsize=4)
def _blob_detector(max_area: float):
    return cv2.SimpleBlobDetector_create(_blob_params(max_area=max_area))


def _asym_handedness(pts: np.ndarray, pattern: PatternSpec) -> float:
    """Sign of the orientation of the affine map from the pattern's local points to `pts`."""
    local = pattern.local_points()
    A, *_ = np.linalg.lstsq(np.column_stack([local, np.ones(len(local))]), pts, rcond=None)
    return float(np.linalg.det(A[:2, :2]))


def _reverse_rows(pts: np.ndarray, pattern: PatternSpec) -> np.ndarray:
    return pts.reshape(pattern.rows, pattern.cols, 2)[::-1].reshape(-1, 2)


def _refine_centroids(gray: np.ndarray, pts: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Intensity-weighted centroids (background subtracted) in a window around each blob."""
    out = pts.copy()
    H, W = gray.shape
    for k, ((x, y), r) in enumerate(zip(pts, radius)):
        R = int(np.ceil(r)) + 2
        x0, x1 = int(round(x)) - R, int(round(x)) + R + 1
        y0, y1 = int(round(y)) - R, int(round(y)) + R + 1
        if x0 < 0 or y0 < 0 or x1 > W or y1 > H:
            continue
        win = gray[y0:y1, x0:x1].astype(np.float64)
        ring = np.concatenate([win[0], win[-1], win[1:-1, 0], win[1:-1, -1]])
        bg = float(np.median(ring))
        wgt = win - bg
        wgt[wgt < 0] = 0
        s = wgt.sum()
        if s <= 0:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1]
        cx, cy = (wgt * xs).sum() / s, (wgt * ys).sum() / s
        if abs(cx - x) < r * 0.5 and abs(cy - y) < r * 0.5:
            out[k] = (cx, cy)
    return out


def _find_circles(gray: np.ndarray, pattern: PatternSpec):
    h, w = gray.shape
    det = _blob_detector(float(h * w) * 0.01)
    kps = det.detect(gray)
    n_need = pattern.n_points
    if len(kps) == 0:
        return DetectionFailure("pattern not found")
    cand = np.array([k.pt for k in kps], np.float32)
    ok, centres = cv2.findCirclesGrid(gray, pattern.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID,
                                      blobDetector=det)
    if not ok:
        ok, centres = cv2.findCirclesGrid(
            gray, pattern.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING,
            blobDetector=det)
    if not ok or centres is None:
        if len(cand) < n_need:
            return DetectionFailure(f"pattern partial: {len(cand)} of {n_need} points")
        return DetectionFailure("pattern not found")
    pts = np.asarray(centres, float).reshape(-1, 2)
    # radii of the matched keypoints, for the centroid refinement
    d = np.linalg.norm(cand[None, :, :] - pts[:, None, :].astype(np.float32), axis=2)
    sizes = np.array([k.size for k in kps])[np.argmin(d, axis=1)]
    pts = _refine_centroids(gray, pts, np.maximum(sizes / 2.0, 1.5))
    if _asym_handedness(pts, pattern) < 0:
        pts = _reverse_rows(pts, pattern)
    return pts


def _find_chessboard(gray: np.ndarray, pattern: PatternSpec):
    ok, corners = cv2.findChessboardCornersSB(gray, pattern.pattern_size, flags=cv2.CALIB_CB_ACCURACY)
    if not ok:
        ok, corners = cv2.findChessboardCorners(
            gray, pattern.pattern_size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return DetectionFailure("pattern not found")
        corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).astype(np.float32), (5, 5), (-1, -1),
                                   (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.001))
    pts = np.asarray(corners, float).reshape(-1, 2)
    return _order_chessboard(gray, pts, pattern)


def _order_chessboard(gray: np.ndarray, pts: np.ndarray, pattern: PatternSpec):
    """Put chessboard corners in PatternSpec order: same handedness as the drawn pattern, and the square
    diagonally before the first corner dark (as PatternSpec draws it)."""
    cols, rows = pattern.cols, pattern.rows
    grid = pts.reshape(rows, cols, 2)
    candidates = [grid, grid[::-1, ::-1], grid[::-1, :], grid[:, ::-1]]
    if cols == rows:
        candidates += [np.transpose(g, (1, 0, 2)) for g in candidates]
    best = None
    for g in candidates:
        p = g.reshape(-1, 2)
        if _asym_handedness(p, pattern) <= 0:
            continue
        ex = g[0, 1] - g[0, 0]
        ey = g[1, 0] - g[0, 0]
        dark = g[0, 0] - 0.5 * ex - 0.5 * ey  # square (0, 0): drawn black
        light = g[0, 0] + 0.5 * ex - 0.5 * ey  # square (0, 1): drawn white
        diff = _sample(gray, light) - _sample(gray, dark)
        if best is None or diff > best[0]:
            best = (diff, p)
    if best is None or best[0] <= 0:
        return DetectionFailure("pattern not found (chessboard orientation is ambiguous)")
    return best[1].copy()


def _sample(gray: np.ndarray, xy: np.ndarray) -> float:
    x, y = int(round(xy[0])), int(round(xy[1]))
    h, w = gray.shape
    x0, x1, y0, y1 = max(x - 1, 0), min(x + 2, w), max(y - 1, 0), min(y + 2, h)
    if x0 >= x1 or y0 >= y1:
        return 0.0
    return float(gray[y0:y1, x0:x1].mean())


def detect_pattern(image: np.ndarray, pattern: PatternSpec, mirrored: bool, board: BoardObservation | None = None,
                   board_spec: CharucoSpec | None = None):
    """The projected pattern in `image` -> (N, 2) camera pixels in PatternSpec.points_px order, or a
    DetectionFailure. `board` (with `board_spec`) masks the printed ChArUco area out of the search."""
    gray = _gray(image)
    return _detect_pattern_gray(gray, pattern, mirrored, board, board_spec)


def _detect_pattern_gray(gray, pattern, mirrored, board=None, board_spec=None):
    W = gray.shape[1]
    img = cv2.flip(gray, 1) if mirrored else gray
    if board is not None and board_spec is not None:
        H = _board_homography(board, board_spec, W, mirrored)
        if H is not None:
            fill = 0 if pattern.kind == "circles" else int(np.median(img))
            img = _mask_board(img, H, board_spec, fill)
    if pattern.kind == "circles":
        pts = _find_circles(img, pattern)
    else:
        pts = _find_chessboard(img, pattern)
    if isinstance(pts, DetectionFailure):
        return pts
    return _flip_x(pts, W) if mirrored else pts


# ---- mirror-calibration views ------------------------------------------------------------------------
def detect_real_virtual(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6):
    """A board seen directly (`real`) and in the mirror (`virtual`) in one image -> MirrorView."""
    gray = _gray(image)
    real = _detect_board_gray(gray, spec, False, min_corners)
    if isinstance(real, DetectionFailure):
        return DetectionFailure(f"real board: {real.reason}")
    virtual = _detect_board_gray(gray, spec, True, min_corners)
    if isinstance(virtual, DetectionFailure):
        return DetectionFailure(f"virtual board (in the mirror): {virtual.reason}")
    return MirrorView(capture_id, STEP_REAL_VIRTUAL, real, virtual)


def detect_real_mirror(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6):
    """A board lying on the mirror, seen directly -> MirrorView (real only)."""
    real = _detect_board_gray(_gray(image), spec, False, min_corners)
    if isinstance(real, DetectionFailure):
        return real
    return MirrorView(capture_id, STEP_REAL_MIRROR, real, None)


# ---- a whole session ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Job:
    capture_id: str
    image_path: str
    step: str
    mirrored: bool
    board: CharucoSpec
    pattern: PatternSpec | None
    camera_size: tuple[int, int]


def _run_job(job: _Job):
    """(capture_id, result) with result a BoardObservation/pattern tuple, MirrorView or DetectionFailure."""
    try:
        if not os.path.exists(job.image_path):
            return job.capture_id, DetectionFailure(f"image missing: {job.image_path}")
        gray = cv2.imread(job.image_path, cv2.IMREAD_GRAYSCALE)
        if gray is None:
            return job.capture_id, DetectionFailure(f"image unreadable: {job.image_path} cannot be decoded")
        h, w = gray.shape
        if (w, h) != tuple(job.camera_size):
            return job.capture_id, DetectionFailure(
                f"image is {w}x{h}, the session's camera is {job.camera_size[0]}x{job.camera_size[1]}")
        if job.step == STEP_REAL_VIRTUAL:
            return job.capture_id, detect_real_virtual(gray, job.board, job.capture_id)
        if job.step == STEP_REAL_MIRROR:
            return job.capture_id, detect_real_mirror(gray, job.board, job.capture_id)
        board = _detect_board_gray(gray, job.board, job.mirrored)
        if isinstance(board, DetectionFailure):
            return job.capture_id, board
        pts = _detect_pattern_gray(gray, job.pattern, job.mirrored, board, job.board)
        if isinstance(pts, DetectionFailure):
            return job.capture_id, pts
        return job.capture_id, (board, pts)
    except cv2.error as e:  # a pathological image must not stop the session
        msg = str(e).strip().splitlines()[-1] if str(e).strip() else "OpenCV error"
        return job.capture_id, DetectionFailure(f"detection failed: {msg}")


def _init_worker():
    cv2.setNumThreads(1)


def detect_session(store, workers: int = 2, progress=None) -> SessionObservations:
    """Detect every capture of a session (SessionStore) -> SessionObservations.

    Each image is read once; detection runs in `workers` processes (1 = inline). A capture whose image
    is missing or unreadable, or whose board/pattern is not found, is listed in `skipped` with the
    reason. `progress(done, total, capture_id)` is called after each capture."""
    m = store.manifest
    mirrored = m.rig.view == VIEW_MIRROR
    mboard = m.mirror_board or m.projector_board
    jobs = []
    for c in m.captures:
        board = m.projector_board if c.step == STEP_PROJECTOR else mboard
        jobs.append(_Job(c.id, str(store.image_path(c)), c.step, mirrored and c.step == STEP_PROJECTOR, board,
                         m.pattern if c.step == STEP_PROJECTOR else None, tuple(m.rig.camera_size)))
    results: dict[str, object] = {}
    total = len(jobs)
    if workers <= 1 or total <= 1:
        for i, job in enumerate(jobs):
            cid, res = _run_job(job)
            results[cid] = res
            if progress is not None:
                progress(i + 1, total, cid)
    else:
        with ProcessPoolExecutor(max_workers=min(workers, total), initializer=_init_worker) as ex:
            futures = [ex.submit(_run_job, job) for job in jobs]
            for i, fut in enumerate(as_completed(futures)):
                cid, res = fut.result()
                results[cid] = res
                if progress is not None:
                    progress(i + 1, total, cid)

    pviews, mviews, skipped = [], [], []
    for c in m.captures:
        res = results[c.id]
        if isinstance(res, DetectionFailure):
            skipped.append(Skipped(c.id, c.image, res.reason))
        elif c.step == STEP_PROJECTOR:
            board, pts = res
            pviews.append(ProjectorView(c.id, board, pts, c.pattern_points_px, c.pattern_position))
        else:
            mviews.append(res)
    return SessionObservations(
        camera_size=tuple(m.rig.camera_size), projector_size=tuple(m.rig.projector_size), view=m.rig.view,
        projector_board=m.projector_board, pattern=m.pattern, projector_views=tuple(pviews),
        mirror_board=m.mirror_board, mirror_views=tuple(mviews), board_thickness=m.board_thickness,
        skipped=tuple(skipped),
    )
