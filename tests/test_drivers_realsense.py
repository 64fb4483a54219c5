"""The RealSense driver on librealsense's own code path, without hardware: a software device
(rs.software_device) feeds the frame queue the driver streams from."""

import threading
import time

import numpy as np
import pyrealsense2 as rs
import pytest

from _drivers_helpers import FramePusher, SoftwareRealSense
from drivers.base import CameraDriver, ExposureControl
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from drivers.realsense import (
    IntrinsicsConversionError,
    RealSenseCamera,
    convert_intrinsics,
    list_realsense_devices,
    rs_distort_normalized,
)


def numbered_image(n, w=64, h=48):
    rng = np.random.default_rng(n)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


@pytest.fixture
def rig():
    return SoftwareRealSense()


@pytest.fixture
def cam(rig):
    c = RealSenseCamera(width=64, height=48, fps=30, context=rig)
    c.start()
    yield c
    c.stop()


def push_and_get(rig, cam, img, number, t_ms, newer_than=None, **push_kw):
    rig.push(img, number, t_ms, **push_kw)
    return cam.get_frame(2.0, newer_than=newer_than)


# ---- frames -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [(64, 48), (1280, 800)])
def test_frames_arrive_pixel_exact_with_device_time_and_numbers(size):
    w, h = size
    rig = SoftwareRealSense(w, h, 30)
    cam = RealSenseCamera(width=w, height=h, fps=30, context=rig)
    assert isinstance(cam, CameraDriver) and cam.size == (w, h)
    cam.start()
    try:
        last = None
        for k in range(4):
            img = numbered_image(k, w, h)
            f = push_and_get(rig, cam, img, 100 + k, 5000.0 + 33.3 * k, newer_than=last)
            assert f.image.shape == (h, w, 3) and f.image.dtype == np.uint8
            assert np.array_equal(f.image, img)
            assert f.timestamp_ms == pytest.approx(5000.0 + 33.3 * k)
            assert f.meta["device_frame_number"] == 100 + k
            assert f.meta["timestamp_domain"] == "hardware_clock"
            assert last is None or f.frame_number == last + 1
            assert not f.image.flags.writeable  # a frame cannot be altered behind the driver's back
            last = f.frame_number
    finally:
        cam.stop()


def test_rgb8_stream_is_delivered_as_bgr():
    rig = SoftwareRealSense(fmt="rgb8")
    cam = RealSenseCamera(width=64, height=48, fps=30, context=rig)
    cam.start()
    try:
        img = numbered_image(3)
        f = push_and_get(rig, cam, img, 1, 10.0)
        assert np.array_equal(f.image, img[:, :, ::-1])
    finally:
        cam.stop()


def test_duplicate_and_late_frames_are_dropped(rig, cam):
    first = push_and_get(rig, cam, numbered_image(1), 10, 1000.0)
    rig.push(numbered_image(2), 10, 1000.0)   # the same frame again
    rig.push(numbered_image(3), 9, 966.7)     # a late frame from before
    with pytest.raises(DeviceTimeout):
        cam.get_frame(0.4, newer_than=first.frame_number)
    assert cam.stats.duplicates == 1 and cam.stats.late == 1
    new = push_and_get(rig, cam, numbered_image(4), 11, 1033.3, newer_than=first.frame_number)
    assert new.frame_number == first.frame_number + 1
    assert np.array_equal(new.image, numbered_image(4))
    # a device counter reset (smaller number, later time) is a new frame, not a late one
    reset = push_and_get(rig, cam, numbered_image(5), 0, 1066.6, newer_than=new.frame_number)
    assert reset.frame_number == new.frame_number + 1 and reset.meta["device_frame_number"] == 0


def test_newer_than_waits_for_the_next_frame(rig, cam):
    first = push_and_get(rig, cam, numbered_image(1), 1, 100.0)
    assert cam.get_frame(1.0).frame_number == first.frame_number  # newest, returned again
    timer = threading.Timer(0.3, rig.push, args=(numbered_image(2), 2, 133.0))
    t0 = time.monotonic()
    timer.start()
    f = cam.get_frame(3.0, newer_than=first.frame_number)
    assert time.monotonic() - t0 >= 0.25
    assert f.frame_number > first.frame_number and np.array_equal(f.image, numbered_image(2))


