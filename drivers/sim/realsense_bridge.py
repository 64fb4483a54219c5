"""`--rig sim-realsense`: the simulated world seen through the real RealSense driver.

    rig = open_sim_realsense_rig("nonoverlap-136", seed=0, quality="live")
    rig.camera        # drivers.realsense.RealSenseCamera, streaming from a librealsense software device
    rig.projector, rig.operator, rig.scenario, rig.ground_truth()   # the simulated rig's own

`SimRealSenseDevice` is a librealsense `rs.software_device` that stands in for a D455: a colour sensor
("RGB Camera") with one BGR8 profile carrying the simulated camera's intrinsics (brown_conrady), the
colour controls the D455 reports (enable_auto_exposure, exposure in 100 us units, gain, auto white
balance, white balance) and a stereo module with `emitter_enabled` (on at power-up, as on a D455).
It is the `context` of drivers.realsense.RealSenseCamera, so everything the driver does (opening the
sensor, the frame queue, option ranges and steps, frame metadata, the devices-changed callback and
reconnecting) runs through librealsense.

Frames: a pusher thread takes frames from the simulated camera and hands them to librealsense with
their frame numbers, in the global_time domain (host system clock, ms, at the start of readout) with
`actual_exposure`, `frame_timestamp` and `sensor_timestamp` metadata, so the driver's exposure_start_s
estimate is exercised as on hardware. Under the no-metadata fault a frame carries none of them and is
stamped in the system_time domain at its arrival, as librealsense does without metadata. The simulated
camera renders lazily, so the pusher renders only what the driver will hand out: it pushes while a
caller waits in get_frame for a frame the driver cannot hand out yet (the camera class below tells it
what each caller asks for), one frame at a time (the next only once the driver's capture thread has
taken the last one, accepted or dropped, so how many frames are rendered does not depend on how
fast the machine runs the threads), no faster than the stream's frame rate, and always the newest
frame the simulated camera has delivered (as the driver's capture thread, draining a streaming
camera, always holds the newest).

Options: every option the driver writes is stored by librealsense; before each frame the pusher
forwards changes to the simulated camera when it implements drivers.base.ExposureControl
(auto exposure, manual exposure in us, the emitter, and the gain: the D455's 0..128 taken as
proportional to the amplification, 128 the simulated camera's maximum, see sim_gain); otherwise they only live on the device.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from drivers._frames import wait_latest
from drivers._realsense_lib import COLOUR_EXPOSURE_UNIT_US, _rs
from drivers.base import ExposureControl
from drivers.errors import DeviceError
from drivers.realsense import RealSenseCamera
from drivers.sim._driver_rig import SimDriverRig
from calib.models.vocab import RenderQuality, RigKind

#: D455 colour sensor controls: (min, max, step, default) in the device's own units.
COLOUR_OPTIONS = {
    "enable_auto_exposure": (0, 1, 1, 1),
    "exposure": (1, 10000, 1, 156),  # x 100 us
    "gain": (0, 128, 1, 64),
    "enable_auto_white_balance": (0, 1, 1, 1),
    "white_balance": (2800, 6500, 10, 4600),
    "auto_exposure_priority": (0, 1, 1, 1),
}


def _resettable_device_class(rs, owner):
    """A software device whose hardware_reset() does what a D455's does (SimRealSenseDevice.hardware_reset);
    made on first use, pyrealsense2 being imported lazily."""

    class ResettableSoftwareDevice(rs.software_device):
        def hardware_reset(self):  # as a D455: it goes away and enumerates again, its controls at defaults
            owner.hardware_reset()

    return ResettableSoftwareDevice


#: under the stall fault: frames streamed before the stream stalls (after the rig check, which takes
#: about 150-250, during the captures), and device frame numbers lost just before it (a USB link in trouble drops frames first)
STALL_AFTER_FRAMES = 300
STALL_DROPPED_FRAMES = 3
#: how long a reset D455 takes to enumerate again, in the emulation
RESET_S = 0.5
#: the colour rates the software device lists at the simulated camera's size, on a USB 3 link and under
#: the usb2 fault (a USB 2 link carries fewer and slower modes; the D455's exact USB 2 list is not
#: emulated: its size stays the simulated camera's)
USB3_RATES = (30, 15, 5)
USB2_RATES = (15, 5)


def offered_rates(faults) -> tuple[int, ...]:
    return USB2_RATES if "usb2" in faults else USB3_RATES


class _Removed:
    """What a devices-changed callback receives when the device goes away."""

    def __init__(self, dev):
        self._dev = dev

    def was_removed(self, dev) -> bool:
        return dev is self._dev or dev == self._dev


class SimRealSenseDevice:
    """A software D455 fed by a simulated camera; a librealsense context for RealSenseCamera (see the
    module doc). `unplug()` / `replug()` take it away and bring a fresh one (controls at their defaults)."""

    def __init__(self, sim_camera, fps: int = 30, serial: str = "SIM-D455-0001", faults=()):
        from drivers.clock import clock_of

        if clock_of(sim_camera).simulated:
            raise DeviceError("the RealSense emulation needs a simulated camera on the host's clock (librealsense "
                              "stamps frames on it): open the simulated rig with clock=drivers.clock.MONOTONIC")
        self.rs = _rs()
        self.sim_camera = sim_camera
        self.fps = int(fps)
        self.serial = serial
        self._callbacks: list = []
        self._lock = threading.Lock()
        self._mono0 = time.monotonic()
        self._applied: dict[str, float] = {}
        self._device_gain: dict[float, float] = {}  # simulated gain -> the device gain last set for it
        self.forwarded: list[tuple[str, Any]] = []  # (what, value) handed to the simulated camera
        self.faults = frozenset(faults)  # drivers/sim/faults.py
        self._awb_gains = np.ones(3)  # auto white balance's colour gains (B, G, R) now
        #: device frame numbers: one per frame pushed (the pusher skips the simulated frames nobody waits
        #: for: a streaming D455 numbers every frame it sends), gaps only where a fault drops frames
        self._device_number = 0
        self.sim_numbers: dict[int, int] = {}  # device frame number -> the simulated camera's frame number
        self.streamed = 0  # frames pushed since power-up or the last reset
        self.stalled = False  # the stall fault: the stream has stopped until hardware_reset()
        self.resets = 0
        self.stall_after_frames = STALL_AFTER_FRAMES
        self.stream_fps = self.fps  # the rate the driver streams (its mode)
        self._build()

    # ---- the software device ------------------------------------------------------------------------
    def _build(self) -> None:
        rs = self.rs
        model = self.sim_camera.model
        w, h = model.size
        dev = _resettable_device_class(rs, self)()
        for key, value in (("name", "Intel RealSense D455 (simulated)"), ("serial_number", self.serial),
                           ("firmware_version", "5.16.0.1"),
                           ("usb_type_descriptor", "2.1" if "usb2" in self.faults else "3.2"),
                           ("product_line", "D400")):
            dev.register_info(getattr(rs.camera_info, key), value)
        colour = dev.add_sensor("RGB Camera")
        intr = rs.intrinsics()
        intr.width, intr.height = w, h
        intr.fx, intr.fy, intr.ppx, intr.ppy = model.fx, model.fy, model.cx, model.cy
        d = np.zeros(5)
        dist = np.asarray(model.dist, float).reshape(-1)
        if dist.size > 5 and np.any(dist[5:] != 0):
            raise DeviceError("the simulated camera's distortion has rational terms, which a RealSense "
                              "brown_conrady profile cannot carry")
        d[: min(5, dist.size)] = dist[:5]
        intr.model = rs.distortion.brown_conrady
        intr.coeffs = [float(c) for c in d]
        profiles = {}
        for uid, rate in enumerate(offered_rates(self.faults)):
            vs = rs.video_stream()
            vs.type, vs.index, vs.uid = rs.stream.color, 0, uid
            vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, rate, 3, rs.format.bgr8
            vs.intrinsics = intr
            profiles[rate] = colour.add_video_stream(vs).as_video_stream_profile()
        profile = profiles.get(self.fps, next(iter(profiles.values())))
        for name, (lo, hi, step, default) in COLOUR_OPTIONS.items():
            self._option(colour, getattr(rs.option, name), lo, hi, step, default)
        depth = dev.add_sensor("Stereo Module")
        self._option(depth, rs.option.emitter_enabled, 0, 2, 1, 1)
        with self._lock:
            self.device, self.colour, self.depth, self.profile = dev, colour, depth, profile
            self.profiles = profiles
            self.present = True
            self._applied = {}

    def _option(self, sensor, opt, lo, hi, step, default) -> None:
        r = self.rs.option_range()
        r.min, r.max, r.step, r.default = lo, hi, step, default  # by name: the constructor's order differs
        sensor.add_option(opt, r, True)
        sensor.set_option(opt, default)

    # ---- librealsense context interface (RealSenseCamera's `context`) -----------------------------------
    def query_devices(self):
        return [self.device] if self.present else []

    def set_devices_changed_callback(self, callback) -> None:
        self._callbacks.append(callback)

    def unplug(self) -> None:
        """The camera goes away: the devices-changed callback fires, frames stop."""
        with self._lock:
            self.present = False
            dev = self.device
        for cb in list(self._callbacks):
            cb(_Removed(dev))

    def replug(self) -> None:
        """A camera with the same serial comes back, its controls at their power-up defaults."""
        self._device_number = 0
        self.streamed = 0
        self.stalled = False
        self._build()

    def hardware_reset(self) -> None:
        """The device's hardware_reset(): it drops off the bus (the devices-changed callback fires) and
        enumerates again RESET_S later, streaming again (a stalled stream too)."""
        self.resets += 1
        self.unplug()
        timer = threading.Timer(RESET_S, self.replug)
        timer.daemon = True
        timer.start()

    # ---- options -> the simulated camera ----------------------------------------------------------------
    def options(self) -> dict:
        """The device's controls as the driver left them (exposure in us)."""
        rs = self.rs
        c, d = self.colour, self.depth
        return {"auto_exposure": bool(c.get_option(rs.option.enable_auto_exposure)),
                "exposure_us": float(c.get_option(rs.option.exposure)) * COLOUR_EXPOSURE_UNIT_US,
                "gain": float(c.get_option(rs.option.gain)),
                "emitter_enabled": bool(d.get_option(rs.option.emitter_enabled))}

    def forward_options(self) -> dict:
        """Hand changed controls to the simulated camera (when it implements ExposureControl)."""
        now = self.options()
        cam = self.sim_camera
        if isinstance(cam, ExposureControl):
            last = self._applied
            if now["emitter_enabled"] != last.get("emitter_enabled"):
                cam.set_emitter(now["emitter_enabled"])
                self.forwarded.append(("emitter", now["emitter_enabled"]))
            if now["auto_exposure"]:
                if last.get("auto_exposure") is not True:
                    cam.set_auto_exposure(True)
                    self.forwarded.append(("auto_exposure", True))
            elif (last.get("auto_exposure") is not False or now["exposure_us"] != last.get("exposure_us")
                  or now["gain"] != last.get("gain")):
                gain = self.sim_gain(now["gain"])
                got = cam.set_manual_exposure(now["exposure_us"], gain)
                self._device_gain[round(float(got["gain"]), 6)] = float(now["gain"])
                self.forwarded.append(("manual", (now["exposure_us"], gain)))
            self._applied = now
        return now

    def sim_gain(self, device_gain: float) -> float:
        """The D455's gain control (0..128, no physical unit) taken as proportional to the amplification:
        the device's maximum is the simulated camera's maximum gain (its exposure_limits), values below
        the simulation's minimum give that minimum (on the 1..8 simulated camera: 0..16 -> 1x, 128 -> 8x)."""
        hi = COLOUR_OPTIONS["gain"][1]
        try:
            glo, ghi = (float(v) for v in self.sim_camera.exposure_limits()["gain"][:2])
        except (AttributeError, KeyError, TypeError, ValueError):
            return float(device_gain)
        return float(np.clip(float(device_gain) / hi * ghi, glo, ghi))

    # ---- frames ----------------------------------------------------------------------------------------
    def white_balance(self, img: np.ndarray) -> np.ndarray:
        """Under the auto-white-balance fault, while the device's auto white balance is on: the colour
        gains it applies, moving each frame halfway to the gains the frame before asks for (grey-world,
        and a colour temperature guessed from the brightness: warmer when dark), so they drift with
        what the projector shows. Off (or without the fault): the fixed white balance, the simulated
        camera's own colours."""
        rs = self.rs
        if "auto-white-balance" not in self.faults or not self.colour.get_option(rs.option.enable_auto_white_balance):
            self._awb_gains = np.ones(3)
            return img
        out = np.clip(img * self._awb_gains, 0, 255).astype(np.uint8)
        means = img.reshape(-1, 3).mean(axis=0) + 1.0
        tint = 0.3 * (means.mean() / 255.0 - 0.5)
        want = means.mean() / means * np.array([1.0 + tint, 1.0, 1.0 - tint])
        self._awb_gains = 0.5 * self._awb_gains + 0.5 * np.clip(want, 0.6, 1.6)
        return out

    def push(self, frame, exposure_us: float, exposure_start_s: float) -> bool:
        """Deliver a simulated frame through librealsense: global-time stamp at the start of readout,
        metadata placing the exposure so that the driver's estimate comes out at `exposure_start_s`
        (never later). False (nothing delivered) while the stream is stalled (the stall fault: after
        `stall_after_frames` frames, the first time only, until hardware_reset())."""
        rs = self.rs
        if "stall" in self.faults and self.resets == 0 and self.streamed >= self.stall_after_frames:
            self.stalled = True
        if self.stalled:
            return False
        units = max(1, int(round(exposure_us / COLOUR_EXPOSURE_UNIT_US)))
        exp_dev_s = units * COLOUR_EXPOSURE_UNIT_US * 1e-6
        readout_s = exposure_start_s + exposure_us * 1e-6
        frame_ts_us = int(round((readout_s - self._mono0) * 1e6))
        # the driver places the start at readout - (frame_ts - sensor_ts) - exposure / 2: round that
        # distance up so the estimate is never after the true start
        sensor_ts_us = frame_ts_us - int(math.ceil((exposure_us * 1e-6 - exp_dev_s / 2) * 1e6))
        wall_minus_mono = time.time() - time.monotonic()
        sensor = self.colour
        if "no-metadata" not in self.faults:
            md = rs.frame_metadata_value
            sensor.set_metadata(md.actual_exposure, units)
            gain = frame.meta.get("gain") if isinstance(frame.meta, dict) else None
            if gain is not None:  # the gain the frame was taken with, in the device's units (as the option)
                device_gain = self._device_gain.get(round(float(gain), 6))
                if device_gain is None:  # not set through the device (the camera's power-on gain)
                    device_gain = float(gain) / self.sim_gain(COLOUR_OPTIONS["gain"][1]) * COLOUR_OPTIONS["gain"][1]
                sensor.set_metadata(md.gain_level, int(round(device_gain)))
            sensor.set_metadata(md.frame_timestamp, frame_ts_us)
            sensor.set_metadata(md.sensor_timestamp, sensor_ts_us)
        img = self.white_balance(np.ascontiguousarray(frame.image, dtype=np.uint8))
        f = rs.software_video_frame()
        f.pixels = img
        f.bpp = 3
        f.stride = img.shape[1] * 3
        if "no-metadata" in self.faults:
            # without metadata librealsense has no hardware timestamp: it stamps the frame with the host's
            # system clock on arrival (librealsense #13241), here when a streaming D455's frame would
            # arrive: a frame interval after its exposure began (the simulated camera delivers it then)
            f.timestamp = (exposure_start_s + 1.0 / self.fps + wall_minus_mono) * 1000.0
            f.domain = rs.timestamp_domain.system_time
        else:
            f.timestamp = (readout_s + wall_minus_mono) * 1000.0
            f.domain = rs.timestamp_domain.global_time
        if "stall" in self.faults and self.resets == 0 and self.streamed == self.stall_after_frames - 1:
            self._device_number += STALL_DROPPED_FRAMES  # dropped on the link, then the stream stops
        self._device_number += 1
        self.streamed += 1
        self.sim_numbers[self._device_number] = int(frame.frame_number)
        f.frame_number = self._device_number
        f.profile = self.profiles.get(self.stream_fps, self.profile)  # the mode the driver opened
        sensor.on_video_frame(f)
        return True


