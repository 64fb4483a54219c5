"""The simulated rig made as unkind as the hardware, fault by fault
(drivers/sim/faults.py, `--sim-faults`), and the driver path working under each. Everything goes
through the RealSense driver on librealsense's software device (`--rig sim-realsense`)."""

import numpy as np
import pytest

from _station_helpers import run_procam
from calib.errors import SpecError
from drivers.base import Frame
from drivers.exposure import search_exposure
from drivers.factory import open_rig
from drivers.projector_images import white
from drivers.sim.faults import FAULTS, parse_faults
from drivers.sim.realsense_bridge import SimRealSenseCamera, SimRealSenseDevice

SCENE = "nonoverlap-136"
DIM_ROOM = {"ambient": 0.002, "background": False, "background_level": 0.002}  # only the projector lights the board


def _lit(rig, image=None):
    W, H = rig.projector.size
    rig.projector.wait_presented(rig.projector.show(white((W, H)) if image is None else image))
    rig.projector.clock.sleep(0.3)  # longer than the latency: the light is on the board


# ---- the registry and the option ----------------------------------------------------------------------
def test_faults_are_parsed_from_one_registry_and_listed_in_every_rig_commands_help():
    assert parse_faults("all") == frozenset(FAULTS)
    assert parse_faults("no-metadata, apply-lag") == {"no-metadata", "apply-lag"}
    assert parse_faults(None) == frozenset()
    with pytest.raises(SpecError, match="--sim-faults: unknown fault.*bogus.*no-metadata"):
        parse_faults("no-metadata,bogus")
    for command in ("session", "station", "verify", "recalibrate"):
        text = run_procam(command, "--help", timeout=120).stdout.replace("\n", " ").replace(" ", "")
        assert all(name.replace(" ", "") in text for name in FAULTS), command


def test_a_bad_fault_name_is_one_line_and_creates_nothing(tmp_path):
    r = run_procam("session", "--rig", "sim", "--sim-faults", "slow", "--auto", "--out", str(tmp_path / "s"))
    assert r.returncode == 2 and "--sim-faults: unknown fault(s) slow" in r.stderr
    assert not (tmp_path / "s").exists()


def test_hardware_faults_change_the_simulated_hardware():
    rig = open_rig("sim", scenario=SCENE, seed=0, latency_ms=100.0, faults=parse_faults("apply-lag,latency-jitter"))
    try:
        assert rig.hardware.settings_lag_frames == 5.0
        assert rig.hardware.jitter_ms == pytest.approx(1000.0 / rig.projector.refresh_hz)
        lat = [rig.projector.timeline.latency_s(t) for t in range(200)]
        assert max(lat) - min(lat) > 1.5 / rig.projector.refresh_hz  # a refresh period either side
    finally:
        rig.close()


def test_no_metadata_frames_carry_neither_exposure_nor_gain_nor_sensor_times():
    for faults, has in ((frozenset(), True), (parse_faults("no-metadata"), False)):
        rig = open_rig("sim-realsense", scenario=SCENE, seed=0, faults=faults)
        try:
            rig.camera.start()
            f = rig.camera.get_frame(5.0)
            keys = {"actual_exposure_us", "gain", "frame_timestamp_us", "sensor_timestamp_us"}
            assert (keys <= set(f.meta)) is has and (not keys & set(f.meta)) is (not has)
        finally:
            rig.close()


# ---- defect 2: the gain can rise from the D455's 0 ---------------------------------------------------------
def test_the_exposure_search_raises_a_gain_that_starts_at_zero():
    """The D455's colour gain runs 0..128: a search that scales the gain multiplicatively from the minimum
    stays at 0 and leaves a dim board dim."""
    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, **DIM_ROOM, projector_gain=0.04)
    try:
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)  # the board in the projector's light
        assert rig.camera.exposure_limits()["gain"][0] == 0.0
        _lit(rig)
        c = search_exposure(rig.camera, rig.projector.refresh_hz)
        assert c.gain > 16 and not c.dim and c.level >= 0.7 * 200
    finally:
        rig.close()


def test_a_board_too_dim_for_the_highest_gain_fails_the_rig_check(tmp_path):
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig as open_station_rig
    from app.station.station import Station

    req = RigRequest("sim-realsense", SCENE, 0)
    rig = open_station_rig(req, latency_ms=0.0, **DIM_ROOM, projector_gain=0.002)
    plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
    try:
        store = create_session(tmp_path / "s", rig, req, plan)
        checks = {c.name: c for c in Station(rig, make_machine(store, rig, plan)).check_rig()}
        assert not checks["camera exposure"].ok and "too dim" in checks["camera exposure"].detail
    finally:
        rig.close()


