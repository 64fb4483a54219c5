"""The camera's recorded response (tone curve): its inverse, the linearised circle centroids, the
session manifest's field (calib/detection/response.py; docs/DETECTION.md)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from calib.detection.detect import detect_pattern, detect_session
from calib.detection.pattern import _refine_centroids
from calib.detection.response import CameraResponse, parse_response, recorded_response
from calib.models.pattern import PatternSpec
from drivers.sim.render import encode_gamma


@pytest.mark.parametrize("gamma", [1.0, 1.8, 2.2, 1 / 0.45, 3.0])
def test_inverse_undoes_the_renderers_tone_curve(gamma):
    light = np.linspace(0.0, 1.0, 2001)
    back = CameraResponse("bt709", gamma).decode(encode_gamma(light, gamma))
    assert np.abs(back - light).max() < 2e-5  # the renderer computes in float32
    # the 8-bit table: each level's light encodes back to that level
    lut = CameraResponse("bt709", gamma).lut()
    assert np.all(np.diff(lut) > 0) and lut[0] == 0.0 and lut[255] == pytest.approx(255.0)
    assert np.array_equal(np.round(255.0 * encode_gamma(lut / 255.0, gamma)), np.arange(256))


def _circles_on_a_ramp():
    """A circle grid (blurred discs of radius 3 px) on a background whose light rises across the image
    (vignetting, light fall-off): the linear image, the same light through a 2.2 tone curve, the centres."""
    W, H, k = 640, 400, 8
    pattern = PatternSpec.default_for(1280, 800)
    centres = (np.asarray(pattern.render(1280, 800, 0)[1], float) - [640, 400]) * 0.45 + [W / 2, H / 2]
    canvas = np.zeros((H * k, W * k), np.float32)
    for x, y in centres:  # anti-aliased by supersampling (k x k) and box filtering
        cv2.circle(canvas, (int(round(((x + 0.5) * k - 0.5) * 16)), int(round(((y + 0.5) * k - 0.5) * 16))),
                   int(3.0 * k * 16), 1.0, -1, cv2.LINE_8, 4)
    disc = cv2.GaussianBlur(cv2.resize(canvas, (W, H), interpolation=cv2.INTER_AREA), (0, 0), 2.0)
    light = 2.0 + 198.0 * np.arange(W, dtype=np.float32)[None, :] / W + 50.0 * disc
    linear = np.clip(light + 0.5, 0, 255).astype(np.uint8)
    encoded = np.clip(255.0 * encode_gamma(light / 255.0, 2.2) + 0.5, 0, 255).astype(np.uint8)
    return pattern, linear, encoded, centres


def test_linearised_centroids_match_the_linear_cameras():
    _, linear, encoded, centres = _circles_on_a_ramp()
    start, radius = np.round(centres), np.full(len(centres), 3.0)
    lin = _refine_centroids(linear, start, radius)
    raw = _refine_centroids(encoded, start, radius)
    fixed = _refine_centroids(encoded, start, radius, CameraResponse("bt709", 2.2).lut())
    # encoded levels weigh the circles' sides unlike the light they received: along the background's
    # gradient the centres move together (0.014 px here), linearised they are as the linear camera's
    bias_x = {name: (found - centres)[:, 0].mean() for name, found in (("lin", lin), ("raw", raw), ("fixed", fixed))}
    assert abs(bias_x["raw"]) > 0.01
    assert abs(bias_x["fixed"]) < 0.005 and abs(bias_x["fixed"] - bias_x["lin"]) < 0.003
    assert np.linalg.norm(fixed - centres, axis=1).mean() < np.linalg.norm(raw - centres, axis=1).mean()


def test_detect_pattern_applies_the_response():
    pattern, _, encoded, _ = _circles_on_a_ramp()
    raw = detect_pattern(encoded, pattern, False)
    fixed = detect_pattern(encoded, pattern, False, response=CameraResponse("bt709", 2.2))
    same = detect_pattern(encoded, pattern, False, response=CameraResponse("bt709", 1.0))  # linear: no change
    assert np.array_equal(same, raw)
    assert np.abs(fixed - raw).max() > 0.001


@pytest.mark.parametrize("bad", [None, "bt709", 2.2, [], {}, {"model": "bt709"}, {"model": "srgb", "gamma": 2.2},
                                 {"model": "bt709", "gamma": "2.2"}, {"model": "bt709", "gamma": True},
                                 {"model": "bt709", "gamma": float("nan")}, {"model": "bt709", "gamma": 1e308 * 10},
                                 {"model": "bt709", "gamma": 0.5}, {"model": "bt709", "gamma": 40.0},
                                 {"model": ["bt709"], "gamma": 2.2}])
def test_a_malformed_response_counts_as_not_recorded(bad):
    assert parse_response(bad) is None
    assert recorded_response({"response": bad}) is None
    assert recorded_response(bad) is None


def test_a_simulated_session_records_the_response_and_detection_uses_it(tmp_path):
    from app.commands.simulate import simulate_session
    from calib.formats.session import SessionStore
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", seed=1)
    sc = replace(sc, per_position=1, mirror_count=2)
    simulate_session(sc, tmp_path / "s", quality="live", workers=1, progress=False)
    store = SessionStore.open(tmp_path / "s")  # read back from the manifest file
    assert recorded_response(store.manifest.rig.camera_settings) == CameraResponse("bt709", sc.render.camera_gamma)
    assert sc.render.camera_gamma == pytest.approx(2.2)

    def centres(settings):
        store.update(rig=replace(store.manifest.rig, camera_settings=settings))
        obs = detect_session(SessionStore.open(tmp_path / "s"), workers=1, cache="off")
        assert obs.projector_views and not any(s.reason.startswith("detection failed") for s in obs.skipped)
        return np.concatenate([v.pattern_cam_px for v in obs.projector_views])

    recorded = dict(store.manifest.rig.camera_settings)
    with_response = centres(recorded)
    without = centres({k: v for k, v in recorded.items() if k != "response"})
    malformed = centres({**recorded, "response": {"model": "bt709", "gamma": "2.2; rm -rf"}})
    assert np.array_equal(malformed, without)
    assert np.abs(with_response - without).max() > 0.001


def test_the_rig_check_records_the_response_of_a_camera_that_knows_it(tmp_path):
    """A session whose manifest has no (or a malformed) response, e.g. written before the field existed:
    the station's rig check records the simulated camera's own tone curve; a camera without `response()`
    (the RealSense) leaves it unrecorded."""
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
    from app.station.station import Station
    from calib.formats.session import SessionStore

    req = RigRequest("sim", "nonoverlap-136", 0)
    rig = open_requested_rig(req, latency_ms=0.0)
    plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
    store = create_session(tmp_path / "s", rig, req, plan)
    settings = dict(store.manifest.rig.camera_settings)
    assert recorded_response(settings) == CameraResponse("bt709", rig.camera.response()["gamma"])
    store.update(rig=replace(store.manifest.rig, camera_settings={**settings, "response": {"model": 7}}))
    checks = {c.name: c for c in Station(rig, make_machine(store, rig, plan)).check_rig()}
    assert checks["camera response"].ok and "bt709" in checks["camera response"].detail
    recorded = SessionStore.open(tmp_path / "s").manifest.rig.camera_settings
    assert recorded_response(recorded) == CameraResponse("bt709", 2.2)


@pytest.mark.parametrize("gamma", [2.2, 1.0])
def test_the_response_measured_through_exposure_control_is_the_sim_cameras(gamma):
    """drivers.exposure.measure_response on the simulated camera (hardware-like: noise, flicker, frames
    a change applies to late), the projector's white on the board: the renderer's own gamma."""
    from drivers.exposure import measure_response
    from drivers.sim.rig import open_sim_rig

    rig = open_sim_rig("nonoverlap-136", 0, quality="live", camera_gamma=gamma, latency_ms=0.0)
    try:
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)
        W, H = rig.projector.size
        rig.projector.wait_presented(rig.projector.show(np.full((H, W), 255, np.uint8)))
        fit = measure_response(rig.camera, rig.projector.refresh_hz)
    finally:
        rig.close()
    assert fit.gamma == pytest.approx(gamma, abs=0.05)
    assert parse_response(fit.camera_settings()["response"]) == CameraResponse("bt709", fit.gamma)


def _realsense_session(tmp_path):
    from app.station.machine import Plan
    from app.station.setup import RigRequest, create_session, open_requested_rig

    req = RigRequest("sim-realsense", "nonoverlap-136", 0)
    rig = open_requested_rig(req, latency_ms=0.0)
    plan = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)
    return req, rig, plan, create_session(tmp_path / "s", rig, req, plan)


def test_the_rig_check_measures_the_realsense_response_and_a_resume_reuses_it(tmp_path, monkeypatch):
    """`--rig sim-realsense` (the RealSense driver on librealsense's software device): the rig check
    measures the tone curve after the exposure search, restores the searched exposure and gain, records
    the fit as "measured"; a resumed session re-uses it without measuring again."""
    import drivers.exposure
    from app.station.setup import make_machine, open_requested_rig
    from app.station.station import Station
    from calib.formats.session import SessionStore

    req, rig, plan, store = _realsense_session(tmp_path)
    try:
        assert not callable(getattr(rig.camera, "response", None))  # the driver does not know its curve
        checks = {c.name: c for c in Station(rig, make_machine(store, rig, plan)).check_rig()}
        assert all(c.ok for c in checks.values()), checks
        rec = SessionStore.open(tmp_path / "s").manifest.rig.camera_settings
        assert rec["response"]["source"] == "measured" and "measured" in checks["camera response"].detail
        truth = rig.sim.camera.response()["gamma"]
        assert truth == pytest.approx(2.2)
        assert recorded_response(rec).gamma == pytest.approx(truth, abs=0.1)
        # the searched exposure and gain are back on the device and on the camera behind it
        dev = rig.device.options()
        assert (dev["exposure_us"], dev["gain"]) == (rec["exposure_us"], rec["gain"])
        sim = rig.sim.camera.settings_timeline.current
        assert sim["exposure_us"] == rec["exposure_us"] and sim["gain"] == rig.device.sim_gain(rec["gain"])
        assert checks["projector latency"].ok
    finally:
        rig.close()

    def never(*a, **k):
        raise AssertionError("measured again")

    monkeypatch.setattr(drivers.exposure, "measure_response", never)
    rig2 = open_requested_rig(req, latency_ms=0.0)
    try:
        store2 = SessionStore.open(tmp_path / "s")
        checks = {c.name: c for c in Station(rig2, make_machine(store2, rig2, plan, resume=True)).check_rig()}
        assert all(c.ok for c in checks.values()), checks
        assert "re-used" in checks["camera response"].detail
        assert SessionStore.open(tmp_path / "s").manifest.rig.camera_settings["response"] == rec["response"]
    finally:
        rig2.close()


def test_a_failed_response_measurement_is_a_warning_and_the_rig_check_goes_on(tmp_path, monkeypatch, caplog):
    import drivers.exposure
    from app.station.setup import make_machine
    from app.station.station import Station
    from calib.formats.session import SessionStore
    from drivers.errors import DeviceError

    real = drivers.exposure.measure_response

    def fails(camera, refresh_hz, **kw):  # the real bracket runs (gains change), then too few dim pixels
        real(camera, refresh_hz, **kw)
        raise DeviceError("too few dim pixels in view to measure the camera's response")

    monkeypatch.setattr(drivers.exposure, "measure_response", fails)
    _, rig, plan, store = _realsense_session(tmp_path)
    try:
        m = make_machine(store, rig, plan)
        with caplog.at_level("WARNING", logger="procam.station"):
            got = Station(rig, m).check_rig()
        checks = {c.name: c for c in got}
        assert all(c.ok for c in checks.values()), checks
        assert "pattern" in checks and m.start_session(got) != "check_rig"  # the session goes on
        assert "not measured" in checks["camera response"].detail and "too few dim pixels" in caplog.text
        assert any("too few dim pixels" in e.text for e in m.events)
        rec = SessionStore.open(tmp_path / "s").manifest.rig.camera_settings
        assert "response" not in rec and recorded_response(rec) is None
        assert checks["projector latency"].ok and "latency_ms" in rec["projector"]
        dev = rig.device.options()
        assert (dev["exposure_us"], dev["gain"]) == (rec["exposure_us"], rec["gain"])
    finally:
        rig.close()