class SimRealSenseCamera(RealSenseCamera):
    """The real driver, unchanged, plus what the emulation needs: the pusher is told what the callers
    waiting in get_frame ask for (the simulated camera renders only on demand), and when the driver's
    capture thread has taken a frame."""

    def __init__(self, device: SimRealSenseDevice, fps: int | None = None, **kw):
        w, h = device.sim_camera.size
        super().__init__(device.serial, w, h, device.fps if fps is None else fps, context=device, **kw)
        self.sim_device = device
        self._requests: list[tuple[int | None, float | None]] = []  # (newer_than, not_before_s) of each waiting caller
        self._taken = 0  # frames the capture thread has dealt with (accepted, held or dropped)
        self._want = threading.Condition()
        self._pusher_stop = threading.Event()
        self._pusher: threading.Thread | None = None
        self.pushed = 0
        #: driver frame number -> the simulated camera's frame number, for every frame handed out (so a
        #: test can look up what the simulator showed during that frame's exposure)
        self.device_numbers: dict[int, int] = {}

    def start(self) -> None:
        super().start()
        self.sim_device.stream_fps = self.fps
        if self._pusher is None or not self._pusher.is_alive():
            self._pusher_stop = threading.Event()
            self._pusher = threading.Thread(target=self._push_loop, args=(self._pusher_stop,),
                                            name="sim-realsense-pusher", daemon=True)
            self._pusher.start()

    def stop(self) -> None:
        self._pusher_stop.set()
        with self._want:
            self._want.notify_all()
        if self._pusher is not None:
            self._pusher.join(5.0)
            self._pusher = None
        super().stop()

    close = stop

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None,
                  not_before_s: float | None = None):
        request = (newer_than, not_before_s)
        with self._want:
            self._requests.append(request)
            self._want.notify_all()
        try:
            f = super().get_frame(timeout_s, newer_than=newer_than, not_before_s=not_before_s)
            self.device_numbers[f.frame_number] = self.sim_device.sim_numbers[int(f.meta["device_frame_number"])]
            return f
        finally:
            with self._want:
                self._requests.remove(request)

    def _accept(self, f) -> None:
        try:
            super()._accept(f)
        finally:
            with self._want:
                self._taken += 1
                self._want.notify_all()

    def _wanted(self) -> bool:
        """Whether a caller waits in get_frame for a frame the driver does not have yet (asked with a
        deadline already passed, the driver's own wait says whether it could hand one out now)."""
        with self._want:
            requests = list(self._requests)
        for newer_than, not_before_s in requests:
            try:
                if wait_latest(self, self._who, time.monotonic(), newer_than, not_before_s, self._fresh) is None:
                    return True
            except DeviceError:
                continue  # that caller's wait ends with this error: no frame reaches it
        return False

    def _taken_or_lost(self, taken: int, stop: threading.Event) -> bool:
        """The frame pushed after `taken` frames has been dealt with by the capture thread, or never
        will be: the stream stopped, the device went away or the capture failed."""
        return (self._taken > taken or stop.is_set() or not self.running or not self.sim_device.present
                or self._disconnected or self._thread_error is not None)

    def _push_loop(self, stop: threading.Event) -> None:
        dev = self.sim_device
        sim = dev.sim_camera
        period = 1.0 / max(1, self.fps)
        last_number: int | None = None
        next_at = 0.0
        while not stop.is_set():
            with self._want:
                if not self._wanted():
                    # woken by a new caller or a frame taken; checked again now and then for a frame going stale
                    self._want.wait(0.1)
                    continue
            if not dev.present or not self.running:
                stop.wait(0.02)
                continue
            delay = next_at - time.monotonic()
            if delay > 0:  # no faster than the stream's rate; meanwhile the caller may have what it needs
                stop.wait(delay)
                continue
            try:
                settings = dev.forward_options()
                started = getattr(sim, "running", True)
                if not started:
                    sim.start()
                t_request = time.monotonic()
                # a streaming D455 is drained continuously by the driver, which keeps the newest frame:
                # take the newest frame the simulated camera has delivered, or wait for the next one
                f = sim.get_frame(2.0)
                if last_number is not None and f.frame_number <= last_number:
                    f = sim.get_frame(2.0, newer_than=last_number)
                exposure_us = float(f.meta.get("exposure_us") or settings["exposure_us"])
                start_s = f.exposure_start_s if f.exposure_start_s is not None else t_request
                with self._want:
                    taken = self._taken
                if not dev.push(f, exposure_us, start_s):  # stalled: nothing reaches the driver
                    last_number = f.frame_number
                    stop.wait(period)
                    continue
            except Exception as e:  # noqa: BLE001 - the driver reports a stalled stream as a timeout
                self.push_error = e
                stop.wait(0.05)
                continue
            last_number = f.frame_number
            self.pushed += 1
            next_at = max(next_at + period, time.monotonic())
            # what is wanted next depends on what the driver made of this frame: wait until its capture
            # thread has taken it (accepted, held after a reset, or dropped as late), however long that
            # takes; a frame pushed as the stream goes is never taken, and the wait ends with the stream
            with self._want:
                while not self._taken_or_lost(taken, stop):
                    self._want.wait(0.05)


