"""How the simulated rig behaves like hardware: projector latency, the camera's own frame clock,
exposure (auto exposure that drifts, manual exposure, flicker) and the depth camera's IR emitter.

The rig (drivers/sim/rig.py) keeps one `HardwareModel` (the constants) and one `Timeline` per device:

- Projector: `show()` at host time t is swapped at the next vsync (a multiple of 1/refresh_hz) and
  becomes visible `latency_ms` (plus a seeded jitter of at most `jitter_ms`) later. What was visible at
  any moment is kept (`ProjectorTimeline.segments`), so a camera frame rendered later shows exactly
  what lit the board during its exposure.
- Camera: frame n's exposure starts at t0 + n / fps and lasts the exposure in force then; the frame is
  delivered one frame period after it started. Frames are rendered lazily, when asked for, but never
  before their delivery time.
- Brightness: the renderer's linear image (calibrated for `REFERENCE_EXPOSURE_US` at gain 1) is scaled
  by exposure x gain and saturates at 255. The projector's light flickers at the refresh rate (PWM /
  DLP): an exposure that is not a whole number of refresh periods catches more or less of it depending
  on the phase of the flicker at which the exposure starts. The D455's colour sensor (OV9782) has a
  global shutter, so every row of a frame catches the same share: the whole frame's projector light
  is brighter or darker (`flicker_amplitude`, `flicker_phase`), from frame to frame as the phase moves.
  The camera's frame clock and the projector's refresh are not locked: the phase drifts by
  `flicker_beat_hz` (a "60 Hz" output at 59.94 Hz beating against 30 fps); under the `flicker` fault
  it is drawn afresh for every frame (the worst case: any phase at any frame).

`ideal=True` switches all of it off: the projector changes at once, frames are rendered on request
with no clock, no auto exposure, no emitter (the fast mode for unit tests that test geometry).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

#: The exposure (us, at gain 1) at which the renderer's levels are the image's levels.
REFERENCE_EXPOSURE_US = 1e6 / 60.0
#: Exposure and gain ranges of the simulated camera (min, max, step), RealSense-like.
EXPOSURE_LIMITS_US = (50.0, 1e6 / 30.0, 1.0)
GAIN_LIMITS = (1.0, 8.0, 0.01)
#: Auto exposure aims at this mean level of the whole image (8-bit).
AE_TARGET_LEVEL = 110.0


@dataclass(frozen=True)
class HardwareModel:
    """The simulated devices' timing and exposure constants (see the module doc)."""

    ideal: bool = False
    latency_ms: float = 90.0
    jitter_ms: float = 4.0
    refresh_hz: float = 60.0
    fps: float = 30.0
    auto_exposure: bool = True  # at power-on, as a RealSense colour sensor
    initial_exposure_us: float = 6000.0
    emitter_enabled: bool = True  # at power-on, as a D455
    flicker_depth: float = 0.35  # flicker amplitude for an exposure half a period off a whole number
    flicker_beat_hz: float = 0.06  # how fast the flicker's phase at the frames' starts drifts
    flicker_random: bool = False  # the phase drawn per frame (the `flicker` fault)
    # a change of exposure, gain, auto exposure or emitter applies to frames whose exposure starts this
    # many frame periods after it (a D455 needs a few frames: allow about 5 before measuring brightness)
    settings_lag_frames: float = 3.0

    @property
    def period_s(self) -> float:
        return 1.0 / self.fps

    @property
    def refresh_s(self) -> float:
        return 1.0 / self.refresh_hz

    @classmethod
    def for_seed(cls, seed: int, latency_ms: float | None = None, ideal: bool = False, **kw) -> "HardwareModel":
        """The default hardware of a seeded rig: latency drawn in 60-120 ms from the seed unless given."""
        if ideal:
            return cls(ideal=True, latency_ms=0.0, jitter_ms=0.0, auto_exposure=False, emitter_enabled=False, **kw)
        if latency_ms is None:
            latency_ms = float(np.random.default_rng([int(seed), 4711]).uniform(60.0, 120.0))
        if not (latency_ms >= 0 and math.isfinite(latency_ms)):
            raise ValueError(f"the simulated projector latency must be >= 0 ms, got {latency_ms}")
        jitter = kw.pop("jitter_ms", min(4.0, 0.1 * latency_ms))
        return cls(latency_ms=float(latency_ms), jitter_ms=float(jitter), **kw)


def flicker_amplitude(exposure_us: float, refresh_hz: float, depth: float) -> float:
    """Relative amplitude of the frame-to-frame flicker of the projector's light: 0 for a whole number
    of refresh periods, growing with the fractional remainder (largest half a period off), smaller the
    more whole periods the exposure holds."""
    periods = exposure_us * 1e-6 * refresh_hz
    frac = periods - math.floor(periods)
    off = min(frac, 1.0 - frac)  # 0 .. 0.5
    if off < 1e-3:  # the exposure's rounding to a microsecond: no visible flicker
        return 0.0
    return float(depth * 2.0 * off / max(periods, 1.0))