def test_a_stale_newest_frame_is_not_returned(rig):
    cam = RealSenseCamera(width=64, height=48, fps=30, context=rig, stale_after_s=0.2)
    cam.start()
    try:
        push_and_get(rig, cam, numbered_image(1), 1, 100.0)
        time.sleep(0.35)
        with pytest.raises(DeviceTimeout):
            cam.get_frame(0.3)
    finally:
        cam.stop()


def test_streaming_frames_are_strictly_new(rig, cam):
    """At 60 fps through the queue: a chain of newer_than requests sees strictly increasing numbers
    and never the same image twice."""
    with FramePusher(rig, lambda n: numbered_image(n % 50), fps=60) as pusher:
        seen, last = [], None
        for _ in range(15):
            f = cam.get_frame(2.0, newer_than=last)
            seen.append((f.frame_number, f.meta["device_frame_number"]))
            assert np.array_equal(f.image, numbered_image(f.meta["device_frame_number"] % 50))
            last = f.frame_number
    numbers = [s[0] for s in seen]
    device_numbers = [s[1] for s in seen]
    assert all(b > a for a, b in zip(numbers, numbers[1:]))
    assert all(b > a for a, b in zip(device_numbers, device_numbers[1:]))
    assert pusher.number > 15


# ---- opening devices ---------------------------------------------------------------------------------

def test_list_devices_reports_serial_name_firmware_usb(rig):
    (d,) = list_realsense_devices(context=rig)
    assert d["serial"] == "SW-D455-0001" and d["name"].startswith("Intel RealSense D455")
    assert d["firmware"] == "5.16.0.1" and d["usb_type"] == "3.2"
    rig.unplug()
    assert list_realsense_devices(context=rig) == []


def test_open_by_serial_and_mode_errors(rig):
    with pytest.raises(DeviceDisconnected, match="serial 123 is not connected.*SW-D455-0001"):
        RealSenseCamera("123", 64, 48, 30, context=rig).start()
    with pytest.raises(DeviceError, match="1280x800@30.*not offered.*640x480@30, 64x48@30"):
        RealSenseCamera(None, 1280, 800, 30, context=rig).start()
    other = RealSenseCamera(None, 640, 480, 30, context=rig)  # a second mode of the same sensor
    other.start()
    assert other.serial == "SW-D455-0001" and other.size == (640, 480)
    other.stop()
    rig.unplug()
    with pytest.raises(DeviceDisconnected, match="no RealSense device is connected"):
        RealSenseCamera(context=rig).start()


def test_get_frame_before_start_is_a_clear_error(rig):
    with pytest.raises(DeviceError, match="call start"):
        RealSenseCamera(width=64, height=48, context=rig).get_frame(0.1)


# ---- disconnects -------------------------------------------------------------------------------------

def test_no_frames_with_device_present_is_a_timeout(rig, cam):
    push_and_get(rig, cam, numbered_image(1), 1, 10.0)
    with pytest.raises(DeviceTimeout, match="no frame newer than"):
        cam.get_frame(0.3, newer_than=1)
    assert not cam.disconnected


def test_unplug_raises_disconnected_at_once_and_reconnect_recovers(rig, cam):
    cam.set_manual_exposure(5000, 20)
    cam.set_emitter(False)
    f = push_and_get(rig, cam, numbered_image(1), 500, 20000.0)
    waiter = {}

    def wait():
        t0 = time.monotonic()
        try:
            cam.get_frame(10.0, newer_than=f.frame_number)
        except DeviceDisconnected as e:
            waiter["error"], waiter["after_s"] = e, time.monotonic() - t0

    th = threading.Thread(target=wait)
    th.start()
    time.sleep(0.2)
    rig.unplug()  # librealsense reports the removal: the waiting call fails now, not after 10 s
    th.join(5)
    assert "disconnected" in str(waiter["error"]) and waiter["after_s"] < 2.0
    with pytest.raises(DeviceDisconnected):
        cam.get_frame(0.1)
    with pytest.raises(DeviceDisconnected, match="did not come back"):
        cam.reconnect(timeout_s=0.3)
    threading.Timer(0.3, rig.replug).start()  # a new device, controls back at their defaults
    cam.reconnect(timeout_s=5.0)
    g = push_and_get(rig, cam, numbered_image(2), 1, 3.0, newer_than=f.frame_number)
    assert g.frame_number == f.frame_number + 1  # numbering continues although the device restarted
    assert g.meta["device_frame_number"] == 1 and np.array_equal(g.image, numbered_image(2))
    s = cam.settings()  # the manual exposure and the emitter were applied again to the new device
    assert s["auto_exposure"] is False and s["exposure_us"] == pytest.approx(5000)
    assert s["gain"] == 20 and s["emitter_enabled"] is False
    assert rig.depth.get_option(rs.option.emitter_enabled) == 0


