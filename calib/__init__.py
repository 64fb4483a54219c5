"""Calibration core: pure computation plus its explicit readers and writers.

Public names are re-exported here; modules are one per concern (camera model, boards, pattern,
observations, session format, result format) and one per pipeline stage.
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
