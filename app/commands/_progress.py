"""Progress of a command on stderr: tqdm bars on a terminal, plain lines in a log, or nothing.

Callbacks follow the project's convention `progress(done, total, label)`. When stderr is not a
terminal (`procam calibrate S 2>log`) no carriage return or escape code is written: a phase of many
items (detection, rendering) gets a line when it starts and one when it ends, and a phase of named
stages (the calibration) gets a line per stage.
"""

from __future__ import annotations

import sys
import time

BARS, LINES, OFF = "bars", "lines", "off"


def progress_mode(no_progress: bool = False, stream=None) -> str:
    """BARS on a terminal, LINES otherwise, OFF with --no-progress."""
    if no_progress:
        return OFF
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return BARS if callable(isatty) and isatty() else LINES
    except ValueError:  # a closed stream
        return OFF


class Progress:
    """One bar (or one set of lines) per phase, fed by progress(done, total, label) callbacks."""

    def __init__(self, mode: str, stream=None):
        self.mode = mode
        self.stream = stream
        self._bars = {}
        self._state = {}

    @property
    def out(self):
        return sys.stderr if self.stream is None else self.stream

    def callback(self, phase: str, unit: str = "step", stages: bool = False):
        """A callback for `phase`. `stages`: the labels name stages (a line per stage in a log);
        otherwise the items are counted (a line at the start and at the end)."""

        def cb(done, total, label=""):
            if self.mode == BARS:
                self._bar(phase, unit, done, total, label)
            elif self.mode == LINES:
                self._line(phase, unit, stages, done, total, label)

        return cb

    def _bar(self, phase, unit, done, total, label):
        from tqdm import tqdm

        bar = self._bars.get(phase)
        if bar is None:
            bar = self._bars[phase] = tqdm(total=total, desc=phase, file=self.out, unit=unit, leave=True,
                                           dynamic_ncols=True)
        if bar.total != total:
            bar.total = total
        bar.n = done
        bar.set_postfix_str(str(label), refresh=False)
        bar.refresh()

    def _line(self, phase, unit, stages, done, total, label):
        st = self._state.setdefault(phase, {"t0": time.monotonic(), "last": None, "ended": False})
        if stages:
            key = (str(label), done)
            if key != st["last"]:
                st["last"] = key
                print(f"{phase}: {label} ({done}/{total})" if label else f"{phase}: {done}/{total}",
                      file=self.out, flush=True)
            return
        if st["last"] is None:
            st["last"] = "started"
            print(f"{phase}: {total} {unit}", file=self.out, flush=True)
        if total and done >= total and not st["ended"]:
            st["ended"] = True
            print(f"{phase}: {done}/{total} {unit} done in {time.monotonic() - st['t0']:.1f} s", file=self.out,
                  flush=True)

    def close(self):
        for bar in self._bars.values():
            bar.close()
        self._bars.clear()
