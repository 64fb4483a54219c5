"""Detection stage: ChArUco boards and projected patterns in camera images -> SessionObservations.

Entry function: `detect_session(store)` (its results kept in detections.json: calib.detection.cache).
Everything else is a pure function on numpy images.

Mirrored views (seen through the mirror) are detected in the horizontally flipped image and the points
are mapped back with x -> (W - 1) - x, so every returned pixel coordinate is in the ORIGINAL image
(pixel (0, 0) = centre of the top-left pixel). A failed detection is a `DetectionFailure` value with a
reason a person can read, never an exception.
"""

from __future__ import annotations

import json
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import lru_cache, partial, wraps

import cv2
import numpy as np

from calib.detection import cache as detect_cache
from calib.detection import structured_session
from calib.detection.response import CameraResponse, recorded_response
from calib.errors import SessionError
from calib.formats.fileio import read_regular
from calib.formats.session import image_header_problem, image_max_bytes
from calib.models.boards import CharucoSpec
from calib.models.observations import (
    STEP_PROJECTOR,
    STEP_REAL_MIRROR,
    STEP_REAL_VIRTUAL,
    VIEW_MIRROR,
    BoardObservation,
    DetectionFailure,
    MirrorView,
    ProjectorView,
    SessionObservations,
    Skipped,
)
from calib.models.pattern import PatternSpec


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


#: adaptive-threshold window sizes of the marker search (min, max, step). A single window first (about
#: 30 % faster on 1080p sessions); when that leaves the board incomplete, OpenCV's default set.
_FAST_WINDOWS = (9, 9, 10)
_FULL_WINDOWS = (3, 23, 10)


def _aruco_params(windows) -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # ChArUco corners are refined later
    params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax, params.adaptiveThreshWinSizeStep = windows
    return params


def _per_thread(fn):
    """lru_cache, one cache per thread: OpenCV's detector objects keep scratch state (the blob
    detector clears a member in detect()), so threads of detect_session do not share them."""
    local = threading.local()

    @wraps(fn)
    def wrapper(*args):
        cached = getattr(local, "fn", None)
        if cached is None:
            cached = local.fn = lru_cache(maxsize=16)(fn)
        return cached(*args)

    return wrapper


@_per_thread
def _detectors(spec: CharucoSpec, legacy: bool = False):
    """((fast, full) ArucoDetectors, (strict, relaxed) CharucoDetectors, {marker id: (4, 2) board
    corners}) for a board spec."""
    board = spec.cv_board()
    if legacy:  # boards printed by OpenCV < 4.6 with an even number of rows
        board = cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_length, spec.marker_length,
                                       board.getDictionary())
        board.setLegacyPattern(True)
    params = _aruco_params(_FULL_WINDOWS)
    arucos = tuple(cv2.aruco.ArucoDetector(board.getDictionary(), _aruco_params(w))
                   for w in (_FAST_WINDOWS, _FULL_WINDOWS))
    cparams = cv2.aruco.CharucoParameters()
    cparams.tryRefineMarkers = False
    charuco = cv2.aruco.CharucoDetector(board, cparams, params)
    relaxed_params = cv2.aruco.CharucoParameters()
    relaxed_params.tryRefineMarkers = False
    relaxed_params.minMarkers = 1
    relaxed = cv2.aruco.CharucoDetector(board, relaxed_params, params)
    obj = {int(i): np.asarray(p, float)[:, :2] for i, p in zip(board.getIds().ravel(), board.getObjPoints())}
    return arucos, (charuco, relaxed), obj


def _consistent_markers(corners, ids, obj: dict):
    """Drop markers that do not belong to the board's plane layout: markers of the mirror image of the
    board (a mirrored marker can decode as another id of the dictionary), duplicates, strays. RANSAC
    homography board -> image over all marker corners; a marker stays if 3 of its 4 corners agree."""
    if ids is None or len(ids) == 0:
        return [], None
    ids = np.asarray(ids, int).ravel()
    pts = [np.asarray(c, np.float64).reshape(4, 2) for c in corners]
    keep = [k for k in range(len(ids)) if int(ids[k]) in obj]
    if len(keep) >= 2:
        src = np.concatenate([obj[int(ids[k])] for k in keep])
        dst = np.concatenate([pts[k] for k in keep])
        side = np.median([np.linalg.norm(pts[k][1] - pts[k][0]) for k in keep])
        H, mask = cv2.findHomography(src, dst, cv2.RANSAC, max(3.0, 0.3 * float(side)), maxIters=500)
        if H is not None:
            proj = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 4, 2)
            err = np.linalg.norm(proj - dst.reshape(-1, 4, 2), axis=2)
            good = (mask.reshape(-1, 4).sum(axis=1) >= 3)
            best: dict[int, tuple[float, int]] = {}
            for j, k in enumerate(keep):
                if good[j] and (int(ids[k]) not in best or err[j].mean() < best[int(ids[k])][0]):
                    best[int(ids[k])] = (float(err[j].mean()), k)
            keep = sorted(k for _, k in best.values())
    if not keep:
        return [], None
    return [pts[k].astype(np.float32).reshape(1, 4, 2) for k in keep], ids[keep].reshape(-1, 1).astype(np.int32)


