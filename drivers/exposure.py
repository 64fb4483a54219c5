"""Choosing the camera's exposure by hand, while the projector's pattern lights the board.

Auto exposure fights the projector (every pattern change moves the brightness) and, on the D4xx RGB
sensor, the exposure auto exposure chose cannot be read back reliably. So the exposure is searched in
manual mode (drivers.base.ExposureControl), with one entry point:

    choice = search_exposure(camera, refresh_hz=projector.refresh_hz)

Rules: the exposure is a whole number of the projector's refresh periods (a PWM / DLP projector
flickers at its refresh rate: any other exposure catches a different share of the light in each frame,
the D455's global shutter making the whole frame brighter or darker; where even one period saturates,
the brightest of FLICKER_FRAMES frames is metered); the gain stays as low as the brightness allows (gain amplifies noise); the lit
board (the `percentile` of the image: its brightest pixels) ends near `target_level` and below
`max_level` (no saturation, so the projected pattern's edges keep their shape). Every change is followed by
`wait_frames` frames exposed after it before the next measurement (the sensor applies a change a
few frames late: which frames show it is read from their metadata, or without metadata from a lag
measured first, frames_after_change and measure_settings_lag).

Brightness is proportional to exposure x gain below saturation, so the search needs few
measurements: one at the longest whole-period exposure that fits, one after stepping down whole
periods if that saturates (predicted from the first), one after setting the gain, and one check.
It converges within MAX_ROUNDS measurements, that is MAX_FRAMES frames exposed after a change (a
driver that skips frames delivers fewer; the frames exposed before a change are not counted).
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np

from drivers.clock import clock_of
from drivers.errors import DeviceError

_log = logging.getLogger(__name__)

#: Measurements the search takes at most.
MAX_ROUNDS = 6
#: Frames waited after each change (the last one is measured).
WAIT_FRAMES = 3
#: Camera frames the search uses at most (MAX_ROUNDS x WAIT_FRAMES + the first frame).
MAX_FRAMES = MAX_ROUNDS * WAIT_FRAMES + 1


@dataclass(frozen=True)
class ExposureChoice:
    """exposure_us, gain: what the camera applied; periods: exposure in refresh periods (a whole
    number unless `whole_periods` is False: even one period saturated at the lowest gain); level: the
    lit board's level measured last; frames: camera frames the search used (exposed after a change, and
    the first)."""

    exposure_us: float
    gain: float
    periods: float
    whole_periods: bool
    level: float
    saturated_fraction: float
    frames: int
    #: the lit board stays below 70 % of the target level at the longest exposure and the highest gain
    dim: bool = False
    #: how the search told frames taken with each setting from older ones (metadata or a measured lag)
    timing: ChangeTiming | None = None
    #: off a whole number of periods: the spread of the levels over FLICKER_FRAMES frames / the highest
    flicker: float = 0.0

    def camera_settings(self) -> dict:
        """The manifest's rig.camera_settings keys (docs/FORMATS.md)."""
        return {"auto_exposure": False, "exposure_us": float(self.exposure_us), "gain": float(self.gain),
                "emitter_enabled": False}


#: Frames exposed after a change that may still show the old settings before the wait gives up on them.
SKIP_LIMIT = 12
#: Frames metered at an exposure that is not a whole number of refresh periods (their brightest counts):
#: such an exposure catches more or less of the projector's flickering light from frame to frame
FLICKER_FRAMES = 8


class ChangeEvidence(str, enum.Enum):
    """How a wait after an exposure or gain change knows which frames were taken with the new settings.
    METADATA: each frame's own metadata says its exposure and gain. MEASURED_LAG: the frames carry none,
    so how long a change takes to show was measured once, from brightness steps in the frames
    (measure_settings_lag), and after every change the frames exposed before that lag (and one frame
    interval more) are skipped. ASSUMED: no metadata and nothing measured: the longest lag allowed
    (SKIP_LIMIT frames) is skipped."""

    METADATA = "frame metadata"
    MEASURED_LAG = "measured lag"
    ASSUMED = "assumed lag"


