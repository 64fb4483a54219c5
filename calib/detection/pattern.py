"""Projected patterns (circle grids, chessboards) in camera images: entry `detect_pattern(image, pattern,
mirrored, board, board_spec)` -> (N, 2) camera pixels in PatternSpec.points_px order, or DetectionFailure.

A mirrored view is detected in the horizontally flipped image and mapped back (x -> (W - 1) - x); with
the board found in the same image, its printed area is masked out and the search kept near it.
"""

from __future__ import annotations

import cv2
import numpy as np

from calib.detection.imaging import (
    SUBPIX_CRITERIA,
    flip_x,
    map_board,
    per_thread,
    to_gray,
)
from calib.detection.response import CameraResponse
from calib.models.boards import CharucoSpec
from calib.models.observations import BoardObservation, DetectionFailure
from calib.models.pattern import PatternSpec
from calib.models.vocab import PatternKind


def _board_homography(obs: BoardObservation, spec: CharucoSpec, width: int, flip: bool):
    """Homography board (x, y) -> pixels of the detection frame (flipped when `flip`), or None."""
    if obs is None or len(obs.ids) < 4:
        return None
    src = spec.corner_points()[obs.ids, :2]
    dst = flip_x(obs.corners_px, width) if flip else np.asarray(obs.corners_px, float)
    H, _ = cv2.findHomography(src, dst, 0)
    return H

def _mask_board(gray: np.ndarray, H: np.ndarray, spec: CharucoSpec, fill: int) -> np.ndarray:
    """Paint the printed ChArUco area (plus a quarter square) with `fill`, so that its squares cannot be
    taken for pattern features."""
    w, h = spec.size
    m = spec.square_length * 0.25
    px = map_board(H, [[-m, -m], [w + m, -m], [w + m, h + m], [-m, h + m]])
    if px is None or not np.all(np.isfinite(px)):
        return gray
    out = gray.copy()
    cv2.fillConvexPoly(out, np.round(px * 16).astype(np.int32), int(fill), cv2.LINE_8, 4)
    return out


def _mask_corner_hull(gray: np.ndarray, corners: np.ndarray, fill: int) -> np.ndarray:
    """Without the board's spec: paint the hull of its detected corners, grown by about one square
    (the median distance between neighbouring corners), with `fill`."""
    pts = np.asarray(corners, float)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    d[np.arange(len(pts)), np.arange(len(pts))] = np.inf
    step = float(np.median(d.min(axis=1)))
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(float)
    c = hull.mean(axis=0)
    r = np.linalg.norm(hull - c, axis=1, keepdims=True)
    grown = c + (hull - c) * (r + 1.25 * step) / np.maximum(r, 1e-9)
    out = gray.copy()
    cv2.fillConvexPoly(out, np.round(grown * 16).astype(np.int32), int(fill), cv2.LINE_8, 4)
    return out


def _search_roi(shape, H: np.ndarray | None, spec: CharucoSpec | None, reach: float = 1.6):
    """(x0, y0, x1, y1): where on the board's plane a projected pattern can be: the ChArUco area grown by
    `reach` times its size on every side, clipped to the image (whole image when unknown)."""
    h, w = shape
    full = (0, 0, w, h)
    if H is None or spec is None:
        return full
    bw, bh = spec.size
    quad = [[-reach * bw, -reach * bh], [(1 + reach) * bw, -reach * bh], [(1 + reach) * bw, (1 + reach) * bh],
            [-reach * bw, (1 + reach) * bh]]
    px = map_board(H, quad)
    if px is None or not np.all(np.isfinite(px)):
        return full
    x0, y0 = np.floor(px.min(axis=0)).astype(int)
    x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return full
    return (x0, y0, x1, y1)


