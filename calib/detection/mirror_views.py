"""The mirror step's views: a board seen directly and in the mirror (`detect_real_virtual`), or lying on
the mirror (`detect_real_mirror`) -> MirrorView or DetectionFailure."""

from __future__ import annotations

import numpy as np

from calib.detection.charuco import detect_board
from calib.detection.imaging import to_gray
from calib.detection.response import CameraResponse
from calib.models.boards import CharucoSpec
from calib.models.observations import (
    STEP_REAL_MIRROR,
    STEP_REAL_VIRTUAL,
    DetectionFailure,
    MirrorView,
)


def detect_real_virtual(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6,
                        response: CameraResponse | None = None):
    """A board seen directly (`real`) and in the mirror (`virtual`) in one image -> MirrorView."""
    gray = to_gray(image)
    real = detect_board(gray, spec, False, min_corners, response)
    if isinstance(real, DetectionFailure):
        return DetectionFailure(f"real board: {real.reason}")
    virtual = detect_board(gray, spec, True, min_corners, response)
    if isinstance(virtual, DetectionFailure):
        return DetectionFailure(f"virtual board (in the mirror): {virtual.reason}")
    return MirrorView(capture_id, STEP_REAL_VIRTUAL, real, virtual)


def detect_real_mirror(image: np.ndarray, spec: CharucoSpec, capture_id: str = "", min_corners: int = 6,
                       response: CameraResponse | None = None):
    """A board lying on the mirror, seen directly -> MirrorView (real only)."""
    real = detect_board(image, spec, False, min_corners, response)
    if isinstance(real, DetectionFailure):
        return real
    return MirrorView(capture_id, STEP_REAL_MIRROR, real, None)
