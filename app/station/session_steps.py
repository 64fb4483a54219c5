"""The session's steps (the machine's states, in the paper's guideline's order), their titles, the
operator's actions, and the refusal an action that is not possible now raises (app.station.machine)."""

from __future__ import annotations

from calib.errors import ProcamError
from calib.models.observations import STEP_REAL_MIRROR, STEP_REAL_VIRTUAL
from calib.models.vocab import MirrorMethod

CHECK_RIG = "check_rig"
MIRROR_CAPTURE = "mirror_capture"
PROJECTOR_CAPTURE = "projector_capture"
CALIBRATION = "calibration"
VERIFICATION = "verification"
DONE = "done"
STATES = (CHECK_RIG, MIRROR_CAPTURE, PROJECTOR_CAPTURE, CALIBRATION, VERIFICATION, DONE)
CAPTURE_STATES = (MIRROR_CAPTURE, PROJECTOR_CAPTURE)

STATE_TITLES = {
    CHECK_RIG: "Check the rig",
    MIRROR_CAPTURE: "Mirror capture",
    PROJECTOR_CAPTURE: "Projector capture",
    CALIBRATION: "Calibration",
    VERIFICATION: "Verification",
    DONE: "Done",
}

ACTIONS = ("start", "choose_mirror_method", "set_board_thickness", "capture", "delete", "retake", "proceed", "back",
           "skip_camera", "use_camera_calibration", "calibrate", "verify", "finish")


def mirror_step(method: str) -> str:
    """The capture step of a mirror method (real-virtual, real-mirror)."""
    return {MirrorMethod.REAL_VIRTUAL: STEP_REAL_VIRTUAL, MirrorMethod.REAL_MIRROR: STEP_REAL_MIRROR}[method]


class ActionRefused(ProcamError):
    """An operator action that is not possible now; `reason` says why and what to do instead."""

    def __init__(self, action: str, reason: str):
        self.action = action
        self.reason = reason
        super().__init__(f"cannot {action.replace('_', ' ')}: {reason}")