# ---- the projected pattern ------------------------------------------------------------------------------
def _blob_params(max_area: float) -> cv2.SimpleBlobDetector_Params:
    """Bright, roughly elliptic blobs (projected circles seen at up to ~70 degrees)."""
    p = cv2.SimpleBlobDetector_Params()
    p.blobColor = 255
    p.filterByColor = True
    p.minThreshold = 40
    p.maxThreshold = 220
    p.thresholdStep = 30
    p.minRepeatability = 2
    p.minDistBetweenBlobs = 2
    p.filterByArea = True
    p.minArea = 5
    p.maxArea = max_area
    p.filterByCircularity = True
    p.minCircularity = 0.45
    p.filterByInertia = True
    p.minInertiaRatio = 0.12
    p.filterByConvexity = True
    p.minConvexity = 0.8
    return p


@per_thread
def _blob_detector(max_area: int):
    return cv2.SimpleBlobDetector_create(_blob_params(float(max_area)))


@per_thread
def _dot_detector():
    """Finds the dots of a clean binary image in one threshold pass (the grid finder's input)."""
    p = cv2.SimpleBlobDetector_Params()
    p.blobColor = 255
    p.minThreshold = 127
    p.maxThreshold = 129
    p.thresholdStep = 10
    p.minRepeatability = 1
    p.minDistBetweenBlobs = 1
    p.filterByArea = False
    p.filterByCircularity = False
    p.filterByInertia = False
    p.filterByConvexity = False
    return cv2.SimpleBlobDetector_create(p)


def _asym_handedness(pts: np.ndarray, pattern: PatternSpec) -> float:
    """Sign of the orientation of the affine map from the pattern's local points to `pts`."""
    local = pattern.local_points()
    A, *_ = np.linalg.lstsq(np.column_stack([local, np.ones(len(local))]), pts, rcond=None)
    return float(np.linalg.det(A[:2, :2]))


def _reverse_rows(pts: np.ndarray, pattern: PatternSpec) -> np.ndarray:
    return pts.reshape(pattern.rows, pattern.cols, 2)[::-1].reshape(-1, 2).copy()


