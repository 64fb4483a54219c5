"""Intel RealSense colour camera (D455 and other D400 devices) behind drivers.base.CameraDriver.

pyrealsense2 is imported lazily, so the rest of procam works on machines without it (or without
Debian's libusb-1.0-0, which the wheel needs).

Frame path: the colour sensor of the chosen device streams one video profile (BGR8, e.g. 1280x800 at
30 fps) into an `rs.frame_queue`; a capture thread drains the queue, copies each frame into a numpy
array and keeps the newest one. A test feeds the same path from `rs.software_device` (see
tests/_drivers_helpers.py) by passing it through the `context` argument: any object with
`query_devices()` works, `rs.context()` is the default.

The driver's jobs live in private modules behind this one (their names are re-exported here):
drivers/_realsense_lib.py (the lazy import of pyrealsense2, the devices it lists),
drivers/_realsense_intrinsics.py (factory intrinsics as a CameraModel), drivers/_realsense_frames.py
(the capture thread: frame numbers and frame times, `Frame.exposure_start_s`) and
drivers/_realsense_exposure.py (manual exposure, gain, the IR emitter, image processing off).

`get_frame(newer_than=N, not_before_s=T)` waits for a frame that is newer than N and whose exposure
started at or after T, so a frame exposed before the projector's image became visible is never handed out.

Disconnects: when librealsense reports the device removed (devices-changed callback) or when no frame
arrives in time and the device is no longer listed, get_frame raises DeviceDisconnected; a timeout
with the device still present raises DeviceTimeout. `reconnect(timeout_s)` (or `stop(); start()`)
reopens the device when it is back and re-applies the manual exposure / gain and the emitter setting.

Factory intrinsics: see `convert_intrinsics` and docs/DRIVERS.md for how each librealsense
distortion model becomes an OpenCV-style calib.models.camera.CameraModel.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from calib.models.camera import CameraModel
from drivers._frames import wait_latest
from drivers._realsense_exposure import RealSenseExposure
from drivers._realsense_frames import RealSenseFrames, _Stats
from drivers._realsense_intrinsics import (
    IntrinsicsConversion,
    IntrinsicsConversionError,
    camera_model_from_rs_intrinsics,
    convert_intrinsics,
    distortion_model_name,
    rs_distort_normalized,
)
from drivers._realsense_lib import (
    COLOUR_EXPOSURE_UNIT_US,
    _colour_profiles,
    _colour_sensor,
    _depth_sensor,
    _info,
    _rs,
    device_info,
    list_realsense_devices,
    realsense_available,
    realsense_import_error,
)
from drivers.base import Frame
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout, StreamReset

__all__ = ["COLOUR_EXPOSURE_UNIT_US", "IntrinsicsConversion", "IntrinsicsConversionError", "RealSenseCamera",
           "camera_model_from_rs_intrinsics", "convert_intrinsics", "device_info", "distortion_model_name",
           "list_realsense_devices", "realsense_available", "realsense_import_error", "rs_distort_normalized"]


class RealSenseCamera(RealSenseFrames, RealSenseExposure):
    """A RealSense colour stream as a drivers.base.CameraDriver.

    serial: the device to open (None: the first device with a colour sensor). width, height, fps: the
    colour profile (BGR8; the D455 offers 1280x800, 1280x720, 848x480, 640x480... at 5-30 fps).
    context: where devices are found (rs.context() by default; tests pass a software device).
    stale_after_s: get_frame() without `newer_than` returns the newest frame only when it arrived at
    most this long ago, else waits for a new one (default: 5 frame intervals, at least 0.5 s).
    emitter_enabled: the depth sensor's IR emitter state applied at start (default off, see
    drivers/_realsense_exposure.py).
    """

    def __init__(self, serial: str | None = None, width: int = 1280, height: int = 800, fps: int = 30, *,
                 context=None, queue_capacity: int = 2, stale_after_s: float | None = None,
                 intrinsics_tolerance_px: float = 0.05, emitter_enabled: bool = False,
                 stall_reset_s: float | None = 2.0, exact_mode: bool = False):
        self._rs = _rs()
        self.serial = serial
        self.width, self.height, self.fps = int(width), int(height), int(fps)
        self._ctx = context if context is not None else self._rs.context()
        self._queue_capacity = int(queue_capacity)
        self._stale_after_s = float(stale_after_s) if stale_after_s is not None else max(0.5, 5.0 / self.fps)
        self._tolerance_px = intrinsics_tolerance_px
        self._cond = threading.Condition()
        self._device = None
        self._sensor = None
        self._profile = None
        self._queue = None
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._running = False
        self._disconnected = False
        self._thread_error: BaseException | None = None
        self._latest: Frame | None = None
        self._counter = 0
        self._last_key: tuple[int, float] | None = None
        self.stats = _Stats()
        self._manual: dict | None = None  # {"exposure_us", "gain"} as applied; re-applied after a reconnect
        self._emitter_wanted = bool(emitter_enabled)
        self._depth_sensor = None
        self._offsets: list[float] = []  # recent (arrival - device time), hardware clock domain
        self._info: dict = {}
        self._callback_registered = False
        self.exact_mode = bool(exact_mode)  # a mode asked for by name: never another one
        self.requested_mode = (self.width, self.height, self.fps)
        self.mode_note: str | None = None  # why the stream runs another mode than the one asked for
        self.stall_reset_s = stall_reset_s  # no frame for this long, the device present: reset it (None: never)
        self._last_arrival_s = time.monotonic()
        self._waiting_since: float | None = None  # when callers began waiting without getting a frame
        self._reset_failed_at: float | None = None  # the last arrival before a reset that failed
        self._hold_until_s = -1e18  # frames exposed before this were taken before a re-applied exposure showed

    # ---- CameraDriver ------------------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    def start(self) -> None:
        """Open the device and start streaming (no-op when already streaming)."""
        if self._running:
            return
        dev, sensor = self._find_device()
        profile = self._select_profile(sensor, dev)
        queue = self._rs.frame_queue(self._queue_capacity, keep_frames=True)
        try:
            sensor.open(profile)
            sensor.start(queue)
        except RuntimeError as e:
            try:
                sensor.close()
            except RuntimeError:
                pass
            raise DeviceError(f"RealSense {self._label(dev)}: cannot start the colour stream "
                              f"{self.width}x{self.height}@{self.fps}: {e}") from None
        with self._cond:
            self._device, self._sensor, self._profile, self._queue = dev, sensor, profile, queue
            self._info = device_info(dev)
            if self.serial is None:
                self.serial = self._info.get("serial")
            self._disconnected = False
            self._thread_error = None
            self._last_key = None
            self._latest = None
            self._offsets = []
            self._running = True
        self._register_callback()
        self._stop_evt = threading.Event()
        self._thread = threading.Thread(target=self._capture_loop, args=(queue, self._stop_evt),
                                        name="realsense-capture", daemon=True)
        self._thread.start()
        self._depth_sensor = _depth_sensor(dev, sensor)
        self.set_emitter(self._emitter_wanted)
        self._fix_image_processing()
        self._last_arrival_s = time.monotonic()
        if self._manual is not None:
            self.set_manual_exposure(self._manual["exposure_us"], self._manual["gain"])

    @property
    def running(self) -> bool:
        return self._running

    def stop(self) -> None:
        """Stop streaming and release the device (safe to call twice or after a disconnect)."""
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        sensor = self._sensor
        with self._cond:
            self._running = False
            self._cond.notify_all()
        if sensor is not None:
            for call in (sensor.stop, sensor.close):
                try:
                    call()
                except RuntimeError:
                    pass  # already stopped, or the device is gone
        self._sensor = None
        self._depth_sensor = None
        self._queue = None

    close = stop

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None,
                  not_before_s: float | None = None) -> Frame:
        """The newest frame (see drivers.base.CameraDriver); with `newer_than`, the first frame with a
        larger number; with `not_before_s` (host time.monotonic() seconds), only a frame whose exposure
        started at or after it: an older frame is never handed out, the call waits for a later one."""
        deadline = time.monotonic() + timeout_s
        if self._waiting_since is None:
            self._waiting_since = time.monotonic()
        f = wait_latest(self, self._who, deadline, newer_than, not_before_s, self._fresh)
        if f is not None:
            self._waiting_since = None
            return f
        if not self._device_present():
            with self._cond:
                self._disconnected = True
            raise DeviceDisconnected(self._disconnect_message())
        # no frame for that long while somebody waited (an idle driver of a lazy emulation is no stall)
        stalled_s = time.monotonic() - max(self._last_arrival_s, self._waiting_since or 0.0)
        if self.stall_reset_s is not None and self._running and stalled_s >= self.stall_reset_s:
            self._reset_stalled(stalled_s)
        what = "no frame" if newer_than is None else f"no frame newer than #{newer_than}"
        if not_before_s is not None:
            what += f" exposed after t={not_before_s:.3f} s"
        raise DeviceTimeout(f"RealSense {self._label()}: {what} within {timeout_s:.2f} s "
                            f"(streaming {self.width}x{self.height}@{self.fps}); check the USB cable "
                            "and that no other program uses the camera")

    def factory_intrinsics(self) -> CameraModel:
        """The colour stream's factory calibration as a CameraModel (see convert_intrinsics)."""
        return self.intrinsics_conversion().model

    def intrinsics_conversion(self) -> IntrinsicsConversion:
        return convert_intrinsics(self._current_profile().get_intrinsics(), self._tolerance_px)

    def settings(self) -> dict:
        """Device, stream, exposure / gain / white balance as used now (for the session manifest)."""
        out: dict[str, Any] = {
            "driver": "realsense",
            "device": dict(self._info) if self._info else {"serial": self.serial},
            "stream": {"width": self.width, "height": self.height, "fps": self.fps, "format": "bgr8"},
            "manual_exposure": self._manual is not None,
        }
        out.update(self._read_controls())
        f = self._latest
        if f is not None and "actual_exposure_us" in f.meta:
            out["exposure_us_actual"] = f.meta["actual_exposure_us"]
        out["emitter_enabled"] = self.emitter_enabled()
        out["frames"] = {"accepted": self.stats.accepted, "dropped_duplicates": self.stats.duplicates,
                         "dropped_late": self.stats.late, "gaps": self.stats.gaps, "missing": self.stats.missing,
                         "resets": self.stats.resets, "held_after_start": self.stats.held}
        return out

    # ---- reconnecting --------------------------------------------------------------------------------
    def reconnect(self, timeout_s: float = 10.0, poll_s: float = 0.25) -> None:
        """Release the stream and reopen the same device (by serial) once it is listed again;
        raises DeviceDisconnected when it does not come back within `timeout_s`."""
        self.stop()
        deadline = time.monotonic() + timeout_s
        last: Exception | None = None
        while True:
            try:
                self.start()
                return
            except DeviceError as e:
                last = e
            if time.monotonic() >= deadline:
                break
            time.sleep(poll_s)
        raise DeviceDisconnected(f"RealSense {self._label()} did not come back within {timeout_s:.1f} s "
                                 f"({last}); reconnect its USB cable and try again")

    def _reset_stalled(self, stalled_s: float, timeout_s: float = 10.0) -> None:
        """The stream stopped with the device still there (a USB or firmware hang: librealsense #7252,
        #2412): reset the device (hardware_reset; it drops off the bus and enumerates again), reopen it
        with its settings re-applied, and raise StreamReset so the caller asks again. DeviceTimeout when
        the device refuses the reset (tried once per stall), DeviceDisconnected when it does not come back."""
        dev = self._device
        if self._reset_failed_at == self._last_arrival_s:  # tried for this stall already
            return
        try:
            dev.hardware_reset()
        except (RuntimeError, AttributeError) as e:
            self._reset_failed_at = self._last_arrival_s
            raise DeviceTimeout(f"RealSense {self._label()}: no frame for {stalled_s:.1f} s with the camera connected, "
                                f"and resetting it failed ({e}): unplug the camera and plug it in again") from None
        self.stats.resets += 1
        deadline = time.monotonic() + 3.0  # until it has gone (or the callback said so)
        while time.monotonic() < deadline and not self._disconnected and self._device_present():
            time.sleep(0.05)
        self.reconnect(timeout_s)
        # the reopened device applies the exposure some frames late, and may report no metadata to tell
        # which: the frames exposed within the longest lag allowed are not handed out
        from drivers.exposure import SKIP_LIMIT

        self._hold_until_s = time.monotonic() + SKIP_LIMIT / max(1, self.fps)
        self._waiting_since = None
        raise StreamReset(f"RealSense {self._label()}: no frame for {stalled_s:.1f} s with the camera connected: "
                          f"it was reset (hardware_reset, {self.stats.resets} so far) and streams again")

    @property
    def disconnected(self) -> bool:
        return self._disconnected

    # ---- internals --------------------------------------------------------------------------------------
    def _fresh(self, f: Frame) -> bool:
        """Whether the newest frame may answer a get_frame() without `newer_than`: it arrived at most
        stale_after_s ago."""
        return time.monotonic() - f.meta["host_time_s"] <= self._stale_after_s

    def _who(self) -> str:
        return f"RealSense {self._label()}"

    def _label(self, dev=None) -> str:
        if dev is not None:
            s = _info(dev, "serial_number")
            n = _info(dev, "name")
        else:
            s, n = self.serial, self._info.get("name")
        return f"{n or 'camera'} ({s})" if s else (n or "camera")

    def _disconnect_message(self) -> str:
        return (f"RealSense {self._label()} was disconnected; plug it back in, then reconnect "
                "(the session can continue where it stopped)")

    def _find_device(self):
        try:
            devices = list(self._ctx.query_devices())
        except RuntimeError as e:
            raise DeviceError(f"cannot list RealSense devices: {e}") from None
        seen = []
        for dev in devices:
            serial = _info(dev, "serial_number")
            seen.append(serial or "?")
            if self.serial is not None and serial != self.serial:
                continue
            sensor = _colour_sensor(dev)
            if sensor is not None:
                return dev, sensor
        if self.serial is not None:
            raise DeviceDisconnected(
                f"RealSense with serial {self.serial} is not connected (connected: {', '.join(seen) or 'none'}); "
                "plug it in or choose another serial (procam devices lists them)")
        if seen:
            raise DeviceError(f"no connected RealSense device has a colour sensor (connected: {', '.join(seen)})")
        raise DeviceDisconnected("no RealSense device is connected; plug in the camera (procam devices lists "
                                 "what is found) or use the simulated rig (--rig sim)")

    def link_note(self) -> str | None:
        """The USB link when it is not USB 3 (fewer and slower modes), and the mode the stream fell back
        to; None on a USB 3 link with the mode asked for."""
        usb = str(self._info.get("usb_type") or "")
        parts = []
        if usb.startswith("2"):
            parts.append(f"the camera is on a USB {usb} link (fewer, slower colour modes): a USB 3 port and "
                         "cable give the full rate")
        if self.mode_note:
            parts.append(self.mode_note)
        return "; ".join(parts) or None

    def _select_profile(self, sensor, dev=None):
        rs = self._rs
        profiles = [p for p in _colour_profiles(sensor) if p.format() in (rs.format.bgr8, rs.format.rgb8)]
        profiles.sort(key=lambda p: p.format() != rs.format.bgr8)
        for p in profiles:
            if p.width() == self.width and p.height() == self.height and p.fps() == self.fps:
                return p
        modes = sorted({(p.width(), p.height(), p.fps()) for p in profiles}, reverse=True)
        listed = ", ".join(f"{w}x{h}@{f}" for w, h, f in modes) or "none"
        usb = str(_info(dev, "usb_type_descriptor") or "") if dev is not None else ""
        same = [p for p in profiles if p.width() == self.width and p.height() == self.height]
        if same and not self.exact_mode:  # the default mode on a slower link: the fastest of its size
            p = max(same, key=lambda q: q.fps())
            self.mode_note = (f"{self.width}x{self.height}@{self.fps} is not offered: streaming "
                              f"{self.width}x{self.height}@{p.fps()} (--camera-mode chooses; offered: {listed})")
            self.fps = int(p.fps())
            return p
        raise DeviceError(f"RealSense colour stream {self.width}x{self.height}@{self.fps} (BGR8) is not "
                          f"offered by this device; available: {listed}; choose one with --camera-mode"
                          + (f" (the camera is on a USB {usb} link: a USB 3 port offers more)" if usb.startswith("2")
                             else ""))

    def _current_profile(self):
        if self._profile is None:
            dev, sensor = self._find_device()
            self._profile = self._select_profile(sensor, dev)
        return self._profile

    def _device_present(self) -> bool:
        dev = self._device
        try:
            if dev is not None and hasattr(dev, "is_connected") and not dev.is_connected():
                return False
        except RuntimeError:
            return False
        try:
            devices = list(self._ctx.query_devices())
        except RuntimeError:
            return False
        if self.serial is None:
            return any(d is dev for d in devices) or bool(devices)
        return any(_info(d, "serial_number") == self.serial for d in devices)

    def _register_callback(self) -> None:
        if self._callback_registered or not hasattr(self._ctx, "set_devices_changed_callback"):
            return

        def changed(info):
            dev = self._device
            try:
                removed = dev is not None and info.was_removed(dev)
            except RuntimeError:
                removed = False
            if removed:
                with self._cond:
                    self._disconnected = True
                    self._cond.notify_all()

        try:
            self._ctx.set_devices_changed_callback(changed)
            self._callback_registered = True
        except RuntimeError:
            pass