# ---- defect 5: metering ----------------------------------------------------------------------------------
class Altered:
    """The simulated camera with its images changed as a real scene would change them (what the
    software device then delivers through librealsense): `alter(image) -> image`."""

    def __init__(self, cam, alter):
        self._cam, self._alter = cam, alter

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def get_frame(self, *a, **k):
        f = self._cam.get_frame(*a, **k)
        return Frame(self._alter(f.image), f.frame_number, f.timestamp_ms, f.meta, f.exposure_start_s)


def _reddish(img):
    out = np.array(img, dtype=np.float32)
    out[:, :, 2] *= 1.5  # a projector whose red is stronger than its green (BGR order)
    return np.clip(out, 0, 255).astype(np.uint8)


def _search_through(rig, alter):
    dev = SimRealSenseDevice(Altered(rig.camera, alter))
    cam = SimRealSenseCamera(dev)
    cam.start()
    try:
        _lit(rig)
        c = search_exposure(cam, rig.projector.refresh_hz)
        return c, cam.get_frame(5.0, newer_than=cam.get_frame(5.0).frame_number).image
    finally:
        cam.stop()


@pytest.fixture
def host_clock_rig():
    from drivers.clock import MONOTONIC
    from drivers.sim.rig import open_sim_rig

    rig = open_sim_rig(SCENE, seed=0, quality="live", clock=MONOTONIC, latency_ms=0.0)
    rig.camera.start()
    yield rig
    rig.close()


def test_a_saturating_red_channel_is_metered(host_clock_rig):
    c, img = _search_through(host_clock_rig, _reddish)
    assert (img[:, :, 2] >= 254).mean() < 1e-3, c


# ---- defect 3: latency jitter measured on the RealSense path ----------------------------------------------
def test_the_settle_measurement_reads_the_exposure_the_realsense_driver_records():
    """The partial-frame timing needs each frame's exposure: the RealSense driver records it as
    `actual_exposure_us` (through librealsense's metadata), which the settle measurement must read."""
    from drivers.settle import _exposure_s

    rig = open_rig("sim-realsense", scenario=SCENE, seed=0)
    try:
        rig.camera.start()
        applied = rig.camera.set_manual_exposure(16700, 16)
        f = rig.camera.get_frame(5.0)
        for _ in range(12):  # until the frames show the change
            if f.meta.get("actual_exposure_us") == applied["exposure_us"]:
                break
            f = rig.camera.get_frame(5.0, newer_than=f.frame_number)
        assert "exposure_us" not in f.meta and _exposure_s(f) == pytest.approx(applied["exposure_us"] * 1e-6)
    finally:
        rig.close()


# ---- defect 4: white balance and auto exposure priority ---------------------------------------------------
def test_the_driver_fixes_the_white_balance_and_clears_auto_exposure_priority():
    """A D455 starts with auto white balance on: its colour gains drift as the projected image changes.
    The driver turns it off (and auto exposure priority, which may halve the frame rate) at start."""
    rs = pytest.importorskip("pyrealsense2")
    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, faults=parse_faults("auto-white-balance"))
    try:
        rig.camera.start()
        colour = rig.device.colour
        assert colour.get_option(rs.option.enable_auto_white_balance) == 0
        assert colour.get_option(rs.option.auto_exposure_priority) == 0
        s = rig.camera.settings()
        assert s["auto_white_balance"] is False and s["auto_exposure_priority"] is False
        f = rig.camera.get_frame(5.0)
        for _ in range(4):
            f = rig.camera.get_frame(5.0, newer_than=f.frame_number)
            means = f.image.reshape(-1, 3).mean(axis=0)
            assert np.ptp(means) < 0.5, means  # the simulated camera's grey, untinted
    finally:
        rig.close()


# ---- defect 1: a change confirmed from the frames when they carry no metadata ------------------------------
def _taken_with(rig, frame) -> dict:
    """The settings the simulated camera really took a frame (handed out by the driver) with."""
    sim_cam = rig.sim.camera
    n = rig.camera.device_numbers[frame.frame_number]
    return sim_cam.settings_timeline.at(sim_cam.exposure_start_s(n))


