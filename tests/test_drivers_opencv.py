"""Any camera OpenCV opens (drivers/opencv_camera.py), tested through cv2.VideoCapture itself: the simulated
camera served as a live MJPEG stream on 127.0.0.1 (drivers/sim/stream.py), its frames stamped with their
exposure start on the rig's simulated clock (drivers/frame_stamp.py). Only exposure and gain, which a
stream has not, go through the stream's side channel."""

import json
import time

import cv2
import numpy as np
import pytest

from _station_helpers import assert_within_its_uncertainty, run_procam
from drivers.base import CameraDriver, ExposureControl
from drivers.errors import DeviceDisconnected, DeviceError, ExposureUnsupported
from drivers.exposure import frames_after_change
from drivers.frame_stamp import FrameStamp, decode_stamp, encode_stamp, split_stamp, strip_rows
from drivers.opencv_camera import OpenCVCamera, list_opencv_cameras
from drivers.sim.stream import SimStreamCamera, open_sim_uvc_rig


@pytest.fixture
def rig():
    r = open_sim_uvc_rig("nonoverlap-136", seed=0, realtime=False)
    r.camera.start()
    yield r
    r.close()


def test_a_frame_stamp_survives_jpeg_and_a_damaged_one_is_refused():
    rng = np.random.default_rng(3)
    for width in (1280, 640, 424):
        for _ in range(5):
            s = FrameStamp(int(rng.integers(0, 2**31)), int(rng.integers(0, 2**62)),
                           round(float(rng.uniform(50, 33333)), 2), round(float(rng.uniform(0, 128)), 3))
            picture = rng.integers(0, 256, (480, width, 3), dtype=np.uint8)
            full = np.vstack([picture, encode_stamp(s, width)])
            assert full.shape[0] - 480 == strip_rows(width) and strip_rows(width) % 16 == 0
            ok, buf = cv2.imencode(".jpg", full, [cv2.IMWRITE_JPEG_QUALITY, 60])
            got_picture, got = split_stamp(cv2.imdecode(buf, cv2.IMREAD_COLOR))
            assert got == s and got_picture.shape == picture.shape
    strip = encode_stamp(FrameStamp(7, 10**12, 16667.0, 2.0), 1280)
    strip[:, 8 * 40:8 * 41] = 255 - strip[:, 8 * 40:8 * 41]  # one bit flipped: the checksum fails
    assert decode_stamp(strip) is None
    assert decode_stamp(np.zeros((16, 1280, 3), np.uint8)) is None


def test_frames_through_videocapture_carry_the_simulated_exposure_times(rig):
    cam = rig.camera
    assert isinstance(cam, CameraDriver) and isinstance(cam, ExposureControl)
    assert cam.size == rig.sim.camera.size and cam.backend == "FFMPEG"
    f = cam.get_frame(2.0)
    assert f.image.shape == (800, 1280, 3)
    last, seen = f.frame_number, []
    for _ in range(8):
        g = cam.get_frame(2.0, newer_than=last)
        assert g.frame_number > last
        last = g.frame_number
        n = g.meta["device_frame_number"]
        # the exposure start is the simulated camera's own, on the rig's clock, to the microsecond
        assert g.exposure_start_s == pytest.approx(rig.sim.camera.exposure_start_s(n), abs=1e-6)
        assert g.exposure_start_s <= rig.clock.now()
        seen.append(n)
    assert seen == sorted(set(seen))
    # while nobody waits, the stream repeats its last frame (a keep-alive): same stamp, dropped, never handed out
    accepted = cam.stats.accepted
    deadline = time.monotonic() + 30.0
    while cam.stats.duplicates == 0 and time.monotonic() < deadline:  # waits on state, not on a duration
        time.sleep(0.05)
    # (one new frame may have been in flight when the last caller stopped waiting)
    assert cam.stats.duplicates >= 1 and cam.stats.accepted <= accepted + 1
    assert cam.get_frame(2.0, newer_than=last).meta["device_frame_number"] > seen[-1]


