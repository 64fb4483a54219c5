"""The epipolar verification (app.verification): verdict logic, report files, pixel picking, and the
check end to end on the simulated rig (correct calibrations pass, perturbed ones are flagged)."""

import json

import numpy as np
import pytest

from app.verification import (
    DEFAULT_THRESHOLD_PX,
    PixelCheck,
    VerificationError,
    VerificationReport,
    grid_pixels,
    judge,
    perturbed,
    region_mask,
    verify,
    verify_pixel,
)
from calib.epipolar import distance_to_polyline
from calib.errors import FormatError
from drivers.settle import apply_timing
from drivers.sim.rig import open_sim_rig


def _check(d_cam, scale=0.25, reason=None, pixel=(10.0, 20.0)):
    if reason is not None:
        return PixelCheck(pixel, np.zeros((3, 2)), np.zeros((0, 2)), None, None, None, None, None, 12.0, None, reason)
    line = np.array([[0.0, 20.0 + d_cam], [100.0, 20.0 + d_cam]])
    return PixelCheck(pixel, np.ones((5, 2)), line, None, d_cam, d_cam, d_cam / scale, scale, 12.0, 0.05)


# ---- verdict and report ------------------------------------------------------------------------------
def test_verdict_on_mean_and_worst_in_projector_pixels():
    good = judge([_check(0.05), _check(0.1), _check(0.2)])
    assert good.passed and good.n_failed_detection == 0
    assert good.mean_px == pytest.approx(0.35 / 3) and good.worst_px == pytest.approx(0.2)
    assert good.worst_proj_px == pytest.approx(0.8) and good.threshold_px == DEFAULT_THRESHOLD_PX
    # a systematic offset: mean 2 projector px > 1.5
    shifted = judge([_check(0.5), _check(0.5), _check(0.5)])
    assert not shifted.passed and "on average" in shifted.verdict
    # one bad pixel: mean fine, worst 3.2 > 2 x 1.5
    one_bad = judge([_check(0.0), _check(0.0), _check(0.0), _check(0.0), _check(0.8)])
    assert one_bad.mean_proj_px < 1.5 and not one_bad.passed and "worst" in one_bad.verdict
    # the threshold is the caller's
    assert judge([_check(0.5)] * 3, threshold_px=2.5).passed


def test_unmeasured_pixels_are_reported_never_passed():
    checks = [_check(0.0), _check(0.0), _check(0.0), _check(0, reason="no projected curve visible")]
    rep = judge(checks)
    assert rep.passed and rep.n_failed_detection == 1 and rep.n_measured == 3
    assert "not measured" in rep.verdict
    # too few measured: fails, with the reasons
    rep = judge([_check(0.0), _check(0, reason="curve off the board"), _check(0, reason="curve off the board")])
    assert not rep.passed and "only 1 of 3" in rep.verdict and "curve off the board" in rep.verdict
    rep = judge([_check(0, reason="nothing")] * 12)
    assert not rep.passed and rep.mean_px is None and rep.n_failed_detection == 12
    # a check without its own scale borrows the others'
    no_scale = PixelCheck((1.0, 1.0), np.ones((2, 2)), np.ones((2, 2)), None, 0.5, 0.5, None, None, 12.0, 0.1)
    rep = judge([_check(0.1, scale=0.25), _check(0.1, scale=0.25), no_scale])
    assert rep.worst_proj_px == pytest.approx(2.0)


def test_report_json_roundtrip_and_errors(tmp_path):
    rep = judge([_check(0.1), _check(0.2), _check(0.1), _check(0, reason="hidden")], calibration={"method": "paper"})
    path = tmp_path / "verification.json"
    rep.save_json(path)
    assert [p.name for p in tmp_path.iterdir()] == ["verification.json"]  # no temporary file left
    d = json.loads(path.read_text())
    assert d["schema"] == "procam-verification" and d["passed"] is True and d["n_failed_detection"] == 1
    assert d["threshold_unit"] == "projector px" and d["calibration"]["method"] == "paper"
    back = VerificationReport.from_json(path)
    assert back.passed == rep.passed and back.verdict == rep.verdict
    assert back.mean_proj_px == pytest.approx(rep.mean_proj_px)
    assert len(back.checks) == 4 and back.checks[3].reason == "hidden" and not back.checks[3].ok
    assert np.allclose(back.checks[0].detected_curve, rep.checks[0].detected_curve)
    path.write_text("{not json")
    with pytest.raises(FormatError, match="not valid JSON"):
        VerificationReport.from_json(path)
    d["threshold_px"] = -1
    path.write_text(json.dumps(d))
    with pytest.raises(FormatError, match="threshold_px"):
        VerificationReport.from_json(path)


