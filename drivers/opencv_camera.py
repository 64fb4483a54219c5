"""Any camera OpenCV can open (`--rig uvc`): a UVC webcam, an industrial camera with a V4L2 / MSMF /
DirectShow / AVFoundation driver, or a network stream, behind drivers.base.CameraDriver and
ExposureControl, over `cv2.VideoCapture`.

    cam = OpenCVCamera(0)                    # /dev/video0 (an index), or a URL / file / pipeline string
    cam.start()
    f = cam.get_frame(timeout_s=2.0, newer_than=last)
    cam.set_manual_exposure(16667, 2.0)      # ExposureUnsupported when the camera ignores it
    cam.reconnect()

Frame path: a capture thread reads VideoCapture continuously (so its buffer never holds old frames for
long) and keeps the newest frame; get_frame hands it out as the RealSense driver does (its own
frame counter, `newer_than`, stale frames, `not_before_s`).

Frame times (`FrameTiming`, the station accepts a frame only when its exposure began after the
projector's image became visible, so `exposure_start_s` must never be later than the truth):
- `stamp`: the source writes each frame's exposure start, exposure and gain in a strip of cells under
  the picture (drivers/frame_stamp.py); the driver crops it off. The simulated camera's stream does.
- `device`: the backend's buffer timestamp (CAP_PROP_POS_MSEC; V4L2 stamps a buffer on the host's
  monotonic clock when its first data arrives): the exposure began at most one exposure and one frame
  period (the readout) before it.
- `arrival`: the host's clock when read() returned, less the exposure and three frame periods
  (readout, transfer and decoding): a conservative bound for backends without timestamps.
The default is `device` on V4L2 (when its timestamps fall within a second before arrival, else
`arrival` for that frame) and `arrival` elsewhere.

Autofocus is switched off at start (CAP_PROP_AUTOFOCUS 0; settings() records whether the camera took it):
a lens that refocuses changes the intrinsics between captures.

Controls: OpenCV writes CAP_PROP_AUTO_EXPOSURE / EXPOSURE / GAIN / AUTO_WB in each backend's own units
(BACKEND_UNITS). A camera or backend that refuses a write, or reads back another value, ignores manual
exposure: set_manual_exposure raises ExposureUnsupported, and the station's rig check goes on with the
camera's own auto exposure and a warning. `controls` replaces the capture's set/get (the simulated
stream forwards them to its camera through a side channel: a stream has no such properties).
"""

from __future__ import annotations

import contextlib
import enum
import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from calib.models.camera import CameraModel
from drivers._frames import wait_latest
from drivers.base import Frame
from drivers.clock import MONOTONIC, Clock
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout, ExposureUnsupported
from drivers.frame_stamp import split_stamp


class FrameTiming(str, enum.Enum):
    """How a frame's exposure start is known (module doc)."""

    STAMP = "stamp"
    DEVICE = "device"
    ARRIVAL = "arrival"


@dataclass(frozen=True)
class BackendUnits:
    """How a backend counts exposure: device value = exposure_us / us_per_unit, or log2 of seconds;
    the CAP_PROP_AUTO_EXPOSURE values for manual and auto; the limits assumed (OpenCV reports none)."""

    us_per_unit: float | None  # None: log2(seconds)
    manual: float
    auto: float
    exposure_us: tuple[float, float, float]
    gain: tuple[float, float, float]


#: From OpenCV's backend sources (cap_v4l.cpp passes V4L2's exposure_absolute, 100 us units, and the
#: V4L2_EXPOSURE_MANUAL / APERTURE_PRIORITY values; DirectShow and MSMF take log2 seconds). Not
#: verified on hardware; a camera whose controls differ reads back otherwise and counts as ignoring them.
BACKEND_UNITS = {
    "V4L2": BackendUnits(100.0, 1.0, 3.0, (100.0, 1e6, 100.0), (0.0, 255.0, 1.0)),
    "DSHOW": BackendUnits(None, 0.25, 0.75, (122.0, 1e6, 0.0), (0.0, 255.0, 1.0)),
    "MSMF": BackendUnits(None, 0.25, 0.75, (122.0, 1e6, 0.0), (0.0, 255.0, 1.0)),
    #: the simulated stream's side channel (drivers/sim/stream.py): microseconds, V4L2's mode values
    "STREAM": BackendUnits(1.0, 1.0, 3.0, (100.0, 1e6, 1.0), (1.0, 8.0, 0.01)),
}


class CaptureControls(Protocol):
    """Property writes and reads of a capture (cv2.VideoCapture.set / get)."""

    backend: str

    def set(self, prop: int, value: float) -> bool: ...

    def get(self, prop: int) -> float: ...


