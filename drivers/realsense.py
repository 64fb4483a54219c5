"""Intel RealSense colour camera (D455 and other D400 devices) behind drivers.base.CameraDriver.

pyrealsense2 is imported lazily, so the rest of procam works on machines without it (or without
Debian's libusb-1.0-0, which the wheel needs).

Frame path: the colour sensor of the chosen device streams one video profile (BGR8, e.g. 1280x800 at
30 fps) into an `rs.frame_queue`; a capture thread drains the queue, copies each frame into a numpy
array and keeps the newest one. A test feeds the same path from `rs.software_device` (see
tests/_drivers_helpers.py) by passing it through the `context` argument: any object with
`query_devices()` works, `rs.context()` is the default.

Frame numbers: `Frame.frame_number` is the driver's own counter, +1 for every frame it accepts, so it
increases strictly for the camera object's whole life (also across reconnects, where the device's own
counter restarts). A frame is accepted only when its device frame number or its device timestamp is
larger than the last accepted frame's: a duplicate (both equal) or a late frame (both smaller or
equal) is dropped and counted; a counter reset (number smaller, time larger) or a timestamp wrap
(number larger, time smaller) is accepted. The device's own number is kept in
`Frame.meta["device_frame_number"]`, its timestamp is `Frame.timestamp_ms` (the device clock: librealsense's
global time or hardware clock, `meta["timestamp_domain"]`), and `meta["host_time_s"]` is the host's
time.monotonic() when the frame arrived.

Frame times: `Frame.exposure_start_s` is the host `time.monotonic()` second at which the frame's
exposure began, estimated from what the frame carries (see `_exposure_start`):
- global_time domain (librealsense maps the device clock onto the host's system clock; the default on
  the D4xx when frame metadata is available): the frame time minus the part of the frame that precedes
  it, converted to the monotonic clock with the offset time.time() - time.monotonic() measured when the
  frame arrives. When the frame carries both `frame_timestamp` (start of readout) and `sensor_timestamp`
  (middle of exposure) metadata, the exposure start is the middle of exposure minus half the exposure;
  otherwise the frame time is taken as the start of readout, i.e. the end of the exposure.
- system_time domain (no frame metadata: the V4L2 backend without librealsense's kernel patch, Windows
  without its registry switch; librealsense #13241): the host's clock at the frame's arrival, so the
  exposure began one frame interval (readout and transfer) and the exposure before it. These times are
  the host's, with its transfer jitter: drivers.base.TimeSource.HOST (the rig check says so).
- hardware_clock domain: the device clock mapped to the host clock by the smallest (arrival - device
  time) of the last frames (transfer delays are never negative, so the smallest one has the least
  jitter), minus one frame interval for the readout and transfer that smallest delay still contains.
- otherwise: the host arrival time minus the exposure and one frame interval (readout and transfer).
The exposure is the frame's `actual_exposure` metadata, else the manual exposure set, else a whole
frame interval (the longest an exposure can be at the stream's rate). A constant error in these
estimates is harmless to the station: the projector latency it measures is measured against the same
exposure_start_s, so the bias ends up in the latency; what matters is the jitter, which the offsets above keep small.
`get_frame(newer_than=N, not_before_s=T)` waits for a frame that is newer than N and whose exposure
started at or after T, so a frame exposed before the projector's image became visible is never handed out.

Exposure: the colour sensor's exposure and gain are only meaningful in manual mode (on the D4xx RGB
sensor the values read while auto exposure is on are stored defaults, and its colour metadata is
stale: librealsense issues #2549, #5035, #11355). The driver therefore implements
drivers.base.ExposureControl: `set_manual_exposure(exposure_us, gain)` turns auto exposure off first,
then sets both (clamped to the option's range, rounded to its step) and returns what the device reports
back; nothing is ever read from auto exposure. The depth sensor's IR emitter (`emitter_enabled`)
is switched off at start (its dots can show in the colour image, librealsense #7181).

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
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from calib.models.camera import CameraModel
from drivers._frames import wait_latest
from drivers.base import Frame
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout, StreamReset

#: Unit of the colour sensor's `exposure` option. librealsense passes the UVC control through: on the
#: D400 RGB sensor it counts 100 microseconds (range 1..10000), unlike the depth sensor's microseconds.
COLOUR_EXPOSURE_UNIT_US = 100.0

_rs_module = None


def _import_error_message(e: BaseException) -> str:
    """What to do when pyrealsense2 does not import, from the import error itself."""
    text = str(e)
    if "libusb" in text:
        return (f"pyrealsense2 cannot be loaded because Debian's libusb is missing ({text}): install it with "
                "`sudo apt-get install libusb-1.0-0`, or use the simulated rig (--rig sim)")
    if isinstance(e, ModuleNotFoundError) and getattr(e, "name", "") == "pyrealsense2":
        return ("pyrealsense2 is not installed: install it with `pip install 'procam-station[realsense]'` "
                "(PyPI has wheels for Linux x86_64 and Windows; elsewhere build librealsense with "
                "-DBUILD_PYTHON_BINDINGS=ON; on Linux it also needs `apt-get install libusb-1.0-0`), "
                "or use the simulated rig (--rig sim)")
    return (f"pyrealsense2 cannot be imported ({text}); install it with pip and Debian's libusb-1.0-0 "
            "(apt-get install libusb-1.0-0), or use the simulated rig (--rig sim)")


def _rs():
    """pyrealsense2, imported on first use."""
    global _rs_module
    if _rs_module is None:
        try:
            import pyrealsense2 as rs
        except ImportError as e:  # pragma: no cover - depends on the machine
            raise DeviceError(_import_error_message(e)) from None
        _rs_module = rs
    return _rs_module


def realsense_import_error() -> str | None:
    """Why pyrealsense2 is not usable here (what to install), or None when it is."""
    try:
        _rs()
        return None
    except DeviceError as e:
        return str(e)


def realsense_available() -> bool:
    """True when pyrealsense2 imports on this machine."""
    return realsense_import_error() is None


# ---- device discovery -----------------------------------------------------------------------------

def _info(dev, key: str) -> str | None:
    rs = _rs()
    ci = getattr(rs.camera_info, key)
    try:
        if dev.supports(ci):
            return str(dev.get_info(ci))
    except RuntimeError:
        pass
    return None


def device_info(dev) -> dict:
    """serial, name, firmware, usb_type (and product line / port when known) of a librealsense device."""
    return {
        "serial": _info(dev, "serial_number"),
        "name": _info(dev, "name"),
        "firmware": _info(dev, "firmware_version"),
        "usb_type": _info(dev, "usb_type_descriptor"),
        "product_line": _info(dev, "product_line"),
        "port": _info(dev, "physical_port"),
    }


def list_realsense_devices(context=None) -> list[dict]:
    """Connected RealSense devices as dicts (serial, name, firmware, usb_type, ...); [] when there is
    none or pyrealsense2 is not usable here."""
    try:
        rs = _rs()
    except DeviceError:
        return []
    ctx = context if context is not None else rs.context()
    try:
        devices = list(ctx.query_devices())
    except RuntimeError:
        return []
    return [device_info(d) for d in devices]


def _colour_profiles(sensor) -> list:
    rs = _rs()
    out = []
    for p in sensor.get_stream_profiles():
        if p.stream_type() == rs.stream.color and p.is_video_stream_profile():
            out.append(p.as_video_stream_profile())
    return out


def _colour_sensor(dev):
    """The device's sensor that streams colour, or None."""
    for s in dev.query_sensors():
        if _colour_profiles(s):
            return s
    return None


