"""Test helpers for the device drivers: a librealsense software device that stands in for a D455,
an Xvfb X server per test, screenshots with xwd, and a camera that films the X screen."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from drivers.base import Frame
from drivers.errors import DeviceTimeout

REPO = Path(__file__).resolve().parents[1]


# ---- a RealSense without hardware ----------------------------------------------------------------

class SoftwareRealSense:
    """A librealsense software device with one colour sensor ("RGB Camera"), its stream profile
    (BGR8, with intrinsics) and the D455 colour sensor's controls. Use it as the `context` of
    RealSenseCamera: `query_devices()` lists the device while `present` is True (set it False to
    "unplug" it: the devices-changed callback fires like librealsense's would)."""

    def __init__(self, width=64, height=48, fps=30, serial="SW-D455-0001", intrinsics=None, fmt="bgr8",
                 extra_modes=((640, 480, 30),), with_emitter=True):
        import pyrealsense2 as rs

        self.rs = rs
        self.width, self.height, self.fps, self.serial = width, height, fps, serial
        self._fmt, self._extra_modes = fmt, tuple(extra_modes)
        self._with_emitter = bool(with_emitter)
        if intrinsics is None:
            intrinsics = rs.intrinsics()
            intrinsics.width, intrinsics.height = width, height
            intrinsics.fx, intrinsics.fy = 0.9 * width, 0.9 * width
            intrinsics.ppx, intrinsics.ppy = (width - 1) / 2, (height - 1) / 2
            intrinsics.model = rs.distortion.inverse_brown_conrady
            intrinsics.coeffs = [-0.0565, 0.0682, 0.00037, 0.00069, -0.0218]
        self.intrinsics = intrinsics
        self._callbacks = []
        self._build()

    def _build(self):
        """A fresh device (controls at their defaults), as after plugging the camera in."""
        rs = self.rs
        self.device = rs.software_device()
        for key, value in (("name", "Intel RealSense D455 (software)"), ("serial_number", self.serial),
                           ("firmware_version", "5.16.0.1"), ("usb_type_descriptor", "3.2"),
                           ("product_line", "D400")):
            self.device.register_info(getattr(rs.camera_info, key), value)
        self.sensor = self.device.add_sensor("RGB Camera")
        self.profile = self._add_stream(self.width, self.height, self.fps, getattr(rs.format, self._fmt),
                                        self.intrinsics, uid=0)
        for i, (w, h, f) in enumerate(self._extra_modes):
            ii = rs.intrinsics()
            ii.width, ii.height, ii.fx, ii.fy, ii.ppx, ii.ppy = w, h, 0.9 * w, 0.9 * w, w / 2, h / 2
            self._add_stream(w, h, f, rs.format.bgr8, ii, uid=i + 1)
        # the D455 colour sensor's controls (ranges as the device reports them)
        self._option(rs.option.enable_auto_exposure, 0, 1, 1, 1)
        self._option(rs.option.exposure, 1, 10000, 1, 156)
        self._option(rs.option.gain, 0, 128, 1, 64)
        self._option(rs.option.enable_auto_white_balance, 0, 1, 1, 1)
        self._option(rs.option.white_balance, 2800, 6500, 10, 4600)
        self.depth = None
        if self._with_emitter:  # the stereo module's IR dot projector, on by default as on a D455
            self.depth = self.device.add_sensor("Stereo Module")
            self._option(rs.option.emitter_enabled, 0, 2, 1, 1, sensor=self.depth)
        self.present = True

    def _add_stream(self, w, h, fps, fmt, intr, uid):
        rs = self.rs
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = rs.stream.color, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, fps, 3, fmt
        vs.intrinsics = intr
        return self.sensor.add_video_stream(vs).as_video_stream_profile()

    def _option(self, opt, lo, hi, step, default, sensor=None):
        sensor = self.sensor if sensor is None else sensor
        r = self.rs.option_range()
        # set fields by name: the positional constructor of this pyrealsense2 swaps step and default
        r.min, r.max, r.step, r.default = lo, hi, step, default
        sensor.add_option(opt, r, True)
        sensor.set_option(opt, default)

    # context interface used by RealSenseCamera
    def query_devices(self):
        return [self.device] if self.present else []

    def set_devices_changed_callback(self, cb):
        self._callbacks.append(cb)

    def unplug(self, notify=True):
        """The device disappears; librealsense's devices-changed callback fires unless notify=False."""
        self.present = False
        if notify:
            for cb in self._callbacks:
                cb(_Removed(self.device))

    def replug(self):
        """A new device with the same serial appears (its controls back at their defaults)."""
        self._build()

    def push(self, image: np.ndarray, frame_number: int, timestamp_ms: float, domain: str = "hardware_clock",
             metadata: dict | None = None) -> None:
        """Deliver one BGR frame through librealsense (as the USB backend would), in timestamp `domain`
        with frame metadata {name: int} (e.g. {"actual_exposure": 100} in 100 us units)."""
        rs = self.rs
        for name, value in (metadata or {}).items():
            self.sensor.set_metadata(getattr(rs.frame_metadata_value, name), int(value))
        f = rs.software_video_frame()
        img = np.ascontiguousarray(image, dtype=np.uint8)
        f.pixels = img
        f.bpp = 3
        f.stride = img.shape[1] * 3
        f.timestamp = float(timestamp_ms)
        f.domain = getattr(rs.timestamp_domain, domain)
        f.frame_number = int(frame_number)
        f.profile = self.profile
        self.sensor.on_video_frame(f)


class _Removed:
    """What librealsense's devices-changed callback receives when a device goes away."""

    def __init__(self, dev):
        self._dev = dev

    def was_removed(self, dev):
        return dev is self._dev or dev == self._dev


class FramePusher:
    """Pushes frames from a thread at `fps` until stopped (a streaming camera)."""

    def __init__(self, rig: SoftwareRealSense, make_image, fps=60.0, first_number=1, t0_ms=1000.0):
        self.rig, self.make_image, self.period = rig, make_image, 1.0 / fps
        self.number, self.t_ms = first_number, t0_ms
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            self.rig.push(self.make_image(self.number), self.number, self.t_ms)
            self.number += 1
            self.t_ms += self.period * 1000
            time.sleep(self.period)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join(2)


# ---- X server -----------------------------------------------------------------------------------------

@contextmanager
def xvfb(size=(1920, 1080)):
    """A private Xvfb server with one screen of `size`; yields its DISPLAY string (":N"). Xvfb picks
    a free display number itself (-displayfd), so parallel tests never collide."""
    if shutil.which("Xvfb") is None:
        raise RuntimeError("Xvfb is not installed (apt-get install xvfb)")
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", f"{size[0]}x{size[1]}x24",
                             "-nolisten", "tcp", "-noreset"], pass_fds=(w,),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(w)
    try:
        num = b""
        deadline = time.monotonic() + 20
        while not num.endswith(b"\n") and time.monotonic() < deadline:
            c = os.read(r, 1)
            if not c:
                break
            num += c
        os.close(r)
        if not num.strip():
            raise RuntimeError("Xvfb did not start")
        yield ":" + num.decode().strip()
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def parse_xwd(data: bytes) -> np.ndarray:
    """An XWD file (ZPixmap, 24/32 bits per pixel, TrueColor) as an (H, W, 3) BGR uint8 array."""
    hdr = struct.unpack(">25I", data[:100])
    header_size, version, fmt, depth, width, height = hdr[:6]
    byte_order, bits_per_pixel, bytes_per_line = hdr[7], hdr[11], hdr[12]
    red_mask, green_mask, blue_mask = hdr[14:17]
    ncolors = hdr[19]
    if version != 7 or fmt != 2 or bits_per_pixel not in (24, 32):
        raise ValueError(f"unsupported xwd image: version {version} format {fmt} bpp {bits_per_pixel}")
    offset = header_size + 12 * ncolors
    bpp = bits_per_pixel // 8
    rows = np.frombuffer(data, np.uint8, count=bytes_per_line * height, offset=offset).reshape(height, bytes_per_line)
    px = rows[:, : width * bpp].reshape(height, width, bpp)
    if bpp == 4:
        v = px.view("<u4" if byte_order == 0 else ">u4")[:, :, 0].astype(np.uint32)
    else:
        p = px.astype(np.uint32)
        v = (p[:, :, 0] | p[:, :, 1] << 8 | p[:, :, 2] << 16) if byte_order == 0 else (p[:, :, 2] | p[:, :, 1] << 8 | p[:, :, 0] << 16)

    def channel(mask):
        shift = (mask & -mask).bit_length() - 1
        return ((v & mask) >> shift).astype(np.uint8)

    return np.dstack([channel(blue_mask), channel(green_mask), channel(red_mask)])