def _agreeing_markers(corners, ids, trusted_corners, trusted_ids, obj: dict):
    """Markers recovered by refineDetectedMarkers that agree with the homography of the decoded
    (trusted) ones: a recovered quad can be a neighbouring square, one square off."""
    if ids is None or len(ids) == 0:
        return [], None
    src = np.concatenate([obj[int(i)] for i in np.ravel(trusted_ids)])
    dst = np.concatenate([np.asarray(c, float).reshape(4, 2) for c in trusted_corners])
    H, _ = cv2.findHomography(src, dst, 0)
    if H is None:
        return trusted_corners, trusted_ids
    side = np.median(np.linalg.norm(dst.reshape(-1, 4, 2)[:, 1] - dst.reshape(-1, 4, 2)[:, 0], axis=1))
    trusted = set(int(i) for i in np.ravel(trusted_ids))
    keep_c, keep_i = [], []
    for c, i in zip(corners, np.ravel(ids)):
        i = int(i)
        if i not in obj:
            continue
        pts = np.asarray(c, float).reshape(4, 2)
        pred = cv2.perspectiveTransform(obj[i].reshape(-1, 1, 2), H).reshape(4, 2)
        if i in trusted or np.linalg.norm(pred - pts, axis=1).max() < 0.25 * side:
            keep_c.append(pts.astype(np.float32).reshape(1, 4, 2))
            keep_i.append(i)
    if len(set(keep_i)) != len(keep_i):
        return trusted_corners, trusted_ids
    return keep_c, np.array(keep_i, np.int32).reshape(-1, 1)


def _charuco_in(img: np.ndarray, spec: CharucoSpec, legacy: bool = False, fast_only: bool = False):
    """(corners (N, 2) or None, ids (N,) or None, board markers (M, 4, 2), corners OpenCV's strict
    rule accepts) found in `img`. `fast_only`: the single-window marker search only."""
    arucos, detectors, obj = _detectors(spec, legacy)
    result = None
    for aruco in arucos[:1] if fast_only else arucos:
        found = _charuco_with(img, spec, aruco, detectors, obj)
        if result is None or len(found[1]) > len(result[1]) or \
                (len(found[1]) == len(result[1]) and len(found[2]) > len(result[2])):
            result = found
        if len(result[1]) == spec.n_corners:
            break
    corners, ids, markers, n_strict = result
    if len(ids) == 0:
        return None, None, markers, 0
    return corners, ids, markers, n_strict


def _charuco_with(img, spec: CharucoSpec, aruco, detectors, obj):
    mcorners, mids, rejected = aruco.detectMarkers(img)
    mcorners, mids = _consistent_markers(mcorners, mids, obj)
    if mids is None:
        return np.zeros((0, 2)), np.zeros(0, int), np.zeros((0, 4, 2)), 0
    best = (*_corners_from(img, mcorners, mids, spec, detectors, obj), mcorners)
    if len(rejected) and len(mids) < len(obj) and len(best[1]) < spec.n_corners:
        # recover markers missed by the first pass where the board layout says they must be; a
        # recovered quad can be wrong (a square of another board), so check again and keep the better
        rc, rids, _, _ = aruco.refineDetectedMarkers(img, detectors[0].getBoard(), list(mcorners), mids, rejected)
        rc, rids = _agreeing_markers(rc, rids, mcorners, mids, obj)
        if rids is not None and len(rids) > len(mids):
            cand = _corners_from(img, rc, rids, spec, detectors, obj)
            if len(cand[1]) > len(best[1]):
                best = (*cand, rc)
    corners, ids, n_strict, mcorners = best
    return corners, ids, np.asarray(mcorners, float).reshape(-1, 4, 2), n_strict


def _corners_from(img, mcorners, mids, spec: CharucoSpec, detectors, obj: dict):
    """(corners (N, 2), ids (N,), how many OpenCV's strict rule gave) interpolated from markers."""
    charuco, relaxed = detectors
    corners, ids, _, _ = charuco.detectBoard(img, markerCorners=mcorners, markerIds=mids)
    n = 0 if ids is None else len(ids)
    if n:
        corners, ids = np.asarray(corners, float).reshape(-1, 2), np.asarray(ids, int).reshape(-1)
    else:
        corners, ids = np.zeros((0, 2)), np.zeros(0, int)
    if 0 < n < spec.n_corners and len(mids) >= 3:
        # small or partly decoded boards: OpenCV keeps a corner only when both markers beside it were
        # decoded; also take corners next to one decoded marker if the markers' plane explains them.
        # (Only once the strict rule found some: with none, the layout itself is in doubt.)
        c1, i1, _, _ = relaxed.detectBoard(img, markerCorners=mcorners, markerIds=mids)
        if i1 is not None and len(i1) > n:
            c1, i1 = np.asarray(c1, float).reshape(-1, 2), np.asarray(i1, int).reshape(-1)
            keep = _plane_consistent(c1, i1, mcorners, mids, obj, spec) | np.isin(i1, ids)
            if keep.sum() > n:
                corners, ids = c1[keep], i1[keep]
    return corners, ids, n


def _plane_consistent(corners, ids, mcorners, mids, obj: dict, spec: CharucoSpec) -> np.ndarray:
    """Mask of ChArUco corners that the homography of the decoded markers (board -> image, all their
    corners) explains to 8 % of a square (at least 1 px)."""
    src = np.concatenate([obj[int(i)] for i in np.ravel(mids)])
    dst = np.concatenate([np.asarray(c, float).reshape(4, 2) for c in mcorners])
    H, _ = cv2.findHomography(src, dst, 0)
    if H is None:
        return np.zeros(len(ids), bool)
    board = spec.corner_points()[ids, :2]
    pred = cv2.perspectiveTransform(board.reshape(-1, 1, 2), H).reshape(-1, 2)
    step = cv2.perspectiveTransform((board + [spec.square_length, 0.0]).reshape(-1, 1, 2), H).reshape(-1, 2)
    square_px = float(np.median(np.linalg.norm(step - pred, axis=1)))
    return np.linalg.norm(pred - corners, axis=1) < max(1.0, 0.08 * square_px)


