"""ChArUco boards in camera images: entry `detect_board(image, spec, mirrored)` -> BoardObservation or
DetectionFailure.

A mirrored board (seen through the mirror) is detected in the horizontally flipped image and its corners
mapped back with x -> (W - 1) - x, so every returned pixel coordinate is in the ORIGINAL image (pixel
(0, 0) = centre of the top-left pixel). A failed detection is a `DetectionFailure` value with a reason a
person can read, never an exception.
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

#: adaptive-threshold window sizes of the marker search (min, max, step). A single window first (about
#: 30 % faster on 1080p sessions); when that leaves the board incomplete, OpenCV's default set.
_FAST_WINDOWS = (9, 9, 10)
_FULL_WINDOWS = (3, 23, 10)


def _aruco_params(windows) -> cv2.aruco.DetectorParameters:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # ChArUco corners are refined later
    params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax, params.adaptiveThreshWinSizeStep = windows
    return params


@per_thread
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
    pts = np.asarray([np.asarray(c, np.float64).reshape(4, 2) for c in corners])
    keep = [k for k in range(len(ids)) if int(ids[k]) in obj]
    if len(keep) >= 2:
        src = np.concatenate([obj[int(ids[k])] for k in keep])
        dst = pts[keep].reshape(-1, 2)
        side = np.median(np.linalg.norm(pts[keep, 1] - pts[keep, 0], axis=1))
        H, mask = cv2.findHomography(src, dst, cv2.RANSAC, max(3.0, 0.3 * float(side)), maxIters=500)
        if H is not None:
            proj = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 4, 2)
            err = np.linalg.norm(proj - dst.reshape(-1, 4, 2), axis=2)
            good = (mask.reshape(-1, 4).sum(axis=1) >= 3)
            mean_err = err.mean(axis=1)
            best: dict[int, tuple[float, int]] = {}
            for j, k in enumerate(keep):
                if good[j] and (int(ids[k]) not in best or mean_err[j] < best[int(ids[k])][0]):
                    best[int(ids[k])] = (float(mean_err[j]), k)
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
    ids = np.ravel(ids).astype(int)
    known = np.array([int(i) in obj for i in ids], bool)
    if not known.any():
        return [], np.zeros((0, 1), np.int32)
    ids = ids[known]
    pts = np.asarray([np.asarray(c, float).reshape(4, 2) for c, k in zip(corners, known) if k])
    pred = cv2.perspectiveTransform(np.concatenate([obj[int(i)] for i in ids]).reshape(-1, 1, 2), H).reshape(-1, 4, 2)
    agree = np.isin(ids, np.ravel(trusted_ids)) | (np.linalg.norm(pred - pts, axis=2).max(axis=1) < 0.25 * side)
    if len(np.unique(ids[agree])) != agree.sum():
        return trusted_corners, trusted_ids
    return [q.astype(np.float32).reshape(1, 4, 2) for q in pts[agree]], ids[agree].astype(np.int32).reshape(-1, 1)


def _charuco_in(img: np.ndarray, spec: CharucoSpec, legacy: bool = False, fast_only: bool = False):
    """(corners (N, 2) or None, ids (N,) or None, board markers (M, 4, 2), corners OpenCV's strict
    rule accepts) found in `img`. `fast_only`: the single-window marker search only."""
    arucos, detectors, obj = _detectors(spec, legacy)
    result = _charuco_with(img, spec, arucos[0], detectors, obj)
    if not fast_only and len(result[1]) < spec.n_corners:
        # OpenCV's full set of thresholding windows costs three single-window searches: run it only where
        # the corners not found can be, around the board the corners found predict (nowhere when every
        # missing corner lies outside the image), else on the whole image
        box = _board_box(result[0], result[1], (0, 0), spec, img.shape)
        if box != ():
            x0, y0, x1, y1 = box if box is not None else (0, 0, img.shape[1], img.shape[0])
            corners, ids, markers, strict = _charuco_with(img[y0:y1, x0:x1], spec, arucos[1], detectors, obj)
            if len(ids) > len(result[1]) or (len(ids) == len(result[1]) and len(markers) > len(result[2])):
                result = (corners + [x0, y0], ids, markers + [x0, y0], strict)
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


def detect_board(image: np.ndarray, spec: CharucoSpec, mirrored: bool, min_corners: int = 6,
                 response: CameraResponse | None = None):
    """ChArUco corners of `spec` in `image` (gray or BGR) -> BoardObservation | DetectionFailure.

    `mirrored`: the board is seen through the mirror; detect in the flipped image and map back.
    `response`: the camera's recorded tone curve (calib.detection.response); the corners are then
    refined on the image's levels linearised (see _refinement_image)."""
    gray = to_gray(image)
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
        corners = flip_x(corners, gray.shape[1])
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
    allpx = map_board(H, obj)
    step = map_board(H, obj[ids] + [spec.square_length, 0.0])
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
        ref = cv2.cornerSubPix(roi, start.copy(), (int(hw), int(hw)), (-1, -1), SUBPIX_CRITERIA).reshape(-1, 2)
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
                                 SUBPIX_CRITERIA).reshape(1, 2).astype(float)
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
    pts = np.asarray(pts, float).reshape(-1, 2)
    if len(pts) == 0:
        return np.empty(0)
    # every patch at once: a patch's pixels share its centre's sub-pixel phase, so each is one bilinear
    # blend of four integer-shifted windows (edges replicated, as cv2.getRectSubPix samples them)
    h, w = smooth.shape
    off = np.arange(-int(hw), int(hw) + 1)
    base = np.floor(pts)
    a = (pts[:, 0] - base[:, 0])[:, None, None]
    b = (pts[:, 1] - base[:, 1])[:, None, None]
    xs = base[:, 0].astype(int)[:, None] + off
    ys = base[:, 1].astype(int)[:, None] + off
    x0, x1 = np.clip(xs, 0, w - 1)[:, None, :], np.clip(xs + 1, 0, w - 1)[:, None, :]
    y0, y1 = np.clip(ys, 0, h - 1)[:, :, None], np.clip(ys + 1, 0, h - 1)[:, :, None]
    img = np.asarray(smooth, np.float64)
    patch = (1 - b) * ((1 - a) * img[y0, x0] + a * img[y0, x1]) + b * ((1 - a) * img[y1, x0] + a * img[y1, x1])
    span = patch.max(axis=(1, 2)) - patch.min(axis=(1, 2))
    diff = np.abs(patch - patch[:, ::-1, ::-1]).mean(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(span > 1e-6, diff / span, 1.0)