def screenshot(display: str) -> np.ndarray:
    """The whole X screen as (H, W, 3) BGR."""
    out = subprocess.run(["xwd", "-root", "-silent", "-display", display], capture_output=True, check=True, timeout=30)
    return parse_xwd(out.stdout)


class ScreenCamera:
    """A CameraDriver that films an X screen with xwd in a thread (a camera looking at the projector):
    frames are the screen, converted to BGR, numbered 1, 2, ... with host timestamps."""

    def __init__(self, display: str, crop=None):
        self.display, self.crop = display, crop
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._stop = threading.Event()
        self._thread = None
        self.grab_durations_s: list[float] = []
        first = self._grab()
        self._size = (first.shape[1], first.shape[0])

    @property
    def size(self):
        return self._size

    def _grab(self):
        img = screenshot(self.display)
        if self.crop is not None:
            x, y, w, h = self.crop
            img = img[y : y + h, x : x + w]
        return img

    def start(self):
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        if self._thread:
            self._thread.join(5)

    def _run(self):
        n = 0
        while not self._stop.is_set():
            t0 = time.monotonic()
            img = self._grab()
            t1 = time.monotonic()
            n += 1
            self.grab_durations_s.append(t1 - t0)
            with self._cond:
                # like a real camera: the frame shows the screen of some moment during the grab and
                # counts from when it arrived
                self._latest = Frame(img, n, t1 * 1000.0, {"host_time_s": t1, "grab_start_s": t0})
                self._cond.notify_all()

    def get_frame(self, timeout_s=2.0, newer_than=None):
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                f = self._latest
                if f is not None and (newer_than is None or f.frame_number > newer_than):
                    return f
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceTimeout("screen camera: no new frame")
                self._cond.wait(left)

    def factory_intrinsics(self):
        return None

    def settings(self):
        return {"driver": "xwd"}


