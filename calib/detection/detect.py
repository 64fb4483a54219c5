"""The detection stages' entry functions under one name, for the callers that import them from here:
`detect_session` and `detect_capture` (calib.detection.session_jobs), `detect_board`
(calib.detection.charuco), `detect_pattern` (calib.detection.pattern), `detect_real_virtual` and
`detect_real_mirror` (calib.detection.mirror_views). The code lives in those modules."""

from calib.detection.charuco import detect_board
from calib.detection.mirror_views import detect_real_mirror, detect_real_virtual
from calib.detection.pattern import detect_pattern
from calib.detection.session_jobs import detect_capture, detect_session
from calib.models.observations import DetectionFailure

__all__ = ["DetectionFailure", "detect_board", "detect_capture", "detect_pattern", "detect_real_mirror",
           "detect_real_virtual", "detect_session"]
