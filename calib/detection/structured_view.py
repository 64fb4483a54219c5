"""One structured-light projector capture -> a ProjectorView: the board, and board points with the
projector pixels that light them.

Stages (each its own module): the board's ChArUco corners in the sequence's white frame
(calib.detection.detect.detect_board; the capture is refused when they moved by more than MAX_MOTION_PX
by the closing white frame), the per-pixel decoding (calib.detection.structured_light), and
the projector pixel of each chosen camera point from a local homography
(calib.detection.local_homography). The points (BoardPoints):
  - CORNERS: the detected ChArUco corners, their homographies fitted over the white squares' pixels
    around them (the black squares are masked out; a larger window, CORNER_HALF_WINDOW_PX), as Moreno &
    Taubin do;
  - BLANK_GRID: camera pixels on a lattice `grid_step_px` apart (windows that do not overlap, so the
    points' errors are independent) where at least GRID_MIN_VALID of the window decoded: the board's
    blank area and its white border;
  - BOTH.
The view's pattern_cam_px are those camera pixels and pattern_proj_px the fitted projector pixels, so
both calibration methods take them like circle centres (the camera pixel maps onto the board through the
board's pose); here the camera side is exact (grid) or a detected corner, and the projector side carries
the fit's uncertainty, returned beside the view and, carried into camera pixels (camera_sigma_px), in
the view's pattern_sigma_px: the joint adjustment weighs each point by it.

Entry point: `detect_structured_view(images, spec, board, projector_size, mirrored) -> StructuredView |
DetectionFailure`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np

from calib.detection.detect import detect_board
from calib.detection.local_homography import HALF_WINDOW_PX, LocalProjectorPoints, fit_local_homographies
from calib.detection.response import CameraResponse
from calib.detection.structured_light import MIN_CONTRAST, DecodedMap, decode_sequence
from calib.errors import SpecError
from calib.models.boards import CharucoSpec
from calib.models.observations import DetectionFailure, ProjectorView
from calib.models.structured_light import StructuredLightSpec

#: half window around a ChArUco corner: half of it is black squares, so it needs a larger one
CORNER_HALF_WINDOW_PX = 10
#: a lattice point is used when at least this share of its window decoded
GRID_MIN_VALID = 0.9
#: fewer board points than this with a projector pixel and the capture is not used
MIN_POINTS = 6
#: a board whose corners moved more than this between the sequence's first and closing white frames
#: (board_motion_px) moved (corner noise is some 0.05-0.15 px, less once fitted over the corners; a board
#: held by hand drifts by a pixel within a quarter of a second)
MAX_MOTION_PX = 0.5


class BoardPoints(str, enum.Enum):
    CORNERS = "corners"
    BLANK_GRID = "blank-grid"
    BOTH = "both"


@dataclass(frozen=True, eq=False)
class StructuredView:
    """The view, each of its pattern points' fit (`points`, in the view's point order), the decoded map
    (its `counts` say how many pixels decoded and why the others did not), how many requested points
    got no projector pixel (`n_failed_points`: unlit, masked or one-sided windows), and `lit_share`
    (lit_share_of), so a board partly outside the projection can be told so."""

    view: ProjectorView
    points: LocalProjectorPoints
    decoded: DecodedMap
    n_failed_points: int
    lit_share: float  # of the image area inside the detected ChArUco corners, the part the projector lights


def grid_points(decoded: DecodedMap, step_px: int, half_window_px: int = HALF_WINDOW_PX,
                min_valid: float = GRID_MIN_VALID) -> np.ndarray:
    """(N, 2) camera pixels on the lattice (multiples of `step_px`) whose window decoded to at least
    `min_valid`."""
    if step_px < 1:
        raise SpecError(f"grid step must be >= 1 px, got {step_px}")
    k = 2 * int(half_window_px) + 1
    frac = cv2.boxFilter(decoded.valid.astype(np.float32), -1, (k, k), normalize=True, borderType=cv2.BORDER_CONSTANT)
    H, W = decoded.shape
    ys, xs = np.mgrid[half_window_px:H - half_window_px:step_px, half_window_px:W - half_window_px:step_px]
    sel = frac[ys, xs] >= min_valid
    return np.column_stack([xs[sel], ys[sel]]).astype(float)


def board_motion_px(first, last) -> float:
    """How far (camera px) the board moved between two detections of it (the first and the closing white
    frame of a sequence, the first and last frame of a mirror placement): the largest displacement, over
    the ChArUco corners found in both, of the homography that maps the first corners onto the last.
    A flat board's motion is such a homography; fitting it over every corner averages the corners' noise
    out, where the largest single corner's displacement would call a still board moved when one corner
    is noisy. inf when the closing frame has no board or fewer than 4 corners in common."""
    import cv2

    if not first or not last:
        return float("inf")
    common, a, b = np.intersect1d(np.asarray(first.ids), np.asarray(last.ids), return_indices=True)
    if len(common) < 4:
        return float("inf")
    p = np.asarray(first.corners_px, np.float64)[a].reshape(-1, 1, 2)
    q = np.asarray(last.corners_px, np.float64)[b].reshape(-1, 1, 2)
    H, _ = cv2.findHomography(p, q, 0)
    if H is None or not np.isfinite(H).all():
        return float("inf")
    d = cv2.perspectiveTransform(p, H).reshape(-1, 2) - p.reshape(-1, 2)
    return float(np.hypot(d[:, 0], d[:, 1]).max())


def motion_refusal(moved_px: float) -> str | None:
    """Why a sequence whose board moved by `moved_px` (board_motion_px) is refused; None when it held still."""
    if moved_px <= MAX_MOTION_PX:
        return None
    how = "out of view" if not np.isfinite(moved_px) else f"by {moved_px:.1f} px"
    return (f"the board moved during the sequence ({how} between its first and last white frames): hold it "
            "still and capture this placement again")


def lit_share_of(decoded: DecodedMap, corners_px: np.ndarray, min_contrast: float = MIN_CONTRAST) -> float:
    """Share of the image area inside the convex hull of the ChArUco corners that the projector lights:
    `lit` (median-filtered over 5 x 5, so that no noise spike counts) above `min_contrast`, with the holes
    of up to 1.5 squares closed (a black square of a dim board reflects too little to show the light
    itself)."""
    pts = np.asarray(corners_px, np.float32).reshape(-1, 2)
    if len(pts) < 3:
        return 0.0
    hull = cv2.convexHull(pts).reshape(-1, 2)
    mask = np.zeros(decoded.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    if not mask.any():
        return 0.0
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    square_px = float(np.median(d.min(axis=1)))
    k = max(3, int(round(1.5 * square_px)) | 1)
    lit = cv2.medianBlur(np.clip(decoded.lit, 0, 255).astype(np.uint8), 5)
    # a closing fills the black squares (holes narrower than the kernel) without moving the light's edge
    near = cv2.morphologyEx((lit >= min_contrast).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((k, k), np.uint8))
    return float(near[mask > 0].mean())


def detect_structured_view(images, spec: StructuredLightSpec, board: CharucoSpec, projector_size: tuple[int, int],
                           mirrored: bool, capture_id: str = "", points: BoardPoints = BoardPoints.BLANK_GRID, *,
                           half_window_px: int = HALF_WINDOW_PX, grid_step_px: int | None = None,
                           corner_half_window_px: int = CORNER_HALF_WINDOW_PX,
                           response: CameraResponse | None = None, min_corners: int = 6):
    """Detect one structured-light capture (module docstring): StructuredView, or DetectionFailure with
    a reason when the board is not found, the sequence does not decode, or too few points remain."""
    images = list(images)
    points = BoardPoints(points)
    try:
        decoded = decode_sequence(images, spec, projector_size, response=response)
    except SpecError as e:
        return DetectionFailure(f"structured-light sequence: {e}")
    obs = detect_board(images[0], board, mirrored, min_corners, response)
    if not obs:
        return DetectionFailure(f"board not found in the sequence's white frame ({obs.reason})")
    moved = motion_refusal(board_motion_px(obs, detect_board(images[-1], board, mirrored, min_corners, response)))
    if moved is not None:
        return DetectionFailure(moved)
    n_valid = decoded.counts["valid"]
    if n_valid == 0:
        c = decoded.counts
        if c["saturated"] > c["unlit"]:
            return DetectionFailure("the projector's light saturates the camera on the board: lower the exposure")
        return DetectionFailure("no camera pixel decoded: the board is not lit by the projector, or the frames "
                                "are too dark (raise the exposure)")
    fits = []
    if points in (BoardPoints.CORNERS, BoardPoints.BOTH):
        fits.append(fit_local_homographies(decoded, np.asarray(obs.corners_px, float), corner_half_window_px))
    if points in (BoardPoints.BLANK_GRID, BoardPoints.BOTH):
        step = int(grid_step_px) if grid_step_px is not None else 2 * int(half_window_px) + 1
        fits.append(fit_local_homographies(decoded, grid_points(decoded, step, half_window_px), half_window_px))
    fit = fits[0] if len(fits) == 1 else LocalProjectorPoints(
        *(np.concatenate([getattr(f, k) for f in fits]) for k in ("cam_px", "proj_px", "cov_px2", "n_pixels",
                                                                   "n_rejected", "rms_px")),
        fits[0].reasons + fits[1].reasons)
    ok = fit.ok
    if ok.sum() < MIN_POINTS:
        return DetectionFailure(f"only {int(ok.sum())} board points have a decoded projector position (need "
                                f"{MIN_POINTS}): the projector lights too little of the board")
    sel = np.flatnonzero(ok)
    kept = LocalProjectorPoints(*(_take(a, sel) for a in (fit.cam_px, fit.proj_px, fit.cov_px2, fit.n_pixels,
                                                          fit.n_rejected, fit.rms_px)),
                                tuple(fit.reasons[i] for i in sel))
    view = ProjectorView(capture_id, obs, kept.cam_px, kept.proj_px, None,
                         camera_sigma_px(kept.cam_px, kept.proj_px, kept.cov_px2))
    return StructuredView(view, kept, decoded, int((~ok).sum()), lit_share_of(decoded, obs.corners_px))


#: the smallest camera-pixel sigma a point is given (a fit over noiseless pixels has none at all)
MIN_SIGMA_PX = 1e-4


def camera_sigma_px(cam_px, proj_px, cov_px2) -> np.ndarray:
    """Each point's 1-sigma per coordinate in camera pixels: its projector pixel's covariance carried
    through the view's projector-to-camera map, here the homography of the board plane fitted over the
    view's points (a Jacobian needs no more: lens distortion bends the map far less than it scales it)."""
    cam, proj = np.asarray(cam_px, float), np.asarray(proj_px, float)
    cov = np.asarray(cov_px2, float).reshape(-1, 2, 2)
    H, _ = cv2.findHomography(proj, cam, 0)
    if H is None:  # degenerate (collinear points): the points alike
        return np.full(len(cam), 1.0)
    w = proj @ H[2, :2] + H[2, 2]
    c = (proj @ H[:2, :2].T + H[:2, 2]) / w[:, None]
    # d cam / d proj of c = (A p + b) / (h . p + h33): (A - c h^T) / w
    J = (H[None, :2, :2] - c[:, :, None] * H[None, 2, None, :2]) / w[:, None, None]
    cov_cam = J @ cov @ np.transpose(J, (0, 2, 1))
    s = np.sqrt(np.maximum(np.trace(cov_cam, axis1=1, axis2=2) / 2.0, 0.0))
    ok = np.isfinite(s)  # a point the map sends to infinity (w = 0) takes the others' median
    return np.where(ok, np.maximum(s, MIN_SIGMA_PX), np.median(s[ok]) if ok.any() else 1.0)


def _take(a, sel):
    out = np.asarray(a)[sel]
    out.setflags(write=False)
    return out