@dataclass(frozen=True)
class ChangeTiming:
    """evidence: ChangeEvidence; lag_s: from a write, how long until frames exposed after it show it
    (the longest of `steps_s`, one per brightness step measured, plus `frame_interval_s`: a frame's
    exposure start is known only to a frame interval on the host's clock); None unless measured."""

    evidence: ChangeEvidence
    lag_s: float | None = None
    steps_s: tuple[float, ...] = ()
    frame_interval_s: float | None = None

    def frames(self) -> float | None:
        """The measured lag in frame intervals."""
        if self.lag_s is None or not self.frame_interval_s:
            return None
        return max(self.steps_s) / self.frame_interval_s

    def describe(self) -> str:
        if self.evidence is ChangeEvidence.METADATA:
            return "settings confirmed by each frame's metadata"
        if self.evidence is ChangeEvidence.MEASURED_LAG:
            return (f"no exposure metadata: a change shows {max(self.steps_s) * 1000:.0f} ms (about {self.frames():.1f} "
                    f"frames) after it is made, measured by brightness steps "
                    f"({', '.join(f'{t * 1000:.0f}' for t in self.steps_s)} ms); frames exposed before "
                    f"{self.lag_s * 1000:.0f} ms after each change are skipped")
        return f"no exposure metadata and no measured lag: {SKIP_LIMIT} frames skipped after each change"

    def to_dict(self) -> dict:
        """The manifest's rig.camera_settings["timing"] keys about changes (docs/FORMATS.md)."""
        out = {"settings_confirmed_by": self.evidence.value}
        if self.lag_s is not None:
            out.update({"lag_ms": round(self.lag_s * 1000.0, 3), "lag_steps_ms": [round(t * 1000.0, 3) for t in self.steps_s],
                        "frame_interval_ms": round(float(self.frame_interval_s or 0.0) * 1000.0, 3)})
        return out


ASSUMED_TIMING = ChangeTiming(ChangeEvidence.ASSUMED)
METADATA_TIMING = ChangeTiming(ChangeEvidence.METADATA)


def has_settings_metadata(frame) -> bool:
    """Whether `frame` reports the exposure or gain it was taken with (see shows_settings)."""
    meta = frame.meta if isinstance(getattr(frame, "meta", None), dict) else {}
    return any(meta.get(k) is not None for k in ("actual_exposure_us", "exposure_us", "gain"))


def _mean_level(frame) -> float:
    a = np.asarray(frame.image)
    return float(a[::4, ::4].mean())


def measure_settings_lag(camera, refresh_hz: float, timeout_s: float = 3.0, min_step_levels: float = 4.0) -> ChangeTiming:
    """Measure how long a change of exposure and one of gain take to show, from the frames themselves,
    for a camera whose frames carry no metadata: settle at two refresh periods and twice the unit gain
    (SKIP_LIMIT frames, longer than any lag allowed), then halve the exposure, then halve the gain; after
    each write, the first frame whose mean level moved halfway to the new steady level marks the lag
    (its exposure start after the write). Timed by exposure starts, not counted in frames: a driver that
    skips or drops frames would make a count too short. Whole refresh periods, so the projector's
    flicker moves no level. The scene must be steadily lit (the projector's pattern on the board).
    Raises DeviceError when a step does not show (a dark scene), shows only after SKIP_LIMIT frames, or
    the frames are not timed."""
    lim = camera.exposure_limits()
    e_lo, e_hi, _ = lim["exposure_us"]
    g_lo, g_hi, _ = lim["gain"]
    fps = getattr(camera, "fps", None)
    if isinstance(fps, (int, float)) and fps > 0:
        e_hi = min(e_hi, 1e6 / float(fps))
    if not refresh_hz or refresh_hz <= 0:
        raise DeviceError(f"the projector's refresh rate is unknown ({refresh_hz}): cannot time the camera")
    period_us = 1e6 / float(refresh_hz)
    e2 = min(e_hi, 2 * period_us) if 2 * period_us <= e_hi + 0.5 * period_us else e_hi
    e1 = max(e_lo, e2 / 2)
    g1 = unit_gain(g_lo, g_hi)
    g2 = min(g_hi, 2 * g1)
    last = camera.get_frame(timeout_s).frame_number
    starts = []

    def frames_after(exposure_us, gain, count):
        nonlocal last
        t_set = clock_of(camera).now()
        camera.set_manual_exposure(exposure_us, gain)
        out, early = [], 0
        while len(out) < count:
            f = camera.get_frame(timeout_s, newer_than=last)
            last = f.frame_number
            if f.exposure_start_s is None:
                raise DeviceError("the camera's frames carry neither exposure metadata nor times: a change of "
                                  "exposure cannot be confirmed")
            starts.append(f.exposure_start_s)
            if f.exposure_start_s < t_set:
                early += 1
                if early > SKIP_LIMIT:
                    raise DeviceError("the camera delivers no frame exposed after the exposure change")
                continue
            out.append((f.exposure_start_s - t_set, _mean_level(f)))
        return out

    base = frames_after(e2, g2, SKIP_LIMIT + 2)[-1][1]
    steps = []
    for exposure_us, gain, what in ((e1, g2, "exposure"), (e1, g1, "gain")):
        seen = frames_after(exposure_us, gain, SKIP_LIMIT + 3)
        levels = [v for _, v in seen]
        new = float(np.mean(levels[-2:]))
        if abs(new - base) < max(min_step_levels, 0.03 * base) or abs(levels[-1] - levels[-2]) > 0.25 * abs(new - base):
            raise DeviceError(f"the camera image did not change steadily when its {what} was halved (level {base:.0f} "
                              f"-> {new:.0f}): light the board with the projector and keep the lens uncovered")
        k = [abs(v - base) >= 0.5 * abs(new - base) for v in levels].index(True)
        if k >= SKIP_LIMIT:
            raise DeviceError(f"the camera shows a change of {what} only {k} frames after it was made (more than "
                              f"{SKIP_LIMIT}): the camera cannot be timed")
        steps.append(max(0.0, seen[k][0]))
        base = new
    # the stream's own frame interval (a driver that skips frames shows longer gaps between the ones it hands out)
    interval = 1.0 / float(fps) if isinstance(fps, (int, float)) and fps > 0 else float(np.median(np.diff(sorted(starts))))
    return ChangeTiming(ChangeEvidence.MEASURED_LAG, max(steps) + interval, tuple(steps), interval)


