"""Where the verification looks (behind app/verification.py): the board as the projector lights it,
the pixels spread over it, and the board's pose for the predicted-curve overlay."""

from __future__ import annotations

import cv2
import numpy as np

from app._verification_report import VerificationError
from calib.models.result import CalibrationResult

#: Default grid of automatically picked pixels (columns, rows).
DEFAULT_GRID = (4, 3)


def region_mask(shape, lit: np.ndarray, board_region=None, close_px: int | None = None) -> np.ndarray:
    """Where to pick pixels: the board as the projector lights it. The lit mask's holes (the printed
    area's black squares) are closed with a disc of `close_px` (default 1/30 of the image width), the
    largest connected part is kept, within `board_region` (a bool mask, a box (x0, y0, x1, y1), or an
    (N, 2) polygon, camera pixels) when given."""
    H, W = shape
    mask = np.asarray(lit, bool).astype(np.uint8)
    k = int(close_px if close_px is not None else max(15, W // 30)) | 1
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
    if board_region is not None:
        br = board_region
        if isinstance(br, np.ndarray) and br.dtype == bool:
            if br.shape != (H, W):
                raise VerificationError(f"board_region mask must be {W}x{H}")
            mask &= br
        else:
            try:
                a = np.asarray(br, float)
            except (TypeError, ValueError):
                a = np.zeros(0)
            m = np.zeros((H, W), np.uint8)
            if a.shape == (4,):
                x0, y0, x1, y1 = a
                m[max(int(np.ceil(y0)), 0) : int(np.floor(y1)) + 1, max(int(np.ceil(x0)), 0) : int(np.floor(x1)) + 1] = 1
            elif a.ndim == 2 and a.shape[1] == 2 and len(a) >= 3:
                cv2.fillPoly(m, [np.round(a).astype(np.int32)], 1)
            else:
                raise VerificationError("board_region must be a bool mask, a box (x0, y0, x1, y1) or an (N, 2) polygon")
            mask &= m.astype(bool)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros((H, W), bool)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k


def grid_pixels(mask: np.ndarray, grid=DEFAULT_GRID, margin_px: int = 12, prefer: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) pixels spread over `mask`: its bounding box split in cols x rows cells, in each cell the
    pixel nearest to the cell's centre that is at least `margin_px` inside the mask, preferably one of
    `prefer` (e.g. the brightly lit pixels: white, not a black square) when the cell has some. Cells
    without a candidate are skipped."""
    cols, rows = int(grid[0]), int(grid[1])
    if cols < 1 or rows < 1:
        raise VerificationError(f"grid must be at least 1x1, got {cols}x{rows}")
    m = np.asarray(mask, bool).astype(np.uint8)
    inner = cv2.distanceTransform(m, cv2.DIST_L2, 5) >= margin_px
    ys, xs = np.nonzero(inner)
    if len(xs) == 0:
        return np.zeros((0, 2))
    good = np.ones(len(xs), bool) if prefer is None else np.asarray(prefer, bool)[ys, xs]
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    out = []
    for r in range(rows):
        for c in range(cols):
            cx0, cx1 = x0 + (x1 - x0) * c / cols, x0 + (x1 - x0) * (c + 1) / cols
            cy0, cy1 = y0 + (y1 - y0) * r / rows, y0 + (y1 - y0) * (r + 1) / rows
            sel = (xs >= cx0) & (xs < cx1) & (ys >= cy0) & (ys < cy1)
            if not sel.any():
                continue
            if (sel & good).any():
                sel &= good
            px, py = xs[sel], ys[sel]
            k = int(np.argmin((px - (cx0 + cx1 - 1) / 2) ** 2 + (py - (cy0 + cy1 - 1) / 2) ** 2))
            out.append((float(px[k]), float(py[k])))
    return np.array(out, float).reshape(-1, 2)


def estimate_board_pose(image: np.ndarray, board, result: CalibrationResult, response=None) -> np.ndarray | None:
    """T_cam_board of the ChArUco `board` (CharucoSpec) in a camera image, with the calibration's camera
    model (and mirror: the board is then detected mirrored). None when the board is not found. Used
    for the predicted-curve overlay only; the measurement never depends on it. `response`: the camera's
    tone curve, as detection uses it (corners refined in light)."""
    from calib.detection.detect import detect_board
    from calib.paper.board_pose import solve_board_pose, usable_reason

    img = np.clip(np.asarray(image), 0, 255).astype(np.uint8)
    obs = detect_board(img, board, mirrored=result.mirror is not None, response=response)
    if not obs or usable_reason(board, obs) is not None:
        return None
    pose = solve_board_pose(result.camera, board, obs)
    return pose.physical(None if result.mirror is None else result.mirror.reflection())