def test_without_metadata_a_change_is_confirmed_by_a_measured_lag_not_by_time_alone():
    """No metadata and a 5-frame apply lag: the frames exposed just after a write still have the old
    exposure and gain, and nothing in them says so. The lag is measured from brightness steps, and every
    wait after a change (apply_exposure, the search's measurements) then hands out only frames really
    taken with the new settings."""
    from drivers.exposure import ChangeEvidence, apply_exposure, measure_settings_lag

    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, latency_ms=0.0,
                   faults=parse_faults("no-metadata,apply-lag"))
    try:
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)
        W, H = rig.projector.size
        _lit(rig, rig.scenario.pattern.render(W, H, 6)[0])
        timing = measure_settings_lag(rig.camera, rig.projector.refresh_hz)
        assert timing.evidence is ChangeEvidence.MEASURED_LAG and len(timing.steps_s) == 2
        # frames are timed on the host's clock, up to an exposure early: the lag comes out a little shorter
        # than the 5 frames in time, never as short as the 3 frames the search waits
        assert timing.lag_s > 4 * rig.sim.hardware.period_s
        for exposure_us, gain in ((8300, 16), (16700, 48), (4100, 96), (16700, 16)):
            applied, f = apply_exposure(rig.camera, exposure_us, gain, timing=timing)
            got = _taken_with(rig, f)
            assert got["exposure_us"] == applied["exposure_us"], (applied, got)
            assert got["gain"] == pytest.approx(rig.device.sim_gain(applied["gain"])), (applied, got)
        c = search_exposure(rig.camera, rig.projector.refresh_hz)
        assert c.timing.evidence is ChangeEvidence.MEASURED_LAG
        # the level the search believes is the level of the frames taken with its choice
        f = rig.camera.get_frame(5.0)
        for _ in range(3):
            f = rig.camera.get_frame(5.0, newer_than=f.frame_number)
        assert _taken_with(rig, f)["exposure_us"] == c.exposure_us
        top = float(np.percentile(f.image.max(axis=2), 99.99))
        assert abs(top - c.level) < 8, (top, c)
    finally:
        rig.close()


def test_the_rig_check_says_and_records_how_the_camera_is_timed(tmp_path):
    """The rig check's findings (the panel's line and the log) and session.json name the clock the
    frames are timed by and how a change is confirmed: metadata, or a lag measured on a camera without
    it; through the emulation without metadata the measured tone curve is the simulated camera's."""
    from app.station.activity import CHECK_RIG_NAME
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig as open_station_rig
    from app.station.station import Station

    plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
    for faults, clock, confirmed in (("", "device clock", "frame metadata"),
                                     ("no-metadata,apply-lag", "host clock", "measured lag")):
        req = RigRequest("sim-realsense", SCENE, 0)
        rig = open_station_rig(req, latency_ms=0.0, faults=parse_faults(faults))
        try:
            store = create_session(tmp_path / (faults or "none"), rig, req, plan)
            machine = make_machine(store, rig, plan)
            st = Station(rig, machine)
            checks = {c.name: c for c in st.check_rig()}
            assert all(c.ok for c in checks.values()), checks
            timing = store.manifest.rig.camera_settings["timing"]
            assert timing["frame_times"] == clock and timing["settings_confirmed_by"] == confirmed
            outcome = st.activities.get(CHECK_RIG_NAME).outcome
            assert f"camera timing: frame times from the {clock}" in outcome
            assert any(f"camera timing ok: frame times from the {clock}" in e.text for e in machine.events)
            gamma = store.manifest.rig.camera_settings["response"]["gamma"]
            assert gamma == pytest.approx(rig.sim.settings.camera_gamma, abs=0.1)
            if confirmed == "measured lag":
                assert timing["lag_ms"] > 4 * 1000 * rig.sim.hardware.period_s
            # the raw evidence: every frame the check used, at 1/8 size, with its metadata
            import json

            import cv2

            doc = json.loads((store.folder / "rig_check" / "frames.json").read_text())
            assert len(doc["frames"]) > 30 and doc["shrink"] == 8
            last = doc["frames"][-1]
            img = cv2.imread(str(store.folder / "rig_check" / last["image"]))
            assert img.shape[:2] == (100, 160) and last["exposure_start_s"] is not None
            has_meta = "actual_exposure_us" in last["meta"]
            assert has_meta is (confirmed == "frame metadata")
            assert last["meta"]["exposure_start_source"] == ("global_time" if has_meta else "system_time")
        finally:
            rig.close()


# ---- defect 6: a stalled stream is reset, frame-number gaps are counted --------------------------------------
def test_a_stalled_stream_is_reset_and_the_frames_lost_before_it_are_counted():
    """The stall fault: the software D455 drops 3 frame numbers, then sends nothing until it is reset.
    The driver, finding no frame for stall_reset_s with the device still listed, calls hardware_reset,
    reopens it with its exposure re-applied and says so (StreamReset); frames come again, and the gap
    is counted in settings()["frames"], which the rig check reports."""
    from app.station.rig_check import stream_findings
    from drivers.errors import StreamReset

    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, latency_ms=0.0, faults=parse_faults("stall"))
    try:
        rig.device.stall_after_frames = 20
        cam = rig.camera
        cam.start()
        cam.set_manual_exposure(16700, 16)
        f = cam.get_frame(5.0)
        got, resets = [f], []
        while len(got) < 40:
            try:
                f = cam.get_frame(3.0, newer_than=f.frame_number)
                got.append(f)
            except StreamReset as e:
                resets.append(str(e))
                assert len(resets) == 1, resets  # once reset, the stream goes on
        assert rig.device.resets == 1 and "was reset (hardware_reset" in resets[0]
        frames = cam.settings()["frames"]
        assert frames["resets"] == 1 and frames["gaps"] == 1 and frames["missing"] == 3, frames
        # the exposure is set again on the reopened device, and no frame taken before it shows is handed out
        assert rig.device.options()["exposure_us"] == 16700 and rig.device.options()["gain"] == 16
        assert frames["held_after_start"] > 0
        text = stream_findings(cam)
        assert "3 lost in 1 gap of the frame numbers" in text and "stalled and was reset (1x)" in text
    finally:
        rig.close()