def change_timing(camera, refresh_hz: float, frame=None, timeout_s: float = 3.0) -> ChangeTiming:
    """How waits after a change on `camera` tell new frames from old: by metadata when its frames carry
    it (`frame`, or the next one), else by the lag measured now (measure_settings_lag)."""
    f = frame if frame is not None else camera.get_frame(timeout_s)
    if has_settings_metadata(f):
        return METADATA_TIMING
    timing = measure_settings_lag(camera, refresh_hz, timeout_s)
    _log.info("the camera's frames carry no exposure metadata: %s", timing.describe())
    return timing


def shows_settings(frame, applied: dict) -> bool | None:
    """Whether `frame` was taken with the exposure and gain `applied` (what set_manual_exposure returned),
    by the frame's own metadata: `actual_exposure_us` (the RealSense driver) or `exposure_us` (the
    simulated camera), and `gain`. None when the frame reports neither."""
    meta = frame.meta if isinstance(getattr(frame, "meta", None), dict) else {}
    said = []
    exposure = meta.get("actual_exposure_us", meta.get("exposure_us"))
    if exposure is not None and applied.get("exposure_us") is not None:
        want = float(applied["exposure_us"])
        said.append(abs(float(exposure) - want) <= max(60.0, 0.01 * want))  # a device step is 100 us
    gain = meta.get("gain")
    if gain is not None and applied.get("gain") is not None:
        want = float(applied["gain"])
        said.append(abs(float(gain) - want) <= 0.02 * max(1.0, abs(want)))  # the device reports what it applied
    return all(said) if said else None


