"""The panel's status in words: the step line, the checklist, the results' summary, the verified pixels,
the log and the capture loop's banner (app/station/panel.py shows them; each is a function of what it says)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from app.station.activity import RIG_FINDINGS
from app.station.machine import (
    CALIBRATION, CHECK_RIG, DONE, MIRROR_CAPTURE, PROJECTOR_CAPTURE, STATE_TITLES, STATES, VERIFICATION,
)
from app.station.panel_results import check_passes, parameters_text, worst_views_text
from app.station.verdict import verdict_text
from app.words import plural
from calib.models.observations import VIEW_MIRROR

LOG_EVENTS = 200  # events the Log tab shows (scrollable), as many as the session machine keeps


def checklist(m) -> str:
    """The checklist of the session's steps, each marked done, current or to come, with its numbers."""
    s = m.state
    idx = STATES.index(s)
    c = m.counts()

    def mark(state):
        i = STATES.index(state)
        if state == CALIBRATION and m.result is not None and not m.result_stale and s != CALIBRATION:
            return "✔"
        if i < idx:
            return "✔"
        return "▶" if i == idx else "○"

    checks = "; ".join(f"{ch.name} " + ("FAILED: " + ch.detail if not ch.ok else
                                        f"ok ({ch.detail})" if ch.name in RIG_FINDINGS else "ok")
                       for ch in m.rig_checks)
    lines = ["**Checklist**", ""]
    lines.append(f"- {mark(CHECK_RIG)} **Check the rig**" + (f": {checks}" if checks else ": not checked yet"))
    if m.direct:
        lines.append("- ✔ **Mirror capture**: none needed (direct view)")
    else:
        method = m.mirror_method or "method not chosen"
        lines.append(f"- {mark(MIRROR_CAPTURE)} **Mirror capture** ({method}): "
                     f"**{c['mirror']} / {c['mirror_total'] or '?'}** captures"
                     + (" (at most: ends when the mirror normal is confident)" if m.plan.stop_on_confidence else ""))
        if m.plan.stop_on_confidence and getattr(m, "mirror_confidence", None) is not None:
            lines += [f"    - {line}" for line in m.mirror_confidence.lines()]
    what = ("placements, each the structured-light sequence" if m.structured else
            f"captures, {c['positions_done']} / {c['positions']} pattern positions complete")
    lines.append(f"- {mark(PROJECTOR_CAPTURE)} **Projector capture**: **{c['projector']} / {c['projector_total']}** "
                 f"{what}" + (" (at most: ends when confident)" if m.plan.stop_on_confidence else ""))
    if m.plan.stop_on_confidence and m.projector_confidence is not None:
        # each 1-sigma the projector step constrains against its target (calib.quality.confidence)
        lines += [f"    - {line}" for line in m.projector_confidence.lines()]
    cam = (f"camera from `{Path(m.camera_intrinsics).name}` (given)" if m.camera_intrinsics
           else "camera from the captures")
    cal = "done" if m.result is not None and not m.result_stale else (
        "out of date: re-run" if m.result is not None else "not run")
    if m.busy == "calibrating":
        cal = "running"
    lines.append(f"- {mark(CALIBRATION)} **Calibration** ({cam}, mirror, projector): {cal}")
    ver = "not run"
    if m.busy == "verifying":
        ver = "running"
    elif m.report is not None:
        ver = "passed" if getattr(m.report, "passed", False) else "FAILED"
    elif m.why_not("verify") == "verification is not available in this installation":
        ver = "not available"
    lines.append(f"- {mark(VERIFICATION)} **Verification**: {ver}")
    lines.append(f"- {mark(DONE)} **Done**")
    lines += ["", f"Board placements so far: **{c['placements']}** (each position the board was put in)"]
    return "\n".join(lines)


def results_summary(m, pixel_check=None) -> str:
    """The top of the results: the calibration's RMS (px), the pose of the projector and the mirror
    with their 1-sigma, and the verification's verdict."""
    r = m.result
    if r is None:
        if m.calibration_error:
            return f"**Calibration failed:** {m.calibration_error}"
        return "No calibration yet."
    u = r.uncertainty or {}
    lines = [verdict_text(r, m.manifest.rig.view == VIEW_MIRROR)]
    if m.result_stale:
        lines.append("**Out of date:** the captures or the camera model changed; re-run the calibration.\n")
    rms = ", ".join(f"{k} {v:.3f} px" for k, v in r.rms.items() if isinstance(v, (int, float)))
    lines.append(f"**Calibration** ({r.method}, lengths in {r.units}). RMS reprojection error: {rms}")
    t = r.T_cam_proj[:3, 3]
    ang = float(np.degrees(np.arccos(np.clip((np.trace(r.T_cam_proj[:3, :3]) - 1) / 2, -1, 1))))
    tu = (u.get("T_cam_proj") or {}) if isinstance(u.get("T_cam_proj"), dict) else {}
    t_pm = f" (± {tu['t_total']:.2f} {r.units})" if isinstance(tu.get("t_total"), (int, float)) else ""
    r_pm = f" (± {tu['rot_total_deg']:.3f} deg)" if isinstance(tu.get("rot_total_deg"), (int, float)) else ""
    lines.append(f"\nProjector in the camera frame: [{t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}] {r.units}{t_pm}, "
                 f"rotated {ang:.2f} deg{r_pm}")
    if r.mirror is not None:
        n = r.mirror.normal
        mu = u.get("mirror") if isinstance(u.get("mirror"), dict) else {}
        extra = ""
        if isinstance(mu.get("d"), (int, float)) and isinstance(mu.get("normal_deg"), (int, float)):
            extra = f" (± {mu['d']:.2f} {r.units}, normal ± {mu['normal_deg']:.3f} deg)"
        lines.append(f"\nMirror: normal [{n[0]:.4f}, {n[1]:.4f}, {n[2]:.4f}] (unit vector), "
                     f"d {r.mirror.d:.2f} {r.units}{extra}")
    if r.skipped:
        lines.append(f"\nSkipped {plural(len(r.skipped), 'capture')}: " + "; ".join(
            f"{s.get('capture_id', '?')}: {s.get('reason', '')}" for s in list(r.skipped)[:5]))
    rep = m.report
    if rep is not None:
        verdict = "PASSED" if getattr(rep, "passed", False) else "FAILED"
        summary = rep.summary() if hasattr(rep, "summary") else ""
        lines.append(f"\n**Verification {verdict}** (threshold {getattr(rep, 'threshold_px', float('nan')):.2f} "
                     f"projector px): {summary}")
    elif m.verification_error:
        lines.append(f"\n**Verification could not run:** {m.verification_error}")
    if pixel_check is not None:
        lines.append(f"\nLast pixel check: {pixel_check_verdict(m.report, pixel_check)}")
    return "\n".join(lines)