def test_a_frame_gated_by_its_stamped_time_shows_only_the_new_image(rig):
    """The station's rule (a frame counts once its exposure began after the image became visible) holds
    through VideoCapture's buffering: the simulator's own record of what each frame saw."""
    cam, proj = rig.camera, rig.projector
    hw = rig.sim.hardware
    proj.settle_s = (hw.latency_ms + hw.jitter_ms) / 1000.0 + 0.005  # what the rig check measures, and a margin
    last = cam.get_frame(2.0).frame_number
    white = np.full((proj.size[1], proj.size[0]), 255, np.uint8)
    mixed = 0
    for k in range(4):
        ticket = proj.show(white if k % 2 == 0 else np.zeros_like(white))
        visible = proj.wait_presented(ticket)
        for _ in range(6):
            f = cam.get_frame(2.0, newer_than=last)
            last = f.frame_number
            truth = rig.sim.frame_truth[cam.device_numbers[f.frame_number]]
            if f.exposure_start_s >= visible:
                assert truth == ((ticket, 1.0),), (truth, ticket)
            elif truth != ((ticket, 1.0),):
                mixed += 1
    assert mixed > 0  # frames before the gate did show the old image: the gate had something to refuse


def test_manual_exposure_goes_through_the_side_channel_and_shows_in_the_frames(rig):
    cam = rig.camera
    lim = cam.exposure_limits()
    assert lim == {k: tuple(v) for k, v in rig.sim.camera.exposure_limits().items()}
    last = cam.get_frame(2.0).frame_number
    t_set = rig.clock.now()
    applied = cam.set_manual_exposure(8333.0, 2.5)
    assert applied == {"exposure_us": 8333.0, "gain": 2.5}
    assert rig.stream.forwarded[-1] == ("manual", (8333.0, 2.5))
    f, _, _ = frames_after_change(cam, t_set, applied, last, 2, 3.0)
    assert f.meta["exposure_us"] == pytest.approx(8333.0) and f.meta["gain"] == pytest.approx(2.5)
    assert cam.settings()["exposure_us"] == 8333.0
    assert cam.settings()["autofocus_off"] is False  # the stream has no focus to hold; a webcam says True


def test_a_camera_that_ignores_manual_exposure_is_named():
    r = open_sim_uvc_rig("nonoverlap-136", seed=0, realtime=False, faults=("ignores-exposure",))
    try:
        r.camera.start()
        with pytest.raises(ExposureUnsupported, match="ignores manual exposure.*reads back"):
            r.camera.set_manual_exposure(8333.0, 2.0)
        assert r.stream.forwarded == []
        # the stream's own properties (FFmpeg has none to set): refused
        plain = OpenCVCamera(r.stream.url, timing="stamp", clock=r.clock)
        with r.stream.hold():
            plain.start()
        try:
            with pytest.raises(ExposureUnsupported, match="FFMPEG backend has no exposure control"):
                plain.set_manual_exposure(8333.0, 2.0)
        finally:
            plain.stop()
    finally:
        r.close()


def test_an_unplugged_camera_is_a_device_error_and_reconnects(rig):
    cam = rig.camera
    last = cam.get_frame(2.0).frame_number
    rig.stream.unplug()
    with pytest.raises(DeviceDisconnected, match="unplugged.*plug it back in"):
        for _ in range(20):
            last = cam.get_frame(2.0, newer_than=last).frame_number
    with pytest.raises(DeviceDisconnected, match="did not come back"):
        cam.reconnect(timeout_s=0.5)
    rig.stream.replug()
    cam.reconnect(timeout_s=5.0)
    f = cam.get_frame(2.0, newer_than=last)
    assert f.frame_number > last


def test_the_station_says_the_camera_is_gone_and_takes_it_back(tmp_path):
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
    from app.station.station import Station, StationOptions

    req = RigRequest("sim-uvc", "nonoverlap-136", 0)
    rig = open_requested_rig(req, realtime=False)
    try:
        plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
        store = create_session(tmp_path / "s", rig, req, plan)
        m = make_machine(store, rig, plan)
        st = Station(rig, m, StationOptions(auto=False, follow_operator=True))
        assert st.tick() is not None and st.device_problem is None
        rig.stream.unplug()
        for _ in range(3):  # unplugged: every tick says so (a reconnect is tried each time)
            assert st.tick() is None
            assert st.device_problem.startswith("camera: camera http") and "plug it back in" in st.device_problem
        rig.stream.replug()
        view = None
        for _ in range(5):
            view = st.tick() or view
        assert view is not None and st.device_problem is None
        assert any("camera reconnected" in e.text for e in m.events)
    finally:
        rig.close()