def frames_after_change(camera, t_set: float, applied: dict, last: int, wait_frames: int = WAIT_FRAMES,
                        timeout_s: float = 3.0, skip_limit: int = SKIP_LIMIT, timing: ChangeTiming | None = None) -> tuple:
    """Read frames until `wait_frames` of them show the change made at host time `t_set`: exposed after
    it and taken with `applied` (a sensor applies a change some frames late: about 5 on a D455,
    HARDWARE facts in docs/DRIVERS.md; the time alone would count frames still taken with the old
    settings). Where a frame's metadata reports its exposure and gain, it says; a frame without
    metadata counts only once the lag has passed (the lag
    measured by measure_settings_lag: frames exposed earlier than `timing.lag_s` after the change are
    skipped; without a measured lag, the first `skip_limit` frames, with a warning when not expected).
    Returns (the last frame, its number, the frames counted). Frames exposed before the change are
    skipped; so are frames whose metadata shows other settings, until `skip_limit` of them: then the
    metadata is taken as not describing the settings (a warning) and the time alone decides. Raises
    DeviceError when no frame is exposed after the change."""
    after = early = stale = blind = 0
    trust_meta = True
    f = None
    while after < max(1, int(wait_frames)):
        f = camera.get_frame(timeout_s, newer_than=last)
        last = f.frame_number
        if f.exposure_start_s is not None and f.exposure_start_s < t_set:
            early += 1
            if early > skip_limit:
                raise DeviceError("the camera delivers no frame exposed after the exposure change")
            continue
        said = shows_settings(f, applied)
        if said is None:  # no metadata: only the measured lag (or the longest allowed) can tell
            blind += 1
            if timing is not None and timing.lag_s is not None and f.exposure_start_s is not None:
                if f.exposure_start_s < t_set + timing.lag_s:
                    continue
            else:
                if blind == 1 and (timing is None or timing.evidence is ChangeEvidence.METADATA):
                    _log.warning("the camera's frames carry no exposure metadata and its lag was not measured: "
                                 "skipping %d frames after the change", skip_limit)
                if blind <= skip_limit:
                    continue
        elif trust_meta and said is False:
            stale += 1
            if stale <= skip_limit:
                continue
            trust_meta = False
            _log.warning("the camera's frames report settings other than those set (%s) %d frames after the "
                         "change: timing the change by frame times alone", applied, stale)
        after += 1
    return f, last, after


def apply_exposure(camera, exposure_us: float, gain: float, timeout_s: float = 3.0,
                   timing: ChangeTiming | None = None) -> tuple:
    """Set a manual exposure and gain and wait for the first frame taken with them (frames_after_change,
    with `timing` when the lag was measured): a recorded exposure re-applied, or the searched one
    restored, holds for every frame read after this returns. Returns (what the camera applied, that frame)."""
    first = camera.get_frame(timeout_s)
    if timing is None and not has_settings_metadata(first):
        timing = ASSUMED_TIMING
    t_set = clock_of(camera).now()
    applied = camera.set_manual_exposure(exposure_us, gain)
    f, _, _ = frames_after_change(camera, t_set, applied, first.frame_number, 1, timeout_s, timing=timing)
    return applied, f


def _level(image: np.ndarray, percentile: float) -> tuple[float, float]:
    """(the `percentile` of the brightest channel of each pixel, the fraction of pixels with a channel at
    saturation): every channel is metered (red or blue saturate first under a coloured light). A lower
    percentile would ignore a specular spot but also the projected pattern's small bright dots, which
    it then overexposes."""
    a = np.asarray(image)
    top = a if a.ndim == 2 else a.max(axis=2)
    return float(np.percentile(top, percentile)), float((top >= 254).mean())


def unit_gain(g_lo: float, g_hi: float) -> float:
    """The gain taken to amplify 1x: the range's minimum, or for a control starting at 0 (the D455's
    0..128, no unit) an eighth of its maximum, the gain proportional to the amplification above it and
    every gain below it amplifying as it does (an assumption verified only in emulation)."""
    return g_lo if g_lo > 0 else g_hi / 8.0


