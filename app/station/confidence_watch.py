"""The projector step's confidence after each of its captures (Plan.stop_on_confidence): the session so
far calibrated in the station's detection thread, its 1-sigmas against their targets
(calib.quality.confidence, docs/CALIBRATION.md "Stopping when confident")."""

from __future__ import annotations

from collections.abc import Callable

from calib.errors import ProcamError
from calib.models.vocab import Step
from calib.quality.confidence import Confidence, confidence_of, unconfident


def projector_confidence(machine) -> Confidence:
    """Calibrate the session's captures so far (its kept detections; joint) and judge the projector step."""
    from calib.pipeline import calibrate_session

    from app.station.structured_step import min_projector_captures

    need = min_projector_captures(machine)
    if len(machine.captures_of(Step.PROJECTOR)) < need:
        return unconfident(Step.PROJECTOR, f"fewer than {need} projector captures")
    try:
        result = calibrate_session(machine.store.folder, camera_intrinsics=machine.intrinsics_path, workers=1)
    except ProcamError as e:
        return unconfident(Step.PROJECTOR, str(e).split("\n")[0])
    return confidence_of(result, Step.PROJECTOR)


def update_after(machine, capture_id: str, log: Callable[[str], None]) -> None:
    """After `capture_id` was detected: the projector step's confidence, when the plan stops on it."""
    if not machine.plan.stop_on_confidence:
        return
    cap = next((c for c in machine.manifest.captures if c.id == capture_id), None)
    if cap is None or cap.step != Step.PROJECTOR:
        return
    conf = projector_confidence(machine)
    machine.set_projector_confidence(conf)
    if conf.all_met:
        log(f"projector step confident after {capture_id}: " + "; ".join(conf.lines()))
    else:
        log(f"projector step after {capture_id}, " + "; ".join(conf.lines()))
