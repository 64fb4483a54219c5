"""The station's recalibration mode (`procam station --recalibrate PREVIOUS`): a checklist in the panel
(Check -> Re-measure what moved -> Compare) over the same flow as `procam recalibrate`
(app/recalibration.py's run_recalibration, RecalibrationMachine, RecalibrationStation), run in a
thread started by the operator's *Start check*; the check's verdict waits for *Accept verdict* (a sign-off
when nothing moved). The station's loop is not started: the flow drives the station's ticks itself (its
preview thread runs, so the live image and its frame rate stay true before, during and after the flow).

The mode's controls replace the normal steps' (no Calibrate: the flow decides what to capture and
re-estimates by itself): per browser, *Start check*, then *Accept verdict* (or *Sign off: unchanged*),
then *Download results*, each highlighted when it is the next action and pressed by the driving browser
only (app/station/panel_driver.py)."""

from __future__ import annotations

import threading

from app.recalibration import RECALIBRATION_FILE, comparison_lines, part_line, run_recalibration
from app.station.machine import STATES, ActionRefused
from calib.formats import session_files

_SIGMA_TARGETS = {  # (part, sigma key) -> target key of calib.recalib.targets_from
    ("projector", "rot_deg"): "projector_rot_deg", ("projector", "t"): "projector_t",
    ("mirror", "normal_deg"): "mirror_normal_deg", ("mirror", "d"): "mirror_d",
    ("camera", "fx_px"): "camera_f_px", ("camera", "fy_px"): "camera_f_px",
}


def sigma_targets(re, units: str) -> list[tuple[str, float, float]]:
    """(name, 1-sigma, target) of each re-estimated parameter."""
    out = []
    for (part, key), tkey in _SIGMA_TARGETS.items():
        s = (re.sigma.get(part) or {}).get(key if key != "t" and key != "d" else f"{key}_{units}")
        if s is not None:
            out.append((f"{part} {key.replace('_', ' ')}", s, re.targets[tkey]))
    return out


def progress_lines(re, units: str) -> list[str]:
    """Each re-estimated parameter's 1-sigma against its target."""
    return [f"{name}: 1-sigma {s:.3f} / target {t:.3f} {'✔' if s <= t else '…'}"
            for name, s, t in sigma_targets(re, units)]


def round_line(re, units: str) -> str:
    """Where a round of the re-estimate stands: "targets reached" only when every 1-sigma is within its
    target; a target only the previous intrinsics keep out of reach is said as such (more captures
    cannot lower it, so the flow stops there)."""
    over = sum(1 for _, s, t in sigma_targets(re, units) if s > t)
    if re.reached and not over:
        return "every 1-sigma target reached"
    if re.reached:
        return (f"{over} 1-sigma target(s) not reached, limited by the previous calibration's intrinsics "
                "(more captures cannot lower them): done capturing")
    return f"{over} 1-sigma target(s) not reached yet: capturing more"