def search_exposure(camera, refresh_hz: float, target_level: float = 200.0, max_level: float = 245.0,
                    percentile: float = 99.99, wait_frames: int = WAIT_FRAMES,
                    timeout_s: float = 3.0, timing: ChangeTiming | None = None) -> ExposureChoice:
    """Search the exposure as the module doc says; leaves the camera in manual mode at the choice. A
    camera whose frames carry no metadata has its lag measured first (change_timing), unless `timing`
    says it. Raises DeviceError when the camera cannot be set or the image stays dark."""
    lim = camera.exposure_limits()
    e_lo, e_hi, e_step = lim["exposure_us"]
    g_lo, g_hi, _ = lim["gain"]
    fps = getattr(camera, "fps", None)  # an exposure longer than the frame period would lower the frame rate
    if isinstance(fps, (int, float)) and fps > 0:
        e_hi = min(e_hi, 1e6 / float(fps))
    if not refresh_hz or refresh_hz <= 0:
        raise DeviceError(f"the projector's refresh rate is unknown ({refresh_hz}): cannot choose an exposure")
    period_us = 1e6 / float(refresh_hz)
    frames = 0
    first = camera.get_frame(timeout_s)
    timing = timing or change_timing(camera, refresh_hz, first, timeout_s)
    last = camera.get_frame(timeout_s).frame_number
    frames += 1

    # a device sets exposure in steps (the D455: 100 us), so a whole number of periods is met to within
    # half a step (16700 us for 16667 us): the residue is at most that share of one period
    tolerance = max(1e-3, 0.5 * float(e_step or 0.0) / period_us + 1e-9)
    flicker = 0.0

    def measure(exposure_us, gain):
        nonlocal last, frames, flicker
        t_set = clock_of(camera).now()
        applied = camera.set_manual_exposure(exposure_us, gain)
        f, last, after = frames_after_change(camera, t_set, applied, last, wait_frames, timeout_s, timing=timing)
        frames += after
        lvl, sat = _level(f.image, percentile)
        periods = float(applied["exposure_us"]) / period_us
        flicker = 0.0
        if round(periods) < 1 or abs(periods - round(periods)) > tolerance:
            # the frames flicker (a global shutter: each catches the light at another phase): the brightest
            # of several must not saturate
            seen = [(lvl, sat)]
            for _ in range(FLICKER_FRAMES - 1):
                f = camera.get_frame(timeout_s, newer_than=last)
                last = f.frame_number
                frames += 1
                seen.append(_level(f.image, percentile))
            levels = [v for v, _ in seen]
            lvl, sat = max(levels), max(x for _, x in seen)
            flicker = (lvl - min(levels)) / max(lvl, 1.0)
        return float(applied["exposure_us"]), float(applied["gain"]), lvl, sat

    n_max = int(math.floor(e_hi / period_us + 1e-9))
    whole = n_max >= 1 and period_us >= e_lo
    n = n_max if whole else 0
    exp = n * period_us if whole else e_hi
    gain = g_lo
    exp, gain, lvl, sat = measure(exp, gain)
    for _ in range(MAX_ROUNDS - 1):
        if lvl > max_level:
            # brightness ~ exposure x gain; a saturated level under-reads, so at least halve
            scale = min(0.5, target_level / lvl) if lvl >= 254 else target_level / lvl
            gain = g_lo
            if whole and n > 1:
                n = max(1, min(n - 1, int(math.floor(n * scale))))
                exp = n * period_us
            else:  # even one period is too bright at the lowest gain: the image will band
                whole = False
                exp = max(e_lo, exp * scale)
        elif lvl < 0.7 * target_level and gain < g_hi:
            if lvl < 2.0:
                raise DeviceError("the camera image stays dark at the longest exposure: is the lens covered, "
                                  "or the projector off?")
            # only as much gain as needed; from a gain of 0 (the D455's minimum) a product stays 0
            gain = float(np.clip(max(gain, unit_gain(g_lo, g_hi)) * target_level / lvl, g_lo, g_hi))
        else:
            break
        exp, gain, lvl, sat = measure(exp, gain)
    periods = exp / period_us
    dim = lvl < 0.7 * target_level and gain >= g_hi
    if dim:
        _log.warning("the lit board reaches only level %.0f of %.0f at the longest exposure and the highest gain",
                     lvl, target_level)
    return ExposureChoice(exp, gain, periods, bool(whole and abs(periods - round(periods)) <= tolerance), lvl, sat,
                          frames, dim, timing, flicker)


def camera_timing(frame, timing: ChangeTiming | None) -> tuple[dict, str]:
    """What the rig check records (rig.camera_settings["timing"]) and says about how a camera's frames
    are timed: the clock of their exposure times (drivers.base.TimeSource, from `frame`) and how a
    changed setting is confirmed (`timing`; None: not changed through this camera)."""
    from drivers.base import TimeSource, frame_time_source

    source = frame_time_source(frame)
    record = {"frame_times": None if source is None else source.value}
    if source is TimeSource.HOST:
        text = ("frame times from the host clock on arrival: the frames carry no device timestamps (Linux: "
                "librealsense's kernel patch or its RSUSB backend; Windows: the metadata registry switch)")
    elif source is TimeSource.DEVICE:
        text = "frame times from the device clock"
    else:
        text = "frames not timed: a few frames are skipped after each change"
    if timing is not None:
        record.update(timing.to_dict())
        text += "; " + timing.describe()
    return record, text


# ---- the camera's response (tone curve) -----------------------------------------------------------------
@dataclass(frozen=True)
class ResponseFit:
    """The camera's tone curve fitted from frames at a bracket of gains: `gamma` of the BT.709-shaped
    model (calib.detection.response), `rms` the fit's residual (relative light), `bins` pixel groups used."""

    gamma: float
    rms: float
    bins: int
    frames: int

    def camera_settings(self) -> dict:
        """The manifest's rig.camera_settings key ("source": measured, vs the simulated camera's "known")."""
        return {"response": {"model": "bt709", "gamma": round(float(self.gamma), 3), "source": "measured",
                             "rms": round(float(self.rms), 4), "frames": int(self.frames)}}