def _depth_sensor(dev, colour_sensor=None):
    """The device's sensor with an IR emitter control (the D4xx "Stereo Module"), or None."""
    rs = _rs()
    try:
        sensors = list(dev.query_sensors())
    except RuntimeError:
        return None
    for s in sensors:
        if colour_sensor is not None and s == colour_sensor:
            continue
        try:
            if s.supports(rs.option.emitter_enabled):
                return s
        except RuntimeError:
            continue
    return None


# ---- intrinsics -------------------------------------------------------------------------------------

class IntrinsicsConversionError(DeviceError):
    """librealsense's intrinsics cannot be expressed as an OpenCV camera model closely enough."""


_MODEL_NAMES = {0: "none", 1: "modified_brown_conrady", 2: "inverse_brown_conrady", 3: "ftheta",
                4: "brown_conrady", 5: "kannala_brandt4"}


def distortion_model_name(model) -> str:
    """librealsense's distortion model as a plain name ('brown_conrady', ...): accepts an
    rs.distortion value, its integer or its name."""
    if isinstance(model, str):
        name = model.split(".")[-1].lower()
    else:
        try:
            name = _MODEL_NAMES[int(model)]
        except (KeyError, TypeError, ValueError):
            name = str(model).split(".")[-1].lower()
    if name not in _MODEL_NAMES.values():
        raise IntrinsicsConversionError(f"unknown librealsense distortion model {model!r}")
    return name