def results_text(m, pixel_check=None) -> str:
    """Everything the results show, as one text (the summary, parameters, worst views)."""
    r = m.result
    if r is None:
        return results_summary(m, pixel_check)
    return "\n\n".join([results_summary(m, pixel_check), parameters_text(r, bool(m.camera_intrinsics)),
                        worst_views_text(r)])


def pixel_check_verdict(report, pc) -> str:
    """A pixel check's line: its label and, when measured, pass or FAIL against the verdict's limit."""
    thr, factor = verdict_threshold(report)
    ok = check_passes(pc, thr, factor)
    if not pc.ok:
        return f"{pc.label()} (no verdict)"
    return f"{pc.label()}: **{'pass' if ok else 'FAIL'}** (limit {factor * thr:.2f} projector px)"


def checks_text(m, pixel_check=None) -> str:
    """The verified pixels drawn on the live image, in words: distance and verdict of each."""
    if m.state not in (CALIBRATION, VERIFICATION, DONE):
        return ""
    thr, factor = verdict_threshold(m.report)
    lines = []
    checks = list(getattr(m.report, "checks", None) or []) if m.report is not None else []
    if checks:
        lines.append(f"**Verified pixels** (each passes within {factor * thr:.2f} projector px):")
        lines.append("")
        for c in checks:
            ok = check_passes(c, thr, factor)
            lines.append(f"- {c.label()}: **{'pass' if ok else 'FAIL'}**" if c.ok else f"- {c.label()}")
    if pixel_check is not None:
        lines.append("")
        lines.append(f"**Pixel check** {pixel_check_verdict(m.report, pixel_check)}")
    return "\n".join(lines)


def verdict_threshold(rep) -> tuple[float, float]:
    """(threshold, worst factor) of the verdict: the report's (`rep`), else the verification's defaults."""
    try:
        from app.verification import DEFAULT_THRESHOLD_PX, WORST_FACTOR
    except ImportError:
        DEFAULT_THRESHOLD_PX, WORST_FACTOR = 1.5, 2.0
    thr = getattr(rep, "threshold_px", None) if rep is not None else None
    return float(thr if isinstance(thr, (int, float)) else DEFAULT_THRESHOLD_PX), float(WORST_FACTOR)


def log_text(m, n: int = LOG_EVENTS) -> str:
    """The Log tab: the session machine's last `n` events, newest first, a traceback under its line."""
    evs = m.events[-n:]
    if not evs:
        return "Nothing yet."
    lines = [f"{plural(len(evs), 'event')}, newest first (the last {n} are kept here; scroll for older ones)", ""]
    for e in reversed(evs):
        head, _, rest = e.text.partition("\n")
        lines.append(f"- {time.strftime('%H:%M:%S', time.localtime(e.time_s))} {head}")
        if rest.strip():  # a traceback: kept as it is, in a code block under its line
            lines.append("")
            lines.append("  ```")
            lines += ["  " + ln for ln in rest.rstrip().splitlines()]
            lines.append("  ```")
    return "\n".join(lines)


def alert_text(frames) -> str:
    """The banner over the panel when the capture loop (`frames`, a FrameSource) failed: restarted, or
    stopped for good."""
    stopped = frames.loop_stopped
    if stopped:
        return f"**The capture loop stopped.** {stopped}"
    errors = frames.loop_errors
    if errors and time.monotonic() - errors[-1].time_s < 20.0:
        e = errors[-1]
        return (f"**The capture loop failed and was restarted** ({e.summary}). The traceback is in the Log "
                "tab; if it keeps failing, restart the station with --resume.")
    return ""


def step_line(m, instruction: str) -> str:
    """The current step, its progress and what to do (`instruction`): the first thing an operator reads."""
    steps = [x for x in STATES if not (m.direct and x == MIRROR_CAPTURE)]
    k = steps.index(m.state) + 1 if m.state in steps else 0
    c = m.counts()
    progress = ""
    if m.state == MIRROR_CAPTURE and m.mirror_method:
        progress = f": {c['mirror']} of {c['mirror_total']} captures"
    elif m.state == PROJECTOR_CAPTURE:
        progress = (f": {c['projector']} of {c['projector_total']} captures, {c['positions_done']} of "
                    f"{c['positions']} pattern positions complete")
    return f"#### Step {k} of {len(steps)}: {STATE_TITLES[m.state]}{progress}\n\n**Next:** {instruction}"
