"""The capture steps' confidence after each capture (Plan.stop_on_confidence): the session so far
calibrated in the station's detection thread, the 1-sigmas of the projector step and of the mirror step
(the mirror normal) against their targets (calib.quality.confidence, docs/CALIBRATION.md "Stopping when
confident"). One calibration judges both steps: the mirror normal can be judged only once the projector
step has captures."""

from __future__ import annotations

from collections.abc import Callable

from calib.errors import ProcamError
from calib.models.observations import STEP_PROJECTOR
from calib.models.vocab import Step
from calib.quality.confidence import Confidence, confidence_of, unconfident


def step_confidences(machine) -> tuple[Confidence, Confidence | None, dict | None, object]:
    """Calibrate the session's captures so far (its kept detections; joint) and judge the projector step
    and, on a mirror rig, the mirror step; with that calibration's projection-uncertainty grids
    (calibration.json's "projection_uncertainty"; None when it failed or gave none), where the next
    placement helps most, and the calibration itself (None when it failed)."""
    from calib.pipeline import calibrate_session

    from app.station.session_steps import mirror_step
    from app.station.structured_step import min_projector_captures

    mirror = None if machine.direct or machine.mirror_method is None else mirror_step(machine.mirror_method)
    need = min_projector_captures(machine)
    why = None
    if len(machine.captures_of(STEP_PROJECTOR)) < need:
        why = f"fewer than {need} projector captures"
    else:
        try:
            result = calibrate_session(machine.store.folder, camera_intrinsics=machine.intrinsics_path, workers=1)
        except ProcamError as e:
            why = str(e).split("\n")[0]
    if why is not None:
        return unconfident(Step.PROJECTOR, why), None if mirror is None else unconfident(mirror, why), None, None
    pu = result.projection_uncertainty if isinstance(result.projection_uncertainty, dict) else None
    return (confidence_of(result, Step.PROJECTOR), None if mirror is None else confidence_of(result, mirror), pu,
            result)


def _judge(machine) -> tuple[Confidence, Confidence | None]:
    """Judge both steps on the captures so far and keep the judgements (and the grids, and with
    Plan.ask_pose the pose to ask for next) in the machine."""
    proj, mirror, pu, result = step_confidences(machine)
    if machine.plan.ask_pose:
        machine.set_asked(_asked(machine, result, proj))
    machine.set_projection_uncertainty(pu)
    machine.set_projector_confidence(proj)
    if mirror is not None:
        machine.set_mirror_confidence(mirror)
    return proj, mirror


def _asked(machine, result, proj: Confidence):
    """The pose the projector step asks for next (app/station/asked.py), None when it asks for none: its
    calibration failed, it is confident, or no candidate could be predicted."""
    from app.station.asked import asked_target, board_layout
    from app.station.targets import candidate_positions

    if result is None or proj.all_met:
        return None
    layout = getattr(machine, "board_layout", None) or board_layout(None, machine.manifest)
    return asked_target(machine, result, layout, candidate_positions(machine))


def update_after(machine, capture_id: str, log: Callable[[str], None]) -> None:
    """After `capture_id` was detected: the steps' confidence, when the plan stops on it (a mirror capture
    is judged once the projector step has its minimum)."""
    if not machine.plan.stop_on_confidence:
        return
    cap = next((c for c in machine.manifest.captures if c.id == capture_id), None)
    if cap is None:
        return
    from app.station.structured_step import min_projector_captures

    if cap.step != STEP_PROJECTOR and len(machine.captures_of(STEP_PROJECTOR)) < min_projector_captures(machine):
        return  # the mirror step before the projector step: nothing to judge yet
    proj, mirror = _judge(machine)
    for name, conf in (("projector", proj), ("mirror", mirror)):
        own = (name == "projector") == (cap.step == STEP_PROJECTOR)
        if conf is None or (not own and conf.all_met == (name == "projector")):
            continue  # each step reported after its own captures; the other only when it says something new
        head = f"{name} step confident after {capture_id}: " if conf.all_met else f"{name} step after {capture_id}, "
        log(head + "; ".join(conf.lines()))


def judge_resumed(machine, log: Callable[[str], None]) -> None:
    """A resumed session stopping on confidence, in a capture step: judge its captures once, so that a step
    confident before the stop is not asked for more (the judgements are not saved: they are recomputed)."""
    from app.station.session_steps import CAPTURE_STATES
    from app.station.structured_step import min_projector_captures

    if not machine.plan.stop_on_confidence or machine.state not in CAPTURE_STATES:
        return
    if len(machine.captures_of(STEP_PROJECTOR)) < min_projector_captures(machine):
        return
    proj, mirror = _judge(machine)
    for name, conf in (("projector", proj), ("mirror", mirror)):
        if conf is not None:
            log(f"{name} step on resume{' confident' if conf.all_met else ''}: " + "; ".join(conf.lines()))
