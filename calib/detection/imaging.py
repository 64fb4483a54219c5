"""Image helpers shared by the detection stages (calib.detection.charuco, .pattern, .mirror_views,
.session_jobs): a camera image as 8-bit gray, the mirror flip of pixel coordinates, board points through
a homography, and OpenCV objects cached per thread."""

from __future__ import annotations

import threading
from functools import lru_cache, wraps

import cv2
import numpy as np


def to_gray(image: np.ndarray) -> np.ndarray:
    """`image` (gray, BGR or BGRA; 8 or 16 bits) as a contiguous 8-bit gray image (itself when it is one)."""
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


def flip_x(pts: np.ndarray, width: int) -> np.ndarray:
    """x -> (W - 1) - x: the map between an image and its cv2.flip(img, 1)."""
    out = np.array(pts, float).reshape(-1, 2)
    out[:, 0] = (width - 1) - out[:, 0]
    return out


def per_thread(fn):
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



def map_board(H: np.ndarray, pts) -> np.ndarray | None:
    """Board points -> pixels; None when a point is at or behind the plane's horizon."""
    p = np.column_stack([np.asarray(pts, float), np.ones(len(pts))]) @ H.T
    if np.any(p[:, 2] * np.sign(H[2, 2] if H[2, 2] != 0 else 1.0) <= 1e-9):
        return None
    return p[:, :2] / p[:, 2:3]


#: cornerSubPix's stopping rule for every corner refinement of detection
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
