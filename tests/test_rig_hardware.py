"""The hardware side of the rig, without hardware: `--rig sim-realsense` (the simulated world through
drivers/realsense.py and librealsense's software device), the projector's screen checks under Xvfb and
`procam devices`."""

import json
import time

import numpy as np
import pyrealsense2 as rs
import pytest

from _station_helpers import assert_within_its_uncertainty, run_procam, tick_until_projector_captures
from drivers.base import ExposureControl
from drivers.errors import DeviceDisconnected
from drivers.factory import RIG_KINDS, open_rig
from drivers.realsense import RealSenseCamera
from drivers.sim.realsense_bridge import SimRealSenseCamera, SimRealSenseDevice, SimRealSenseRig


class RecordingExposure:
    """A simulated camera that implements ExposureControl and records what it is told (the bridge
    must forward the driver's option writes to it)."""

    def __init__(self, cam):
        self._cam = cam
        self.calls = []

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def exposure_limits(self):
        return {"exposure_us": (100.0, 1e6, 100.0), "gain": (0.0, 128.0, 1.0)}

    def _pass(self, name, *args):  # and on to the simulated camera, when it has exposure control itself
        fn = getattr(self._cam, name, None)
        return fn(*args) if callable(fn) else None

    def set_auto_exposure(self, enabled):
        self.calls.append(("auto", bool(enabled)))
        self._pass("set_auto_exposure", enabled)

    def set_manual_exposure(self, exposure_us, gain):
        self.calls.append(("manual", float(exposure_us), float(gain)))
        self._pass("set_manual_exposure", exposure_us, gain)
        return {"exposure_us": exposure_us, "gain": gain}

    def set_emitter(self, enabled):
        self.calls.append(("emitter", bool(enabled)))
        self._pass("set_emitter", enabled)


@pytest.fixture
def sim_rig():
    from drivers.sim.rig import open_sim_rig

    from drivers.clock import MONOTONIC

    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live", clock=MONOTONIC)  # librealsense's clock
    rig.camera.start()
    yield rig
    rig.close()


def test_sim_realsense_is_a_rig_kind_with_the_real_driver(sim_rig):
    assert "sim-realsense" in RIG_KINDS
    rig = open_rig("sim-realsense", scenario="nonoverlap-136", seed=0)
    try:
        assert isinstance(rig, SimRealSenseRig) and rig.kind == "sim-realsense"
        assert isinstance(rig.camera, RealSenseCamera)  # the driver's code, streaming from librealsense
        rig.camera.start()
        f = rig.camera.get_frame(5.0)
        assert f.image.shape == (800, 1280, 3) and f.meta["timestamp_domain"] == "global_time"
        assert f.meta["serial"] == "SIM-D455-0001"
        # the factory intrinsics come from the librealsense profile, i.e. the simulated camera's (float32)
        K = rig.camera.factory_intrinsics().K
        assert np.allclose(K, rig.scenario.rig.camera.K, atol=1e-3)
        assert rig.camera.settings()["emitter_enabled"] is False
    finally:
        rig.close()


def test_the_bridge_forwards_the_drivers_option_writes_to_the_simulated_camera(sim_rig):
    sim_cam = RecordingExposure(sim_rig.camera)
    assert isinstance(sim_cam, ExposureControl)
    dev = SimRealSenseDevice(sim_cam)
    cam = SimRealSenseCamera(dev)
    cam.start()
    try:
        cam.get_frame(5.0)
        # the driver switched the emitter off at start; the device started with auto exposure
        assert ("emitter", False) in sim_cam.calls and ("auto", True) in sim_cam.calls
        applied = cam.set_manual_exposure(8333, 20.6)
        assert applied == {"exposure_us": pytest.approx(8300), "gain": 21}
        # like a real camera, the new exposure shows in the frames a frame or two later (frames already
        # queued before the write come first: a loaded machine queues more of them, so allow a second's worth)
        f = cam.get_frame(5.0)
        for _ in range(30):
            f = cam.get_frame(5.0, newer_than=f.frame_number)
            if f.meta["actual_exposure_us"] == pytest.approx(8300):
                break
        # the frame carries the exposure it was taken with, as D455 metadata (100 us units)
        assert f.meta["actual_exposure_us"] == pytest.approx(8300)
        manual = [c for c in sim_cam.calls if c[0] == "manual"]
        assert manual[-1] == ("manual", 8300.0, 21.0) and sim_cam.calls[-1] == manual[-1]
        n = len(sim_cam.calls)
        cam.get_frame(5.0, newer_than=f.frame_number)
        assert len(sim_cam.calls) == n  # nothing changed, nothing forwarded again
    finally:
        cam.stop()


