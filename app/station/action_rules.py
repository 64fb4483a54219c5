"""When each operator action of the session machine is possible, and why not when it is not.

Whether the current step allows an action is the transition table's answer (transitions'
`may_<trigger>`, conditions included) for the actions that move the machine, and for those that stay in
their step the steps listed in the action's `Rule`; each action adds only its own checks, one small
guard (enough captures, a readable intrinsics file, ...). `SessionMachine.why_not` asks the rules; every
function here takes the machine (`m`) and reads only its public state.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from app.station.operator_files import checked_intrinsics
from app.station.session_steps import (
    ACTIONS, CALIBRATION, CAPTURE_STATES, CHECK_RIG, DONE, MIRROR_CAPTURE, PROJECTOR_CAPTURE, STATE_TITLES, VERIFICATION,
    mirror_step,
)
from app.words import plural
from calib.errors import ProcamError
from calib.formats.session import MIRROR_METHODS
from calib.models.observations import STEP_PROJECTOR

FILE_CHECKED = object()  # why_not("skip_camera", FILE_CHECKED): the file was read and checked already


def _title(m) -> str:
    return STATE_TITLES[m.state]


def guard_start(m, _arg) -> str | None:
    if not m.rig_checks:
        return "the rig has not been checked yet"
    bad = [c for c in m.rig_checks if not c.ok]
    if bad:
        return "the rig check failed: " + "; ".join(f"{c.name}: {c.detail}" for c in bad)
    return None


def guard_mirror_method(m, arg) -> str | None:
    if arg is not None and arg not in MIRROR_METHODS:
        return f"unknown mirror method '{arg}' (one of {', '.join(MIRROR_METHODS)})"
    if m.manifest.mirror_board is None:
        return "the session has no mirror board; it cannot calibrate the mirror"
    if arg is not None and arg != m.mirror_method:
        others = m.mirror_captures()
        if others:
            return (f"{plural(len(others), m.mirror_method + ' capture')} taken; delete them first to "
                    f"switch to {arg}")
    return None


def guard_thickness(m, arg) -> str | None:
    if arg is None:
        return None
    try:
        v = float(arg)
    except (TypeError, ValueError):
        return f"the board thickness must be a number ({m.manifest.units}), got '{arg}'"
    if not v >= 0:
        return f"the board thickness must be 0 or more ({m.manifest.units}), got {arg}"
    return None


def guard_capture(m, _arg) -> str | None:
    if m.state == MIRROR_CAPTURE and m.mirror_method is None:
        return "choose the mirror method (real-virtual or real-mirror) first"
    if m.target is not None:
        return None
    if m.state == MIRROR_CAPTURE:
        return (f"all {m.mirror_total} mirror captures are taken; press 'Next step', or delete or "
                "retake a capture")
    return f"all {m.projector_total} projector captures are taken; calibrate, or delete or retake a capture"


def guard_capture_id(m, arg) -> str | None:
    if arg is None:
        return "choose a capture first"
    if not any(c.id == arg for c in m.manifest.captures):
        return f"there is no capture '{arg}' in this session"
    return None


def guard_retake(m, arg) -> str | None:
    reason = guard_capture_id(m, arg)
    if reason is None:
        cap = next(c for c in m.manifest.captures if c.id == arg)
        if cap.step != STEP_PROJECTOR and m.direct:
            return "this rig has no mirror step; delete the capture instead"
    return reason


def guard_proceed(m, _arg) -> str | None:
    if m.state == MIRROR_CAPTURE:
        if m.mirror_method is None:
            return "choose the mirror method and take the mirror captures first"
        n = len(m.captures_of(mirror_step(m.mirror_method)))
        need = m.plan.min_mirror(m.mirror_method)
        return f"take at least {need} {m.mirror_method} captures first ({n} so far)" if n < need else None
    if m.target is not None:  # the projector step, not complete
        n = len(m.captures_of(STEP_PROJECTOR))
        return (f"{n} of {m.projector_total} projector captures are taken; finish them, or "
                "press Calibrate to calibrate with what is there")
    return None


def guard_skip_camera(m, arg) -> str | None:
    if arg is FILE_CHECKED:
        return None
    if not arg:
        return "give the path of an intrinsics file (a calibration.json or a camera JSON)"
    try:
        checked_intrinsics(arg, m.manifest.rig.camera_size)
    except ProcamError as e:
        return str(e)
    return None


def guard_calibrate(m, _arg) -> str | None:
    from app.station.structured_step import min_projector_captures

    n, need = len(m.captures_of(STEP_PROJECTOR)), min_projector_captures(m)
    if n < need:
        return f"take at least {need} projector captures first ({n} so far)"
    if m.direct:
        return None
    if m.mirror_method is None:
        return "the mirror has no captures yet; go back to the mirror step"
    have = len(m.captures_of(mirror_step(m.mirror_method)))
    need = m.plan.min_mirror(m.mirror_method)
    if have < need:
        return f"the mirror step needs at least {need} {m.mirror_method} captures ({have} so far)"
    return None


def guard_verify(m, _arg) -> str | None:
    if m.result is None:
        return "calibrate first"
    if m.result_stale:
        return "the captures or the camera model changed since the last calibration; calibrate again"
    return None


def guard_finish(m, _arg) -> str | None:
    if m.state == VERIFICATION:
        return "run the verification first" if m.report is None else None
    return "calibrate first" if m.result is None or m.result_stale else None  # a rig without verification


@dataclass(frozen=True)
class Rule:
    """When an operator action is possible. `where`: a trigger of the transition table (the table and
    its conditions decide) or the states an action that moves nothing is possible in; `refused`: the
    reason when the state does not allow it; `before`: a check that comes before the state's (what no
    step can change); `guard`: the action's own checks once the state allows it."""

    where: str | tuple[str, ...]
    refused: Callable[[object], str]
    guard: Callable[[object, object], str | None] | None = None
    before: Callable[[object, object], str | None] | None = None