def test_silent_unplug_is_detected_when_frames_stop(rig, cam):
    f = push_and_get(rig, cam, numbered_image(1), 1, 10.0)
    rig.unplug(notify=False)  # no callback: found when the frame does not come and the device is gone
    with pytest.raises(DeviceDisconnected, match="plug it back in"):
        cam.get_frame(0.3, newer_than=f.frame_number)
    rig.replug()
    cam.stop()
    cam.start()  # re-start recovers as well
    g = push_and_get(rig, cam, numbered_image(2), 1, 1.0, newer_than=f.frame_number)
    assert g.frame_number > f.frame_number


# ---- exposure ------------------------------------------------------------------------------------------

def test_manual_exposure_turns_auto_off_first_and_reads_back_what_the_device_applied(rig, cam):
    assert isinstance(cam, ExposureControl)
    s0 = cam.settings()
    assert s0["auto_exposure"] is True and s0["manual_exposure"] is False
    lim = cam.exposure_limits()  # the D455 colour sensor counts exposure in 100 us
    assert lim["exposure_us"] == (pytest.approx(100), pytest.approx(1e6), pytest.approx(100))
    assert lim["gain"] == (0, 128, 1)

    applied = cam.set_manual_exposure(8333.3, 30.4)  # rounded to the steps: 83 x 100 us, gain 30
    assert applied == {"exposure_us": pytest.approx(8300), "gain": 30}
    assert rig.sensor.get_option(rs.option.enable_auto_exposure) == 0
    assert rig.sensor.get_option(rs.option.exposure) == 83 and rig.sensor.get_option(rs.option.gain) == 30
    s1 = cam.settings()
    assert s1["auto_exposure"] is False and s1["exposure_us"] == pytest.approx(8300) and s1["gain"] == 30
    # out of range: clamped to the range, and the reply says so
    assert cam.set_manual_exposure(5e7, 500) == {"exposure_us": pytest.approx(1e6), "gain": 128}
    assert cam.set_manual_exposure(1, -4) == {"exposure_us": pytest.approx(100), "gain": 0}
    with pytest.raises(DeviceError, match="finite"):
        cam.set_manual_exposure(float("nan"), 1)
    cam.set_auto_exposure(True)
    assert rig.sensor.get_option(rs.option.enable_auto_exposure) == 1 and cam.settings()["manual_exposure"] is False


def test_manual_exposure_switches_auto_exposure_off_before_setting_values(rig):
    """On the D4xx the exposure is only valid in manual mode: the driver never writes (or reads) it while
    auto exposure is on. A sensor that refuses exposure writes in auto mode proves the order."""
    from drivers.realsense import RealSenseCamera as Cam

    calls = []

    class Recording:
        def __init__(self, sensor):
            self._s = sensor

        def __getattr__(self, name):
            return getattr(self._s, name)

        def set_option(self, opt, value):
            calls.append((opt, value, self._s.get_option(rs.option.enable_auto_exposure)))
            if opt in (rs.option.exposure, rs.option.gain) and self._s.get_option(rs.option.enable_auto_exposure):
                raise RuntimeError("exposure can only be set in manual mode")
            return self._s.set_option(opt, value)

    cam = Cam(width=64, height=48, fps=30, context=rig)
    cam.start()
    try:
        cam._sensor = Recording(cam._sensor)
        cam.set_manual_exposure(10000, 16)
        assert calls[0][:2] == (rs.option.enable_auto_exposure, 0.0)
        assert [c[0] for c in calls[1:]] == [rs.option.exposure, rs.option.gain]
        assert all(c[2] == 0 for c in calls[1:])  # auto exposure already off when they were written
    finally:
        cam._sensor = cam._sensor._s
        cam.stop()


