"""The pipeline (paper method) on synthetic observations: every rig, noise-free and noisy, and the
ways a session can fail to calibrate."""

import json

import numpy as np
import pytest

from _calib_helpers import metrics, observations, replace_obs, session
from calib.errors import CalibrationError
from calib.models.observations import Skipped
from calib.models.result import CalibrationResult
from calib.pipeline import METHODS, calibrate_observations


@pytest.mark.parametrize("rig", ["90", "136", "180", "direct"])
def test_noise_free_recovers_ground_truth(rig, tmp_path):
    r = calibrate_observations(observations(rig), method="paper")
    m = metrics(r, rig)
    assert m.cam_k_px < 1e-2 and m.proj_k_px < 1e-2  # K entries ~600-2300 px: ~1e-6 relative
    assert m.cam_d < 1e-5 and m.proj_d < 1e-5
    assert m.distance < 2e-3 and m.angle_deg < 1e-4
    if rig == "direct":
        assert r.mirror is None and m.mirror_angle_deg is None
    else:
        assert m.mirror_angle_deg < 1e-4 and m.mirror_offset < 1e-3
    assert r.method == "paper" and r.units == "mm"
    assert set(r.rms) == {"camera", "mirror_plane", "projector", "stereo"}
    timing = r.diagnostics["timing_s"]
    assert {"camera", "projector", "total"} <= set(timing) and all(v >= 0 for v in timing.values())
    # the result round-trips through calibration.json
    r.save_json(tmp_path / "c.json")
    back = CalibrationResult.load_json(tmp_path / "c.json")
    assert np.allclose(back.T_cam_proj, r.T_cam_proj) and back.rms == json.loads(json.dumps(r.rms))
    assert len(back.per_view) == len(r.per_view)


def test_noisy_session_gives_paper_order_errors():
    """0.2 px noise on every corner and pattern point, 136 degrees, three noise draws."""
    ms = [metrics(calibrate_observations(observations("136", 0.2, s), method="paper"), "136") for s in range(3)]
    mean = {k: float(np.mean([getattr(m, k) for m in ms])) for k in
            ("distance", "angle_deg", "proj_k_px", "proj_d", "mirror_offset", "mirror_angle_deg")}
    assert mean["distance"] < 15.0 and mean["angle_deg"] < 1.0
    assert mean["proj_k_px"] < 50.0 and mean["proj_d"] < 0.05
    assert mean["mirror_offset"] < 1.5 and mean["mirror_angle_deg"] < 0.3
    r = calibrate_observations(observations("136", 0.2, 0), method="paper")
    assert 0.2 < r.rms["camera"] < 0.35 and r.rms["projector"] > r.rms["camera"]


def test_result_reports_stages_and_skips():
    obs = observations("136")
    obs = replace_obs(obs, skipped=(Skipped("p0099", "images/p0099.png", "pattern not found"),))
    r = calibrate_observations(obs, method="paper")
    stages = {pv["stage"] for pv in r.per_view}
    assert stages == {"camera", "mirror", "projector"}
    assert r.skipped[0] == {"capture_id": "p0099", "image": "images/p0099.png", "stage": "detection",
                            "reason": "pattern not found"}
    assert r.diagnostics["mirror"]["n_inliers"] == 7 * 35 and r.diagnostics["mirror"]["n_outliers"] == 0


def test_precalibrated_camera_is_kept():
    gt = session("136").rig
    r = calibrate_observations(observations("136", 0.2, 1), camera=gt.camera, method="paper")
    assert r.camera is gt.camera and r.diagnostics["camera"]["precalibrated"]
    assert "camera" in r.rms and r.rms["camera"] > 0


def test_mirrored_session_without_mirror_images_fails_clearly():
    obs = replace_obs(observations("136"), mirror_views=())
    with pytest.raises(CalibrationError, match="no usable mirror-calibration images"):
        calibrate_observations(obs, method="paper")


def test_too_few_projector_views_fails_clearly():
    obs = observations("136")
    obs = replace_obs(obs, projector_views=obs.projector_views[:2],
                      skipped=(Skipped("p0002", "images/p0002.png", "board not found"),))
    with pytest.raises(CalibrationError, match=r"only 2 usable projector image.*board not found"):
        calibrate_observations(obs, method="paper")


def test_unknown_method_lists_the_available_ones():
    with pytest.raises(CalibrationError, match="available: .*paper"):
        calibrate_observations(observations("136"), method="nope")


def test_methods_registry_is_one_line_to_extend(monkeypatch):
    calls = []

    def fake(obs, camera, progress):
        calls.append((obs, camera))
        return METHODS["paper"](obs, camera, progress)

    monkeypatch.setitem(METHODS, "fake", fake)
    r = calibrate_observations(observations("direct"), method="fake")
    assert calls and r.method == "paper" and "total" in r.diagnostics["timing_s"]


def test_progress_reports_each_stage():
    seen = []
    calibrate_observations(observations("136"), method="paper", progress=lambda d, t, label: seen.append((d, t, label)))
    # "starting", then each call names the stage just finished, so a log reads camera 1/3, mirror 2/3, ...
    assert seen[0] == (0, 3, "starting") and seen[-1] == (3, 3, "projector")
    assert [s[2] for s in seen] == ["starting", "camera", "mirror", "projector"]
    assert [s[0] for s in seen] == [0, 1, 2, 3]
