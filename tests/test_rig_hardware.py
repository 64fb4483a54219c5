"""The hardware side of the rig, without hardware: `--rig sim-realsense` (the simulated world through
drivers/realsense.py and librealsense's software device), the projector's screen checks under Xvfb and
`procam devices`."""

import json
import time

import numpy as np
import pyrealsense2 as rs
import pytest

from _station_helpers import run_procam
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

    def set_auto_exposure(self, enabled):
        self.calls.append(("auto", bool(enabled)))

    def set_manual_exposure(self, exposure_us, gain):
        self.calls.append(("manual", float(exposure_us), float(gain)))
        return {"exposure_us": exposure_us, "gain": gain}

    def set_emitter(self, enabled):
        self.calls.append(("emitter", bool(enabled)))


@pytest.fixture
def sim_rig():
    from drivers.sim.rig import open_sim_rig

    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live")
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
        f = cam.get_frame(5.0, newer_than=cam.get_frame(5.0).frame_number)
        assert sim_cam.calls[-1] == ("manual", applied["exposure_us"], applied["gain"]) == ("manual", 8300.0, 21.0)
        # the frame carries the exposure it was taken with, as D455 metadata (100 us units)
        assert f.meta["actual_exposure_us"] == pytest.approx(8300)
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
def test_a_whole_session_runs_through_the_realsense_driver(tmp_path):
    out = tmp_path / "S"
    r = run_procam("session", "--rig", "sim-realsense", "--auto", "--poses-per-position", "2",
                   "--mirror-captures", "6", "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "camera through the RealSense driver" in r.stdout and "verification PASSED" in r.stdout
    man = json.loads((out / "session.json").read_text())
    assert man["state"]["rig_request"]["kind"] == "sim-realsense"
    settings = man["rig"]["camera_settings"]
    assert settings["driver"] == "realsense" and settings["emitter_enabled"] is False
    from calib.metrics import compare
    from calib.result import CalibrationResult

    m = compare(CalibrationResult.load_json(out / "calibration.json"),
                CalibrationResult.load_json(out / "ground_truth.json"))
    assert m.distance < 0.5 and m.angle_deg < 0.05 and m.proj_k_px < 1.0
    assert json.loads((out / "verification.json").read_text())["passed"] is True
