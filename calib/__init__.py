"""Calibration core: pure computation plus its explicit readers and writers.

Subpackages by concern (each __init__ lists its modules): models (camera model, boards, pattern,
observations, result), detection (images -> points), paper (the published method, one module per
stage), joint (the joint maximum-likelihood method), quality (trust check, projection uncertainty,
metrics against ground truth), formats (session folder, atomic writes, importers), export (the
calibration for other software: OpenCV, ROS, mrcal, OpenGL, Unity, three.js). At the top:
errors, transforms, epipolar (epipolar geometry of a calibrated rig), pipeline (the method registry
and entry), recalib (on-site recalibration) and synthetic (rigs with exact ground truth).
The names most code needs are re-exported here. Layout: docs/CONVENTIONS.md, "Where things are".
"""

from calib.errors import CalibrationError, FormatError, ProcamError, SessionError, SpecError
from calib.formats.session import Capture, RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import BoardObservation, MirrorView, ProjectorView, SessionObservations, Skipped
from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult, MirrorPlane

__all__ = [
    "BoardObservation", "CalibrationError", "CalibrationResult", "CameraModel", "Capture", "CharucoSpec",
    "FormatError", "MirrorPlane", "MirrorView", "PatternSpec", "ProcamError", "ProjectorView", "RigInfo",
    "SessionError", "SessionManifest", "SessionObservations", "SessionStore", "SpecError", "Skipped",
]
