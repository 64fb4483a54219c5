"""What the station is doing and what its last actions came to: one Activity per action name (running,
done or failed), each with its progress lines while it runs and its outcome once it ended. The panel
renders every status line and notification of a long action from here, so a "running" line ends with
its action, "Done" is said only once it finished, and a failure is replaced by a later success of the
same action. Shared by the station's threads (one lock).
"""

from __future__ import annotations

import enum
import itertools
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

from calib.errors import ProcamError

MAX_LINES = 8  # progress lines kept per running action (the log keeps them all)


class Status(str, enum.Enum):
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


@dataclass(frozen=True)
class Activity:
    name: str  # the action as the operator knows it: its button's label ("Calibrate", "Check rig")
    status: Status
    seq: int  # grows with every change of any activity (a browser says what it has not said yet)
    lines: tuple[str, ...] = ()  # progress while running
    outcome: str = ""  # once ended: what it came to, or why it failed
    started_s: float = field(default_factory=time.time)

    def text(self) -> str:
        """One line (markdown) for the panel."""
        if self.status is Status.RUNNING:
            return f"**{self.name}: running.**" + (f" {self.lines[-1]}" if self.lines else "")
        if self.status is Status.FAILED:
            return f"**{self.name} failed:** {self.outcome}"
        return f"**{self.name}: done.** {self.outcome}".rstrip()


class Activities:
    def __init__(self, log=None):
        self._lock = threading.Lock()
        self._by_name: dict[str, Activity] = {}
        self._seq = itertools.count(1)
        self._log = log  # where progress lines and outcomes are logged too (the session's log)

    def _put(self, name: str, new: bool = False, **changes) -> Activity:
        with self._lock:
            old = self._by_name.get(name)
            if new or old is None:
                a = Activity(name, Status.RUNNING, next(self._seq), **changes)
            else:
                a = replace(old, seq=next(self._seq), **changes)
            self._by_name[name] = a
            return a

    def start(self, name: str, line: str = "") -> Activity:
        return self._put(name, new=True, lines=(line,) if line else ())

    def progress(self, name: str, line: str, log: bool = True) -> None:
        """A progress line of a running action (logged too, unless it is a counter that changes often)."""
        a = self.get(name)
        if a is None or a.status is not Status.RUNNING:
            return
        self._put(name, lines=(a.lines + (line,))[-MAX_LINES:])
        if log:
            self._say(f"{name}: {line}")

    def finish(self, name: str, outcome: str = "") -> Activity:
        return self._put(name, status=Status.DONE, outcome=outcome)

    def fail(self, name: str, why: str) -> Activity:
        return self._put(name, status=Status.FAILED, outcome=why)

    def _say(self, text: str) -> None:
        if self._log is not None:
            self._log(text)

    @contextmanager
    def running(self, name: str, line: str = ""):
        """`with activities.running("Check rig") as act:` the action runs; an exception ends it failed and
        is re-raised; otherwise it ends with `act.outcome` (set by the body), failed when `act.failed`."""
        self.start(name, line)
        box = _Outcome()
        try:
            yield box
        except BaseException as e:
            self.fail(name, failure_text(e))
            raise
        if box.failed:
            self.fail(name, box.outcome)
        else:
            self.finish(name, box.outcome)

    def conclude(self, name: str, fn, outcome_of):
        """Run `fn` for the started activity `name` and end it: done with outcome_of(result), or failed
        (the exception re-raised)."""
        try:
            out = fn()
        except BaseException as e:
            self.fail(name, failure_text(e))
            raise
        self.finish(name, outcome_of(out))
        return out

    def get(self, name: str) -> Activity | None:
        with self._lock:
            return self._by_name.get(name)

    def all(self) -> list[Activity]:
        """Running ones first, then the ended ones, newest first."""
        with self._lock:
            acts = list(self._by_name.values())
        return sorted(acts, key=lambda a: (a.status is not Status.RUNNING, -a.seq))

    def running_names(self) -> list[str]:
        return [a.name for a in self.all() if a.status is Status.RUNNING]


class _Outcome:
    outcome: str = ""
    failed: bool = False


def failure_text(e: BaseException) -> str:
    """Why an action failed, for the operator: a project error's own words, else the exception named."""
    if isinstance(e, ProcamError):
        reason = getattr(e, "reason", None)
        return reason[:1].upper() + reason[1:] if reason else str(e)
    return f"{type(e).__name__}: {e} (details in the Log tab)"


#: the long actions, by the station's name for them, as the operator knows them (their buttons)
ACTIVITY_NAMES = {"calibrate": "Calibrate", "verify": "Verify", "check pixel": "Check pixel"}
CHECK_RIG_NAME = "Check rig"
DOWNLOAD_NAME = "Download results (zip)"
#: the rig check's findings worth reading when they are fine (the others only say "ok")
RIG_FINDINGS = ("camera link", "camera exposure", "camera timing", "camera response", "projector latency", "camera stream")


def activity_name(name: str) -> str:
    return ACTIVITY_NAMES.get(name, name[:1].upper() + name[1:])


def rig_findings(checks) -> str:
    """What the rig check found: exposure, gain, latency and response, and every check that failed."""
    parts = [f"{c.name}: {c.detail}" for c in checks if not c.ok or c.name in RIG_FINDINGS]
    bad = sum(not c.ok for c in checks)
    head = f"{bad} of {len(checks)} checks failed" if bad else f"all {len(checks)} checks passed"
    return head + (". " + "; ".join(parts) if parts else "")


def outcome_text(name: str, out) -> str:
    """What a finished long action came to, in one line."""
    if name == "calibrate" and out is not None:
        rms = ", ".join(f"{k} {v:.3f} px" for k, v in out.rms.items() if isinstance(v, (int, float)))
        return f"RMS reprojection error {rms}; the results are at the top." if rms else "the results are at the top."
    if name == "verify" and out is not None:
        return ("PASSED" if getattr(out, "passed", False) else "FAILED") + "; the verdict is at the top."
    if name == "check pixel" and out is not None and hasattr(out, "label"):
        return out.label()
    return ""


def activities_text(activities: list[Activity], ended: int = 2) -> str:
    """The panel's activity lines: every running action with its newest progress line, then the last
    `ended` actions that ended (one line each: an action's failure is gone once it succeeded)."""
    running = [a for a in activities if a.status is Status.RUNNING]
    done = [a for a in activities if a.status is not Status.RUNNING][:ended]
    return "\n\n".join(a.text() for a in running + done)