def test_the_emitter_is_switched_off_at_start(rig):
    assert rig.depth.get_option(rs.option.emitter_enabled) == 1  # as a D455 comes up
    cam = RealSenseCamera(width=64, height=48, fps=30, context=rig)
    cam.start()
    try:
        assert rig.depth.get_option(rs.option.emitter_enabled) == 0
        assert cam.settings()["emitter_enabled"] is False
        cam.set_emitter(True)
        assert rig.depth.get_option(rs.option.emitter_enabled) == 1
    finally:
        cam.stop()
    # a device without a stereo module: nothing to switch, no error
    bare = SoftwareRealSense(with_emitter=False)
    cam = RealSenseCamera(width=64, height=48, fps=30, context=bare)
    cam.start()
    try:
        cam.set_emitter(False)
        assert cam.settings()["emitter_enabled"] is None
    finally:
        cam.stop()


# ---- frame times ---------------------------------------------------------------------------------------

def test_exposure_start_from_global_time_and_exposure_metadata(rig, cam):
    """A global-time frame: its timestamp (host system clock, ms) marks the start of readout; with the
    exposure metadata the driver places the exposure start on the monotonic clock."""
    wall_minus_mono = time.time() - time.monotonic()
    t_end = time.monotonic() - 0.010  # readout began 10 ms ago, after an exposure of 20 ms
    f = push_and_get(rig, cam, numbered_image(1), 1, (t_end + wall_minus_mono) * 1000, domain="global_time",
                     metadata={"actual_exposure": 200})
    assert f.meta["exposure_start_source"] == "global_time"
    assert f.exposure_start_s == pytest.approx(t_end - 0.020, abs=0.002)
    # with frame_timestamp (readout) and sensor_timestamp (middle of exposure), that one counts
    g = push_and_get(rig, cam, numbered_image(2), 2, (t_end + 0.033 + wall_minus_mono) * 1000, domain="global_time",
                     metadata={"actual_exposure": 200, "frame_timestamp": 1_000_000, "sensor_timestamp": 985_000},
                     newer_than=f.frame_number)
    assert g.exposure_start_s == pytest.approx(t_end + 0.033 - 0.015 - 0.010, abs=0.002)


def test_exposure_start_on_the_hardware_clock_is_never_after_arrival_and_keeps_order(rig, cam):
    cam.set_manual_exposure(5000, 16)
    starts, last = [], None
    for k in range(6):
        f = push_and_get(rig, cam, numbered_image(k), 10 + k, 7000.0 + 33.3 * k, newer_than=last)
        assert f.meta["exposure_start_source"] == "hardware_clock"
        # the exposure (5 ms) and a frame interval for readout come before the frame's arrival
        assert f.exposure_start_s <= f.meta["host_time_s"] - 0.005 - 1 / 30 + 1e-6
        starts.append(f.exposure_start_s)
        last = f.frame_number
        time.sleep(0.02)
    assert all(b > a for a, b in zip(starts, starts[1:]))


def test_a_frame_exposed_before_the_requested_time_is_never_handed_out(rig, cam):
    """get_frame(not_before_s=T) waits for a frame whose exposure began at or after T, even if newer
    frames keep arriving that were exposed before it."""
    wall_minus_mono = time.time() - time.monotonic()
    t0 = time.monotonic()
    visible = t0 + 0.3  # the projector's image counts as visible from here
    first = push_and_get(rig, cam, numbered_image(0), 1, (t0 + wall_minus_mono) * 1000, domain="global_time",
                         metadata={"actual_exposure": 100})
    # late frames: arriving after `visible`, but exposed before it (a long transfer queue)
    def late():
        time.sleep(0.35)
        for k in range(1, 4):
            rig.push(numbered_image(k), 1 + k, (visible - 0.05 + 0.01 * k + wall_minus_mono) * 1000,
                     domain="global_time", metadata={"actual_exposure": 100})
            time.sleep(0.03)
        rig.push(numbered_image(9), 9, (visible + 0.02 + wall_minus_mono) * 1000, domain="global_time",
                 metadata={"actual_exposure": 100})

    th = threading.Thread(target=late)
    th.start()
    f = cam.get_frame(3.0, newer_than=first.frame_number, not_before_s=visible)
    th.join()
    assert f.meta["device_frame_number"] == 9 and np.array_equal(f.image, numbered_image(9))
    assert f.exposure_start_s >= visible
    with pytest.raises(DeviceTimeout, match="exposed after"):
        cam.get_frame(0.3, not_before_s=time.monotonic() + 5)