def _roi_around(markers: np.ndarray, shape, grow: float = 2.5):
    """(x0, y0, x1, y1) around found markers, grown by `grow` marker sides plus the markers' spread
    (the rest of the board may lie beyond them), or None when the ROI would not be much smaller."""
    if len(markers) == 0:
        return None
    h, w = shape
    pts = markers.reshape(-1, 2)
    side = float(np.median(np.linalg.norm(markers[:, 1] - markers[:, 0], axis=1)))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = grow * side + 0.6 * (hi - lo) if len(markers) < 4 else grow * side + 0.25 * (hi - lo)
    x0, y0 = np.floor(lo - pad).astype(int)
    x1, y1 = np.ceil(hi + pad).astype(int) + 1
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if (x1 - x0) * (y1 - y0) > 0.7 * w * h:
        return None
    return (int(x0), int(y0), int(x1), int(y1))


# ---- the board ---------------------------------------------------------------------------------------
def detect_board(image: np.ndarray, spec: CharucoSpec, mirrored: bool, min_corners: int = 6,
                 response: CameraResponse | None = None):
    """ChArUco corners of `spec` in `image` (gray or BGR) -> BoardObservation | DetectionFailure.

    `mirrored`: the board is seen through the mirror; detect in the flipped image and map back.
    `response`: the camera's recorded tone curve (calib.detection.response); the corners are then
    refined on the image's levels linearised (see _refinement_image)."""
    gray = _gray(image)
    return _detect_board_gray(gray, spec, mirrored, min_corners, response)


def _refinement_image(img: np.ndarray, response: CameraResponse | None):
    """The image the corners are refined on: `img` itself, or with the camera's recorded response its
    levels linearised (float32, light in 0..255 units; _Linearised: only the regions the refinement
    reads are converted). An X-junction is point-symmetric under any tone
    curve, so the curve does not bias a corner, but it spreads the sensor's noise unevenly: the dark toe
    is steep (about 4 levels per level of light at the black squares, 0.8 at the white ones), so the
    black squares' noise dominates the encoded image and corners scatter more (projector-step boards at
    live quality: 0.050 px mean instead of the linear camera's 0.037; docs/SIMULATOR.md, "Photometric
    realism"). In light, the noise is the sensor's again."""
    if response is None or response.linear:
        return img
    return _Linearised(img, response.lut())


class _Linearised:
    """An 8-bit image read as light through a 256-level table, converted region by region as it is
    sliced (`lin[y0:y1, x0:x1]`): the corner refinement reads a few patches around the corners, and
    converting a whole 1080p frame to float32 cost more than all of them together. Slicing gives
    exactly the values the converted whole image would hold."""

    def __init__(self, img: np.ndarray, lut: np.ndarray):
        self._img = img
        self._lut = np.asarray(lut, np.float32)
        self.shape = img.shape

    def __getitem__(self, index) -> np.ndarray:
        return self._lut[self._img[index]]


def _detect_board_gray(gray: np.ndarray, spec: CharucoSpec, mirrored: bool, min_corners: int = 6,
                       response: CameraResponse | None = None):
    img = cv2.flip(gray, 1) if mirrored else gray
    fine = _refinement_image(img, response)
    found = None
    h, w = img.shape
    x0 = y0 = 0
    search = img
    if min(h, w) >= 480:
        # find the board at half resolution first (4x less work). Complete: its corners are re-refined
        # at full resolution below, so accuracy does not suffer. Incomplete: search again at full
        # resolution, only around the markers found (small boards far away), else everywhere.
        h2, w2 = h // 2, w // 2
        small = cv2.resize(img[: 2 * h2, : 2 * w2], (w2, h2), interpolation=cv2.INTER_AREA)
        corners, ids, markers, _ = _charuco_in(small, spec, fast_only=True)
        if ids is not None and len(ids) == spec.n_corners and \
                np.min(_margins_px(corners * 2.0 + 0.5, ids, spec)) >= _MIN_REFINE_MARGIN_PX:
            refined, ok = _refine_corners(fine, corners * 2.0 + 0.5, ids, spec)
            if ok.all():  # every corner pulled onto its X-junction at full resolution
                found = (refined, ids)
        if found is None:
            roi = _roi_around(markers * 2.0 + 0.5, (h, w))
            if roi is not None:
                x0, y0, x1, y1 = roi
                search = img[y0:y1, x0:x1]
    if found is None:
        corners, ids, markers, strict = _charuco_in(search, spec)
        n = 0 if ids is None else len(ids)
        if search is not img and n < spec.n_corners and _missing_beyond(corners, ids, (x0, y0), spec, roi, (h, w)):
            # the ROI guess missed part of the board (corners found inside it need no second search)
            corners2, ids2, markers2, strict2 = _charuco_in(img, spec)
            if ids2 is not None and len(ids2) > n:
                corners, ids, markers, strict, n = corners2, ids2, markers2, strict2, len(ids2)
                x0 = y0 = 0
        if strict == 0 and len(markers) >= 4 and spec.rows % 2 == 0:
            # many markers, not one corner where the layout puts them: a board printed by OpenCV < 4.6
            lc, lids, _, lstrict = _charuco_in(img, spec, legacy=True)
            if lids is not None and lstrict > 0 and len(lids) > n:
                corners, ids, n = lc, lids, len(lids)
                x0 = y0 = 0
        if n < spec.n_corners:
            # camera images are gamma-encoded, not linear in light: where a marker's cells are a pixel or
            # two wide, the pixels that mix black and white encode brighter than the light they received
            # and the black cells fade. A linearised copy decodes them again (docs/SIMULATOR.md,
            # "Photometric realism"); the corners are refined below as any others (in the image itself,
            # or linearised with the session's recorded response: _refinement_image).
            # Only where corners can still be found: around the board the corners found predict (none
            # when every missing corner lies outside the image), else where the board was looked for
            # first, then the whole image.
            board_box = _board_box(corners, ids, (x0, y0), spec, (h, w))
            if board_box is None:
                regions = [(img, 0, 0)] if search is img else [(search, *roi[:2]), (img, 0, 0)]
            elif board_box == ():
                regions = []
            else:
                bx0, by0, bx1, by1 = board_box
                regions = [(img[by0:by1, bx0:bx1], bx0, by0)]
            for region, ox, oy in regions:
                lc, lids, lmarkers, lstrict = _charuco_in(cv2.LUT(region, _LINEARISE_LUT), spec)
                if lids is not None and len(lids) > n:
                    corners, ids, markers, strict, n = lc, lids, lmarkers, lstrict, len(lids)
                    x0, y0 = ox, oy
                if n == spec.n_corners:
                    break
        if n == 0 and len(markers) == 0:
            return DetectionFailure("board not found")
        if n < min_corners:
            return DetectionFailure(f"only {n} ChArUco corners (need {min_corners})")
        corners, done = _refine_corners(fine, corners + [x0, y0], ids, spec)
        corners, ids = _verify_corners(fine, corners, ids, spec, done)
        if len(ids) < min_corners:
            return DetectionFailure(f"only {len(ids)} ChArUco corners (need {min_corners})")
        found = (corners, ids)
    corners, ids = found
    if mirrored:
        corners = _flip_x(corners, gray.shape[1])
    order = np.argsort(ids)
    return BoardObservation(ids[order], corners[order], mirrored)