def test_the_bridge_renders_only_what_the_driver_hands_out(sim_rig):
    dev = SimRealSenseDevice(sim_rig.camera)
    cam = SimRealSenseCamera(dev)
    cam.start()
    try:
        last = None
        for _ in range(5):
            last = cam.get_frame(5.0, newer_than=last).frame_number
        pushed = cam.pushed
        assert 5 <= pushed <= 7
        time.sleep(0.5)  # nobody asks: nothing is rendered
        assert cam.pushed == pushed
    finally:
        cam.stop()


def test_exposure_start_is_ordered_and_a_frame_before_the_requested_time_is_never_handed_out(sim_rig):
    dev = SimRealSenseDevice(sim_rig.camera)
    cam = SimRealSenseCamera(dev)
    cam.start()
    try:
        f = cam.get_frame(5.0)
        starts = [f.exposure_start_s]
        for _ in range(4):
            f = cam.get_frame(5.0, newer_than=f.frame_number)
            starts.append(f.exposure_start_s)
        assert all(b > a for a, b in zip(starts, starts[1:]))
        t = time.monotonic() + 0.2
        g = cam.get_frame(5.0, not_before_s=t)
        assert g.exposure_start_s >= t and g.frame_number > f.frame_number
    finally:
        cam.stop()


def test_unplug_and_reconnect_through_the_bridge(sim_rig):
    dev = SimRealSenseDevice(sim_rig.camera)
    cam = SimRealSenseCamera(dev)
    cam.start()
    try:
        cam.set_manual_exposure(10000, 8)
        f = cam.get_frame(5.0)
        dev.unplug()
        with pytest.raises(DeviceDisconnected):
            cam.get_frame(2.0, newer_than=f.frame_number)
        dev.replug()  # a fresh device: emitter on, auto exposure on
        assert dev.depth.get_option(rs.option.emitter_enabled) == 1
        cam.reconnect(timeout_s=5.0)
        g = cam.get_frame(5.0, newer_than=f.frame_number)
        assert g.frame_number > f.frame_number
        assert dev.options() == {"auto_exposure": False, "exposure_us": 10000.0, "gain": 8.0,
                                 "emitter_enabled": False}
    finally:
        cam.stop()


@pytest.mark.slow
def test_captures_through_the_driver_show_only_the_image_recorded_for_them(tmp_path):
    """With a 150 ms projector latency, every capture and every verification frame that went through
    librealsense and the driver saw only the projector image recorded for it, for its whole exposure
    (the hardware-like simulator's own record, SimRig.frame_truth)."""
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig as open_station_rig
    from app.station.station import Station, StationOptions
    from app.verification import verify
    from calib.models.observations import STEP_PROJECTOR

    req = RigRequest("sim-realsense", "nonoverlap-136", 0)
    rig = open_station_rig(req, latency_ms=150.0)
    try:
        plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
        store = create_session(tmp_path / "s", rig, req, plan)
        m = make_machine(store, rig, plan)
        st = Station(rig, m, StationOptions(auto=False, follow_operator=True, auto_capture=True))
        checks = st.check_rig()
        assert all(c.ok for c in checks), checks
        tick_until_projector_captures(st, m, 3)
        assert len(m.captures_of(STEP_PROJECTOR)) >= 3
        numbers = rig.camera.device_numbers
        for c in m.manifest.captures:
            sim_n, ticket = numbers[c.meta["frame_number"]], c.meta["projector_ticket"]
            assert rig.sim.frame_truth[sim_n] == ((int(ticket), 1.0),), (c.id, rig.sim.frame_truth[sim_n], ticket)
        rig.operator.request_pose("verification", None, 0)
        rep = verify(rig.camera, rig.projector, None, rig.ground_truth(), grid=(3, 2))
        assert rep.passed, rep.summary()
        for fn, ticket in rep.settings["frames"]:
            sim_n = numbers[fn]
            assert rig.sim.frame_truth[sim_n] == ((int(ticket), 1.0),), (fn, rig.sim.frame_truth[sim_n], ticket)
    finally:
        rig.close()