def test_grid_pixels_spread_over_the_region():
    lit = np.zeros((400, 600), bool)
    lit[100:300, 150:450] = True
    lit[190:206, 262:278] = False  # a dark square inside: closed over, but avoided when possible
    region = region_mask(lit.shape, lit)
    assert region[200, 270] and not region[50, 50]
    pts = grid_pixels(region, (4, 3), prefer=lit)
    assert len(pts) == 12
    assert np.all(lit[pts[:, 1].astype(int), pts[:, 0].astype(int)])
    assert pts[:, 0].min() < 220 and pts[:, 0].max() > 380 and pts[:, 1].min() < 150 and pts[:, 1].max() > 250
    assert len(np.unique(pts, axis=0)) == 12
    # a box restricts the region
    box = region_mask(lit.shape, lit, (300, 0, 599, 399))
    assert box[:, :300].sum() == 0 and box.any()
    with pytest.raises(VerificationError):
        grid_pixels(region, (0, 3))
    with pytest.raises(VerificationError):
        region_mask(lit.shape, lit, "everywhere")


# ---- on the simulated rig ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sim():
    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live")
    rig.camera.start()
    rig.operator.request_pose("verification", None, 0)
    apply_timing(rig.camera, rig.projector)  # exposure searched, latency measured, as the station does
    return rig


def test_ground_truth_passes_and_the_detected_curve_is_the_predicted_one(sim):
    from calib.detection.response import parse_response

    gt = sim.ground_truth()
    # frames read as light, as the station and `procam verify` read them (read as levels the worst pixel
    # scatters from 0.12 to 0.51 projector px between runs of this very test: the tone curve's noise)
    rep = verify(sim.camera, sim.projector, sim.operator, gt, grid=(3, 2), board_pose=sim.board.T_cam_board,
                 response=parse_response(sim.camera.response()))
    assert rep.passed, rep.summary()
    assert rep.n_measured == 6 and rep.n_failed_detection == 0
    assert rep.worst_proj_px < 0.5 and rep.worst_px < 0.15
    for c in rep.checks:
        assert 0.15 < c.scale < 0.35  # a camera pixel covers about 4 projector pixels on this rig
        # the calibration's prediction of where the camera sees the stroke (through the board plane)
        assert distance_to_polyline(c.pixel, c.predicted_curve).distance[0] < 1e-3
        near = c.detected_curve[np.linalg.norm(c.detected_curve - c.pixel, axis=1) < 150]
        assert len(near) > 30
        assert np.median(distance_to_polyline(near, c.predicted_curve).distance) < 0.15
    # the projector is left dark
    assert not sim.projector.image.any()


@pytest.mark.parametrize("name,kw", [
    ("rotation 0.5 deg about the projector's x", dict(rotation_deg=0.5, axis=(1, 0, 0))),
    ("rotation 0.5 deg about the projector's y", dict(rotation_deg=0.5, axis=(0, 1, 0))),
    ("principal point +5 px in x", dict(principal_shift_px=(5.0, 0.0))),
    ("principal point +5 px in y", dict(principal_shift_px=(0.0, 5.0))),
])
def test_perturbed_calibration_is_flagged(sim, name, kw):
    bad = perturbed(sim.ground_truth(), **kw)
    rep = verify(sim.camera, sim.projector, sim.operator, bad, grid=(3, 2))
    assert rep.n_measured == 6, rep.summary()
    assert not rep.passed, f"{name}: {rep.summary()}"
    assert rep.mean_proj_px > DEFAULT_THRESHOLD_PX


