"""Calibration core: pure computation plus its explicit readers and writers.

Public names are re-exported here; modules are one per concern (camera model, boards, pattern,
observations, session format, result format) and one per pipeline stage.
"""

from calib.boards import CharucoSpec
from calib.camera import CameraModel
from calib.errors import CalibrationError, FormatError, ProcamError, SessionError, SpecError
from calib.observations import BoardObservation, MirrorView, ProjectorView, SessionObservations, Skipped
from calib.pattern import PatternSpec
from calib.result import CalibrationResult, MirrorPlane
from calib.session import Capture, RigInfo, SessionManifest, SessionStore

__all__ = [
    "BoardObservation", "CalibrationError", "CalibrationResult", "CameraModel", "Capture", "CharucoSpec",
    "FormatError", "MirrorPlane", "MirrorView", "PatternSpec", "ProcamError", "ProjectorView", "RigInfo",
    "SessionError", "SessionManifest", "SessionObservations", "SessionStore", "SpecError", "Skipped",
]