def rs_distort_normalized(model, coeffs, xy: np.ndarray) -> np.ndarray:
    """librealsense's projection (rs2_project_point_to_pixel in rsutil.h) from normalized undistorted
    coordinates (x/z, y/z) to normalized distorted ones, in float64. (N, 2) -> (N, 2).

    - none: identity.
    - brown_conrady: OpenCV's model, coeffs [k1, k2, p1, p2, k3].
    - modified_brown_conrady and inverse_brown_conrady (librealsense projects both the same way):
      the radial factor first, then the tangential terms evaluated at the radially distorted point
      (with the undistorted r^2).
    - ftheta: r_d = atan(2 r tan(w / 2)) / w with w = coeffs[0].
    - kannala_brandt4: theta = atan(r), r_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
      coeffs [k1, k2, k3, k4, -].
    """
    name = distortion_model_name(model)
    c = np.zeros(5)
    cc = np.asarray(coeffs, float).reshape(-1)[:5]
    c[: cc.size] = cc
    xy = np.asarray(xy, float).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    if name == "none":
        return xy.copy()
    if name in ("brown_conrady", "modified_brown_conrady", "inverse_brown_conrady"):
        f = 1 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2
        if name == "brown_conrady":
            xt, yt = x, y
        else:
            xt, yt = x * f, y * f
        xd = x * f + 2 * c[2] * xt * yt + c[3] * (r2 + 2 * xt * xt)
        yd = y * f + 2 * c[3] * xt * yt + c[2] * (r2 + 2 * yt * yt)
        return np.column_stack([xd, yd])
    r = np.maximum(np.sqrt(r2), np.finfo(np.float32).eps)
    if name == "ftheta":
        if c[0] == 0:
            raise IntrinsicsConversionError("ftheta distortion with a zero field-of-view coefficient")
        rd = np.arctan(2 * r * np.tan(c[0] / 2)) / c[0]
    else:  # kannala_brandt4
        t = np.arctan(r)
        t2 = t * t
        rd = t * (1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3]))))
    s = rd / r
    return np.column_stack([x * s, y * s])


def _invert(fn: Callable[[np.ndarray], np.ndarray], target: np.ndarray, iterations: int = 60):
    """Solve fn(xy) = target by Newton steps with a numerical Jacobian; (xy, converged mask)."""
    xy = target.copy()
    h = 1e-7
    for _ in range(iterations):
        f = fn(xy) - target
        if np.all(np.abs(f) < 1e-13):
            break
        jx = (fn(xy + [h, 0]) - fn(xy - [h, 0])) / (2 * h)
        jy = (fn(xy + [0, h]) - fn(xy - [0, h])) / (2 * h)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (jy[:, 1] * f[:, 0] - jy[:, 0] * f[:, 1]) / det
            dy = (-jx[:, 1] * f[:, 0] + jx[:, 0] * f[:, 1]) / det
        step = np.column_stack([dx, dy])
        step[~np.isfinite(step)] = 0.0
        xy = xy - np.clip(step, -0.5, 0.5)
    ok = np.all(np.abs(fn(xy) - target) < 1e-9, axis=1) & np.isfinite(xy).all(axis=1)
    return xy, ok