def _predicted_corners(corners, ids, offset, spec: CharucoSpec):
    """(every corner of the board in pixels, mask of those not found, square side px) from the homography
    of the corners found (at `corners` + `offset`), or None when it cannot be estimated (under 4 corners,
    a degenerate fit, a corner beyond the plane's horizon)."""
    if ids is None or corners is None or len(ids) < 4:
        return None
    obj = spec.corner_points()[:, :2]
    H, _ = cv2.findHomography(obj[ids], np.asarray(corners, float) + np.asarray(offset, float), 0)
    if H is None:
        return None
    allpx = _map_board(H, obj)
    step = _map_board(H, obj[ids] + [spec.square_length, 0.0])
    if allpx is None or step is None or not np.all(np.isfinite(allpx)):
        return None
    missing = np.ones(len(obj), bool)
    missing[ids] = False
    return allpx, missing, float(np.median(np.linalg.norm(step - allpx[ids], axis=1)))


def _in_view(pts: np.ndarray, shape, grow_px: float) -> np.ndarray:
    """Mask of points inside the image grown by `grow_px` on every side."""
    h, w = shape
    return (pts[:, 0] >= -0.5 - grow_px) & (pts[:, 0] <= w - 0.5 + grow_px) & \
        (pts[:, 1] >= -0.5 - grow_px) & (pts[:, 1] <= h - 0.5 + grow_px)


def _missing_beyond(corners, ids, offset, spec: CharucoSpec, roi, shape) -> bool:
    """Whether a corner not found may lie in view but outside the region searched (`roi`, its edges
    inside the image shrunk by two squares, so that the markers beside the corner are whole in it):
    only then can a search of the whole image find more. True when that cannot be predicted."""
    pred = _predicted_corners(corners, ids, offset, spec)
    if pred is None:
        return True
    allpx, missing, side = pred
    pts = allpx[missing & _in_view(allpx, shape, 0.25 * side)]
    h, w = shape
    x0, y0, x1, y1 = roi
    m = 2.0 * side
    lo = np.array([x0 + m if x0 > 0 else -np.inf, y0 + m if y0 > 0 else -np.inf])
    hi = np.array([x1 - m if x1 < w else np.inf, y1 - m if y1 < h else np.inf])
    return bool(np.any((pts < lo) | (pts > hi)))


def _board_box(corners, ids, offset, spec: CharucoSpec, shape):
    """Where a second search can find the corners not found: (x0, y0, x1, y1) around the whole board as
    the corners found predict it, grown by 2.5 squares (its outer markers and the thresholding windows
    around them); () when every missing corner lies outside the image (a corner less than a quarter
    square inside the border has its outer marker cut: no search finds it); None when it cannot be
    predicted."""
    pred = _predicted_corners(corners, ids, offset, spec)
    if pred is None:
        return None
    allpx, missing, side = pred
    if not np.any(missing & _in_view(allpx, shape, 0.25 * side)):
        return ()
    h, w = shape
    lo = np.floor(allpx.min(axis=0) - 2.5 * side).astype(int)
    hi = np.ceil(allpx.max(axis=0) + 2.5 * side).astype(int) + 1
    x0, y0, x1, y1 = max(lo[0], 0), max(lo[1], 0), min(hi[0], w), min(hi[1], h)
    if x1 - x0 < 16 or y1 - y0 < 16:
        return None
    return (int(x0), int(y0), int(x1), int(y1))