def test_pixels_off_the_board_are_not_measured(sim):
    gt = sim.ground_truth()
    on_board = [(600.0, 360.0), (700.0, 420.0), (640.0, 460.0)]
    rep = verify(sim.camera, sim.projector, sim.operator, gt, pixels=on_board + [(40.0, 40.0), (1200.0, 700.0)])
    assert rep.n_measured == 3 and rep.n_failed_detection == 2
    assert rep.passed and "2 pixel(s) not measured" in rep.verdict
    for c in rep.checks[3:]:
        assert not c.ok and c.distance_px is None and c.reason
    only_off = verify(sim.camera, sim.projector, sim.operator, gt, pixels=[(40.0, 40.0), (1200.0, 700.0), (20, 780)])
    assert not only_off.passed and only_off.n_measured == 0


def test_single_pixel_and_errors(sim):
    gt = sim.ground_truth()
    c = verify_pixel(sim.camera, sim.projector, gt, (640.0, 400.0), board_pose=sim.board.T_cam_board)
    assert c.ok and c.distance_px < 0.1 and c.distance_proj_px < 0.5
    ov = c.overlay()
    assert ov["pixel"] == (640.0, 400.0) and len(ov["detected"]) > 50 and len(ov["predicted"]) > 10
    assert "camera px" in ov["label"]
    # the panel's click passes the session's response: the references it captures are read as light
    from calib.detection.response import CameraResponse

    c = verify_pixel(sim.camera, sim.projector, gt, (640.0, 400.0), response=CameraResponse("bt709", 2.2))
    assert c.ok and c.distance_px < 0.1 and c.distance_proj_px < 0.5
    with pytest.raises(VerificationError, match="outside"):
        verify_pixel(sim.camera, sim.projector, gt, (5000.0, 1.0))
    wrong_size = gt.with_(projector=gt.projector.__class__(1280, 720, gt.projector.K, gt.projector.dist))
    with pytest.raises(VerificationError, match="1920x1080"):
        verify(sim.camera, sim.projector, None, wrong_size)


def test_nothing_lit_is_an_error_not_a_verdict():
    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live")
    rig.camera.start()
    rig.operator.move_out()
    with pytest.raises(VerificationError, match="nothing lit"):
        verify(rig.camera, rig.projector, None, rig.ground_truth())


def test_station_call_writes_the_session_report_with_predicted_curves(sim, tmp_path):
    """The station calls verify(camera, projector, operator, result, session_dir=...): the report lands
    in the session, and the session's projector board (found in the white frame) gives the overlay."""
    from _epipolar_helpers import make_sim_session

    make_sim_session(tmp_path)
    gt = sim.ground_truth()
    rep = verify(sim.camera, sim.projector, sim.operator, gt, session_dir=tmp_path, grid=(2, 2))
    assert rep.passed and rep.settings["board_pose_known"]
    back = VerificationReport.from_json(tmp_path / "verification.json")
    assert back.passed and len(back.checks) == 4
    for c in back.checks:
        assert c.predicted_curve is not None and len(c.predicted_curve) > 10
        assert distance_to_polyline(c.pixel, c.predicted_curve).distance[0] < 0.01
        assert np.median(distance_to_polyline(c.detected_curve, c.predicted_curve).distance) < 0.2


def test_board_pose_from_the_white_frame(sim):
    from app.verification import capture_references, estimate_board_pose
    from calib.transforms import invert_T, rotation_angle_deg

    refs = capture_references(sim.camera, sim.projector)
    gt = sim.ground_truth()
    T = estimate_board_pose(refs.white, sim.scenario.projector_board, gt)
    D = invert_T(sim.board.T_cam_board) @ T
    assert np.linalg.norm(D[:3, 3]) < 5.0 and rotation_angle_deg(D) < 0.5  # mm, degrees
    assert estimate_board_pose(refs.off * 0, sim.scenario.projector_board, gt) is None