def measure_response(camera, refresh_hz: float, gains=(1.0, 1.41, 2.0, 2.83, 4.0, 5.66, 8.0),
                     wait_frames: int = WAIT_FRAMES, timeout_s: float = 3.0,
                     timing: ChangeTiming | None = None) -> ResponseFit:
    """Measure the camera's tone curve while a steady light (the projector's white) lights the scene:
    one whole refresh period of exposure, frames at a bracket of gains (x the lowest gain; the sensor's
    signal is proportional to exposure x gain before the tone curve), pixels grouped by their level in a
    first frame (groups of dim pixels, whose light the bracket multiplies up to 8x), each group's mean
    level at each gain, and the gamma whose inverse makes those levels proportional to the gain.
    Verified on the simulated camera and through the RealSense driver on `--rig sim-realsense`
    (tests/test_response.py); a real camera's black level and gain steps are not modelled. The
    station's rig check calls it for a camera without `response()` and restores the exposure after. Raises DeviceError when the scene has too few dim pixels or levels."""
    from calib.detection.response import CameraResponse

    lim = camera.exposure_limits()
    e_lo, e_hi, _ = lim["exposure_us"]
    g_lo, g_hi, _ = lim["gain"]
    if not refresh_hz or refresh_hz <= 0:
        raise DeviceError(f"the projector's refresh rate is unknown ({refresh_hz}): cannot measure the response")
    exposure = float(np.clip(1e6 / float(refresh_hz), e_lo, e_hi))
    # a device whose gain control starts at 0 (the D455: 0..128, no unit) is taken as proportional to the
    # amplification, the bracket ending at its maximum (an assumption verified only in emulation)
    base = unit_gain(g_lo, g_hi)
    first = camera.get_frame(timeout_s)
    timing = timing or change_timing(camera, refresh_hz, first, timeout_s)
    last = camera.get_frame(timeout_s).frame_number
    frames = 1

    def frame_at(gain):
        nonlocal last, frames
        t_set = clock_of(camera).now()
        applied = camera.set_manual_exposure(exposure, gain)
        f, last, after = frames_after_change(camera, t_set, applied, last, wait_frames, timeout_s, timing=timing)
        frames += after
        a = np.asarray(f.image)
        return float(applied["gain"]), (a if a.ndim == 2 else a[:, :, 1]).astype(np.float64)

    g0, first = frame_at(base * gains[0])  # groups the pixels; its own noise stays out of the levels below
    shots = [frame_at(float(np.clip(base * g, g_lo, g_hi))) for g in gains]
    edges = np.arange(8.0, 64.0, 4.0)
    groups = [(first >= lo) & (first < lo + 4.0) for lo in edges]
    groups = [m for m in groups if m.sum() >= 200]
    if len(groups) < 3:
        raise DeviceError("too few dim pixels in view to measure the camera's response: light the board with "
                          "the projector's white and keep part of the room in view")
    levels = np.array([[img[m].mean() for _, img in shots] for m in groups])  # (groups, gains)
    rel = np.array([g for g, _ in shots]) / shots[0][0]
    use = levels < 245.0
    if use.sum() < 2 * len(groups):
        raise DeviceError("the camera's response could not be measured: the image saturates at the lowest gains")

    def misfit(gamma):
        light = CameraResponse("bt709", gamma).decode(levels / 255.0)
        res = []
        for b in range(len(groups)):
            x, y = rel[use[b]], light[b, use[b]]
            scale = (x @ y) / (x @ x)  # this group's light at the lowest gain
            res.append(y / (scale * x) - 1.0)
        r = np.concatenate(res)
        return float(np.sqrt((r * r).mean()))

    grid = np.arange(1.0, 3.5001, 0.01)
    costs = [misfit(g) for g in grid]
    # near gamma 1 the model's straight toe covers the whole dim range: gammas up to ~1.15 fit a linear
    # camera equally well, so the smallest gamma that fits about as well as the best is taken
    k = int(np.argmax(np.asarray(costs) <= 1.1 * min(costs) + 1e-4))
    return ResponseFit(float(round(grid[k], 2)), float(costs[k]), len(groups), frames)