# ---- defect 7: the camera's modes, a USB 2 link -----------------------------------------------------------
def test_on_a_usb2_link_the_camera_falls_back_to_a_listed_mode_and_the_rig_check_says_so(tmp_path):
    """Under the usb2 fault the software D455 lists its size at 15 and 5 fps only and reports a USB 2.1
    link: the default 1280x800@30 falls back to the fastest listed mode (no session could start before),
    --camera-mode picks a listed one and refuses another with the list, and the rig check's camera line
    names the link (its own line, among the findings)."""
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig as open_station_rig
    from app.station.station import Station
    from drivers.errors import DeviceError

    usb2 = parse_faults("usb2")
    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, latency_ms=0.0, faults=usb2)
    try:
        rig.camera.start()
        assert rig.camera.fps == 15 and rig.sim.hardware.fps == 15.0
        assert "USB 2.1 link" in rig.camera.link_note() and "1280x800@30 is not offered" in rig.camera.link_note()
        f = rig.camera.get_frame(5.0)
        g = rig.camera.get_frame(5.0, newer_than=f.frame_number)
        n = rig.camera.device_numbers  # the simulated camera's frames run at the stream's rate
        per_frame = (g.exposure_start_s - f.exposure_start_s) / (n[g.frame_number] - n[f.frame_number])
        assert per_frame == pytest.approx(1 / 15, abs=0.005)
        plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
        req = RigRequest("sim-realsense", SCENE, 0)
        store = create_session(tmp_path / "s", rig, req, plan)
        checks = {c.name: c for c in Station(rig, make_machine(store, rig, plan)).check_rig()}
        assert all(c.ok for c in checks.values()), checks
        assert "USB 2.1 link" in checks["camera link"].detail
        assert checks["camera exposure"].detail.startswith(("16700 us", "33300 us", "50000 us", "66700 us"))
    finally:
        rig.close()
    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, latency_ms=0.0, faults=usb2, camera_mode=(1280, 800, 5))
    try:
        rig.camera.start()
        assert rig.camera.fps == 5 and rig.camera.link_note().startswith("the camera is on a USB 2.1 link")
    finally:
        rig.close()
    with pytest.raises(DeviceError, match=r"1280x800@30 .*not offered.*available: 1280x800@15, 1280x800@5"):
        open_rig("sim-realsense", scenario=SCENE, seed=0, faults=usb2, camera_mode=(1280, 800, 30))


def test_camera_mode_option_is_checked_while_parsed(tmp_path):
    r = run_procam("session", "--rig", "sim-realsense", "--camera-mode", "1280x800", "--auto",
                   "--out", str(tmp_path / "s"))
    assert r.returncode == 2 and "--camera-mode" in r.stderr and "WIDTHxHEIGHT@FPS" in r.stderr
    assert not (tmp_path / "s").exists()


def test_without_metadata_frames_still_carry_the_exposure_the_settle_measurement_times_by():
    """No metadata: the driver marks each frame with the manual exposure it set (`exposure_us_set`), which
    the settle measurement reads to time a frame that caught the projector's change part-way (its
    jitter estimate needs it; without it the latency is timed by whole frames only)."""
    from drivers.settle import _exposure_s

    rig = open_rig("sim-realsense", scenario=SCENE, seed=0, latency_ms=0.0, faults=parse_faults("no-metadata"))
    try:
        rig.camera.start()
        f = rig.camera.get_frame(5.0)
        assert "exposure_us_set" not in f.meta and _exposure_s(f) is None  # auto exposure: nothing known
        applied = rig.camera.set_manual_exposure(16700, 16)
        f = rig.camera.get_frame(5.0, newer_than=f.frame_number)
        assert "actual_exposure_us" not in f.meta and f.meta["exposure_us_set"] == applied["exposure_us"]
        assert _exposure_s(f) == pytest.approx(applied["exposure_us"] * 1e-6)
    finally:
        rig.close()