class RecalibrationPanel:
    """Adds the recalibration checklist and its buttons to a StationPanel."""

    def __init__(self, panel, previous, verify=None, max_captures: int | None = None, workers: int = 2,
                 resume: bool = False):
        self.panel = panel
        self.station = panel.station
        self.machine = panel.machine
        self.previous = previous
        self.verify = verify
        self.max_captures = max_captures
        self.workers = workers
        self.resume = resume  # a stopped recalibration continued: its captures are kept
        self.now = ""  # what the operator should do for the capture asked for (the flow's prompt)
        self.stage = "ready"  # ready -> checking -> verdict -> remeasuring -> done | failed
        self.report = None
        self.rounds: list = []
        self.outcome = None
        self.error = None
        self.sign_off = None
        self._accepted = threading.Event()
        self._thread = None
        g = panel.server.gui
        with g.add_folder("Recalibration", order=0.5):
            self.h_text = g.add_markdown(self.text())
        # the normal session's "Step n of 6 / Next" line and checklist would ask for a Calibrate this mode
        # never needs
        panel.step_line = lambda: ("**Recalibration mode**: follow the *Recalibration* checklist above; its "
                                   "next action is the highlighted button.")
        panel.checklist = lambda: ""
        panel.controls.mode = self

    # ---- per browser: the mode's controls in place of the steps' (panel_controls.py calls these) ---------
    def build(self, ctl) -> None:
        g, h = ctl.client.gui, ctl.handles
        h["recal_start"] = g.add_button("Start check", order=1.3, color="green")
        h["recal_accept"] = g.add_button(self.accept_label(), order=1.3, color="green", visible=False)
        h["steps"].visible = False
        for name, fn in (("recal_start", self.start_check), ("recal_accept", self.accept)):
            h[name].on_click(self.panel.controls.handler(ctl, name, fn))

    def refresh(self, ctl) -> None:
        h, cached = ctl.handles, self.panel.controls.cached
        for name, shown in (("recal_start", self.stage == "ready"), ("recal_accept", self.stage == "verdict")):
            if cached(ctl, (name, "visible"), shown):
                h[name].visible = shown
        if cached(ctl, ("recal_accept", "label"), self.accept_label()):
            h["recal_accept"].label = self.accept_label()

    def recommended(self) -> set[str]:
        """The normal controls highlighted: only the download, once the flow has ended with a result."""
        return {"download"} if self.stage in ("done", "failed") else set()

    def accept_label(self) -> str:
        unchanged = self.report is not None and self.report.verdict == "unchanged"
        return "Sign off: unchanged" if unchanged else "Accept verdict"

    # ---- operator actions ------------------------------------------------------------------------
    def start_check(self) -> str:
        if self._thread is not None:
            raise ActionRefused("start the check", "it has started already")
        self.stage = "checking"
        self._thread = threading.Thread(target=self._run, name="recalibration", daemon=True)
        self._thread.start()
        self.update()
        return "the check runs; its captures are taken when the board is still and detected"

    def accept(self) -> str:
        if self.stage != "verdict":
            raise ActionRefused("accept the verdict", "there is no verdict waiting")
        self.machine.log(f"recalibration: verdict '{self.report.verdict}' accepted by the operator")
        import datetime

        self.sign_off = {"by": "operator", "button": self.accept_label(), "verdict": self.report.verdict,
                         "at_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
        self.stage = "remeasuring" if self.report.moved else "comparing"
        self._accepted.set()
        self.update()
        return f"verdict '{self.report.verdict}' accepted"

    # ---- the flow --------------------------------------------------------------------------------
    def _on_stage(self, name, value) -> dict | None:
        self.now = ""
        if name == "verdict":
            self.report = value
            self.stage = "verdict"
            self.update()
            self._accepted.wait()
            return self.sign_off  # recorded in recalibration.json
        elif name == "reestimate":
            self.rounds.append(value)
        elif name == "done":
            self.outcome = value
        self.update()

    def _prompt(self, text: str) -> None:
        """The flow's prompt before each capture: shown in the checklist; auto-capture then takes the frame
        when the board is still and detected (nothing to press)."""
        self.now = text
        self.update()

    def _run(self) -> None:
        from app.recalibration import DEFAULT_MAX_CAPTURES

        try:
            run_recalibration(self.previous, self.station, self.machine, log=self.machine.log,
                              max_captures=self.max_captures or DEFAULT_MAX_CAPTURES, workers=self.workers,
                              verify=self._verify if self.verify else None, on_stage=self._on_stage,
                              prompt=self._prompt, resume=self.resume)
            self.stage = "done" if self.outcome.ok else "failed"
        except Exception as e:  # shown in the checklist; the log has it too
            self.error = f"{type(e).__name__}: {e}"
            self.machine.log(f"recalibration failed: {self.error}")
            self.stage = "failed"
        self.update()

    def _verify(self, result, final: bool):
        """The epipolar verification drives the camera and projector itself: the preview thread pauses."""
        with self.machine.hold("verifying", allowed_states=STATES):
            return self.verify(result, final)

    # ---- what the panel shows --------------------------------------------------------------------
    def update(self) -> None:
        try:
            self.h_text.content = self.text()
        except Exception:  # the server is stopping
            pass

    def text(self) -> str:
        mark = {"ready": "☐", "checking": "▶", "verdict": "?", "remeasuring": "▶", "comparing": "▶",
                "done": "✔", "failed": "✖"}
        lines = [f"**Recalibration of** `{self.previous}` ({mark[self.stage]} {self.stage})", ""]
        n = len(self.machine.manifest.captures)
        if self.stage == "ready":
            if self.resume:
                lines.append(f"Resumed with {n} captures on disk: they are kept, only the rest is taken.")
            lines.append("1. Check: press *Start check* (a few captures test the camera, mirror and projector "
                         "against the previous calibration).")
            return "\n".join(lines)
        lines.append(f"1. **Check** ({n} captures so far)" + (": running" if self.report is None else ""))
        if self.report is not None:
            for p, c in self.report.parts.items():
                lines.append(f"    - {p}: **{c.status}** ({part_line(c, self.report.current.units)})")
            ask = self.accept_label()
            lines.append(f"    - verdict: **{self.report.verdict}**"
                         + (f": press *{ask}*" if self.stage == "verdict" else ""))
        if self.report is not None and self.report.moved:
            lines.append(f"2. **Re-measure what moved**: {', '.join(self.report.moved)}")
            units = self.report.current.units
            if self.rounds:
                last = self.rounds[-1]
                lines.append(f"    - round {len(self.rounds)}: {round_line(last, units)}")
                lines += [f"    - {t}" for t in progress_lines(last, units)]
            elif self.stage == "remeasuring":
                lines.append("    - capturing")
        if self.now and self.stage in ("checking", "remeasuring"):
            lines.append(f"**Now:** {self.now} (the capture is taken when the board is still and detected)")
        if self.outcome is not None:
            lines.append("3. **Compare**: " + self.outcome.message + (" (ok)" if self.outcome.ok else " (FAILED)"))
            lines += [f"    - {t}" for t in comparison_lines(self.outcome.record)]
            lines.append("    - files written: " + ", ".join(self.files()))
        if self.error:
            lines.append(f"**Failed:** {self.error}")
        return "\n".join(lines)

    def files(self) -> list[str]:
        from pathlib import Path

        folder = Path(self.machine.store.folder)
        return [f for f in (RECALIBRATION_FILE, session_files.CALIBRATION,
                                  f"{session_files.PREVIOUS_DIR}/{session_files.CALIBRATION}", session_files.VERIFICATION)
                if (folder / f).exists()]