def test_a_camera_index_that_does_not_exist_is_a_device_error():
    with pytest.raises(DeviceError, match="no camera at index 63.*procam devices"):
        OpenCVCamera(63).start()
    with pytest.raises(DeviceError, match="cannot open the camera source"):
        OpenCVCamera("http://127.0.0.1:9/none.mjpg", open_timeout_s=2.0).start()


def test_a_missing_camera_is_one_line_and_no_session_folder(tmp_path):
    out = tmp_path / "S"
    r = run_procam("session", "--rig", "uvc", "--camera", "63", "--board", "8x6:DICT_4X4_50:50:30", "--out", str(out),
                   timeout=120)
    assert r.returncode == 2 and not out.exists()
    assert r.stderr.strip().splitlines() == ["procam session: error: no camera at index 63 (or it is in use by another "
                                             "program): plug it in; `procam devices` lists the cameras OpenCV can open"]


@pytest.mark.parametrize("text, ok", [("0", 0), ("12", 12), ("http://127.0.0.1:8080/video", "http://127.0.0.1:8080/video"),
                                      ("100", None), ("", None), ("cam\x01", None)])
def test_the_camera_option_takes_an_index_or_a_url(text, ok):
    import argparse

    from app.commands._types import camera_source

    if ok is None:
        with pytest.raises(argparse.ArgumentTypeError, match="camera index from 0 to 99, or a URL"):
            camera_source(text)
    else:
        assert camera_source(text) == ok


def test_a_pre_calibration_asks_the_camera_for_its_size(rig, tmp_path):
    import argparse

    from app.commands.session import rig_options

    rig.sim.ground_truth().save_json(tmp_path / "calibration.json")
    args = argparse.Namespace(camera=rig.stream.url, projector_screen=None, settle_s=None,
                              camera_intrinsics=str(tmp_path / "calibration.json"))
    opts = rig_options(args, "uvc")
    assert (opts["width"], opts["height"]) == (1280, 800) and opts["intrinsics"].size == (1280, 800)
    assert "fps" not in opts and rig_options(argparse.Namespace(**vars(args), camera_fps=15.0), "uvc")["fps"] == 15.0
    # the stream's frames carry the stamp strip under the picture: another size than the pre-calibration's
    cam = OpenCVCamera(opts["camera"], opts["width"], opts["height"], intrinsics=opts["intrinsics"])
    with rig.stream.hold(), pytest.raises(DeviceError, match=r"delivers 1280x816 frames, not the 1280x800 asked for"):
        cam.start()
    cam = OpenCVCamera(opts["camera"], 1280, 800, timing="stamp", clock=rig.clock, intrinsics=opts["intrinsics"])
    with rig.stream.hold():
        cam.start()
    try:
        assert cam.factory_intrinsics() is opts["intrinsics"] and cam.size == (1280, 800)
    finally:
        cam.stop()


def test_the_rig_check_warns_about_a_camera_that_ignores_exposure_and_goes_on(tmp_path):
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
    from app.station.station import Station, StationOptions

    req = RigRequest("sim-uvc", "nonoverlap-136", 0)
    rig = open_requested_rig(req, realtime=False, faults=("ignores-exposure",))
    try:
        plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
        store = create_session(tmp_path / "s", rig, req, plan)
        st = Station(rig, make_machine(store, rig, plan), StationOptions(auto=False, follow_operator=True))
        checks = {c.name: c for c in st.check_rig()}
        assert all(c.ok for c in checks.values()), checks
        assert "WARNING" in checks["camera exposure"].detail and "ignores manual exposure" in checks["camera exposure"].detail
        # its auto exposure follows the dark-to-bright switch the latency is measured by: when that defeats
        # the measurement, a latency longer than projectors' is assumed, and said
        lat = checks["projector latency"]
        assert lat.ok and ("300 ms assumed" in lat.detail or lat.detail.startswith("latency ")), lat
        assert "camera response" not in checks  # no gains to bracket
        settings = store.manifest.rig.camera_settings
        assert settings["manual_exposure"] == "ignored by the camera"
        # the manifest records the latency to the microsecond
        assert settings["projector"]["latency_ms"] > 0
        assert rig.projector.settle_s == pytest.approx(settings["projector"]["latency_ms"] / 1000.0, abs=1e-6)
    finally:
        rig.close()