def run_python(code: str, display: str | None, timeout=120, args=()) -> subprocess.CompletedProcess:
    """Run `code` in a fresh interpreter (pyglet reads DISPLAY when it first connects) in the repo."""
    env = dict(os.environ)
    env.pop("DISPLAY", None)
    if display is not None:
        env["DISPLAY"] = display
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(REPO / "tests"), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=timeout, cwd=str(REPO))


def send_key(projector_window, keysym: str = "Escape") -> None:
    """Deliver a key press to a ProjectorWindow's X window through the X server (XSendEvent), as if
    typed: the window sees it in its event loop."""
    import ctypes

    from pyglet.libs.x11 import xlib

    win = projector_window._window
    d = win._x_display
    ev = xlib.XEvent()
    ev.xkey.type = xlib.KeyPress
    ev.xkey.display = d
    ev.xkey.window = win._window
    ev.xkey.root = xlib.XDefaultRootWindow(d)
    ev.xkey.time = xlib.CurrentTime
    ev.xkey.same_screen = 1
    ev.xkey.keycode = xlib.XKeysymToKeycode(d, xlib.XStringToKeysym(keysym.encode()))
    if not xlib.XSendEvent(d, win._window, 1, xlib.KeyPressMask, ctypes.byref(ev)):
        raise RuntimeError("XSendEvent failed")
    xlib.XFlush(d)