@pytest.mark.slow
def test_a_whole_session_runs_through_the_realsense_driver(tmp_path):
    out = tmp_path / "S"
    r = run_procam("session", "--rig", "sim-realsense", "--auto", "--poses-per-position", "2",
                   "--mirror-captures", "6", "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "camera through the RealSense driver" in r.stdout and "verification PASSED" in r.stdout
    # before the rig check, the person is told what to do during it
    hint = r.stdout.index("Rig check (the simulated operator does it here): hold the board in the mirror")
    assert hint < r.stdout.index("Check rig: projector")
    man = json.loads((out / "session.json").read_text())
    assert man["state"]["rig_request"]["kind"] == "sim-realsense"
    settings = man["rig"]["camera_settings"]
    assert settings["driver"] == "realsense" and settings["emitter_enabled"] is False
    # a frame from the wrong image or a dropped exposure setting costs mm and px; one short live-quality
    # session on the photometric renderer scatters by itself as far as its own uncertainty says
    assert_within_its_uncertainty(out)
    assert json.loads((out / "verification.json").read_text())["passed"] is True
    # `procam verify` sets the camera as the session recorded it (as the station's exposure search records it)
    # (one refresh period at 60 Hz, which the D455's 100 us steps cannot hit exactly; the lowest gain)
    man["rig"]["camera_settings"].update({"auto_exposure": False, "exposure_us": 16666.7, "gain": 0.0,
                                          "emitter_enabled": False})
    (out / "session.json").write_text(json.dumps(man))
    v = run_procam("verify", str(out), "--rig", "sim-realsense", "--out", str(tmp_path / "v.json"), timeout=600)
    assert v.returncode == 0, v.stdout[-2000:] + v.stderr[-2000:]
    assert "camera: manual exposure 16700 us, gain 0 as the session recorded (recorded 16666.7 us" in v.stderr
    assert "emitter off" in v.stderr


def test_verify_applies_the_recorded_camera_settings_and_latency(sim_rig):
    from types import SimpleNamespace

    from app.commands.verify import apply_recorded, recorded_latency_s

    def manifest(settings):
        return SimpleNamespace(rig=SimpleNamespace(camera_settings=settings))

    assert recorded_latency_s(manifest({"projector": {"latency_ms": 85.5}})) == pytest.approx(0.0855)
    assert recorded_latency_s(manifest({"projector": {"latency_ms": "x"}})) is None
    assert recorded_latency_s(manifest({})) is None
    dev = SimRealSenseDevice(sim_rig.camera)
    cam = SimRealSenseCamera(dev)
    rig = SimpleNamespace(camera=cam, projector=sim_rig.projector)
    sim_rig.projector.settle_s = 0.0
    cam.start()
    try:
        cam.set_emitter(True)
        lines = apply_recorded(rig, manifest({"auto_exposure": False, "exposure_us": 12000.0, "gain": 4.0,
                                              "emitter_enabled": False, "projector": {"latency_ms": 85.5}}))
        assert dev.options() == {"auto_exposure": False, "exposure_us": 12000.0, "gain": 4.0, "emitter_enabled": False}
        assert lines[0] == "camera: manual exposure 12000 us, gain 4 as the session recorded; emitter off"
        assert sim_rig.projector.settle_s == pytest.approx(0.0855)
        assert lines[1] == "projector latency: 86 ms (as the session measured)"
        apply_recorded(rig, manifest({"auto_exposure": False, "exposure_us": 12000.0, "gain": 4.0,
                                      "projector": {"latency_ms": 85.5}}), settle_s=0.2)  # --settle wins
        assert sim_rig.projector.settle_s == pytest.approx(0.2)
    finally:
        cam.stop()


# ---- the projector's screen ------------------------------------------------------------------------------

from _drivers_helpers import run_python, xvfb  # noqa: E402
from drivers.errors import DeviceError  # noqa: E402
from drivers.projector_window import choose_projector_screen  # noqa: E402


def _screens(*specs):
    return [{"index": i, "name": n, "primary": p, "x": x, "y": 0, "width": w, "height": h, "refresh_hz": r}
            for i, (n, p, x, w, h, r) in enumerate(specs)]


def test_the_default_projector_screen_is_the_non_primary_one():
    laptop, projector = ("eDP-1", True, 0, 1920, 1080, 60.0), ("HDMI-1", False, 1920, 1920, 1080, 60.0)
    assert choose_projector_screen(_screens(laptop, projector)) == 1
    assert choose_projector_screen(_screens(projector, laptop)) == 0  # whatever order the outputs come in
    assert choose_projector_screen(_screens(laptop, projector), 0) == 0  # an explicit choice stands
    with pytest.raises(DeviceError, match=r"3 screens are connected: choose .*--projector-screen.*"
                                          r"0: eDP-1 1920x1080 at \(0, 0\), 60 Hz, primary; 1: HDMI-1"):
        choose_projector_screen(_screens(laptop, projector, ("DP-2", False, 3840, 1280, 720, 59.94)))
    with pytest.raises(DeviceError, match="no primary screen is set.*--projector-screen"):
        choose_projector_screen(_screens(("A", None, 0, 800, 600, None), ("B", None, 800, 800, 600, None)))
    with pytest.raises(DeviceError, match="there is no screen 2; the screens are 0: eDP-1"):
        choose_projector_screen(_screens(laptop, projector), 2)


SCREEN_CHECKS = r"""
import json, time
from pyglet.libs.x11 import xlib, xrandr
import drivers.projector_images as pi
from drivers.errors import DeviceError
from drivers.projector_window import ProjectorWindow

out = {}
other = xlib.XOpenDisplay(None)  # another X client (a window manager, a user) acting on our windows

def err(fn):
    try:
        fn()
        return None
    except DeviceError as e:
        return str(e)

def present(win, image=None):
    win.wait_presented(win.show(pi.white(win.size) if image is None else image), 3.0)

win = ProjectorWindow(None)  # one screen: it is the one
out["describe"] = win.describe()
out["refresh"] = [win.refresh_hz, win.refresh_hz_known]
present(win)
out["first_ok"] = win.fault is None
xlib.XMoveWindow(other, win._window._window, 100, 50)
xlib.XSync(other, False)
time.sleep(0.2)
out["moved"] = err(lambda: present(win, pi.black(win.size)))
out["moved_again"] = err(lambda: win.show(pi.black(win.size)))
win.close()

w2 = ProjectorWindow(None)
present(w2)
xlib.XUnmapWindow(other, w2._window._window)
xlib.XSync(other, False)
time.sleep(0.2)
out["hidden"] = err(lambda: present(w2))
w2.close()

w3 = ProjectorWindow(None)
present(w3)
w3.close()
out["closed"] = err(lambda: present(w3))

w4 = ProjectorWindow(None, output_check_s=0.0)
present(w4)
root = xlib.XDefaultRootWindow(other)
res = xrandr.XRRGetScreenResourcesCurrent(other, root)
crtc = res.contents.crtcs[0]
info = xrandr.XRRGetCrtcInfo(other, res, crtc).contents
xrandr.XRRSetCrtcConfig(other, res, crtc, xlib.CurrentTime, 0, 0, 0, info.rotation, None, 0)  # output off
xlib.XSync(other, False)
time.sleep(0.2)
out["vanished"] = err(lambda: present(w4))
w4.close()
print(json.dumps(out))
"""


def test_screen_checks_refuse_a_moved_hidden_or_closed_window_and_a_vanished_output():
    """A real pyglet window under Xvfb; another X client moves it off its screen's origin, unmaps it, or
    switches the output off (RandR): the next presentation fails with the reason."""
    with xvfb((1280, 720)) as display:
        r = run_python(SCREEN_CHECKS, display)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    d = out["describe"]
    assert (d["index"], d["name"], d["x"], d["y"], d["width"], d["height"]) == (0, "screen", 0, 0, 1280, 720)
    assert d["window_size"] == [1280, 720] and d["fullscreen"] is True
    assert out["refresh"] == [60.0, False]  # Xvfb reports no refresh rate
    assert out["first_ok"]
    assert "is at (100, 50) but its screen screen starts at (0, 0)" in out["moved"]
    assert out["moved_again"] == out["moved"]  # the window stays refused
    assert "not visible" in out["hidden"]
    assert "closed" in out["closed"]
    assert "output screen (1280x720 at (0, 0)) is gone" in out["vanished"]


# ---- procam devices and its messages -----------------------------------------------------------------------

def test_devices_lists_outputs_with_name_primary_resolution_position_refresh():
    with xvfb((1280, 720)) as display:
        r = run_procam("devices", env_extra={"DISPLAY": display}, timeout=120)
        j = run_procam("devices", "--json", env_extra={"DISPLAY": display}, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "0: screen 1280x720 at (0, 0), refresh rate unknown  <- projector (default)" in r.stdout
    found = json.loads(j.stdout)
    (s,) = found["screens"]
    assert s == {"index": 0, "name": "screen", "primary": False, "x": 0, "y": 0, "width": 1280, "height": 720,
                 "refresh_hz": None}
    assert found["projector_screen"] == 0


def test_devices_messages_say_what_to_fix(tmp_path):
    no_display = run_procam("devices", env_extra={"DISPLAY": ""}, timeout=120)
    assert "no display available: no display available" not in no_display.stdout
    assert "DISPLAY is not set" in no_display.stdout
    unreachable = run_procam("devices", env_extra={"DISPLAY": ":987"}, timeout=120)
    assert "DISPLAY=:987 cannot be reached" in unreachable.stdout and "None" not in unreachable.stdout
    # pyrealsense2 failing to load its libusb, as on a machine without Debian's libusb-1.0-0
    fake = tmp_path / "pyrealsense2"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('libusb-1.0.so.0: cannot open shared object file: "
                                      "No such file or directory')\n")
    import os

    from _station_helpers import REPO

    env = {"PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)]), "DISPLAY": ""}
    r = run_procam("devices", env_extra=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "apt-get install libusb-1.0-0" in r.stdout and "libusb-1.0.so.0" in r.stdout


def test_exposure_search_through_the_driver_fits_the_frame_and_whole_periods_within_a_step():
    """Through the RealSense driver the exposure range reaches 1 s and is set in 100 us steps: the
    search stays within one frame period (a longer exposure would lower the frame rate) and counts
    16700 us as one refresh period of a 60 Hz projector (the nearest step to 16667 us)."""
    from drivers.exposure import search_exposure
    from drivers.projector_images import white

    rig = open_rig("sim-realsense", scenario="nonoverlap-136", seed=0)
    try:
        rig.camera.start()
        lo, hi, step = rig.camera.exposure_limits()["exposure_us"]
        assert hi > 1e6 / rig.camera.fps and step == 100.0
        rig.projector.wait_presented(rig.projector.show(white(tuple(rig.projector.size))))
        c = search_exposure(rig.camera, rig.projector.refresh_hz)
        assert c.exposure_us <= 1e6 / rig.camera.fps
        assert c.exposure_us % step == 0 and c.whole_periods
        assert abs(c.periods - round(c.periods)) <= 0.5 * step / (1e6 / rig.projector.refresh_hz) + 1e-9
    finally:
        rig.close()