def flicker_phase(model: "HardwareModel", seed: int, frame_number: int, exposure_start_s: float) -> float:
    """The flicker's phase (0..1) at which frame `frame_number`'s exposure starts (module doc)."""
    if model.flicker_random:
        return float(np.random.default_rng([int(seed), 77, int(frame_number)]).uniform())
    return float((exposure_start_s * (model.refresh_hz + model.flicker_beat_hz)) % 1.0)


def emitter_dots(shape: tuple[int, int], seed: int, count: int = 2500) -> np.ndarray:
    """(H, W) float32 of the IR dot pattern as the colour sensor sees it (levels at reference exposure)."""
    H, W = shape
    rng = np.random.default_rng([int(seed), 8128])
    out = np.zeros((H, W), np.float32)
    ys = rng.integers(1, H - 1, count)
    xs = rng.integers(1, W - 1, count)
    val = rng.uniform(25.0, 60.0, count).astype(np.float32)
    out[ys, xs] = val
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):  # a small blob per dot
        np.maximum.at(out, (ys + dy, xs + dx), 0.4 * val)
    return out


class ProjectorTimeline:
    """What the simulated projector showed when: (visible_from_s, ticket, image) in time order."""

    def __init__(self, model: HardwareModel, seed: int, start_s: float, image: np.ndarray):
        self.model = model
        self.seed = int(seed)
        self._vsync0 = start_s
        self._times = [-math.inf]
        self._entries = [(0, image)]
        self.swaps: dict[int, float] = {}

    def next_vsync(self, t: float) -> float:
        r = self.model.refresh_s
        return self._vsync0 + math.ceil((t - self._vsync0) / r - 1e-9) * r

    def latency_s(self, ticket: int) -> float:
        """The true latency of one presentation (seeded jitter within +-jitter_ms)."""
        m = self.model
        j = 0.0
        if m.jitter_ms > 0:
            j = float(np.random.default_rng([self.seed, 31, int(ticket)]).uniform(-1.0, 1.0)) * m.jitter_ms
        return max(0.0, (m.latency_ms + j) * 1e-3)

    def add(self, ticket: int, image: np.ndarray, request_s: float) -> float:
        """Record a show() at `request_s`; returns the swap (presentation) time."""
        if self.model.ideal:
            swap = request_s
            vis = request_s
        else:
            swap = self.next_vsync(request_s)
            vis = swap + self.latency_s(ticket)
        vis = max(vis, self._times[-1])  # a projector never shows images out of order
        self._times.append(vis)
        self._entries.append((ticket, image))
        self.swaps[ticket] = swap
        if len(self._times) > 4096:  # keep the recent history only
            del self._times[1:1024], self._entries[1:1024]
            for k in [k for k in self.swaps if k <= ticket - 4096]:
                del self.swaps[k]
        return swap

    def image_of(self, ticket: int) -> np.ndarray | None:
        """The image of `ticket` (None once it left the kept history)."""
        for tk, img in reversed(self._entries):
            if tk == int(ticket):
                return img
        return None

    def visible_at(self, t: float) -> tuple[int, np.ndarray]:
        i = bisect.bisect_right(self._times, t) - 1
        return self._entries[max(i, 0)]

    def segments(self, t0: float, t1: float) -> list[tuple[int, np.ndarray, float]]:
        """[(ticket, image, fraction of [t0, t1])] of what was visible during [t0, t1]."""
        if t1 <= t0:
            tk, img = self.visible_at(t0)
            return [(tk, img, 1.0)]
        i = max(bisect.bisect_right(self._times, t0) - 1, 0)
        out = []
        while i < len(self._times):
            a = max(self._times[i], t0)
            b = self._times[i + 1] if i + 1 < len(self._times) else math.inf
            b = min(b, t1)
            if b > a:
                tk, img = self._entries[i]
                out.append((tk, img, (b - a) / (t1 - t0)))
            if i + 1 >= len(self._times) or self._times[i + 1] >= t1:
                break
            i += 1
        return out


class CameraSettingsTimeline:
    """Exposure, gain, auto exposure and emitter as set over time; a change applies to frames whose
    exposure starts `settings_lag_frames` frame periods after it was made (the sensor's pipeline); each
    frame's meta says which settings it was taken with, as a RealSense's metadata does."""

    def __init__(self, model: HardwareModel):
        self.model = model
        first = {"auto_exposure": model.auto_exposure, "exposure_us": model.initial_exposure_us, "gain": 1.0,
                 "emitter_enabled": model.emitter_enabled}
        self._times = [-math.inf]
        self._states = [first]

    @property
    def current(self) -> dict:
        return dict(self._states[-1])

    def set(self, t: float, **changes) -> None:
        state = {**self._states[-1], **changes}
        eff = t + (0.0 if self.model.ideal else self.model.settings_lag_frames * self.model.period_s)
        while len(self._times) > 1 and self._times[-1] >= eff:  # superseded before it took effect
            self._times.pop()
            self._states.pop()
        self._times.append(eff)
        self._states.append(state)

    def at(self, t: float) -> dict:
        i = bisect.bisect_right(self._times, t) - 1
        return dict(self._states[max(i, 0)])