_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)

#: 8-bit level -> level linear in light, for a camera with the usual video encoding (gamma about 2.2)
_LINEARISE_LUT = np.clip(np.round(255.0 * (np.arange(256) / 255.0) ** 2.2), 0, 255).astype(np.uint8)


_MIN_REFINE_MARGIN_PX = 3.5


def _margins_px(corners: np.ndarray, ids: np.ndarray, spec: CharucoSpec) -> np.ndarray:
    """Per corner: pixels from the corner to the nearest marker edge (the clean X-junction around it),
    from the local scale of the board -> image homography. Infinite when it cannot be estimated."""
    n = len(ids)
    if n < 4:
        return np.full(n, np.inf)
    obj = spec.corner_points()[ids, :2]
    H, _ = cv2.findHomography(obj, corners, 0)
    if H is None:
        return np.full(n, np.inf)
    sq = spec.square_length
    probe = np.concatenate([obj, obj + [sq, 0.0], obj + [0.0, sq]])
    m = cv2.perspectiveTransform(probe.reshape(-1, 1, 2), H).reshape(3, n, 2)
    side_px = np.minimum(np.linalg.norm(m[1] - m[0], axis=1), np.linalg.norm(m[2] - m[0], axis=1))
    side_px[~np.isfinite(side_px)] = np.inf
    return side_px * (spec.square_length - spec.marker_length) / (2.0 * spec.square_length)


