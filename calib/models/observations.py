"""What the detection stage hands to the calibration stages: measured 2D points, no images.

Every pixel coordinate here is in the ORIGINAL (unflipped) camera image, pixel (0, 0) the centre of the
top-left pixel, even for views seen through the mirror (detection flips, detects and maps back).
Stages that work in the flipped frame convert with CameraModel.flip_points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.models.boards import CharucoSpec
from calib.models.pattern import PatternSpec
from calib.models.vocab import CALIBRATION_STEPS, Step, View

STEP_PROJECTOR = Step.PROJECTOR
STEP_REAL_VIRTUAL = Step.REAL_VIRTUAL
STEP_REAL_MIRROR = Step.REAL_MIRROR
STEPS = CALIBRATION_STEPS

VIEW_MIRROR = View.MIRROR
VIEW_DIRECT = View.DIRECT


def _ro(a, shape_tail, dtype=float):
    a = np.array(a, dtype=dtype).reshape((-1,) + shape_tail)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class DetectionFailure:
    """Why a detection failed, in plain words ("board not found", "pattern partial: 30 of 36 points").
    Returned (never raised) by calib.detection.detect and kept in the detection cache (calib.detection.cache)."""

    reason: str

    def __bool__(self) -> bool:  # a failure is falsy, so `if result:` reads naturally
        return False


@dataclass(frozen=True, eq=False)
class BoardObservation:
    """ChArUco corners found in one image: `ids` index CharucoSpec.corner_points()."""

    ids: np.ndarray
    corners_px: np.ndarray
    mirrored: bool

    def __post_init__(self):
        object.__setattr__(self, "ids", _ro(self.ids, (), int))
        object.__setattr__(self, "corners_px", _ro(self.corners_px, (2,)))
        if len(self.ids) != len(self.corners_px):
            raise ValueError("ids and corners_px differ in length")


@dataclass(frozen=True, eq=False)
class ProjectorView:
    """One projector-calibration capture: the board, and the projected pattern points seen in the
    camera image (`pattern_cam_px`) with the projector pixels they were drawn at (`pattern_proj_px`).

    `pattern_sigma_px`: each point's own 1-sigma in camera pixels (per coordinate), where its detection
    measured one (a structured-light point's local-homography fit); None when every point of the view
    is alike (circle centres: the calibration estimates their one noise level)."""

    capture_id: str
    board: BoardObservation
    pattern_cam_px: np.ndarray
    pattern_proj_px: np.ndarray
    pattern_position: int | None = None
    pattern_sigma_px: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "pattern_cam_px", _ro(self.pattern_cam_px, (2,)))
        object.__setattr__(self, "pattern_proj_px", _ro(self.pattern_proj_px, (2,)))
        if len(self.pattern_cam_px) != len(self.pattern_proj_px):
            raise ValueError("pattern_cam_px and pattern_proj_px differ in length")
        if self.pattern_sigma_px is not None:
            s = _ro(self.pattern_sigma_px, ())
            if len(s) != len(self.pattern_cam_px):
                raise ValueError("pattern_sigma_px and pattern_cam_px differ in length")
            if not np.all(np.isfinite(s) & (s > 0)):
                raise ValueError("pattern_sigma_px must be positive and finite")
            object.__setattr__(self, "pattern_sigma_px", s)


@dataclass(frozen=True, eq=False)
class MirrorView:
    """One mirror-calibration capture. Real-virtual: `real` (direct view) and `virtual` (through the
    mirror, mirrored=True) of the same board. Real-mirror: `real` only (board lying on the mirror)."""

    capture_id: str
    method: str
    real: BoardObservation | None
    virtual: BoardObservation | None = None


@dataclass(frozen=True)
class Skipped:
    capture_id: str
    image: str
    reason: str
    copy_of: str | None = None  # the capture this one repeats (the same image or detections), if it is a copy


@dataclass(frozen=True, eq=False)
class SessionObservations:
    """Everything the calibration stages need, in one immutable bundle."""

    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    view: str  # VIEW_MIRROR or VIEW_DIRECT (projector-calibration images)
    projector_board: CharucoSpec
    pattern: PatternSpec
    projector_views: tuple[ProjectorView, ...]
    mirror_board: CharucoSpec | None = None
    mirror_views: tuple[MirrorView, ...] = ()
    board_thickness: float = 0.0  # real-mirror: printed face above the mirror surface, board units
    skipped: tuple[Skipped, ...] = field(default_factory=tuple)

    @property
    def units(self) -> str:
        return self.projector_board.units