class _Capture:
    """The capture's own properties."""

    def __init__(self, cap, backend: str):
        self._cap, self.backend = cap, backend

    def set(self, prop: int, value: float) -> bool:
        return bool(self._cap.set(prop, float(value)))

    def get(self, prop: int) -> float:
        return float(self._cap.get(prop))


@dataclass
class _Stats:
    accepted: int = 0
    duplicates: int = 0
    unstamped: int = 0
    read_failures: int = 0


def _cv2():
    import cv2

    return cv2


@contextlib.contextmanager
def quiet_opencv():
    """OpenCV's own warnings off (a camera that is not there prints two WARN lines per open): the driver
    says what happened in its own error."""
    cv2 = _cv2()
    try:
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    except AttributeError:
        level = None
    try:
        yield
    finally:
        if level is not None:
            cv2.utils.logging.setLogLevel(level)


def default_api(source) -> int:
    """The VideoCapture backend for a source: V4L2 for an index on Linux, FFmpeg for a URL or file,
    else OpenCV's choice."""
    cv2 = _cv2()
    if isinstance(source, int):
        return cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY
    return cv2.CAP_FFMPEG


def parse_source(text: str | int):
    """`--camera` as given: an index (digits) or a URL / path / pipeline (anything else)."""
    if isinstance(text, int):
        return text
    t = str(text).strip()
    if not t:
        raise DeviceError("the camera source is empty: give an index (0, 1, ...) or a URL")
    return int(t) if t.isdigit() else t