def _refine_corners(img: np.ndarray, corners: np.ndarray, ids: np.ndarray, spec: CharucoSpec):
    """Re-refine ChArUco corners: cornerSubPix on a Gaussian-smoothed copy, with a window that stays
    inside the white margin between the corner and the neighbouring markers.

    On sharp images cornerSubPix is pulled towards pixel centres (errors up to ~0.1 px, periodic in
    the sub-pixel phase); an X-junction is point-symmetric, so smoothing does not move it but removes
    that bias (rendered boards: ~0.05 -> ~0.01 px rms). Where the margin is under 3.5 px the window
    would reach the markers; those corners keep OpenCV's own full-resolution refinement.
    Returns (corners, refined mask)."""
    margin_px = _margins_px(corners, ids, spec)
    todo = np.isfinite(margin_px) & (margin_px >= _MIN_REFINE_MARGIN_PX)
    done = np.zeros(len(ids), bool)
    if not todo.any():
        return corners, done
    half = np.zeros(len(ids), int)
    half[todo] = np.clip(np.floor(0.65 * margin_px[todo]), 3, 10).astype(int)
    h, w = img.shape
    out = corners.copy()
    pad = 16
    for hw in np.unique(half[todo]):
        sel = np.nonzero(todo & (half == hw))[0]
        p = corners[sel]
        x0 = max(int(np.floor(p[:, 0].min())) - hw - pad, 0)
        y0 = max(int(np.floor(p[:, 1].min())) - hw - pad, 0)
        x1 = min(int(np.ceil(p[:, 0].max())) + hw + pad + 1, w)
        y1 = min(int(np.ceil(p[:, 1].max())) + hw + pad + 1, h)
        sigma = float(np.clip(0.33 * hw, 1.0, 2.0))
        roi = cv2.GaussianBlur(img[y0:y1, x0:x1].astype(np.float32), (0, 0), sigma)
        start = (p - [x0, y0]).astype(np.float32).reshape(-1, 1, 2)
        ref = cv2.cornerSubPix(roi, start.copy(), (int(hw), int(hw)), (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2)
        ref = ref.astype(float) + [x0, y0]
        ok = (np.linalg.norm(ref - p, axis=1) < 1.5) & (_asymmetry(roi, ref - [x0, y0], hw) < _MAX_ASYMMETRY)
        out[sel[ok]] = ref[ok]
        done[sel[ok]] = True
    return out, done


_MAX_ASYMMETRY = 0.1


def _verify_corners(img, corners, ids, spec: CharucoSpec, verified: np.ndarray):
    """Check the corners not re-refined (clean margin under 3.5 px: OpenCV's own estimate) for point
    symmetry; an asymmetric one gets one more try with a small window and is dropped if it stays
    asymmetric. On simulated boards with 0.75 markers this removes ~95 % of the corners that are more
    than 0.3 px off, and < 0.5 % of the good ones."""
    todo = np.nonzero(~verified)[0]
    if len(todo) == 0:
        return corners, ids
    h, w = img.shape
    p = corners[todo]
    x0, y0 = max(int(p[:, 0].min()) - 12, 0), max(int(p[:, 1].min()) - 12, 0)
    x1, y1 = min(int(p[:, 0].max()) + 13, w), min(int(p[:, 1].max()) + 13, h)
    smooth = cv2.GaussianBlur(img[y0:y1, x0:x1].astype(np.float32), (0, 0), 1.0)
    margin = _margins_px(corners, ids, spec)[todo]
    hw = np.clip(np.floor(0.65 * np.where(np.isfinite(margin), margin, 4.0)), 2, 10).astype(int)
    keep = np.ones(len(ids), bool)
    out = corners.copy()
    local = p - [x0, y0]
    for j, k in enumerate(todo):
        if _asymmetry(smooth, local[j:j + 1], hw[j])[0] < _MAX_ASYMMETRY:
            continue
        retry = cv2.cornerSubPix(smooth, local[j:j + 1].astype(np.float32).reshape(1, 1, 2).copy(), (2, 2), (-1, -1),
                                 _SUBPIX_CRITERIA).reshape(1, 2).astype(float)
        if np.linalg.norm(retry - local[j]) < 1.5 and _asymmetry(smooth, retry, hw[j])[0] < _MAX_ASYMMETRY:
            out[k] = retry[0] + [x0, y0]
        else:
            keep[k] = False
    return out[keep], ids[keep]


def _asymmetry(smooth: np.ndarray, pts: np.ndarray, hw: int) -> np.ndarray:
    """How far the neighbourhood of each point is from point symmetry (an X-junction is symmetric under
    a half turn about its centre): mean |I(p + d) - I(p - d)| over a (2 hw + 1)^2 patch, divided by the
    patch's contrast. ~0.01 at a corner, > 0.1 a pixel or more away from it (rendered and simulated
    boards)."""
    out = np.empty(len(pts))
    size = (2 * int(hw) + 1, 2 * int(hw) + 1)
    for k, (x, y) in enumerate(np.asarray(pts, float)):
        patch = cv2.getRectSubPix(smooth, size, (float(x), float(y)))
        span = float(patch.max() - patch.min())
        out[k] = np.abs(patch - patch[::-1, ::-1]).mean() / span if span > 1e-6 else 1.0
    return out


def _board_homography(obs: BoardObservation, spec: CharucoSpec, width: int, flip: bool):
    """Homography board (x, y) -> pixels of the detection frame (flipped when `flip`), or None."""
    if obs is None or len(obs.ids) < 4:
        return None
    src = spec.corner_points()[obs.ids, :2]
    dst = _flip_x(obs.corners_px, width) if flip else np.asarray(obs.corners_px, float)
    H, _ = cv2.findHomography(src, dst, 0)
    return H


def _map_board(H: np.ndarray, pts) -> np.ndarray | None:
    """Board points -> pixels; None when a point is at or behind the plane's horizon."""
    p = np.column_stack([np.asarray(pts, float), np.ones(len(pts))]) @ H.T
    if np.any(p[:, 2] * np.sign(H[2, 2] if H[2, 2] != 0 else 1.0) <= 1e-9):
        return None
    return p[:, :2] / p[:, 2:3]


def _mask_board(gray: np.ndarray, H: np.ndarray, spec: CharucoSpec, fill: int) -> np.ndarray:
    """Paint the printed ChArUco area (plus a quarter square) with `fill`, so that its squares cannot be
    taken for pattern features."""
    w, h = spec.size
    m = spec.square_length * 0.25
    px = _map_board(H, [[-m, -m], [w + m, -m], [w + m, h + m], [-m, h + m]])
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
    px = _map_board(H, quad)
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


@_per_thread
def _blob_detector(max_area: int):
    return cv2.SimpleBlobDetector_create(_blob_params(float(max_area)))


@_per_thread
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
    ref = cv2.cornerSubPix(sm, start.copy(), (hw, hw), (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2).astype(float)
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
    gray = _gray(image)
    return _detect_pattern_gray(gray, pattern, mirrored, board, board_spec, response)


def _detect_pattern_gray(gray, pattern, mirrored, board=None, board_spec=None, response=None):
    W = gray.shape[1]
    img = cv2.flip(gray, 1) if mirrored else gray
    H = None
    fill = 0 if pattern.kind == "circles" else int(np.median(img[::8, ::8]))
    if board is not None and board_spec is not None:
        H = _board_homography(board, board_spec, W, mirrored)
        if H is not None:
            img = _mask_board(img, H, board_spec, fill)
    elif board is not None and len(board.ids) >= 3:
        img = _mask_corner_hull(img, _flip_x(board.corners_px, W) if mirrored else board.corners_px, fill)
    roi = _search_roi(img.shape, H, board_spec)
    lut = response.lut() if response is not None and not response.linear else None
    if pattern.kind == "circles":
        pts = _find_circles(img, pattern, roi, lut)
    else:
        pts = _find_chessboard(img, pattern, roi)
    if isinstance(pts, DetectionFailure) and roi != (0, 0, img.shape[1], img.shape[0]):
        full = (0, 0, img.shape[1], img.shape[0])
        pts = _find_circles(img, pattern, full, lut) if pattern.kind == "circles" else _find_chessboard(img, pattern, full)
    if isinstance(pts, DetectionFailure):
        return pts
    return _flip_x(pts, W) if mirrored else pts


# ---- mirror-calibration views ------------------------------------------------------------------------
def detect_real_virtual(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6,
                        response: CameraResponse | None = None):
    """A board seen directly (`real`) and in the mirror (`virtual`) in one image -> MirrorView."""
    gray = _gray(image)
    real = _detect_board_gray(gray, spec, False, min_corners, response)
    if isinstance(real, DetectionFailure):
        return DetectionFailure(f"real board: {real.reason}")
    virtual = _detect_board_gray(gray, spec, True, min_corners, response)
    if isinstance(virtual, DetectionFailure):
        return DetectionFailure(f"virtual board (in the mirror): {virtual.reason}")
    return MirrorView(capture_id, STEP_REAL_VIRTUAL, real, virtual)


def detect_real_mirror(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6,
                       response: CameraResponse | None = None):
    """A board lying on the mirror, seen directly -> MirrorView (real only)."""
    real = _detect_board_gray(_gray(image), spec, False, min_corners, response)
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
    cached: dict | None = None  # this capture's detections.json entry, if any (calib.detection.cache)
    refused: str | None = None  # why the image is not read at all (its path leads out of the session folder)
    response: CameraResponse | None = None  # the camera's tone curve the session recorded, if any


def _read_file(path: str, camera_size: tuple[int, int]) -> np.ndarray:
    """An image file's bytes (the one place detect_session reads images): a regular file no larger than
    a PNG of the camera can be (calib.formats.fileio.read_regular); its header is checked before decoding."""
    return np.frombuffer(read_regular(path, image_max_bytes(camera_size), "image"), np.uint8)


def _run_job(job: _Job, seen: dict | None = None):
    """(capture_id, result, image SHA-1 or None) with result a BoardObservation/pattern tuple, MirrorView
    or DetectionFailure. The file is read once and hashed, then decoded and detected unless `job.cached`
    holds a valid result for exactly these bytes, or `seen` ({(SHA-1, step, mirrored): result}, shared
    by the jobs of one run) holds the result of a byte-identical image detected for the same step."""
    digest = None
    if isinstance(job, structured_session.StructuredJob):
        return job.run()
    if job.refused is not None:
        return job.capture_id, DetectionFailure(job.refused), None
    try:
        try:
            data = _read_file(job.image_path, job.camera_size)
        except FileNotFoundError:
            return job.capture_id, DetectionFailure(f"image missing: {job.image_path}"), None
        except SessionError as e:  # a link, FIFO, device or huge file: never read
            return job.capture_id, DetectionFailure(str(e)), None
        digest = detect_cache.image_digest(data)
        same = (digest, job.step, job.mirrored)
        if seen is not None and same in seen:
            res = seen[same]
            if isinstance(res, MirrorView):  # a mirror result names its capture
                res = replace(res, capture_id=job.capture_id)
            return job.capture_id, res, digest
        res = _cached_result(job, digest)
        if res is None:
            res = _detect_job(job, data)
        if seen is not None:
            seen.setdefault(same, res)
        return job.capture_id, res, digest
    except Exception as e:  # noqa: BLE001 - a pathological image must not stop the whole session
        lines = str(e).strip().splitlines()
        msg = lines[-1] if lines else ""
        why = f"detection failed ({e.__class__.__name__}): {msg}".rstrip(": ")
        return job.capture_id, DetectionFailure(why), digest


def _cached_result(job: _Job, digest: str):
    """The result `job.cached` holds for an image with this SHA-1, or None (no entry, another image, or
    an entry that does not fit the capture: detect again)."""
    if job.cached is None or job.cached.get("image_sha1") != digest:
        return None
    try:
        return detect_cache.decode_result(job.cached.get("result"), job.capture_id, job.step, job.mirrored,
                                          job.board, job.pattern, job.camera_size)
    except ValueError:
        return None


def _detect_job(job: _Job, data: np.ndarray):
    problem = image_header_problem(data, job.camera_size, job.image_path)
    if problem is not None:  # another size (a lying header too) is never decoded
        return DetectionFailure(problem)
    gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return DetectionFailure(f"image unreadable: {job.image_path} cannot be decoded")
    h, w = gray.shape
    if (w, h) != tuple(job.camera_size):
        return DetectionFailure(f"image is {w}x{h}, the session's camera is {job.camera_size[0]}x{job.camera_size[1]}")
    if job.step == STEP_REAL_VIRTUAL:
        return detect_real_virtual(gray, job.board, job.capture_id, response=job.response)
    if job.step == STEP_REAL_MIRROR:
        return detect_real_mirror(gray, job.board, job.capture_id, response=job.response)
    board = _detect_board_gray(gray, job.board, job.mirrored, response=job.response)
    if isinstance(board, DetectionFailure):
        return board
    pts = _detect_pattern_gray(gray, job.pattern, job.mirrored, board, job.board, job.response)
    if isinstance(pts, DetectionFailure):
        return pts
    return board, pts


#: serialises detections.json read-modify-writes within one process (the station detects each capture in
#: the background while it captures the next; calibration may run detect_session on the same folder)
_CACHE_LOCK = threading.Lock()


def _job_for(store, c, old: dict, cache_on: bool):
    """(_Job, job key or None) of capture `c` of a SessionStore; `old` its detections.json entries."""
    if c.structured:
        return structured_session.job_for(store, c), None
    m = store.manifest
    board = m.projector_board if c.step == STEP_PROJECTOR else (m.mirror_board or m.projector_board)
    flip = m.rig.view == VIEW_MIRROR and c.step == STEP_PROJECTOR
    pattern = m.pattern if c.step == STEP_PROJECTOR else None
    response = recorded_response(m.rig.camera_settings)
    key = detect_cache.job_key(c.step, flip, board, pattern, m.rig.camera_size, response) if cache_on else None
    entry = old.get(c.id)
    cached = entry if entry is not None and entry.get("job") == key else None
    try:
        path, refused = str(store.image_path(c)), None
    except SessionError as e:  # never read, hashed or named: the reason does not tell whether it exists
        path, refused = "", str(e)
    return _Job(c.id, path, c.step, flip, board, pattern, tuple(m.rig.camera_size), cached,
                refused=refused, response=response), key


def detect_capture(store, capture_id: str):
    """Detect one capture of a SessionStore now and put the result in the session's detections.json,
    so that a later detect_session (calibration) finds it there instead of decoding and detecting the
    image again. The station calls this in the background right after each capture: by the time the
    operator presses Calibrate every image has been detected, once, from the bytes on disk (so the
    result is bit for bit what detect_session would compute). Returns the result: a DetectionFailure
    (with the reason calibration will skip this capture for), (board, pattern points) or a MirrorView.
    Raises SessionError for an unknown capture id."""
    c = next((c for c in store.manifest.captures if c.id == capture_id), None)
    if c is None:
        raise SessionError(f"no capture '{capture_id}' in this session")
    job, key = _job_for(store, c, {}, True)  # detected now: the capture is new, it has no entry yet
    cid, result, digest = _run_job(job)
    if digest is not None:
        with _CACHE_LOCK:
            entries = detect_cache.load(store.folder)
            live = {x.id for x in store.manifest.captures} | {cid}
            entries = {k: v for k, v in entries.items() if k in live}
            entries[cid] = {"image_sha1": digest, "job": key, "result": detect_cache.encode_result(result)}
            detect_cache.save(store.folder, entries)
    return result


def _detect_threaded(jobs, workers: int, done) -> None:
    """Run jobs in `workers` threads. OpenCV releases the GIL in decoding and in every detector, which
    is nearly all of the time, so threads scale like processes here (1.9x on 2 cores) without the
    half second a process pool takes to start. OpenCV's own thread pool is set to one thread per
    stream while the jobs run (one detection stream per core) and restored after."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(max_workers=workers) as ex:
            for out in ex.map(partial(_run_job, seen={}), jobs):  # in job order; `done` runs in this thread only
                done(*out)
    finally:
        cv2.setNumThreads(threads)


def detect_session(store, workers: int = 2, progress=None, cache: str = "use") -> SessionObservations:
    """Detect every capture of a session (SessionStore) -> SessionObservations.

    Each image is read once; detection runs in `workers` threads (1 = inline). A capture whose image
    is missing or unreadable, or whose board/pattern is not found, is listed in `skipped` with the
    reason. `progress(done, total, capture_id)` is called after each capture. A capture that repeats
    an earlier one (_copies) is detected once and skipped as a copy of it (Skipped.copy_of).

    `cache`: "use" takes the results of earlier runs from the session's detections.json for captures
    whose image, job and detector are unchanged (calib.detection.cache) and writes the file back;
    "refresh" detects every image and writes the file; "off" neither reads nor writes it."""
    if cache not in ("use", "refresh", "off"):
        raise ValueError(f"cache must be 'use', 'refresh' or 'off', not {cache!r}")
    m = store.manifest
    if cache == "use":
        with _CACHE_LOCK:
            old = detect_cache.load(store.folder)
    else:
        old = {}
    jobs, keys = [], {}
    for c in m.captures:
        job, keys[c.id] = _job_for(store, c, old, cache != "off")
        jobs.append(job)
    results: dict[str, object] = {}
    digests: dict[str, str | None] = {}
    total = len(jobs)

    def done(cid, res, digest):
        results[cid] = res
        digests[cid] = digest
        if progress is not None:
            progress(len(results), total, cid)

    if workers > 1 and total > 1:
        _detect_threaded(jobs, min(workers, total), done)
    else:
        seen = {}
        for job in jobs:
            done(*_run_job(job, seen))

    if cache != "off":
        entries = {cid: {"image_sha1": digests[cid], "job": keys[cid],
                         "result": detect_cache.encode_result(results[cid])}
                   for cid in results if digests.get(cid)}
        if entries != old:
            with _CACHE_LOCK:
                detect_cache.save(store.folder, entries)

    copies = _copies(m.captures, results, digests)
    pviews, mviews, skipped = [], [], []
    for c in m.captures:
        res = results[c.id]
        if c.id in copies:
            skipped.append(copies[c.id])
        elif isinstance(res, DetectionFailure):
            skipped.append(Skipped(c.id, c.image, res.reason))
        elif c.step == STEP_PROJECTOR:
            board, pts = res
            pviews.append(structured_session.projector_view(c, board, pts) if c.structured else
                          ProjectorView(c.id, board, pts, c.pattern_points_px, c.pattern_position))
        else:
            mviews.append(res)
    return SessionObservations(
        camera_size=tuple(m.rig.camera_size), projector_size=tuple(m.rig.projector_size), view=m.rig.view,
        projector_board=m.projector_board, pattern=m.pattern, projector_views=tuple(pviews),
        mirror_board=m.mirror_board, mirror_views=tuple(mviews), board_thickness=m.board_thickness,
        skipped=tuple(skipped),
    )


def _copies(captures, results: dict, digests: dict) -> dict[str, Skipped]:
    """{capture id: why it is skipped} for the captures that repeat an earlier one: a byte-identical image
    (same SHA-1) or, for the same step, identical detections. A copy adds no information, so it is counted
    once: kept, it would shrink the uncertainty and defeat the quality gate (calib.quality.trust)."""
    first_image: dict[str, str] = {}
    first_found: dict[tuple, str] = {}
    out = {}
    for c in captures:
        res = results[c.id]
        if isinstance(res, DetectionFailure):
            continue
        found = (c.step, _detections_key(res))
        orig, what = first_image.get(digests.get(c.id)), "the same image bytes"
        if orig is None:
            orig, what = first_found.get(found), "the same detections"
        if orig is not None:
            out[c.id] = Skipped(c.id, c.image, f"{c.id} is a copy of {orig} ({what}): counted once", copy_of=orig)
            continue
        if digests.get(c.id):
            first_image[digests[c.id]] = c.id
        first_found[found] = c.id
    return out


def _detections_key(result) -> str:
    """A detection result's points as text, whichever capture it belongs to."""
    enc = detect_cache.encode_result(result)
    if "mirror" in enc:
        enc["mirror"] = dict(enc["mirror"], capture_id=None)
    return json.dumps(enc, sort_keys=True)