# ---- intrinsics ----------------------------------------------------------------------------------------

D455_COEFFS = [-0.0565362684428692, 0.068201869726181, 0.0003659751964733, 0.000692575704306364, -0.0218431670218706]


def rs_intrinsics(model, coeffs, W=1280, H=800, fx=642.5, fy=641.8, cx=637.3, cy=402.6):
    i = rs.intrinsics()
    i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = W, H, fx, fy, cx, cy
    i.model, i.coeffs = model, list(coeffs)
    return i


def points_in_view(intr, n, rng):
    """3D points whose librealsense projections fall inside the image."""
    uv = rng.uniform([0, 0], [intr.width - 1, intr.height - 1], (n, 2))
    xy = np.column_stack([(uv[:, 0] - intr.ppx) / intr.fx, (uv[:, 1] - intr.ppy) / intr.fy])
    # radial distortion here is small: undistorted ~ distorted; keep points inside by a margin
    X = np.column_stack([xy * 0.97, np.ones(n)])
    return X * rng.uniform(0.3, 4.0, (n, 1))


def rs_project(intr, X):
    return np.array([rs.rs2_project_point_to_pixel(intr, [float(v) for v in x]) for x in X])


def test_numpy_reimplementation_matches_librealsense(rng):
    for model, coeffs in ((rs.distortion.brown_conrady, D455_COEFFS), (rs.distortion.modified_brown_conrady, D455_COEFFS),
                          (rs.distortion.inverse_brown_conrady, [0.1, -0.2, 0.01, -0.02, 0.05]),
                          (rs.distortion.kannala_brandt4, [0.01, -0.005, 0.001, 0.0005, 0]),
                          (rs.distortion.ftheta, [0.9, 0, 0, 0, 0]), (rs.distortion.none, D455_COEFFS)):
        intr = rs_intrinsics(model, coeffs)
        X = points_in_view(intr, 300, rng)
        mine = rs_distort_normalized(model, coeffs, X[:, :2] / X[:, 2:]) * [intr.fx, intr.fy] + [intr.ppx, intr.ppy]
        assert np.abs(mine - rs_project(intr, X)).max() < 2e-3, model  # librealsense computes in float32


def test_brown_conrady_is_exact(rng):
    intr = rs_intrinsics(rs.distortion.brown_conrady, D455_COEFFS)
    conv = convert_intrinsics(intr)
    assert conv.method == "exact" and conv.max_error_px == 0
    assert np.allclose(conv.model.dist, np.float32(D455_COEFFS))  # same order [k1, k2, p1, p2, k3]
    assert conv.model.K[0, 0] == pytest.approx(642.5) and conv.model.cx == pytest.approx(637.3)
    X = points_in_view(intr, 2000, rng)
    assert np.abs(conv.model.project(X) - rs_project(intr, X)).max() < 2e-3


def test_brown_conrady_coefficients_are_not_permuted(rng):
    """Strong tangential terms: swapping p1/p2 or k3 into another slot would be off by pixels."""
    coeffs = [0.12, -0.25, 0.004, -0.006, 0.09]
    intr = rs_intrinsics(rs.distortion.brown_conrady, coeffs)
    X = points_in_view(intr, 500, rng)
    ref = rs_project(intr, X)
    good = convert_intrinsics(intr).model
    assert np.abs(good.project(X) - ref).max() < 2e-3
    swapped = good.with_params(dist=[0.12, -0.25, -0.006, 0.004, 0.09])
    assert np.abs(swapped.project(X) - ref).max() > 1.0


