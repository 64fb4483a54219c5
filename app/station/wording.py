"""The station's words: the instruction to the person at the rig, the live hint and the status line.

Pure functions of the session machine's state (and of what the live view and the light watch say), so
the wording is read, changed and tested without a rig.
"""

from __future__ import annotations

from pathlib import Path

from app.station.machine import CALIBRATION, CHECK_RIG, MIRROR_CAPTURE, PROJECTOR_CAPTURE, STATE_TITLES, VERIFICATION
from app.station.projector_light import LOST_MESSAGE as LIGHT_LOST
from calib.formats import session_files
from calib.models.vocab import MirrorMethod


def instruction(m, device_problem: str | None, problem: str | None, hint: str) -> str:
    """What the person at the rig should do next, in plain words: `m` is the session machine, `hint` the
    live view's hint (live_hint) that follows a capture step's instruction."""
    s = m.state
    if device_problem:
        return f"Device problem: {device_problem}."
    if problem:
        return f"Problem: {problem}."
    if m.busy == "calibrating":
        return "Calibrating the captures. This takes a little while."
    if m.busy == "verifying":
        return "Verifying: the projector draws epipolar lines and the camera checks where they land."
    if s == CHECK_RIG:
        bad = [c for c in m.rig_checks if not c.ok]
        if not m.rig_checks:
            return ("Check the rig: the camera must stream and the projector window must be up. Hold the board "
                    "in the projector's light where the camera sees it (the check sets the exposure and "
                    "measures the projector's latency) and press Check rig.")
        if bad:
            return "Fix the rig: " + "; ".join(f"{c.name}: {c.detail}" for c in bad) + ". Then press Check rig."
        return "The rig is ready. Press Start to begin the captures."
    if s == MIRROR_CAPTURE:
        if m.mirror_method is None:
            return ("Choose how to calibrate the mirror: real-virtual (hold the small board between camera "
                    "and mirror, seen directly and in the mirror) or real-mirror (lay it flat on the mirror).")
        tgt = m.target
        c = m.counts()
        if tgt is None:
            if m.plan.stop_on_confidence and c['mirror'] < c['mirror_total']:
                conf = m.mirror_confidence
                if conf is not None and conf.all_met:
                    return (f"The mirror normal is confident after {c['mirror']} mirror captures. Press 'Next step'.")
                return (f"The first {c['mirror']} mirror captures are taken. Press 'Next step' to go on to the "
                        "projector; the mirror step asks for more afterwards if its normal is not confident yet.")
            return f"All {c['mirror_total']} mirror captures are taken. Press 'Next step' to go on to the projector."
        if m.mirror_method == MirrorMethod.REAL_VIRTUAL:
            what = ("Hold the mirror board between the camera and the mirror so that the camera sees it "
                    "both directly and in the mirror; change its place and tilt from the last capture.")
        else:
            what = (f"Lay the mirror board flat on the mirror, at a new place and angle (at least "
                    f"{m.plan.min_mirror(MirrorMethod.REAL_MIRROR)} placements: one alone leaves the mirror's tilt uncertain).")
        most = "at most " if m.plan.stop_on_confidence else ""
        head = f"Mirror capture {c['mirror'] + 1} of {most}{c['mirror_total']}: {what}"
        return head + hint
    if s == PROJECTOR_CAPTURE:
        tgt = m.target
        c = m.counts()
        if tgt is None and m.more_mirror_wanted():
            return ("The projector step is complete; the mirror normal is not confident yet ("
                    + "; ".join(m.mirror_confidence_lines()) + "). Press 'Back' for more mirror captures, or Calibrate with what is there.")
        if tgt is None:
            if m.plan.stop_on_confidence and c['projector'] < c['projector_total']:
                return f"The projector step is confident after {c['projector']} captures. Press Calibrate."
            return f"All {c['projector_total']} projector captures are taken. Press Calibrate."
        best = m.next_placement
        why = f" Next-best: {best.reason()} (dashed on the projector map)." if best is not None else ""
        asked = m.asked_pose
        if asked is not None:
            why = f" Asked pose: {asked.reason()}."
        if m.structured:
            place = (f"towards the {best.where} of the projector's image" if best is not None else
                     "at a new place")
            how = ("on the dashed outline in the camera image" if asked is not None else
                   "where the projector lights it" + ("" if m.direct else " and the camera sees it in the mirror") +
                   f", {place} and a new tilt")
            where = (f"Placement {c['projector'] + 1} of at most {c['projector_total']}: set the board on a stand "
                     f"{how}, and leave it there while the projector shows its coded sequence (a few seconds; "
                     "a board held by hand moves too much).")
            return where + why + hint
        where = (f"The projector shows the pattern at position {tgt.pattern_position + 1} of {m.positions}. "
                 f"Pose {tgt.pose_index + 1} of {m.plan.poses_per_position}: hold the board so the pattern "
                 "falls on its blank part")
        where += " and the camera sees the board in the mirror" if not m.direct else ""
        where += ("; hold it on the dashed outline in the camera image." if asked is not None else
                  "; tilt it differently from the poses already taken.")
        return where + why + hint
    if s == CALIBRATION:
        if m.calibration_error:
            return f"The calibration failed: {m.calibration_error}. Retake or add captures, then calibrate again."
        if m.result is None:
            return "The captures are complete. Press Calibrate."
        if m.result_stale:
            return "The captures changed since the last calibration. Press Calibrate to re-run it."
        low = low_quality_note(m.result)
        if low:
            return low + (" Or press Verify to check it as it is." if m.why_not("verify") is None else "")
        if m.why_not("verify") is None:
            return "Calibrated. Press Verify to check the calibration with epipolar lines."
        return "Calibrated. Press Finish to end the session."
    if s == VERIFICATION:
        if m.verification_error:
            return f"The verification could not run: {m.verification_error}."
        if m.report is None:
            return "Press Verify to check the calibration."
        if getattr(m.report, "passed", False):
            return "The calibration passed the verification. Press Finish."
        return ("The calibration failed the verification. Go back, retake captures that look wrong, "
                "and calibrate again.")
    return f"The session is complete. The calibration is in {Path(m.store.folder) / session_files.CALIBRATION}."


def live_hint(light_lost: bool, live) -> str:
    """" Now: ..." after a capture step's instruction: the projector's light lost, or why the live frame
    is not being captured; "" when nothing holds the capture back."""
    if light_lost:
        return f" Now: {LIGHT_LOST}."
    if live is None or live.decision is None:
        return ""
    d = live.decision
    if d.capture:
        return ""
    msg = d.message
    if not msg:
        return ""
    return f" Now: {msg}."


def status_line(m) -> str:
    """The step and the captures taken of each, on one line."""
    c = m.counts()
    parts = [STATE_TITLES[m.state]]
    if m.mirror_method:
        parts.append(f"mirror {c['mirror']}/{c['mirror_total']}")
    parts.append(f"projector {c['projector']}/{c['projector_total']}")
    return " | ".join(parts)


def low_quality_note(result) -> str:
    """The instruction for a LOW QUALITY calibration (calib.quality.trust's quality gate), "" when it is not."""
    from calib.quality.trust import QUALITY_CODES, low_quality_lines

    lines = low_quality_lines(result)
    if not lines:
        return ""
    codes = [ln[1:ln.index("]")] for ln in lines if ln.startswith("[") and "]" in ln]
    what = "; ".join(QUALITY_CODES.get(c, c) for c in codes)
    return (f"Calibrated, but LOW QUALITY: {what} (details in the log). Add captures at more pattern positions "
            "with more varied tilts that reach the image corners, then press Calibrate again.")