_BEFORE_VERIFICATION = (CHECK_RIG, MIRROR_CAPTURE, PROJECTOR_CAPTURE, CALIBRATION)


def _captures_frozen(m) -> str:
    return f"captures cannot change during {_title(m)}; go back to the calibration step first"


def _no_mirror(m, _arg) -> str | None:
    return "this rig views the board directly (overlapping): there is no mirror to calibrate" if m.direct else None


def _no_verifier(m, _arg) -> str | None:
    return "verification is not available in this installation" if not m.has_verification() else None


def _proceed_refused(m) -> str:
    nxt = {CHECK_RIG: "Start", CALIBRATION: "Verify", VERIFICATION: "Finish"}.get(m.state)
    return f"use '{nxt}' to leave the {_title(m)} step" if nxt else "the session is complete"


def _finish_refused(m) -> str:
    if m.state == CALIBRATION:
        return "verify the calibration first"
    if m.state == DONE:
        return "the session is already complete"
    return f"the session ends after calibration and verification (now: {_title(m)})"


def _camera_frozen(_m) -> str:
    return "the camera model cannot change now; go back to the calibration step first"


RULES: dict[str, Rule] = {
    "start": Rule("ev_start", lambda m: "the rig check is already done; go back to it first",
                   guard_start),
    "choose_mirror_method": Rule(
        (CHECK_RIG, MIRROR_CAPTURE),
        lambda m: f"the mirror method is chosen in the mirror step (now: {_title(m)}); go back first",
        guard_mirror_method, before=_no_mirror),
    "set_board_thickness": Rule(
        _BEFORE_VERIFICATION,
        lambda m: "the board thickness cannot change now; go back to the calibration step first",
        guard_thickness),
    "capture": Rule(
        CAPTURE_STATES,
        lambda m: f"nothing is captured in the {_title(m)} step; go back to a capture step to add captures",
        guard_capture),
    "delete": Rule(_BEFORE_VERIFICATION, _captures_frozen, guard_capture_id),
    "retake": Rule("ev_retake",
                    lambda m: "finish the rig check first" if m.state == CHECK_RIG else _captures_frozen(m),
                    guard_retake),
    "proceed": Rule("ev_proceed", _proceed_refused, guard_proceed),
    "back": Rule("ev_back", lambda m: "this is the first step"),
    "skip_camera": Rule(_BEFORE_VERIFICATION, _camera_frozen, guard_skip_camera),
    "use_camera_calibration": Rule(
        _BEFORE_VERIFICATION, _camera_frozen,
        lambda m, _arg: "the camera is already calibrated from the captures" if m.camera_intrinsics is None else None),
    "calibrate": Rule("ev_calibrate", lambda m: f"calibration comes after the captures (now: {_title(m)})",
                       guard_calibrate),
    "verify": Rule("ev_verify", lambda m: f"verification comes after calibration (now: {_title(m)})",
                    guard_verify, before=_no_verifier),
    "finish": Rule("ev_finish", _finish_refused, guard_finish),
}
assert set(RULES) == set(ACTIONS), "every operator action has its rule"
