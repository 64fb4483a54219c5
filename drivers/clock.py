"""The clocks devices keep time on: the host's monotonic clock for real hardware, a simulated clock for
the simulated rig.

    clock = clock_of(rig.camera)          # the device's own clock (MONOTONIC when it has none)
    t_set = clock.now()
    clock.sleep(0.5)                      # on a SimClock: simulated time passes, the CPU does not wait

Why a simulated clock: the simulated rig's frame times, projector presentation and latency and the
camera's settings lag are a model of hardware. On the wall clock a starved CPU changes that model: a
frame rendered slowly is delivered late, frames are skipped, a latency measured 90 ms long. On a
SimClock the simulated hardware only moves when someone waits for it (a frame's delivery, an image's
presentation, a sleep), so what the rig does depends on what was asked of it, never on how fast the
machine is. Rendering takes no simulated time.

Waits for another thread's work (a frame from the station's preview thread, a calibration finishing)
are not device waits: they use threading primitives and real timeouts, never a clock's sleep (on a
SimClock with `realtime=False` a sleeping poll would run simulated time ahead of the thread it waits
for).
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """Seconds on one device timeline: `now()` and `sleep(s)`, `sleep_until(t)`."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def sleep_until(self, t: float) -> None: ...


class MonotonicClock:
    """The host's clock (time.monotonic): what real cameras and projector windows stamp their times on."""

    simulated = False

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def sleep_until(self, t: float) -> None:
        self.sleep(t - time.monotonic())


MONOTONIC = MonotonicClock()


class SimClock:
    """Simulated seconds that advance only when a caller sleeps: `sleep_until(t)` moves the time to t
    (if it is later), so concurrent sleepers see one time that never goes back.

    `realtime=True` (the default, for a person watching the station): a sleep also waits until as much
    real time has passed since the clock started, so the simulation never runs ahead of the wall clock;
    on a starved machine it falls behind instead, and what it does is unchanged. `realtime=False` (tests
    and benchmarks of the drivers): sleeps return at once. Either way the simulated time a caller sees
    is the same sequence on any machine."""

    simulated = True

    def __init__(self, start_s: float = 1000.0, realtime: bool = True):
        self._t = float(start_s)
        self._start = float(start_s)
        self._wall0 = time.monotonic()
        self.realtime = bool(realtime)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep(self, seconds: float) -> None:
        with self._lock:
            target = self._t + max(0.0, float(seconds))
        self.sleep_until(target)

    def sleep_until(self, t: float) -> None:
        t = float(t)
        with self._lock:
            if t > self._t:
                self._t = t
        if self.realtime:
            ahead = (t - self._start) - (time.monotonic() - self._wall0)
            if ahead > 0:
                time.sleep(ahead)

    def advance(self, seconds: float) -> None:
        """Let `seconds` of simulated time pass at once (never waits): for tests."""
        with self._lock:
            self._t += max(0.0, float(seconds))


def clock_of(device) -> Clock:
    """The clock a device's times are on (its `clock` attribute), else the host's monotonic clock."""
    c = getattr(device, "clock", None)
    return c if isinstance(c, Clock) else MONOTONIC