class SimRealSenseRig(SimDriverRig):
    """A simulated rig whose camera is the RealSense driver on a software device (module doc)."""

    kind = RigKind.SIM_REALSENSE

    def __init__(self, sim_rig, fps: int = 30, faults=(), camera_mode=None):
        self.sim = sim_rig
        self.device = SimRealSenseDevice(sim_rig.camera, fps, faults=faults)
        # the driver asks for a mode by name (--camera-mode, refused unless listed) or for 30 fps (falling
        # back to the fastest listed, as on a real USB 2 link)
        self.camera = SimRealSenseCamera(self.device, 30 if camera_mode is None else int(camera_mode[2]),
                                         exact_mode=camera_mode is not None)


def open_sim_realsense_rig(scenario: str | None = None, seed: int = 0, quality: str = RenderQuality.LIVE, fps: int | None = None,
                           faults=(), camera_mode=None, **settings) -> SimRealSenseRig:
    """The simulated rig of `scenario` (drivers.sim.rig.open_sim_rig options) with its camera delivered
    through librealsense and drivers/realsense.py; `faults` (drivers.sim.faults) apply to both.
    camera_mode: (width, height, fps) the driver asks for (the simulated camera's size at a listed rate);
    the simulated camera then runs at that rate (default: 30 fps, or the fastest rate listed)."""
    from drivers.sim.rig import open_sim_rig
    from drivers.sim.scenarios import DEFAULT_SCENARIO, get_scenario

    args = () if scenario is None else (scenario,)
    from drivers.clock import MONOTONIC

    # librealsense stamps frames on the host's clock: the simulated hardware behind it must keep the same
    settings.setdefault("clock", MONOTONIC)
    rates = offered_rates(faults)
    if camera_mode is not None:
        w, h = get_scenario(scenario or DEFAULT_SCENARIO, seed).rig.camera.size
        modes = ", ".join(f"{w}x{h}@{r}" for r in rates)
        if tuple(camera_mode[:2]) != (w, h) or int(camera_mode[2]) not in rates:
            raise DeviceError(f"RealSense colour stream {camera_mode[0]}x{camera_mode[1]}@{camera_mode[2]} (BGR8) is not "
                              f"offered by this device; available: {modes}; choose one with --camera-mode")
        fps = int(camera_mode[2])
    elif fps is None:
        fps = 30 if 30 in rates else max(rates)
    sim = open_sim_rig(*args, seed=seed, quality=quality, faults=faults, fps=fps, **settings)
    sim.camera.start()
    return SimRealSenseRig(sim, fps, faults, camera_mode)