@dataclass(frozen=True, eq=False)
class IntrinsicsConversion:
    """A librealsense intrinsics record turned into a CameraModel, and how exactly.

    method: 'exact' (the same formula) or 'fit-5' / 'fit-8' (OpenCV coefficients least-squares fitted
    to librealsense's projection over the whole image); max_error_px: the largest pixel difference
    between CameraModel.project and librealsense's projection over a dense grid covering the image."""

    model: CameraModel
    source_model: str
    source_coeffs: tuple
    method: str
    max_error_px: float

    def to_dict(self) -> dict:
        return {"camera": self.model.to_dict(), "source_model": self.source_model,
                "source_coeffs": list(self.source_coeffs), "method": self.method,
                "max_error_px": self.max_error_px}


def _image_grid(width: int, height: int, nx: int, ny: int) -> np.ndarray:
    u = np.linspace(-0.5, width - 0.5, nx)
    v = np.linspace(-0.5, height - 0.5, ny)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def _fit_brown5(xy: np.ndarray, xyd: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Linear least squares for OpenCV's [k1, k2, p1, p2, k3] mapping xy -> xyd (pixel-weighted)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    ax = np.column_stack([x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x, x * r2 ** 3]) * fx
    ay = np.column_stack([y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y, y * r2 ** 3]) * fy
    A = np.vstack([ax, ay])
    b = np.concatenate([(xyd[:, 0] - x) * fx, (xyd[:, 1] - y) * fy])
    return np.linalg.lstsq(A, b, rcond=None)[0]


def convert_intrinsics(intr, tolerance_px: float = 0.05) -> IntrinsicsConversion:
    """Turn an `rs.intrinsics` (or any object with width, height, fx, fy, ppx, ppy, model, coeffs)
    into a CameraModel (OpenCV order [k1, k2, p1, p2, k3, k4, k5, k6]).

    Both libraries put pixel (0, 0) at the centre of the top-left pixel, so K is [[fx, 0, ppx],
    [0, fy, ppy], [0, 0, 1]] in every case. The distortion:
    - none -> no coefficients (exact).
    - brown_conrady -> coeffs as they are, [k1, k2, p1, p2, k3] (exact: the same formula).
    - modified_brown_conrady / inverse_brown_conrady -> librealsense projects both with the same
      "modified" formula (tangential terms at the radially distorted point). Exact (coeffs as they
      are) when p1 = p2 = 0; otherwise OpenCV's 5 coefficients are fitted to librealsense's projection
      over the whole image (then 8 rational ones if 5 are not within `tolerance_px`).
    - ftheta, kannala_brandt4 (fisheye models) -> the same fit; when no OpenCV model reproduces
      librealsense's projection within `tolerance_px` everywhere in the image, raise
      IntrinsicsConversionError (calibrate the camera instead).
    """
    name = distortion_model_name(intr.model)
    coeffs = tuple(float(c) for c in list(intr.coeffs)[:5])
    c = np.zeros(5)
    c[: len(coeffs)] = coeffs
    W, H = int(intr.width), int(intr.height)
    fx, fy, cx, cy = float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy)
    if W <= 0 or H <= 0 or fx <= 0 or fy <= 0:
        raise IntrinsicsConversionError(f"librealsense intrinsics are not usable: {W}x{H}, fx={fx}, fy={fy}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    if name == "none":
        return IntrinsicsConversion(CameraModel(W, H, K, []), name, coeffs, "exact", 0.0)
    if name == "brown_conrady" or (name in ("modified_brown_conrady", "inverse_brown_conrady")
                                   and c[2] == 0.0 and c[3] == 0.0):
        return IntrinsicsConversion(CameraModel(W, H, K, c), name, coeffs, "exact", 0.0)

    def fwd(xy):
        return rs_distort_normalized(name, c, xy)

    def to_norm(uv):
        return np.column_stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy])

    def error_px(model: CameraModel, xy_u: np.ndarray) -> float:
        ref = fwd(xy_u) * [fx, fy] + [cx, cy]
        got = model.project(np.column_stack([xy_u, np.ones(len(xy_u))]))
        e = np.linalg.norm(got - ref, axis=1)
        return float(np.inf) if not np.isfinite(e).all() else float(e.max())

    fit_uv = _image_grid(W, H, 41, 27)
    check_uv = _image_grid(W, H, 97, 61)
    xy_fit, ok_fit = _invert(fwd, to_norm(fit_uv))
    xy_chk, ok_chk = _invert(fwd, to_norm(check_uv))
    if not (ok_fit.all() and ok_chk.all()):
        raise IntrinsicsConversionError(
            f"librealsense's {name} distortion {list(coeffs)} cannot be inverted over the whole "
            f"{W}x{H} image, so no OpenCV model can stand in for it: calibrate the camera instead of "
            "using its factory intrinsics")
    xyd_fit = fwd(xy_fit)
    d5 = _fit_brown5(xy_fit, xyd_fit, fx, fy)
    m5 = CameraModel(W, H, K, d5)
    err5 = error_px(m5, xy_chk)
    if err5 <= tolerance_px:
        return IntrinsicsConversion(m5, name, coeffs, "fit-5", err5)

    from scipy.optimize import least_squares

    def resid(p):
        m = CameraModel(W, H, K, p)
        d = m.distort_normalized(xy_fit) - xyd_fit
        return np.concatenate([d[:, 0] * fx, d[:, 1] * fy])

    p0 = np.concatenate([d5, np.zeros(3)])
    sol = least_squares(resid, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=4000)
    m8 = CameraModel(W, H, K, sol.x)
    err8 = error_px(m8, xy_chk)
    if err8 <= tolerance_px:
        return IntrinsicsConversion(m8, name, coeffs, "fit-8", err8)
    def how_far(e: float) -> str:
        return f"off by {e:.3g} px" if np.isfinite(e) else "not even valid (it folds over inside the image)"

    raise IntrinsicsConversionError(
        f"librealsense's {name} distortion {list(coeffs)} has no OpenCV equivalent on this {W}x{H} "
        f"stream: the best 5-coefficient fit is {how_far(err5)} and the best 8-coefficient (rational) "
        f"fit is {how_far(err8)} somewhere in the image; {tolerance_px} px is allowed. Calibrate the "
        "camera instead of using its factory intrinsics")