@pytest.mark.parametrize("model", [rs.distortion.modified_brown_conrady, rs.distortion.inverse_brown_conrady])
def test_modified_and_inverse_brown_conrady_are_fitted_within_tolerance(model, rng):
    intr = rs_intrinsics(model, D455_COEFFS)  # what a D455 reports for its colour stream
    conv = convert_intrinsics(intr)
    assert conv.method == "fit-5" and 0 < conv.max_error_px < 0.05
    X = points_in_view(intr, 2000, rng)
    assert np.abs(conv.model.project(X) - rs_project(intr, X)).max() < 0.05
    # for D455-sized coefficients the fit is the coefficients themselves, nearly
    assert np.abs(conv.model.dist - D455_COEFFS).max() < 2e-5
    # without tangential terms the modified formula is OpenCV's: exact
    radial = rs_intrinsics(model, [D455_COEFFS[0], D455_COEFFS[1], 0, 0, D455_COEFFS[4]])
    assert convert_intrinsics(radial).method == "exact"


def test_modified_model_with_strong_tangential_terms_is_refused_or_fitted_to_a_tolerance(rng):
    """librealsense's modified formula has tangential x radial cross terms OpenCV's model lacks: with
    strong tangential distortion the best OpenCV model is ~0.09 px off, refused at the default
    0.05 px, accepted (and better than reading the coefficients as OpenCV's) at 0.15 px."""
    intr = rs_intrinsics(rs.distortion.modified_brown_conrady, [0.05, -0.05, 0.002, -0.002, 0.01])
    with pytest.raises(IntrinsicsConversionError, match="no OpenCV equivalent.*off by 0.0[6-9]"):
        convert_intrinsics(intr)
    conv = convert_intrinsics(intr, tolerance_px=0.15)
    assert conv.method.startswith("fit") and 0.05 < conv.max_error_px < 0.15
    X = points_in_view(intr, 1000, rng)
    ref = rs_project(intr, X)
    err = np.abs(conv.model.project(X) - ref).max()
    naive = convert_intrinsics(rs_intrinsics(rs.distortion.brown_conrady, intr.coeffs)).model
    assert err < 0.15 and err < np.abs(naive.project(X) - ref).max()


def test_fisheye_models_fit_when_possible_and_fail_clearly_otherwise(rng):
    mild = rs_intrinsics(rs.distortion.kannala_brandt4, [-0.0077, 0.045, -0.043, 0.008, 0], fx=700, fy=700, cx=639.5, cy=399.5)
    conv = convert_intrinsics(mild)
    assert conv.method in ("fit-5", "fit-8") and conv.max_error_px < 0.05
    X = points_in_view(mild, 1000, rng)
    assert np.abs(conv.model.project(X) - rs_project(mild, X)).max() < 0.05
    wide = rs_intrinsics(rs.distortion.kannala_brandt4, [-0.0077, 0.045, -0.043, 0.008, 0], W=848, H=800, fx=285, fy=285, cx=424, cy=400)
    with pytest.raises(IntrinsicsConversionError, match="kannala_brandt4.*calibrate the camera|kannala_brandt4.*Calibrate the camera"):
        convert_intrinsics(wide)
    semi = rs_intrinsics(rs.distortion.kannala_brandt4, [0, 0, 0, 0, 0], fx=500, fy=500, cx=639.5, cy=399.5)
    with pytest.raises(IntrinsicsConversionError, match="no OpenCV equivalent"):
        convert_intrinsics(semi)
    with pytest.raises(IntrinsicsConversionError, match="ftheta"):
        convert_intrinsics(rs_intrinsics(rs.distortion.ftheta, [0.9, 0, 0, 0, 0], W=848, H=800, fx=285, fy=285, cx=424, cy=400))


def test_factory_intrinsics_come_from_the_stream_profile(rng):
    intr = rs_intrinsics(rs.distortion.inverse_brown_conrady, D455_COEFFS)
    rig = SoftwareRealSense(1280, 800, 30, intrinsics=intr)
    cam = RealSenseCamera(width=1280, height=800, fps=30, context=rig)
    model = cam.factory_intrinsics()  # works before start(): reads the profile only
    assert model.size == (1280, 800)
    X = points_in_view(intr, 500, rng)
    assert np.abs(model.project(X) - rs_project(intr, X)).max() < 0.05
    assert cam.intrinsics_conversion().to_dict()["source_model"] == "inverse_brown_conrady"