def test_the_cameras_response_brings_a_correct_calibration_closer_to_0():
    """The simulated camera encodes light with a BT.709-like 2.2 curve: on its encoded levels the white
    and black frames do not divide out the print exactly (strokes across a black square's edge lean).
    Read as light through the camera's response, the ground truth measures far closer to 0. A
    noise-free rig renders the same frames for every check, so the comparison is exact; a linear
    response changes nothing (the levels as they are), and the report records what was applied."""
    from calib.detection.response import CameraResponse, parse_response

    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live", ideal=True, latency_ms=0.0, read_noise_dn=0.0,
                       electrons_per_dn=0.0)
    try:
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)
        gt = rig.ground_truth()
        response = parse_response(rig.camera.response())
        assert response == CameraResponse("bt709", 2.2)
        raw = verify(rig.camera, rig.projector, None, gt, grid=(4, 3))
        light = verify(rig.camera, rig.projector, None, gt, grid=(4, 3), response=response)
        same = verify(rig.camera, rig.projector, None, gt, grid=(4, 3), response=CameraResponse("bt709", 1.0))
    finally:
        rig.close()
    assert raw.n_measured == light.n_measured == 12
    assert [c.pixel for c in light.checks] == [c.pixel for c in raw.checks]  # the same pixels
    assert light.mean_proj_px < 0.5 * raw.mean_proj_px and light.worst_proj_px < 0.5 * raw.worst_proj_px, \
        (raw.summary(), light.summary())
    assert [(c.distance_px, c.scale) for c in same.checks] == [(c.distance_px, c.scale) for c in raw.checks]
    assert raw.response is None and raw.to_dict()["response"] is None
    assert light.response == {"model": "bt709", "gamma": 2.2}
    assert VerificationReport.from_dict(json.loads(json.dumps(light.to_dict()))).response == light.response


def test_the_station_and_the_recalibration_verify_with_the_sessions_recorded_response(sim, tmp_path):
    """The station's verification step (app.station.setup.make_verify_fn) and the recalibration's check of
    the previous calibration (app.recalibration.rig_verify_fn) read the response the session's rig check
    recorded when they run (it is recorded after they are made); none recorded: the levels as they are."""
    from dataclasses import replace

    from app.recalibration import rig_verify_fn
    from app.station.setup import make_verify_fn
    from calib.formats.session import SessionStore
    from _epipolar_helpers import make_sim_session

    make_sim_session(tmp_path)
    gt = sim.ground_truth()
    station_verify, previous_verify = make_verify_fn(sim, tmp_path), rig_verify_fn(sim, tmp_path)
    store = SessionStore.open(tmp_path)
    assert station_verify(gt, grid=(2, 2)).response is None
    settings = {**store.manifest.rig.camera_settings, "response": {"model": "bt709", "gamma": 2.2, "source": "known"}}
    store.update(rig=replace(store.manifest.rig, camera_settings=settings))
    rep = station_verify(gt, grid=(2, 2))
    assert rep.passed and rep.response == {"model": "bt709", "gamma": 2.2}
    assert json.loads((tmp_path / "verification.json").read_text())["response"] == rep.response
    assert previous_verify(gt, False).response == rep.response


@pytest.mark.parametrize("bad", [{"model": 7, "gamma": 2.2}, {"model": "bt709", "gamma": 99.0},
                                 {"model": "bt709", "gamma": "2.2"}, ["bt709", 2.2], "<script>alert(1)</script>"])
def test_a_damaged_response_in_verification_json_reads_as_none(tmp_path, bad):
    """verification.json is untrusted: its "response" is kept only as a known tone curve, with short
    strings for where it came from; anything else reads as null, the rest of the report as written."""
    import dataclasses

    rep = judge([_check(0.1), _check(0.2), _check(0.1)])
    good = dataclasses.replace(rep, response={"model": "bt709", "gamma": 2.2, "from": "session", "junk": [1] * 5,
                                              "source": "x" * 500})
    path = tmp_path / "verification.json"
    good.save_json(path)
    assert VerificationReport.from_json(path).response == {"model": "bt709", "gamma": 2.2, "from": "session"}
    d = json.loads(path.read_text())
    d["response"] = bad
    path.write_text(json.dumps(d))
    back = VerificationReport.from_json(path)
    assert back.response is None and back.passed == rep.passed and back.mean_proj_px == rep.mean_proj_px