def test_opencv_cameras_are_listed(rig):
    found = list_opencv_cameras([rig.stream.url])
    assert found == [{"source": rig.stream.url, "backend": "FFMPEG", "width": 1280, "height": 800 + strip_rows(1280),
                      "fps": found[0]["fps"]}]
    assert list_opencv_cameras(["http://127.0.0.1:9/none.mjpg"]) == []
    r = run_procam("devices", "--json", timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert isinstance(out["opencv_cameras"], list)
    text = run_procam("devices", timeout=120)
    assert text.returncode == 0 and "OpenCV cameras (index for --rig uvc --camera):" in text.stdout


UVC_RIG_SCRIPT = r"""
import json
import sys
from drivers import projector_images as pi
from drivers.factory import open_rig
from drivers.projector_window import run_projector_loop
from drivers.sim.rig import open_sim_rig
from drivers.sim.stream import SimCameraStream

sim = open_sim_rig("nonoverlap-136", seed=0, realtime=False)
sim.camera.start()
stream = SimCameraStream(sim.camera)
with stream.hold():
    rig = open_rig("uvc", camera=stream.url, projector_screen=0, settle_s=0.05, fps=float(sys.argv[1]))
out = {"kind": rig.kind, "camera": type(rig.camera).__name__, "projector": type(rig.projector).__name__,
       "operator": type(rig.operator).__name__, "size": rig.camera.size, "timing": rig.camera.settings()["frame_timing"], "fps": rig.camera.fps}

def worker():
    t = rig.projector.wait_presented(rig.projector.show(pi.white(rig.projector.size)), 5.0)
    with stream.hold():
        f = rig.camera.get_frame(5.0)
    return {"presented": t > 0, "shape": list(f.image.shape), "source": f.meta["exposure_start_source"],
            "before_arrival_s": f.meta["host_time_s"] - f.exposure_start_s}

out.update(run_projector_loop(rig.projector, worker, close=False))
rig.close()
out["closed"] = rig.projector.closed and not rig.camera.running
stream.close()
sim.close()
print(json.dumps(out))
"""


@pytest.mark.display
def test_the_uvc_rig_combines_an_opencv_camera_with_the_projector_window():
    """`--rig uvc --camera URL`: the plain driver (frame times by arrival: an FFmpeg stream has no
    timestamps) and a real projector window under Xvfb."""
    from _drivers_helpers import run_python, xvfb

    with xvfb((1280, 720)) as display:
        r = run_python(UVC_RIG_SCRIPT, display, timeout=180, args=("10",))  # --camera-fps 10
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert (out["kind"], out["camera"], out["projector"], out["operator"]) == (
        "uvc", "OpenCVCamera", "ProjectorWindow", "HumanOperator")
    assert out["size"] == [1280, 800 + strip_rows(1280)] and out["timing"] == "arrival"  # the strip is picture here
    assert out["presented"] and out["shape"] == [800 + strip_rows(1280), 1280, 3] and out["source"] == "arrival"
    # an exposure (a whole frame period under auto exposure) and three frame periods before it arrived, at
    # the rate given (FFmpeg would say 25 fps for any MJPEG stream): never later than it could have begun
    assert out["fps"] == 10.0 and out["before_arrival_s"] == pytest.approx(0.4, abs=1e-6)
    assert out["closed"]


def test_the_station_runs_on_the_streamed_camera(tmp_path):
    from _station_helpers import StationProcess

    folder = tmp_path / "s"
    st = StationProcess("--rig", "sim-uvc", "--session", str(folder), timeout_s=180)
    try:
        man = json.loads((folder / "session.json").read_text())
        assert man["state"]["rig_request"]["kind"] == "sim-uvc"
        assert man["rig"]["camera_settings"]["driver"] == "opencv" and man["rig"]["driver"] == "sim-uvc"
        assert man["rig"]["camera"] == {"width": 1280, "height": 800}  # the picture, the stamp strip cropped off
        assert any("Simulated rig" in ln or "simulated rig" in ln for ln in st.lines), st.lines
    finally:
        st.stop()
    assert st.proc.returncode is not None


@pytest.mark.slow
def test_captures_through_the_stream_show_only_the_image_recorded_for_them(tmp_path):
    """A short session's captures through VideoCapture: each saw only its projector image for its whole
    exposure (SimRig.frame_truth), with the rig check's measured exposure, latency and response."""
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
    from app.station.station import Station, StationOptions
    from calib.models.observations import STEP_PROJECTOR
    from _station_helpers import tick_until_projector_captures

    req = RigRequest("sim-uvc", "nonoverlap-136", 0)
    rig = open_requested_rig(req, latency_ms=150.0, realtime=False)
    try:
        assert isinstance(rig.camera, SimStreamCamera)
        plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
        store = create_session(tmp_path / "s", rig, req, plan)
        m = make_machine(store, rig, plan)
        st = Station(rig, m, StationOptions(auto=False, follow_operator=True, auto_capture=True))
        checks = {c.name: c for c in st.check_rig()}
        assert all(c.ok for c in checks.values()), checks
        assert "gamma 2.2" in checks["camera response"].detail
        tick_until_projector_captures(st, m, 3)
        numbers = rig.camera.device_numbers
        for c in m.manifest.captures:
            sim_n, ticket = numbers[c.meta["frame_number"]], c.meta["projector_ticket"]
            assert rig.sim.frame_truth[sim_n] == ((int(ticket), 1.0),), (c.id, rig.sim.frame_truth[sim_n], ticket)
    finally:
        rig.close()


@pytest.mark.slow
def test_a_whole_session_runs_through_the_opencv_driver(tmp_path):
    out = tmp_path / "S"
    r = run_procam("session", "--rig", "sim-uvc", "--auto", "--poses-per-position", "2",
                   "--mirror-captures", "6", "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "camera through the OpenCV driver" in r.stdout and "verification PASSED" in r.stdout
    man = json.loads((out / "session.json").read_text())
    assert man["state"]["rig_request"]["kind"] == "sim-uvc"
    settings = man["rig"]["camera_settings"]
    assert settings["driver"] == "opencv" and settings["frame_timing"] == "stamp"
    assert settings["timing"]["frame_times"] == "device clock"  # the stamps carry the rig's own clock
    assert settings["auto_exposure"] is False and settings["response"]["source"] == "measured"
    # every capture's frame is the right image (the frame-truth test above); its accuracy is what one short
    # live-quality session's own uncertainty allows
    assert_within_its_uncertainty(out)
    assert json.loads((out / "verification.json").read_text())["passed"] is True


@pytest.mark.slow
def test_a_session_with_a_camera_that_ignores_exposure_goes_on_with_warnings(tmp_path):
    out = tmp_path / "S"
    r = run_procam("session", "--rig", "sim-uvc", "--sim-faults", "ignores-exposure", "--auto", "--poses-per-position",
                   "2", "--mirror-captures", "6", "--out", str(out), timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "rig check: camera exposure ok: WARNING: camera http" in r.stdout and "ignores manual exposure" in r.stdout
    assert "verification PASSED" in r.stdout
    settings = json.loads((out / "session.json").read_text())["rig"]["camera_settings"]
    assert settings["manual_exposure"] == "ignored by the camera" and "response" not in settings
    v = run_procam("verify", str(out), "--rig", "sim-uvc", "--sim-faults", "ignores-exposure", "--out",
                   str(tmp_path / "v.json"), timeout=600)
    assert v.returncode == 0, v.stdout[-2000:] + v.stderr[-2000:]
    assert "warning: camera: ignores manual exposure" in v.stderr
