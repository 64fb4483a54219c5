"""Measure the projector's latency: how long after an image is presented (the swap time that
drivers.base.ProjectorDriver.wait_presented returns when its settle time is 0) the camera sees it.

The delay is the projector's own processing (scaler, DLP/LCD response). The station then treats an
image as visible `settle_s` after its presentation and accepts only camera frames whose exposure
started at or after that moment (Frame.exposure_start_s), so it never uses a frame exposed before the
pattern changed (see docs/STATION.md, "timing").

One trial: show a dark image and wait until the camera's frames are steady (a reference frame); show
a bright image, note the presentation time; watch every new camera frame until the change has
happened and the frames are steady again (or `observe_s` passed). The pixels that changed by more
than `change_levels` between the reference and the last frame are where the camera sees the
projection (directly or through the mirror). For each frame, f is the fraction of the final change it
shows. A frame that shows part of the change (0 < f < 1) was exposed while the image appeared: with
its exposure start s and duration d, the image appeared at s + (1 - f) d. Otherwise the first frame
that shows it fully bounds the moment from above (its exposure start, or for a driver that cannot
time its frames its arrival) and the last one showing none of it from below (its exposure end). The
camera's exposures start at a different phase of the projector's refresh in every trial, so the
smallest upper bound over the trials is the tightest (never below a lower bound). The trials
timed within an exposure measure the projector's jitter (their spread: a compositor, a GPU queue or
the projector's frame conversion can add a whole refresh period), so the recommended settle time is
the longest delay seen (the tightest bound plus that spread) plus a margin for a delay longer than
any of the few trials showed: max(10 ms, spread / (timed trials - 1)).
The exposure is the frame's own metadata: `actual_exposure_us` (the RealSense driver) or
`exposure_us` (the simulated camera), else the manual exposure the RealSense driver last set
(`exposure_us_set`, on frames without metadata); a camera that reports none is timed by whole frames only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from drivers.clock import clock_of
from drivers.errors import DeviceError, ExposureUnsupported
from drivers.projector_images import black, white

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SettleMeasurement:
    """settle_s: the recommended settle time (see the module doc); samples_s: each trial's upper bound
    of the delay; frame_interval_s: median camera frame interval seen;
    changed_fraction: the part of the camera image that saw the change; jitter_s: the spread of the
    trials timed within an exposure (None when fewer than two were)."""

    settle_s: float
    samples_s: tuple[float, ...]
    frame_interval_s: float
    changed_fraction: float
    jitter_s: float | None = None

    def to_dict(self) -> dict:
        return {"settle_s": self.settle_s, "samples_s": list(self.samples_s),
                "frame_interval_s": self.frame_interval_s, "changed_fraction": self.changed_fraction,
                "jitter_s": self.jitter_s}


def _grey_small(img: np.ndarray, step: int) -> np.ndarray:
    a = np.asarray(img)
    g = a.astype(np.float32) if a.ndim == 2 else a.astype(np.float32).mean(axis=2)
    if step > 1:
        h, w = (g.shape[0] // step) * step, (g.shape[1] // step) * step
        g = g[:h, :w].reshape(h // step, step, w // step, step).mean(axis=(1, 3))
    return g


def _arrival(frame, clock) -> float:
    t = frame.meta.get("host_time_s") if isinstance(frame.meta, dict) else None
    return float(t) if t is not None else clock.now()


def _exposure_s(frame) -> float | None:
    meta = frame.meta if isinstance(frame.meta, dict) else {}
    e = meta.get("actual_exposure_us", meta.get("exposure_us", meta.get("exposure_us_set")))
    return float(e) * 1e-6 if isinstance(e, (int, float)) and e > 0 else None


def _changed_fraction(a: np.ndarray, b: np.ndarray, levels: float) -> float:
    return float((np.abs(a - b) > levels).mean())


def _steady(camera, last: int, timeout_s: float, downsample: int, levels: float, away_from=None,
            max_frames: int = 60):
    """Frames until two in a row differ by more than `levels` nowhere (but for specks) and, with
    `away_from` = (grey image, mask), the frame no longer shows that image on the mask; returns
    (frame, grey)."""
    prev = None
    for _ in range(max_frames):
        f = camera.get_frame(timeout_s, newer_than=last)
        last = f.frame_number
        g = _grey_small(f.image, downsample)
        gone = away_from is None or float((np.abs(g - away_from[0]) > levels)[away_from[1]].mean()) > 0.5
        if prev is not None and gone and _changed_fraction(g, prev, levels) < 1e-4:
            return f, g
        prev = g
    return f, g


def measure_settle(projector, camera, trials: int = 5, observe_s: float = 1.5, rest_s: float = 0.0,
                   fraction: float = 0.97, change_levels: float = 20.0, min_changed_fraction: float = 1e-4,
                   dark: np.ndarray | None = None, bright: np.ndarray | None = None,
                   frame_timeout_s: float = 2.0, downsample: int = 4, first_rest_s: float = 0.5) -> SettleMeasurement:
    """Measure the settle time over `trials` dark-to-bright switches (see the module doc); the first
    dark image is given `first_rest_s` (longer than any projector's latency) to show. The
    projector's own `settle_s` (if it has one) is set to 0 while measuring and restored after.
    Raises DeviceError when the camera does not see the projection change."""
    size = tuple(projector.size)
    dark = black(size) if dark is None else dark
    bright = white(size) if bright is None else bright
    old_settle = getattr(projector, "settle_s", None)
    if old_settle is not None:
        projector.settle_s = 0.0
    samples, intervals, changed, exact, lows = [], [], [], [], []
    clock = clock_of(projector)  # the projector's presentation times and the camera's frame times share it
    try:
        last = camera.get_frame(frame_timeout_s).frame_number
        away = None
        for k in range(trials):
            projector.wait_presented(projector.show(dark), frame_timeout_s)
            if k == 0:  # what was shown before is unknown: wait for any projector to have caught up
                clock.sleep(max(rest_s, first_rest_s))
            elif rest_s > 0:
                clock.sleep(rest_s)
            ref, ref_img = _steady(camera, last, frame_timeout_s, downsample, change_levels / 2, away)
            last = ref.frame_number
            t_swap = projector.wait_presented(projector.show(bright), frame_timeout_s)
            seen = []
            while True:
                f = camera.get_frame(frame_timeout_s, newer_than=last)
                last = f.frame_number
                g = _grey_small(f.image, downsample)
                seen.append((f, _arrival(f, clock), g))
                moved = _changed_fraction(g, ref_img, change_levels) >= min_changed_fraction
                if len(seen) >= 3 and moved and _changed_fraction(g, seen[-2][2], change_levels / 2) < 1e-4 \
                        and _changed_fraction(seen[-2][2], seen[-3][2], change_levels / 2) < 1e-4:
                    break  # changed, and steady for three frames
                if seen[-1][1] - t_swap >= observe_s:
                    break
            final = seen[-1][2]
            diff = np.abs(final - ref_img)
            mask = diff > change_levels
            frac = float(mask.mean())
            if frac < min_changed_fraction:
                raise DeviceError(
                    "the camera does not see the projector change (no pixel brightened by more than "
                    f"{change_levels:g} levels within {observe_s:g} s): point the camera at the projected "
                    "image (or its mirror view), or raise observe_s for a slow projector")
            total = float(diff[mask].mean())
            away = (final, mask)  # the next trial's dark frame must have left this bright one
            lo, hi, exact_k = 0.0, None, None
            for f, t_arr, g in seen:
                part = float(np.abs(g - ref_img)[mask].mean()) / total
                start, dur = f.exposure_start_s, _exposure_s(f)
                if part >= fraction:  # fully changed: the image appeared before this exposure
                    hi = start if start is not None else t_arr
                    break
                if part > 1 - fraction and start is not None and dur is not None:
                    exact_k = hi = start + (1.0 - part) * dur  # appeared during this exposure
                    break
                if start is not None and dur is not None:  # unchanged: it appeared after this exposure
                    lo = start + dur
            if exact_k is not None:
                exact.append(exact_k - t_swap)
            samples.append(max(0.0, hi - t_swap))
            lows.append(max(0.0, lo - t_swap))
            changed.append(frac)
            times = [f.exposure_start_s if f.exposure_start_s is not None else t for f, t, _ in seen]
            intervals.extend(np.diff(times).tolist())
    finally:
        if old_settle is not None:
            projector.settle_s = old_settle
    interval = float(np.median(intervals)) if intervals else 0.0
    # each trial bounds the latency from above (the first changed frame; exact when a frame caught the
    # change); the smallest bound is the tightest, as long as it is not below another trial's lower bound
    latency = max(min(samples), max(lows))
    jitter = max(exact) - min(exact) if len(exact) > 1 else None
    spread = jitter or 0.0
    margin = max(0.010, spread / max(1, len(exact) - 1))
    return SettleMeasurement(latency + spread + margin, tuple(samples), interval, float(np.mean(changed)), jitter)


#: the latency assumed when it cannot be measured (a camera's auto exposure follows the change): longer
#: than projectors' (60-150 ms, a compositor's frame included), so no frame of an old image counts
UNMEASURED_LATENCY_S = 0.3


def measure_settle_time(projector, camera, **kwargs) -> float:
    """The recommended settle time in seconds (measure_settle(...).settle_s)."""
    return measure_settle(projector, camera, **kwargs).settle_s


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v and abs(v) != float("inf")


def recorded_exposure(camera_settings: dict | None) -> tuple[float, float] | None:
    """(exposure_us, gain) of a manifest's rig.camera_settings when it recorded a manual exposure with
    numbers (a session file is untrusted: anything else counts as not recorded), else None."""
    rec = camera_settings if isinstance(camera_settings, dict) else {}
    exposure, gain = rec.get("exposure_us"), rec.get("gain", 1.0)
    if rec.get("auto_exposure") is False and _finite(exposure) and exposure > 0 and _finite(gain) and gain >= 0:
        return float(exposure), float(gain)
    return None


def recorded_latency_s(camera_settings: dict | None) -> float | None:
    """The projector latency (seconds) a manifest's rig.camera_settings recorded, or None."""
    rec = camera_settings if isinstance(camera_settings, dict) else {}
    proj = rec.get("projector")
    v = proj.get("latency_ms") if isinstance(proj, dict) else None
    return float(v) / 1000.0 if _finite(v) and v >= 0 else None


def apply_timing(camera, projector, camera_settings: dict | None = None, search_image: np.ndarray | None = None,
                 measure: bool = True) -> dict:
    """Make a rig's frames trustworthy for a command that shows images and reads them back (the
    station's rig check does the same, with a report per step): the IR emitter off, the exposure
    re-applied from `camera_settings` (a session manifest's rig.camera_settings) or searched while
    `search_image` (default full white) lights the board, and the projector latency re-applied from
    camera_settings["projector"]["latency_ms"] or measured (when `measure`). Returns the settings
    applied, in the manifest's form."""
    from drivers.base import ExposureControl
    from drivers.exposure import apply_exposure, search_exposure

    rec = dict(camera_settings or {})
    out = {}
    if isinstance(camera, ExposureControl):
        camera.set_emitter(False)
        recorded = recorded_exposure(rec)
        try:
            if recorded is not None:
                applied, _ = apply_exposure(camera, *recorded)
            else:
                img = white(tuple(projector.size)) if search_image is None else search_image
                projector.wait_presented(projector.show(img))
                clock_of(projector).sleep(0.5)  # longer than any projector's latency
                c = search_exposure(camera, float(getattr(projector, "refresh_hz", 60.0) or 60.0))
                applied = {"exposure_us": c.exposure_us, "gain": c.gain}
            out.update({"auto_exposure": False, "exposure_us": float(applied["exposure_us"]),
                        "gain": float(applied["gain"]), "emitter_enabled": False})
        except ExposureUnsupported as e:  # a webcam's own auto exposure: frames are still timed
            _log.warning("%s", e)
            out.update({"auto_exposure": True, "manual_exposure": "ignored by the camera"})
    timing = dict(rec.get("projector") or {})
    if hasattr(projector, "settle_s"):
        latency_s = recorded_latency_s(rec)
        if latency_s is not None:
            projector.settle_s = latency_s
        elif measure:
            try:
                projector.settle_s = measure_settle(projector, camera).settle_s
            except DeviceError:
                if out.get("manual_exposure") != "ignored by the camera":
                    raise
                projector.settle_s = UNMEASURED_LATENCY_S  # the rig check's rule (app/station/station.py)
                timing["assumed"] = True
        timing.update({"latency_ms": round(float(projector.settle_s) * 1000.0, 3),
                       "refresh_hz": float(getattr(projector, "refresh_hz", 0.0) or 0.0)})
        out["projector"] = timing
    return out
