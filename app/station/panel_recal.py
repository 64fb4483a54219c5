"""The station's recalibration mode (`procam station --recalibrate PREVIOUS`): a checklist in the panel
(Check -> Re-measure what moved -> Compare) over the same flow as `procam recalibrate`
(app/recalibration.py's run_recalibration, RecalibrationMachine, RecalibrationStation), run in a
thread started by the operator's *Start check*; the check's verdict waits for *Accept verdict* (a sign-off
when nothing moved). The station's loop is not started: the flow drives the station's ticks itself."""

from __future__ import annotations

import threading

from app.recalibration import RECALIBRATION_FILE, comparison_lines, run_recalibration

_SIGMA_TARGETS = {  # (part, sigma key) -> target key of calib.recalib.targets_from
    ("projector", "rot_deg"): "projector_rot_deg", ("projector", "t"): "projector_t",
    ("mirror", "normal_deg"): "mirror_normal_deg", ("mirror", "d"): "mirror_d",
    ("camera", "fx_px"): "camera_f_px", ("camera", "fy_px"): "camera_f_px",
}


def progress_lines(re, units: str) -> list[str]:
    """Each re-estimated parameter's 1-sigma against its target."""
    out = []
    for (part, key), tkey in _SIGMA_TARGETS.items():
        s = (re.sigma.get(part) or {}).get(key if key != "t" and key != "d" else f"{key}_{units}")
        if s is None:
            continue
        t = re.targets[tkey]
        out.append(f"{part} {key.replace('_', ' ')}: 1-sigma {s:.3f} / target {t:.3f} {'✔' if s <= t else '…'}")
    return out


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
            self.h_start = g.add_button("Start check", color="teal")
            self.h_accept = g.add_button("Accept verdict", visible=False)
        # the normal session's "Step n of 6 / Next" line would ask for a Calibrate this mode never needs
        panel.step_line = lambda: ("**Recalibration mode**: follow the *Recalibration* checklist above; the step "
                                   "controls below are not needed.")
        self.h_start.on_click(lambda event: self.start_check())
        self.h_accept.on_click(lambda event: self.accept())

    # ---- operator actions ------------------------------------------------------------------------
    def start_check(self) -> None:
        if self._thread is not None:
            return
        self.stage = "checking"
        self.h_start.visible = False
        self._thread = threading.Thread(target=self._run, name="recalibration", daemon=True)
        self._thread.start()
        self.update()

    def accept(self) -> None:
        if self.stage == "verdict":
            self.machine.log(f"recalibration: verdict '{self.report.verdict}' accepted by the operator")
            import datetime

            self.sign_off = {"by": "operator", "button": self.h_accept.label, "verdict": self.report.verdict,
                             "at_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
            self.stage = "remeasuring" if self.report.moved else "comparing"
            self.h_accept.visible = False
            self._accepted.set()
            self.update()

    # ---- the flow --------------------------------------------------------------------------------
    def _on_stage(self, name, value) -> dict | None:
        self.now = ""
        if name == "verdict":
            self.report = value
            self.stage = "verdict"
            self.h_accept.label = "Sign off: unchanged" if value.verdict == "unchanged" else "Accept verdict"
            self.h_accept.visible = True
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
                              verify=self.verify, on_stage=self._on_stage, prompt=self._prompt, resume=self.resume)
            self.stage = "done" if self.outcome.ok else "failed"
        except Exception as e:  # shown in the checklist; the log has it too
            self.error = f"{type(e).__name__}: {e}"
            self.machine.log(f"recalibration failed: {self.error}")
            self.stage = "failed"
        self.update()

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
                lines.append(f"    - {p}: **{c.status}** ({c.reason})")
            ask = "Sign off: unchanged" if self.report.verdict == "unchanged" else "Accept verdict"
            lines.append(f"    - verdict: **{self.report.verdict}**"
                         + (f": press *{ask}*" if self.stage == "verdict" else ""))
        if self.report is not None and self.report.moved:
            lines.append(f"2. **Re-measure what moved**: {', '.join(self.report.moved)}")
            units = self.report.current.units
            if self.rounds:
                last = self.rounds[-1]
                lines.append(f"    - round {len(self.rounds)}: "
                             + ("1-sigma targets reached" if last.reached else "capturing more"))
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
        return [f for f in (RECALIBRATION_FILE, "calibration.json", "previous/calibration.json", "verification.json")
                if (folder / f).exists()]
