"""The frame wait both camera drivers share (drivers/opencv_camera.py, drivers/realsense.py).

Each driver's capture thread keeps the newest frame in `_latest` and notifies `_cond`; `get_frame`
waits under that condition for a frame the caller may have (see `wait_latest`).
"""

from __future__ import annotations

import time
from typing import Callable, Protocol

from drivers.base import Frame
from drivers.errors import DeviceDisconnected, DeviceError


class LatestFrameSource(Protocol):
    """What `wait_latest` reads from a driver: the state its capture thread keeps under `_cond`."""

    _cond: object  # threading.Condition
    _disconnected: bool
    _thread_error: BaseException | None
    _running: bool
    _latest: Frame | None

    def _disconnect_message(self) -> str: ...


def wait_latest(cam: LatestFrameSource, who: Callable[[], str], deadline: float, newer_than: int | None,
                not_before_s: float | None, fresh: Callable[[Frame], bool]) -> Frame | None:
    """The driver's newest frame once it may be handed out, or None when `deadline` (time.monotonic())
    passes first. With `newer_than`, the first frame with a larger number; with `not_before_s`, only a
    frame whose exposure began at or after it; with neither, only a frame `fresh(frame)` accepts (not
    stale). Raises DeviceDisconnected / DeviceError (naming the camera `who()`) once the capture has gone or failed."""
    with cam._cond:
        while True:
            if cam._disconnected:
                raise DeviceDisconnected(cam._disconnect_message())
            if cam._thread_error is not None:
                raise DeviceError(f"{who()}: capture failed: {cam._thread_error}")
            if not cam._running:
                raise DeviceError(f"{who()}: not streaming; call start() first")
            f = cam._latest
            if f is not None and (not_before_s is None or (f.exposure_start_s is not None
                                                           and f.exposure_start_s >= not_before_s)):
                if newer_than is None:
                    if not_before_s is not None or fresh(f):
                        return f
                elif f.frame_number > newer_than:
                    return f
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            cam._cond.wait(min(remaining, 0.25))