class OpenCVCamera:
    """drivers.base.CameraDriver and ExposureControl over cv2.VideoCapture (module doc).

    source: an index or a URL / file; width, height, fps: asked of the backend (None: its default);
    timing: a FrameTiming (None: by backend); clock: the clock frame times are on (the host's; the
    simulated stream's camera, the rig's SimClock); controls: CaptureControls replacing the capture's
    properties; intrinsics: a pre-calibrated CameraModel, reported as factory_intrinsics;
    exposure_limits: {"exposure_us": (min, max, step), "gain": (...)} instead of the backend's assumed."""

    def __init__(self, source=0, width: int | None = None, height: int | None = None, fps: float | None = None, *,
                 api: int | None = None, timing: FrameTiming | str | None = None, clock: Clock = MONOTONIC,
                 controls=None, intrinsics: CameraModel | None = None, exposure_limits: dict | None = None,
                 stale_after_s: float | None = None, open_timeout_s: float = 10.0, read_timeout_s: float = 5.0):
        self.source = parse_source(source)
        self._want = (width, height, fps)
        self._api = api
        self.timing = FrameTiming(timing) if timing is not None else None
        self.clock = clock
        self._controls_override = controls
        self._intrinsics = intrinsics
        self._limits = exposure_limits
        self._stale_after_s = stale_after_s
        self._open_timeout_s, self._read_timeout_s = float(open_timeout_s), float(read_timeout_s)
        self._cond = threading.Condition()
        self._cap = None
        self._controls = None
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._running = False
        self._disconnected = False
        self._thread_error: BaseException | None = None
        self._latest: Frame | None = None
        self._latest_wall = 0.0
        self._counter = 0
        self._last_device_number: int | None = None
        self._size: tuple[int, int] | None = None
        self.fps = float(fps) if fps else 30.0
        self.backend = "?"
        self._manual: dict | None = None
        self.autofocus_off: bool | None = None  # whether the camera accepted autofocus off (None: not started)
        self.stats = _Stats()

    # ---- CameraDriver ------------------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        if self._size is None:
            raise DeviceError(f"camera {self.label}: start() it before asking its size")
        return self._size

    @property
    def label(self) -> str:
        return f"{self.source}" if not isinstance(self.source, int) else f"#{self.source}"

    @property
    def running(self) -> bool:
        return self._running

    @property
    def disconnected(self) -> bool:
        return self._disconnected

    def start(self) -> None:
        """Open the capture, read a first frame (its size) and start the capture thread."""
        if self._running:
            return
        cv2 = _cv2()
        api = self._api if self._api is not None else default_api(self.source)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(self._open_timeout_s * 1000),
                  cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self._read_timeout_s * 1000)]
        with quiet_opencv():
            cap = cv2.VideoCapture(self.source, api, params)
        if not cap.isOpened():
            cap.release()
            if isinstance(self.source, int):
                raise DeviceDisconnected(f"no camera at index {self.source} (or it is in use by another program): "
                                         "plug it in; `procam devices` lists the cameras OpenCV can open")
            raise DeviceDisconnected(f"cannot open the camera source {self.source}: check the URL and that the "
                                     "camera or stream is up")
        w, h, fps = self._want
        for prop, v in ((cv2.CAP_PROP_FRAME_WIDTH, w), (cv2.CAP_PROP_FRAME_HEIGHT, h), (cv2.CAP_PROP_FPS, fps)):
            if v:
                cap.set(prop, float(v))
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # a backend that queues frames hands out old ones
        backend = cap.getBackendName()
        got_fps = cap.get(cv2.CAP_PROP_FPS)
        ok, img = cap.read()
        if not ok or img is None:
            cap.release()
            raise DeviceDisconnected(f"camera {self.label} opened but delivers no frame: plug it back in, or "
                                     "close the program that uses it")
        stamped = self.timing == FrameTiming.STAMP
        picture = split_stamp(img)[0] if stamped else img
        size = (int(picture.shape[1]), int(picture.shape[0]))
        if w and h and size != (int(w), int(h)):
            cap.release()
            raise DeviceError(f"camera {self.label} delivers {size[0]}x{size[1]} frames, not the {w}x{h} asked "
                              "for: ask for a size the camera offers (`procam devices`)")
        with self._cond:
            self._cap = cap
            self.backend = backend
            self._controls = self._controls_override or _Capture(cap, backend)
            if not fps and got_fps and 1.0 <= got_fps <= 1000.0 and not stamped:
                self.fps = float(got_fps)
            self._size = size
            self._disconnected = False
            self._thread_error = None
            self._latest = None
            self._last_device_number = None  # a source reopened may count its frames from 0 again
            self._running = True
        # a lens that refocuses moves the focal length mid-session: the intrinsics must hold for every capture
        self.autofocus_off = bool(self._controls.set(cv2.CAP_PROP_AUTOFOCUS, 0.0))
        self._stop_evt = threading.Event()
        self._thread = threading.Thread(target=self._capture_loop, args=(cap, self._stop_evt),
                                        name="opencv-capture", daemon=True)
        self._thread.start()
        if self._manual is not None:  # a reconnect: the exposure as it was
            self.set_manual_exposure(self._manual["exposure_us"], self._manual["gain"])

    def stop(self) -> None:
        """Stop reading and release the capture (safe twice or after a disconnect)."""
        self._stop_evt.set()
        t = self._thread
        if t is not None:
            t.join(timeout=self._read_timeout_s + 1.0)
            self._thread = None
        with self._cond:
            self._running = False
            cap, self._cap = self._cap, None
            self._cond.notify_all()
        if cap is not None and (t is None or not t.is_alive()):
            cap.release()

    close = stop

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def reconnect(self, timeout_s: float = 10.0, poll_s: float = 0.25) -> None:
        """Reopen the same source once it is back; the manual exposure is applied again."""
        self.stop()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.start()
                return
            except DeviceDisconnected:
                if time.monotonic() >= deadline:
                    with self._cond:  # still gone: get_frame keeps saying so, and the station keeps trying
                        self._disconnected = True
                    raise DeviceDisconnected(f"camera {self.label} did not come back within {timeout_s:.1f} s: "
                                             "plug it back in, then reconnect") from None
                time.sleep(poll_s)

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None,
                  not_before_s: float | None = None) -> Frame:
        """The newest frame (drivers.base.CameraDriver); with `newer_than`, the first with a larger number;
        with `not_before_s` (on the camera's clock), only a frame whose exposure began at or after it."""
        deadline = time.monotonic() + timeout_s
        stale_s = self._stale_after_s if self._stale_after_s is not None else max(0.5, 5.0 / self.fps)
        f = wait_latest(self, lambda: f"camera {self.label}", deadline, newer_than, not_before_s,
                        lambda f: time.monotonic() - self._latest_wall <= stale_s)
        if f is not None:
            return f
        what = "no frame" if newer_than is None else f"no frame newer than #{newer_than}"
        raise DeviceTimeout(f"camera {self.label}: {what} within {timeout_s:.2f} s ({self.backend}); check the "
                            "cable and that no other program uses the camera")

    def factory_intrinsics(self) -> CameraModel | None:
        """The pre-calibration given (a UVC camera reports none): else the session calibrates it."""
        return self._intrinsics

    def settings(self) -> dict:
        out: dict[str, Any] = {"driver": "opencv", "source": self.source, "backend": self.backend,
                               "stream": {"width": self._size[0] if self._size else None,
                                          "height": self._size[1] if self._size else None, "fps": self.fps},
                               "frame_timing": self._timing().value, "manual_exposure": self._manual is not None,
                               "autofocus_off": self.autofocus_off,
                               "frames": {"accepted": self.stats.accepted,
                                          "dropped_duplicates": self.stats.duplicates,
                                          "dropped_unstamped": self.stats.unstamped}}
        if self._manual is not None:
            out.update({"auto_exposure": False, **self._manual})
        return out

    # ---- ExposureControl ---------------------------------------------------------------------------
    def _units(self) -> BackendUnits | None:
        ctl = self._controls
        return BACKEND_UNITS.get(getattr(ctl, "backend", self.backend) if ctl is not None else self.backend)

    def exposure_limits(self) -> dict:
        if self._limits is not None:
            return dict(self._limits)
        lim = getattr(self._controls, "limits", None)
        if callable(lim):
            return dict(lim())
        u = self._units()
        if u is None:
            raise ExposureUnsupported(self._unsupported(f"OpenCV's {self.backend} backend has no exposure control"))
        return {"exposure_us": u.exposure_us, "gain": u.gain}

    def set_auto_exposure(self, enabled: bool) -> None:
        cv2 = _cv2()
        u = self._require_units()
        self._controls.set(cv2.CAP_PROP_AUTO_EXPOSURE, u.auto if enabled else u.manual)
        if enabled:
            self._manual = None

    def set_manual_exposure(self, exposure_us: float, gain: float) -> dict:
        """Auto exposure and auto white balance off, then exposure and gain; returns what the camera
        reads back. Raises ExposureUnsupported when it refuses or reads back other values."""
        cv2 = _cv2()
        try:
            exposure_us, gain = float(exposure_us), float(gain)
        except (TypeError, ValueError):
            raise DeviceError(f"exposure and gain must be numbers, got {exposure_us!r} and {gain!r}") from None
        if not (math.isfinite(exposure_us) and math.isfinite(gain)) or exposure_us <= 0:
            raise DeviceError(f"exposure and gain must be finite (exposure > 0), got {exposure_us} us and {gain}")
        u = self._require_units()
        ctl = self._controls
        lim = self.exposure_limits()
        e_lo, e_hi, _ = lim["exposure_us"]
        g_lo, g_hi, _ = lim["gain"]
        exposure_us = float(np.clip(exposure_us, e_lo, e_hi))
        gain = float(np.clip(gain, g_lo, g_hi))
        if not ctl.set(cv2.CAP_PROP_AUTO_EXPOSURE, u.manual):
            raise ExposureUnsupported(self._unsupported("auto exposure cannot be switched off"))
        ctl.set(cv2.CAP_PROP_AUTO_WB, 0.0)  # white balance drifting with the pattern shifts the levels
        value = exposure_us / u.us_per_unit if u.us_per_unit else math.log2(exposure_us * 1e-6)
        if u.us_per_unit:
            value = float(round(value))
        if not ctl.set(cv2.CAP_PROP_EXPOSURE, value):
            raise ExposureUnsupported(self._unsupported(f"the exposure ({exposure_us:g} us) cannot be written"))
        ctl.set(cv2.CAP_PROP_GAIN, gain)
        back = ctl.get(cv2.CAP_PROP_EXPOSURE)
        got_us = back * u.us_per_unit if u.us_per_unit else 2.0 ** back * 1e6
        if not math.isfinite(got_us) or abs(got_us - exposure_us) > max(0.02 * exposure_us, u.us_per_unit or 0.0):
            raise ExposureUnsupported(self._unsupported(f"it reads back {got_us:g} us after {exposure_us:g} us was written"))
        got_gain = ctl.get(cv2.CAP_PROP_GAIN)
        if not math.isfinite(got_gain):
            got_gain = gain
        self._manual = {"exposure_us": float(got_us), "gain": float(got_gain)}
        return dict(self._manual)

    def set_emitter(self, enabled: bool) -> None:
        """No IR emitter on a camera OpenCV opens."""

    def _require_units(self) -> BackendUnits:
        if self._controls is None:
            raise DeviceError(f"camera {self.label}: start() it before setting its exposure")
        u = self._units()
        if u is None:
            raise ExposureUnsupported(self._unsupported(f"OpenCV's {self.backend} backend has no exposure control"))
        return u

    def _unsupported(self, why: str) -> str:
        return (f"camera {self.label} ignores manual exposure ({why}): its own auto exposure stays on, so "
                "brightness may drift with the pattern; a camera with manual exposure gives steadier captures")

    # ---- the capture thread ------------------------------------------------------------------------
    def _timing(self) -> FrameTiming:
        if self.timing is not None:
            return self.timing
        return FrameTiming.DEVICE if self.backend == "V4L2" else FrameTiming.ARRIVAL

    def _disconnect_message(self) -> str:
        return f"camera {self.label} stopped delivering frames (unplugged?): plug it back in, then reconnect"

    def _capture_loop(self, cap, stop_evt: threading.Event) -> None:
        fails = 0
        try:
            while not stop_evt.is_set():
                ok, img = cap.read()
                if stop_evt.is_set():
                    break
                if not ok or img is None:
                    fails += 1
                    self.stats.read_failures += 1
                    if fails >= 3:  # an unplugged camera or a closed stream fails every read at once
                        with self._cond:
                            self._disconnected = True
                            self._cond.notify_all()
                        break
                    continue
                fails = 0
                self._accept(cap, img)
        except Exception as e:  # noqa: BLE001 - reported to the caller of get_frame
            with self._cond:
                self._thread_error = e
                self._cond.notify_all()
        finally:
            if stop_evt.is_set() or self._disconnected:
                cap.release()

    def _accept(self, cap, img: np.ndarray) -> None:
        cv2 = _cv2()
        arrival_s = self.clock.now()
        timing = self._timing()
        period_s = 1.0 / max(self.fps, 1.0)
        meta: dict[str, Any] = {"host_time_s": arrival_s, "timing": timing.value}
        if timing == FrameTiming.STAMP:
            img, stamp = split_stamp(img)
            if stamp is None:
                with self._cond:
                    self.stats.unstamped += 1
                return
            with self._cond:
                if self._last_device_number is not None and stamp.frame_number <= self._last_device_number:
                    self.stats.duplicates += 1
                    return
            start_s = stamp.exposure_start_s
            meta.update({"device_frame_number": stamp.frame_number, "exposure_us": stamp.exposure_us,
                         "gain": stamp.gain})
            timestamp_ms = (start_s + stamp.exposure_us * 1e-6) * 1000.0
            number = stamp.frame_number
        else:
            exposure_s = (self._manual or {}).get("exposure_us", period_s * 1e6) * 1e-6
            start_s, source = arrival_s - exposure_s - 3 * period_s, "arrival"
            timestamp_ms = arrival_s * 1000.0
            if timing == FrameTiming.DEVICE:
                ref_s = cap.get(cv2.CAP_PROP_POS_MSEC) * 1e-3
                if arrival_s - 1.0 <= ref_s <= arrival_s:
                    start_s, source, timestamp_ms = ref_s - exposure_s - period_s, "device", ref_s * 1000.0
            meta["exposure_start_source"] = source
            if self._manual is not None:
                meta["exposure_us"] = self._manual["exposure_us"]
            number = None
        picture = np.ascontiguousarray(img)
        if (picture.shape[1], picture.shape[0]) != self._size:
            with self._cond:
                self.stats.unstamped += 1
            return
        picture.setflags(write=False)
        with self._cond:
            if number is not None:
                self._last_device_number = number
            self._counter += 1
            self.stats.accepted += 1
            self._latest = Frame(picture, self._counter, float(timestamp_ms), meta, float(start_s))
            self._latest_wall = time.monotonic()
            self._cond.notify_all()


def list_opencv_cameras(sources=None, max_index: int = 8) -> list[dict]:
    """Cameras OpenCV opens: every /dev/video* on Linux (indices 0..max_index-1 elsewhere), or the given
    sources; each {"source", "backend", "width", "height", "fps"}. Opening a camera another program
    streams from fails: it is not listed."""
    cv2 = _cv2()
    if sources is None:
        if sys.platform.startswith("linux"):
            import glob
            import re

            sources = sorted(int(m.group(1)) for p in glob.glob("/dev/video*")
                             if (m := re.fullmatch(r"/dev/video(\d+)", p)))
        else:
            sources = list(range(max_index))
    out = []
    with quiet_opencv():
        for s in sources:
            src = parse_source(s)
            cap = cv2.VideoCapture(src, default_api(src), [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, 3000])
            try:
                if not cap.isOpened():
                    continue
                ok, img = cap.read()
                if not ok or img is None:
                    continue  # a metadata node of a UVC camera opens but streams nothing
                out.append({"source": src, "backend": cap.getBackendName(), "width": int(img.shape[1]),
                            "height": int(img.shape[0]), "fps": float(cap.get(cv2.CAP_PROP_FPS) or 0.0)})
            finally:
                cap.release()
    return out
