"""Stage 3 (projector): exact pattern points on the board, Zhang for the projector, stereo with fixed
intrinsics through the flipped virtual camera, chained through the mirror."""

import numpy as np
import pytest

from _calib_helpers import observations, rel_err, replace_obs, session
from calib.errors import CalibrationError
from calib.models.observations import BoardObservation, ProjectorView
from calib.paper.board_pose import solve_board_pose
from calib.paper.projector import calibrate_projector, pattern_points_on_board
from calib.synthetic import projector_points_on_board
from calib.transforms import FLIP_X, invert_T, rotation_angle_deg


@pytest.mark.parametrize("rig", ["136", "direct"])
def test_pattern_points_on_board_are_exact_with_distortion(rig):
    ss = session(rig)
    obs = observations(rig)
    for i in (0, 17, 40):
        v = obs.projector_views[i]
        pose = solve_board_pose(ss.rig.camera, ss.layout.charuco, v.board)
        X = pattern_points_on_board(ss.rig.camera, pose, v.pattern_cam_px)
        truth = projector_points_on_board(ss.rig, ss.projector_T_cam_board[i][1], v.pattern_proj_px)
        assert np.abs(X - truth).max() < 1e-6
        assert np.all(X[:, 2] == 0)


@pytest.mark.parametrize("rig", ["90", "180", "direct"])
def test_noise_free_recovers_projector_and_pose(rig):
    gt = session(rig).rig
    pc = calibrate_projector(observations(rig), gt.camera, gt.mirror)
    assert rel_err(pc.projector.K, gt.projector.K) < 2e-6
    assert np.abs(pc.projector.dist - gt.projector.dist).max() < 1e-5
    assert np.linalg.norm(pc.T_cam_proj[:3, 3] - gt.T_cam_proj[:3, 3]) < 2e-3
    assert rotation_angle_deg(pc.T_cam_proj[:3, :3].T @ gt.T_cam_proj[:3, :3]) < 1e-4
    assert pc.rms_px < 1e-3 and pc.stereo_rms_px < 1e-3
    assert pc.mirrored == (rig != "direct") and pc.diagnostics["n_rejected_points"] == 0
    # every view's board pose is the physical one
    ss = session(rig)
    for (pos, T), v in zip(ss.projector_T_cam_board[:5], observations(rig).projector_views[:5]):
        assert np.abs(pc.board_poses[v.capture_id] - T).max() < 1e-6


def test_stereo_goes_through_the_flipped_virtual_camera():
    """stereoCalibrate estimates T_proj_V' and T_cam_proj = S F T_V'_proj (docs/GEOMETRY.md)."""
    gt = session("136").rig
    pc = calibrate_projector(observations("136"), gt.camera, gt.mirror)
    S = gt.mirror.reflection()
    T_Vp_proj = FLIP_X @ S @ gt.T_cam_proj
    assert np.linalg.det(T_Vp_proj[:3, :3]) == pytest.approx(1.0)
    assert np.abs(invert_T(pc.T_proj_ref) - T_Vp_proj).max() < 2e-3
    assert np.allclose(S @ FLIP_X @ invert_T(pc.T_proj_ref), pc.T_cam_proj)
    assert np.linalg.det(pc.T_cam_proj[:3, :3]) == pytest.approx(1.0)


def test_noisy_views_with_the_true_camera_and_mirror():
    gt = session("136").rig
    dist, ang, projk = [], [], []
    for seed in range(3):
        pc = calibrate_projector(observations("136", 0.2, seed), gt.camera, gt.mirror)
        dist.append(np.linalg.norm(pc.T_cam_proj[:3, 3] - gt.T_cam_proj[:3, 3]))
        ang.append(rotation_angle_deg(pc.T_cam_proj[:3, :3].T @ gt.T_cam_proj[:3, :3]))
        projk.append(np.linalg.norm(pc.projector.K - gt.projector.K))
        assert 0.5 < pc.rms_px < 2.0  # 0.2 px in the camera is ~0.8 px in this projector
        assert len(pc.per_view) == 52 and all(r["stereo_proj_px"] < 5 for r in pc.per_view)
    assert np.mean(dist) < 15 and np.mean(ang) < 1.0 and np.mean(projk) < 50


def test_a_misdetected_pattern_point_is_rejected():
    gt = session("180").rig
    obs = observations("180", 0.05, 3)
    clean = calibrate_projector(obs, gt.camera, gt.mirror)
    pv = list(obs.projector_views)
    v = pv[9]
    cam_px = np.array(v.pattern_cam_px)
    cam_px[4] += [6.0, -3.0]  # one circle centre off by ~7 px
    pv[9] = ProjectorView(v.capture_id, v.board, cam_px, v.pattern_proj_px, v.pattern_position)
    bad = replace_obs(obs, projector_views=tuple(pv))
    pc = calibrate_projector(bad, gt.camera, gt.mirror)
    rec = next(r for r in pc.per_view if r["capture_id"] == v.capture_id)
    assert rec["n_rejected_points"] >= 1 and pc.diagnostics["n_rejected_points"] <= 3
    assert np.linalg.norm(pc.projector.K - clean.projector.K) < 2.0
    naive = calibrate_projector(bad, gt.camera, gt.mirror, reject_outliers=False)
    assert np.linalg.norm(naive.projector.K - gt.projector.K) > np.linalg.norm(pc.projector.K - gt.projector.K)


def test_mirrored_views_need_the_mirror():
    gt = session("136").rig
    with pytest.raises(CalibrationError, match="mirror plane is needed"):
        calibrate_projector(observations("136"), gt.camera, None)


def test_inconsistent_views_are_skipped_with_reasons():
    gt = session("136").rig
    obs = observations("136")
    pv = list(obs.projector_views)
    v0, v1 = pv[0], pv[1]
    pv[0] = ProjectorView(v0.capture_id, BoardObservation(v0.board.ids, v0.board.corners_px, False),
                          v0.pattern_cam_px, v0.pattern_proj_px, 0)  # claims a direct view
    pv[1] = ProjectorView(v1.capture_id, v1.board, v1.pattern_cam_px[:4], v1.pattern_proj_px[:4], 0)
    pc = calibrate_projector(replace_obs(obs, projector_views=tuple(pv)), gt.camera, gt.mirror)
    reasons = {s["capture_id"]: s["reason"] for s in pc.skipped}
    assert "seen directly in a mirrored session" in reasons[v0.capture_id]
    assert "only 4 pattern points" in reasons[v1.capture_id]
    assert len(pc.per_view) == 50


def test_too_few_projector_views():
    gt = session("136").rig
    obs = replace_obs(observations("136"), projector_views=observations("136").projector_views[:3])
    with pytest.raises(CalibrationError, match="only 3 usable projector view"):
        calibrate_projector(obs, gt.camera, gt.mirror)