def _stretch(img: np.ndarray) -> np.ndarray:
    """Contrast stretch (0.5 / 99.8 percentiles) so that fixed blob thresholds suit dim images."""
    sample = img[:: max(1, img.shape[0] // 200), :: max(1, img.shape[1] // 200)]
    lo, hi = np.percentile(sample, (0.5, 99.8))
    hi = max(hi, float(img.max()) * 0.9)
    if hi - lo < 8:
        return img
    lut = np.clip((np.arange(256, dtype=np.float32) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    return cv2.LUT(img, lut)


def _local_contrast(crop: np.ndarray) -> np.ndarray:
    """Bright detail above the local background, stretched to 0..255: projected circles on a lit board
    are often only a little brighter than the board, which a global threshold cannot separate."""
    sm = cv2.GaussianBlur(crop, (0, 0), 1.0)
    k = int(max(31, min(crop.shape) // 6)) | 1
    diff = cv2.subtract(sm, cv2.blur(crop, (k, k)))  # saturates at 0
    return _stretch(diff)


def _refine_centroids(gray: np.ndarray, pts: np.ndarray, radius: np.ndarray, lut: np.ndarray | None = None) -> np.ndarray:
    """Intensity-weighted centroid of each blob in a disc that excludes its neighbours; the background
    (the median of the disc's rim, sloped as the background around all the blobs) is subtracted. On
    anti-aliased blobs this is the blob's area centroid. `lut` (256 levels -> light, the inverse of the
    camera's recorded tone curve, calib.detection.response) weighs pixels by the light they received."""
    n = len(pts)
    if n == 0:
        return pts.copy()
    h, w = gray.shape
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    d[np.arange(n), np.arange(n)] = np.inf
    nn = d.min(axis=1) if n > 1 else np.full(n, np.inf)
    R = np.minimum(1.35 * radius + 2.0, nn - 1.15 * radius)
    R = np.maximum(R, radius + 0.75)
    Ri = int(np.ceil(R.max()))
    off = np.arange(-Ri, Ri + 1)
    xi = np.round(pts[:, 0]).astype(int)
    yi = np.round(pts[:, 1]).astype(int)
    inside_img = (xi - Ri >= 0) & (yi - Ri >= 0) & (xi + Ri < w) & (yi + Ri < h)
    out = pts.copy()
    if not inside_img.any():
        return out
    sel = np.nonzero(inside_img)[0]
    X = xi[sel, None, None] + off[None, None, :]  # (m, 1, k)
    Y = yi[sel, None, None] + off[None, :, None]  # (m, k, 1)
    # weights in light, not in encoded levels, when the camera's response is known: a tone curve reshapes
    # a blurred circle's profile, and noise in the dark toe is amplified, which the positive-part clip below
    # turns into a pull towards the window's centre (docs/DETECTION.md, "The camera's tone curve")
    win = gray[Y, X].astype(np.float64) if lut is None else lut[gray[Y, X]]  # (m, k, k)
    rr = np.hypot(X - pts[sel, 0, None, None], Y - pts[sel, 1, None, None])
    Rs = R[sel, None, None]
    inside = rr <= Rs
    rim = inside & (rr > Rs - 1.5)
    # the background under each blob is its rim's level plus the local slope of the background, not a
    # constant: a brightness gradient across the window (vignetting, the projector's and the room's light
    # fall-off) would otherwise weigh one side of the window more, 0.01-0.06 px of systematic shift
    # towards the brighter side, enough to move the projector's focal length and principal point
    # (docs/SIMULATOR.md, "Photometric realism"). The slope comes from one smooth (quadratic) surface
    # fitted to all the rims together: a plane per rim would add more noise than the slope removes.
    dx = (X - pts[sel, 0, None, None]).astype(np.float64) * np.ones_like(win)
    dy = (Y - pts[sel, 1, None, None]).astype(np.float64) * np.ones_like(win)
    gx, gy = _background_slopes(win, rim, X * np.ones_like(win), Y * np.ones_like(win), pts[sel])
    ramp = gx[:, None, None] * dx + gy[:, None, None] * dy
    bg = _rim_medians(win - ramp, rim)[:, None, None] + ramp
    wgt = np.where(inside, win - bg, 0.0)
    wgt[wgt < 0] = 0.0
    s = wgt.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = (wgt * X).sum(axis=(1, 2)) / s
        cy = (wgt * Y).sum(axis=(1, 2)) / s
    r = radius[sel]
    ok = (s > 0) & np.isfinite(cx) & np.isfinite(cy) & (np.abs(cx - pts[sel, 0]) < 0.5 * r + 0.5) \
        & (np.abs(cy - pts[sel, 1]) < 0.5 * r + 0.5)
    out[sel[ok], 0] = cx[ok]
    out[sel[ok], 1] = cy[ok]
    return out


def _rim_medians(values: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """Per window (axis 0), the median of `values` over its `rim` pixels (NaN for an empty rim): all the
    windows at once, as np.median of each would give (the mean of the two middle values for an even
    count)."""
    m = len(values)
    flat = np.where(rim, values, np.inf).reshape(m, -1)
    flat.sort(axis=1)
    count = rim.reshape(m, -1).sum(axis=1)
    rows = np.arange(m)
    out = (flat[rows, np.maximum(count - 1, 0) // 2] + flat[rows, count // 2]) / 2.0
    out[count == 0] = np.nan
    return out


def _background_slopes(win, rim, X, Y, centres) -> tuple[np.ndarray, np.ndarray]:
    """The background's gradient (levels per pixel, x and y) at each blob centre, from a quadratic
    surface fitted to the rim pixels of all the blobs (one refit without the rim pixels more than
    3 sigma off). Zero when there are too few blobs for a surface."""
    m = len(centres)
    zero = (np.zeros(m), np.zeros(m))
    if m < 6 or not rim.any():
        return zero
    c0 = centres.mean(axis=0)
    scale = max(float(np.ptp(centres, axis=0).max()), 1.0)
    u, v, val = (X[rim] - c0[0]) / scale, (Y[rim] - c0[1]) / scale, win[rim]
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    keep = np.ones(len(val), bool)
    for _ in range(2):
        coef = _least_squares(A[keep], val[keep])
        res = val - A @ coef
        mad = 1.4826 * np.median(np.abs(res[keep]))
        keep = np.abs(res) <= max(3.0 * mad, 1e-9)
        if keep.sum() < 12:
            return zero
    cu, cv = (centres[:, 0] - c0[0]) / scale, (centres[:, 1] - c0[1]) / scale
    gx = (coef[1] + 2 * coef[3] * cu + coef[4] * cv) / scale
    gy = (coef[2] + coef[4] * cu + 2 * coef[5] * cv) / scale
    return gx, gy


def _least_squares(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |A x - b| for a tall, well-conditioned A of a few columns, by its normal equations summed
    without BLAS: np.linalg.lstsq hands a 2000 x 6 problem to multi-threaded OpenBLAS, whose threads spin
    against the detection threads (and anything else on the cores) for ten times the arithmetic."""
    return np.linalg.solve(np.einsum("ni,nj->ij", A, A), np.einsum("ni,n->i", A, b))


def _find_circles(gray: np.ndarray, pattern: PatternSpec, roi, lut: np.ndarray | None = None):
    x0, y0, x1, y1 = roi
    crop = gray[y0:y1, x0:x1]
    work = _local_contrast(crop)
    max_area = int(work.shape[0] * work.shape[1] * 0.02)
    kps = _blob_detector(max(max_area, 50)).detect(work)
    n_need = pattern.n_points
    if len(kps) == 0:
        return DetectionFailure("pattern not found")
    cand = np.array([k.pt for k in kps], float)
    sizes = np.array([k.size for k in kps], float)
    # the grid finder runs on a clean image of dots at the candidates (no second blob search), only as
    # large as the candidates' box: its dot search scanned the whole crop, most of it empty (the grid's
    # points serve only to pick candidates, so a shifted image finds the same ones)
    lo = np.maximum(np.floor(cand.min(axis=0)).astype(int) - 8, 0)
    hi = np.ceil(cand.max(axis=0)).astype(int) + 9
    dots = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
    for (x, y) in cand - lo:
        cv2.circle(dots, (int(round(x * 4)), int(round(y * 4))), 8, 255, -1, cv2.LINE_8, 2)
    found = None
    for flags in (cv2.CALIB_CB_ASYMMETRIC_GRID, cv2.CALIB_CB_ASYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING):
        ok, centres = cv2.findCirclesGrid(dots, pattern.pattern_size, flags=flags, blobDetector=_dot_detector())
        if ok and centres is not None:
            found = np.asarray(centres, float).reshape(-1, 2) + lo
            break
    if found is None:
        if len(cand) < n_need:
            return DetectionFailure(f"pattern partial: {len(cand)} of {n_need} points")
        return DetectionFailure("pattern not found")
    idx = np.argmin(np.linalg.norm(found[:, None, :] - cand[None, :, :], axis=2), axis=1)
    if len(np.unique(idx)) != n_need:
        return DetectionFailure("pattern not found (ambiguous circle grid)")
    pts = cand[idx] + [x0, y0]
    pts = _refine_centroids(gray, pts, np.maximum(sizes[idx] / 2.0, 1.5), lut)
    if _asym_handedness(pts, pattern) < 0:
        pts = _reverse_rows(pts, pattern)
    return pts


def _find_chessboard(gray: np.ndarray, pattern: PatternSpec, roi):
    x0, y0, x1, y1 = roi
    crop = np.ascontiguousarray(gray[y0:y1, x0:x1])
    # the sector-based finder first: on projected chessboards it finds the grid in 0.1-0.2 s where the
    # classic finder spends up to a second before failing; the classic one is the fallback
    ok, corners = cv2.findChessboardCornersSB(crop, pattern.pattern_size)
    if not ok:
        ok, corners = cv2.findChessboardCorners(
            crop, pattern.pattern_size,
            flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK)
    if not ok:
        return DetectionFailure("pattern not found")
    pts = np.asarray(corners, float).reshape(-1, 2)
    pts = _refine_chess_corners(crop, pts, pattern)
    ordered = _order_chessboard(crop, pts, pattern)
    if isinstance(ordered, DetectionFailure):
        return ordered
    return ordered + [x0, y0]


def _refine_chess_corners(img: np.ndarray, pts: np.ndarray, pattern: PatternSpec) -> np.ndarray:
    """cornerSubPix on a smoothed copy with a window of ~0.3 square (see _refine_corners)."""
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    d[np.arange(len(pts)), np.arange(len(pts))] = np.inf
    side = float(np.percentile(d.min(axis=1), 10))  # (the finder's point order may be transposed)
    hw = int(np.clip(np.floor(0.3 * side), 3, 10))
    sigma = float(np.clip(0.25 * hw, 1.0, 1.5))
    sm = cv2.GaussianBlur(img.astype(np.float32), (0, 0), sigma)
    start = pts.astype(np.float32).reshape(-1, 1, 2)
    ref = cv2.cornerSubPix(sm, start.copy(), (hw, hw), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2).astype(float)
    # the grid finder's corners are unrefined (often 1-2 px off); the clean X-junction pulls them in
    ok = np.linalg.norm(ref - pts, axis=1) < max(2.5, 0.8 * hw)
    out = pts.copy()
    out[ok] = ref[ok]
    return out


def _order_chessboard(gray: np.ndarray, pts: np.ndarray, pattern: PatternSpec):
    """Put chessboard corners in PatternSpec order: same handedness as the drawn pattern, and the square
    diagonally before the first corner dark, the one to its right light (as PatternSpec draws them)."""
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
                   board_spec: CharucoSpec | None = None, response: CameraResponse | None = None):
    """The projected pattern in `image` -> (N, 2) camera pixels in PatternSpec.points_px order, or a
    DetectionFailure. With `board` and its `board_spec`, the printed ChArUco area is masked out and the
    search is limited to the board's neighbourhood. With the camera's `response` (recorded in the
    session, calib.detection.response), circle centroids weigh the image's levels linearised."""
    gray = to_gray(image)
    W = gray.shape[1]
    img = cv2.flip(gray, 1) if mirrored else gray
    H = None
    fill = 0 if pattern.kind == PatternKind.CIRCLES else int(np.median(img[::8, ::8]))
    if board is not None and board_spec is not None:
        H = _board_homography(board, board_spec, W, mirrored)
        if H is not None:
            img = _mask_board(img, H, board_spec, fill)
    elif board is not None and len(board.ids) >= 3:
        img = _mask_corner_hull(img, flip_x(board.corners_px, W) if mirrored else board.corners_px, fill)
    roi = _search_roi(img.shape, H, board_spec)
    lut = response.lut() if response is not None and not response.linear else None
    if pattern.kind == PatternKind.CIRCLES:
        pts = _find_circles(img, pattern, roi, lut)
    else:
        pts = _find_chessboard(img, pattern, roi)
    if isinstance(pts, DetectionFailure) and roi != (0, 0, img.shape[1], img.shape[0]):
        full = (0, 0, img.shape[1], img.shape[0])
        pts = _find_circles(img, pattern, full, lut) if pattern.kind == PatternKind.CIRCLES else _find_chessboard(img, pattern, full)
    if isinstance(pts, DetectionFailure):
        return pts
    return flip_x(pts, W) if mirrored else pts
