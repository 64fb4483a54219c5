"""Measure the projector's settle time: how long after a presented image (drivers.base.ProjectorDriver
.wait_presented, settle time 0) a camera frame arrives that fully shows it.

The delay adds up the projector's own processing (scaler, DLP/LCD response), the wait for the camera's
next exposure to start and the camera's transfer. The station then treats an image as visible only
`settle_s` after its presentation and asks for a camera frame newer than the last one seen at that
moment, so it never captures a frame exposed before the pattern changed.

One trial: show a dark image, let it settle, take a reference frame; show a bright image, note the
presentation time; watch every new camera frame for `observe_s`. The pixels that changed by more than
`change_levels` between the reference and the last frame are where the camera sees the projection
(directly or through the mirror); the first frame whose mean change over those pixels reaches
`fraction` of the final change marks the delay. Frames are timed by their host arrival time
(Frame.meta["host_time_s"] when the driver records it, else when get_frame returned).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from drivers.errors import DeviceError
from drivers.projector_images import black, white


@dataclass(frozen=True)
class SettleMeasurement:
    """settle_s: the recommended settle time (largest delay seen plus half a camera frame interval,
    for the phase between projector refresh and camera exposure the trials may have missed);
    samples_s: the delay of each trial; frame_interval_s: median camera frame interval seen;
    changed_fraction: the part of the camera image that saw the change."""

    settle_s: float
    samples_s: tuple[float, ...]
    frame_interval_s: float
    changed_fraction: float

    def to_dict(self) -> dict:
        return {"settle_s": self.settle_s, "samples_s": list(self.samples_s),
                "frame_interval_s": self.frame_interval_s, "changed_fraction": self.changed_fraction}


def _grey_small(img: np.ndarray, step: int) -> np.ndarray:
    a = np.asarray(img)
    g = a.astype(np.float32) if a.ndim == 2 else a.astype(np.float32).mean(axis=2)
    if step > 1:
        h, w = (g.shape[0] // step) * step, (g.shape[1] // step) * step
        g = g[:h, :w].reshape(h // step, step, w // step, step).mean(axis=(1, 3))
    return g


def _arrival(frame) -> float:
    t = frame.meta.get("host_time_s") if isinstance(frame.meta, dict) else None
    return float(t) if t is not None else time.monotonic()


def measure_settle(projector, camera, trials: int = 3, observe_s: float = 1.0, rest_s: float = 0.5,
                   fraction: float = 0.9, change_levels: float = 20.0, min_changed_fraction: float = 1e-4,
                   dark: np.ndarray | None = None, bright: np.ndarray | None = None,
                   frame_timeout_s: float = 2.0, downsample: int = 4) -> SettleMeasurement:
    """Measure the settle time over `trials` dark-to-bright switches (see the module doc). The
    projector's own `settle_s` (if it has one) is set to 0 while measuring and restored after.
    Raises DeviceError when the camera does not see the projection change."""
    size = tuple(projector.size)
    dark = black(size) if dark is None else dark
    bright = white(size) if bright is None else bright
    old_settle = getattr(projector, "settle_s", None)
    if old_settle is not None:
        projector.settle_s = 0.0
    samples, intervals, changed = [], [], []
    try:
        for _ in range(trials):
            projector.wait_presented(projector.show(dark), frame_timeout_s)
            time.sleep(rest_s)
            ref = camera.get_frame(frame_timeout_s)
            ref = camera.get_frame(frame_timeout_s, newer_than=ref.frame_number)  # exposed after the rest
            ref_img = _grey_small(ref.image, downsample)
            t_swap = projector.wait_presented(projector.show(bright), frame_timeout_s)
            seen, last = [], ref.frame_number
            while True:
                f = camera.get_frame(frame_timeout_s, newer_than=last)
                last = f.frame_number
                t = _arrival(f)
                seen.append((t, _grey_small(f.image, downsample)))
                if t - t_swap >= observe_s:
                    break
            final = seen[-1][1]
            diff = np.abs(final - ref_img)
            mask = diff > change_levels
            frac = float(mask.mean())
            if frac < min_changed_fraction:
                raise DeviceError(
                    "the camera does not see the projector change (no pixel brightened by more than "
                    f"{change_levels:g} levels within {observe_s:g} s): point the camera at the projected "
                    "image (or its mirror view), or raise observe_s for a slow projector")
            total = float(diff[mask].mean())
            hit = None
            for t, g in seen:
                if float(np.abs(g - ref_img)[mask].mean()) >= fraction * total:
                    hit = t
                    break
            samples.append(max(0.0, hit - t_swap))
            changed.append(frac)
            times = [t for t, _ in seen]
            intervals.extend(np.diff(times).tolist())
    finally:
        if old_settle is not None:
            projector.settle_s = old_settle
    interval = float(np.median(intervals)) if intervals else 0.0
    return SettleMeasurement(max(samples) + 0.5 * interval, tuple(samples), interval, float(np.mean(changed)))


def measure_settle_time(projector, camera, **kwargs) -> float:
    """The recommended settle time in seconds (measure_settle(...).settle_s)."""
    return measure_settle(projector, camera, **kwargs).settle_s