def camera_model_from_rs_intrinsics(intr, tolerance_px: float = 0.05) -> CameraModel:
    """The CameraModel of `convert_intrinsics` (see there for each distortion model)."""
    return convert_intrinsics(intr, tolerance_px).model


# ---- the camera -----------------------------------------------------------------------------------

@dataclass
class _Stats:
    accepted: int = 0
    duplicates: int = 0
    late: int = 0
    bad: int = 0
    gaps: int = 0  # jumps in the device's frame numbers: frames lost between the device and the driver
    missing: int = 0  # frames those jumps skipped
    resets: int = 0  # stalled streams reset (hardware_reset)
    held: int = 0  # frames dropped after a (re)start, until the re-applied exposure shows


class RealSenseCamera:
    """A RealSense colour stream as a drivers.base.CameraDriver.

    serial: the device to open (None: the first device with a colour sensor). width, height, fps: the
    colour profile (BGR8; the D455 offers 1280x800, 1280x720, 848x480, 640x480... at 5-30 fps).
    context: where devices are found (rs.context() by default; tests pass a software device).
    stale_after_s: get_frame() without `newer_than` returns the newest frame only when it arrived at
    most this long ago, else waits for a new one (default: 5 frame intervals, at least 0.5 s).
    emitter_enabled: the depth sensor's IR emitter state applied at start (default off, see the module doc).
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
        f = wait_latest(self, lambda: f"RealSense {self._label()}", deadline, newer_than, not_before_s,
                        lambda f: time.monotonic() - f.meta["host_time_s"] <= self._stale_after_s)
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

    # ---- exposure (drivers.base.ExposureControl) ----------------------------------------------------
    def exposure_limits(self) -> dict:
        """{"exposure_us": (min, max, step), "gain": (min, max, step)} as the colour sensor reports them
        (exposure in microseconds)."""
        rs = self._rs
        self._require_started("read the exposure limits")
        out = {}
        for key, opt, scale in (("exposure_us", rs.option.exposure, COLOUR_EXPOSURE_UNIT_US),
                                ("gain", rs.option.gain, 1.0)):
            self._require(opt, key.split("_")[0])
            r = self._sensor.get_option_range(opt)
            out[key] = (float(r.min) * scale, float(r.max) * scale, float(r.step) * scale)
        return out

    def set_auto_exposure(self, enabled: bool) -> None:
        """Auto exposure on (the manual values are forgotten) or off (the device keeps what it has)."""
        rs = self._rs
        self._require_started("change the auto exposure")
        self._require(rs.option.enable_auto_exposure, "auto exposure")
        self._set_option(rs.option.enable_auto_exposure, 1.0 if enabled else 0.0, "auto exposure")
        if enabled:
            self._manual = None

    def set_manual_exposure(self, exposure_us: float, gain: float) -> dict:
        """Auto exposure off first, then exposure (us) and gain, each clamped to the sensor's range and
        rounded to its step. Returns what the device reports back: {"exposure_us", "gain"}; the values
        are re-applied after a reconnect."""
        rs = self._rs
        self._require_started("set the exposure")
        try:
            exposure_us, gain = float(exposure_us), float(gain)
        except (TypeError, ValueError):
            raise DeviceError(f"exposure and gain must be numbers, got {exposure_us!r} and {gain!r}") from None
        if not (np.isfinite(exposure_us) and np.isfinite(gain)):
            raise DeviceError(f"exposure and gain must be finite, got {exposure_us} us and {gain}")
        if self._sensor.supports(rs.option.enable_auto_exposure):
            self._set_option(rs.option.enable_auto_exposure, 0.0, "auto exposure")
        self._require(rs.option.exposure, "exposure")
        self._require(rs.option.gain, "gain")
        applied_exposure = self._set_option(rs.option.exposure, exposure_us / COLOUR_EXPOSURE_UNIT_US, "exposure",
                                            unit_scale=COLOUR_EXPOSURE_UNIT_US, unit="us", clamp=True)
        applied_gain = self._set_option(rs.option.gain, gain, "gain", clamp=True)
        applied = {"exposure_us": applied_exposure * COLOUR_EXPOSURE_UNIT_US, "gain": applied_gain}
        if self._sensor.supports(rs.option.enable_auto_exposure) and \
                float(self._sensor.get_option(rs.option.enable_auto_exposure)) != 0.0:
            raise DeviceError(f"RealSense {self._label()}: auto exposure is still on after switching it off")
        self._manual = dict(applied)
        return applied

    def set_emitter(self, enabled: bool) -> None:
        """The depth sensor's IR emitter on or off; a device without one (or without the option) is left
        as it is. Applied again after a reconnect."""
        rs = self._rs
        self._emitter_wanted = bool(enabled)
        d = self._depth_sensor
        if d is None or not d.supports(rs.option.emitter_enabled):
            return
        try:
            d.set_option(rs.option.emitter_enabled, 1.0 if enabled else 0.0)
        except RuntimeError as e:
            raise DeviceError(f"RealSense {self._label()}: cannot switch the IR emitter "
                              f"{'on' if enabled else 'off'}: {e}") from None

    def emitter_enabled(self) -> bool | None:
        """The emitter as the depth sensor reports it; None when the device has none."""
        d = self._depth_sensor
        rs = self._rs
        try:
            if d is not None and d.supports(rs.option.emitter_enabled):
                return bool(d.get_option(rs.option.emitter_enabled))
        except RuntimeError:
            pass
        return None

    def _fix_image_processing(self) -> None:
        """Auto white balance off, at the white balance the sensor has (its colour gains would follow
        the projected image between the exposure search, the tone-curve bracket and the captures; the
        published method's own code turns it off too), and auto exposure priority off (it may lower the
        frame rate at long exposures, librealsense #7242). A sensor without a control is left as it is."""
        rs = self._rs
        for opt, label in ((rs.option.enable_auto_white_balance, "auto white balance"),
                           (rs.option.auto_exposure_priority, "auto exposure priority")):
            if self._sensor.supports(opt):
                self._set_option(opt, 0.0, label)

    def _require_started(self, what: str) -> None:
        if self._sensor is None:
            raise DeviceError(f"RealSense {self._label()}: start() the camera before trying to {what}")

    def _require(self, opt, label: str) -> None:
        if not self._sensor.supports(opt):
            raise DeviceError(f"RealSense {self._label()}: the colour sensor has no {label} control")

    def _set_option(self, opt, value: float, label: str, unit_scale: float = 1.0, unit: str = "",
                    clamp: bool = False) -> float:
        s = self._sensor
        r = s.get_option_range(opt)
        if clamp:
            value = min(max(value, r.min), r.max)
        if not (r.min - 1e-9 <= value <= r.max + 1e-9):
            raise DeviceError(
                f"RealSense {self._label()}: {label} {value * unit_scale:g}{unit} is outside the camera's "
                f"range {r.min * unit_scale:g}..{r.max * unit_scale:g}{unit}")
        if r.step > 0:
            value = r.min + round((value - r.min) / r.step) * r.step
        value = min(max(value, r.min), r.max)
        try:
            s.set_option(opt, float(value))
        except RuntimeError as e:
            raise DeviceError(f"RealSense {self._label()}: cannot set {label} to {value * unit_scale:g}{unit}: {e}") from None
        return float(s.get_option(opt))

    def _read_controls(self) -> dict:
        rs = self._rs
        s = self._sensor
        out: dict[str, Any] = {}
        if s is None:
            return out

        def read(opt):
            try:
                if s.supports(opt):
                    return float(s.get_option(opt))
            except RuntimeError:
                pass
            return None

        v = read(rs.option.enable_auto_exposure)
        out["auto_exposure"] = None if v is None else bool(v)
        v = read(rs.option.exposure)
        out["exposure_us"] = None if v is None else v * COLOUR_EXPOSURE_UNIT_US
        out["gain"] = read(rs.option.gain)
        v = read(rs.option.enable_auto_white_balance)
        out["auto_white_balance"] = None if v is None else bool(v)
        out["white_balance_k"] = read(rs.option.white_balance)
        v = read(rs.option.auto_exposure_priority)
        out["auto_exposure_priority"] = None if v is None else bool(v)
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

    def _capture_loop(self, queue, stop_evt: threading.Event) -> None:
        try:
            while not stop_evt.is_set():
                ok, f = queue.try_wait_for_frame(100)
                if ok:
                    self._accept(f)
        except Exception as e:  # noqa: BLE001 - reported to the caller of get_frame
            with self._cond:
                self._thread_error = e
                self._cond.notify_all()

    def _accept(self, f) -> None:
        rs = self._rs
        host_t = time.monotonic()
        if not f.is_video_frame():
            return
        vf = f.as_video_frame()
        key = (int(vf.get_frame_number()), float(vf.get_timestamp()))
        with self._cond:
            last = self._last_key
            if last is not None and key[0] <= last[0] and key[1] <= last[1]:
                if key == last:
                    self.stats.duplicates += 1
                else:
                    self.stats.late += 1
                return
        img = np.asanyarray(vf.get_data())
        h, w = vf.get_height(), vf.get_width()
        if img.dtype != np.uint8 or img.size != h * w * 3:
            with self._cond:
                self.stats.bad += 1
            return
        img = np.array(img, copy=True).reshape(h, w, 3)
        if vf.get_profile().format() == rs.format.rgb8:
            img = np.ascontiguousarray(img[:, :, ::-1])
        img.setflags(write=False)
        meta = {"device_frame_number": key[0], "timestamp_domain": str(vf.get_frame_timestamp_domain()).split(".")[-1],
                "host_time_s": host_t, "serial": self.serial}
        md = rs.frame_metadata_value
        for name, value, scale in (("actual_exposure_us", md.actual_exposure, COLOUR_EXPOSURE_UNIT_US),
                                  ("frame_timestamp_us", md.frame_timestamp, 1.0),
                                  ("sensor_timestamp_us", md.sensor_timestamp, 1.0),
                                  ("gain", md.gain_level, 1.0)):
            try:
                if vf.supports_frame_metadata(value):
                    meta[name] = float(vf.get_frame_metadata(value)) * scale
            except RuntimeError:
                pass
        if "actual_exposure_us" not in meta and self._manual is not None:
            # no metadata: the manual exposure last set (the rig check confirms it shows before timing
            # anything by it), so a frame that caught a change part-way can still be timed
            meta["exposure_us_set"] = float(self._manual["exposure_us"])
        start_s, source = self._exposure_start(key[1], meta, host_t, time.time() - time.monotonic())
        meta["exposure_start_source"] = source
        with self._cond:
            last = self._last_key
            if last is not None and key[0] <= last[0] and key[1] <= last[1]:
                self.stats.late += 1
                return
            if last is not None and key[0] > last[0] + 1:  # frames the device numbered never reached us
                self.stats.gaps += 1
                self.stats.missing += key[0] - last[0] - 1
            self._last_key = key
            self._last_arrival_s = host_t
            if start_s < self._hold_until_s:
                self.stats.held += 1
                return
            self._counter += 1
            self.stats.accepted += 1
            self._latest = Frame(img, self._counter, key[1], meta, start_s)
            self._cond.notify_all()

    def _exposure_start(self, timestamp_ms: float, meta: dict, arrival_s: float,
                        wall_minus_mono_s: float) -> tuple[float, str]:
        """(host monotonic seconds at which the exposure began, how it was estimated); see the module doc."""
        period_s = 1.0 / max(self.fps, 1)
        exposure_s = meta.get("actual_exposure_us")
        if exposure_s is None and self._manual is not None:
            exposure_s = self._manual["exposure_us"]
        exposure_s = period_s if exposure_s is None else float(exposure_s) * 1e-6
        # the exposure start relative to the instant the frame's timestamp stands for
        if "frame_timestamp_us" in meta and "sensor_timestamp_us" in meta:
            before_ref_s = (meta["frame_timestamp_us"] - meta["sensor_timestamp_us"]) * 1e-6 + exposure_s / 2
        else:
            before_ref_s = exposure_s  # the timestamp marks the start of readout = the end of the exposure
        domain = meta.get("timestamp_domain")
        if domain == "global_time":
            return timestamp_ms * 1e-3 - wall_minus_mono_s - before_ref_s, domain
        if domain == "system_time":
            # no hardware timestamp (no frame metadata, librealsense #13241): librealsense stamped the
            # frame with the host's clock when it arrived, after the exposure, the readout and the transfer
            return timestamp_ms * 1e-3 - wall_minus_mono_s - period_s - exposure_s, domain
        if domain == "hardware_clock":
            self._offsets.append(arrival_s - timestamp_ms * 1e-3)
            del self._offsets[:-max(8, 2 * self.fps)]
            ref_s = timestamp_ms * 1e-3 + min(self._offsets)
            # a device-clock jump (reset, wrap) makes the mapped time land after the arrival or
            # implausibly long before it: start over
            if not arrival_s - 1.0 <= ref_s <= arrival_s:
                self._offsets = [arrival_s - timestamp_ms * 1e-3]
                ref_s = arrival_s
            return ref_s - period_s - before_ref_s, domain
        return arrival_s - period_s - exposure_s, "arrival"
