"""Stage 1 (camera): Zhang over direct and mirrored board views in one calibration."""

import numpy as np
import pytest

from _calib_helpers import observations, rel_err, replace_obs, session
from calib.errors import CalibrationError
from calib.models.observations import BoardObservation, ProjectorView
from calib.paper.board_pose import MIRROR_BOARD, solve_board_pose, view_object_points
from calib.paper.camera import calibrate_camera
from calib.transforms import transform_points


def test_mirrored_view_is_a_rigid_view_of_the_mirrored_board():
    """u = project(S T X) = project((S T F_b)(F_b X)), and S T F_b is a proper rigid transform."""
    ss = session("136")
    rig, board = ss.rig, ss.layout.charuco
    S = rig.mirror.reflection()
    T = ss.projector_T_cam_board[7][1]
    X = board.corner_points()
    M = S @ T @ MIRROR_BOARD
    assert np.linalg.det(M[:3, :3]) == pytest.approx(1.0)
    assert np.allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3))
    u_seen = rig.camera.project(transform_points(S @ T, X))
    u_virtual = rig.camera.project(transform_points(M, X * [-1, 1, 1]))
    assert np.abs(u_seen - u_virtual).max() < 1e-9
    # and PnP with the mirrored object points finds exactly that pose, whose un-mirroring is T
    obs = observations("136").projector_views[7].board
    pose = solve_board_pose(rig.camera, board, obs)
    assert np.allclose(view_object_points(board, obs)[:, 0], -X[obs.ids, 0])
    assert np.abs(pose.T_cam_view - M).max() < 1e-6
    assert np.abs(pose.physical(S) - T).max() < 1e-6


@pytest.mark.parametrize("rig", ["90", "136", "180", "direct"])
def test_noise_free_recovers_intrinsics(rig):
    cc = calibrate_camera(observations(rig))
    gt = session(rig).rig.camera
    assert rel_err(cc.camera.K, gt.K) < 2e-6
    assert np.abs(cc.camera.dist - gt.dist).max() < 1e-5
    assert cc.rms_px < 1e-3 and not cc.precalibrated
    assert cc.n_views == len(cc.per_view) == len(cc.poses)
    assert cc.std_intrinsics is not None and cc.std_intrinsics.size >= 9


def test_mirrored_views_alone_give_the_real_camera():
    """Only views through the mirror (no direct view at all): the intrinsics are the real camera's,
    not the flipped one's (cx is not mirrored to W-1-cx)."""
    obs = replace_obs(observations("136"), mirror_views=())
    assert all(v.board.mirrored for v in obs.projector_views)
    cc = calibrate_camera(obs)
    gt = session("136").rig.camera
    assert cc.camera.cx == pytest.approx(gt.cx, abs=1e-3)
    assert rel_err(cc.camera.K, gt.K) < 2e-6
    # the reported poses are those of the virtual board, proper rotations
    for pose in cc.poses.values():
        assert pose.mirrored and np.linalg.det(pose.T_cam_view[:3, :3]) == pytest.approx(1.0)


def test_noisy_observations_give_paper_order_errors():
    gt = session("136").rig.camera
    errs = []
    for seed in range(3):
        cc = calibrate_camera(observations("136", 0.2, seed))
        errs.append(np.linalg.norm(cc.camera.K - gt.K))
        assert 0.2 < cc.rms_px < 0.35  # 0.2 px per axis -> ~0.28 px in 2D
        assert np.linalg.norm(cc.camera.dist - gt.dist) < 0.03
    assert np.mean(errs) < 6.0


def test_precalibrated_camera_skips_estimation():
    gt = session("136").rig.camera
    cc = calibrate_camera(observations("136", 0.2, 1), camera=gt)
    assert cc.precalibrated and cc.camera is gt
    assert 0.2 < cc.rms_px < 0.35
    assert cc.std_intrinsics is None
    with pytest.raises(CalibrationError, match="session's images"):
        calibrate_camera(observations("136"), camera=gt.with_params().__class__(640, 400, gt.K, gt.dist))


def test_views_with_too_few_corners_are_skipped():
    obs = observations("136")
    v = obs.projector_views[0]
    few = BoardObservation(v.board.ids[:4], v.board.corners_px[:4], True)
    pv = (ProjectorView(v.capture_id, few, v.pattern_cam_px, v.pattern_proj_px, 0),) + obs.projector_views[1:]
    cc = calibrate_camera(replace_obs(obs, projector_views=pv))
    reasons = [s for s in cc.skipped if s["capture_id"] == v.capture_id]
    assert len(reasons) == 1 and "only 4 ChArUco corners" in reasons[0]["reason"]
    assert v.capture_id not in cc.poses


def test_a_misdetected_view_is_rejected(rng):
    obs = observations("136", 0.2, 2)
    v = obs.projector_views[3]
    bad = BoardObservation(v.board.ids, v.board.corners_px + rng.normal(0, 15, v.board.corners_px.shape), True)
    pv = list(obs.projector_views)
    pv[3] = ProjectorView(v.capture_id, bad, v.pattern_cam_px, v.pattern_proj_px, v.pattern_position)
    cc = calibrate_camera(replace_obs(obs, projector_views=tuple(pv)))
    assert any(s["capture_id"] == v.capture_id and "misdetection" in s["reason"] for s in cc.skipped)
    assert np.linalg.norm(cc.camera.K - session("136").rig.camera.K) < 8.0


def test_too_few_views_is_an_actionable_error():
    obs = observations("136")
    obs = replace_obs(obs, projector_views=obs.projector_views[:2], mirror_views=())
    with pytest.raises(CalibrationError, match=r"only 2 usable board view.*--camera-intrinsics"):
        calibrate_camera(obs)


def test_a_misdetected_corner_is_dropped_not_the_view():
    obs = observations("136", 0.2, 3)
    clean = calibrate_camera(obs)
    pv = list(obs.projector_views)
    v = pv[11]
    c = np.array(v.board.corners_px)
    c[7] += [7.0, 5.0]
    pv[11] = ProjectorView(v.capture_id, BoardObservation(v.board.ids, c, True), v.pattern_cam_px, v.pattern_proj_px,
                           v.pattern_position)
    cc = calibrate_camera(replace_obs(obs, projector_views=tuple(pv)))
    rec = next(r for r in cc.per_view if r["capture_id"] == v.capture_id)
    assert rec["n_rejected_points"] == 1 and rec["n_points"] == 34
    assert sum(r["n_rejected_points"] for r in cc.per_view) == 1
    assert np.linalg.norm(cc.camera.K - clean.camera.K) < 0.5
    assert cc.rms_px < 0.35
    # the PnP of a pre-calibrated camera drops the same corner
    gt = session("136").rig.camera
    pose = solve_board_pose(gt, session("136").layout.charuco, pv[11].board)
    assert pose.n_outliers == 1 and not pose.inliers[7] and pose.rms_px < 0.4


@pytest.mark.parametrize("flags", [0, "fix_k3", "rational"])
def test_zhang_statistics_equal_opencvs_extended_calibration(flags):
    """calibrate_zhang's 1-sigma intrinsics and per-view RMS (computed by zhang_statistics) are the ones
    cv2.calibrateCameraExtended reports, and its closed-form start finds a projector's off-centre
    principal point."""
    import cv2

    from calib.paper.board_pose import calibrate_zhang, zhang_closed_form, zhang_statistics

    flags = {0: 0, "fix_k3": cv2.CALIB_FIX_K3, "rational": cv2.CALIB_RATIONAL_MODEL}[flags]
    obs = observations("136", noise_px=0.1)
    views = [v.board for v in obs.projector_views]
    spec = obs.projector_board
    objp = [view_object_points(spec, b).astype(np.float32) for b in views]
    imgp = [np.asarray(b.corners_px, np.float32) for b in views]
    ref = cv2.calibrateCameraExtended(objp, imgp, obs.camera_size, None, None, flags=flags)
    std, pve = zhang_statistics(objp, imgp, ref[1], ref[2], ref[3], ref[4], flags)
    ref_std = np.asarray(ref[5], float).ravel()
    assert np.count_nonzero(ref_std) == np.count_nonzero(std) > 4
    assert np.allclose(std, ref_std, rtol=1e-3, atol=0)
    assert np.allclose(pve, np.asarray(ref[7], float).ravel(), rtol=1e-9)
    rms, K, _d, _r, _t, std2, _pve = calibrate_zhang(objp, imgp, obs.camera_size, flags)
    assert rms <= ref[0] * (1 + 1e-6) and rel_err(K, ref[1]) < 1e-3 and std2.shape == (18,)



def test_zhang_closed_form_finds_an_off_centre_principal_point():
    """A projector's principal point lies near its bottom edge; the closed form (used to start OpenCV's
    LM, whose own start fixes it at the image centre) recovers it exactly from noise-free planar views."""
    from calib.models.camera import CameraModel
    from calib.paper.board_pose import zhang_closed_form
    from calib.transforms import T_from_rvec_tvec

    K = np.array([[2300.0, 0, 975.0], [0, 2300.0, 1010.0], [0, 0, 1]])
    proj = CameraModel(1920, 1080, K, np.zeros(5))
    X = np.array([[x, y, 0.0] for x in np.linspace(-200, 200, 9) for y in np.linspace(-150, 150, 7)])
    rng = np.random.default_rng(3)
    objp, imgp = [], []
    for _ in range(8):
        T = T_from_rvec_tvec(rng.normal(0, 0.35, 3), np.array([0, -150, 1600.0]) + rng.normal(0, 60, 3))
        objp.append(X)
        imgp.append(proj.project(transform_points(T, X)))
    K0 = zhang_closed_form(objp, imgp)
    assert K0 is not None and rel_err(K0, K) < 1e-6
    assert zhang_closed_form(objp[:2], imgp[:2]) is None  # two views cannot fix five unknowns
    assert zhang_closed_form([X * [1, 1, 0] + [0, 0, 1] * np.arange(len(X))[:, None]] * 3, imgp[:3]) is None


def test_zhang_restarts_only_when_a_gauss_newton_step_would_still_move_the_intrinsics(monkeypatch):
    """_converged: False for an answer OpenCV's LM left short of the minimum (two iterations), True at
    the minimum; calibrate_zhang then restarts only in the first case."""
    import cv2

    from calib.paper import board_pose as BP

    obs = observations("136", noise_px=0.1)
    spec = obs.projector_board
    objp = [view_object_points(spec, v.board).astype(np.float32) for v in obs.projector_views]
    imgp = [np.asarray(v.board.corners_px, np.float32) for v in obs.projector_views]
    size = obs.camera_size
    short = cv2.calibrateCamera(objp, imgp, size, None, None, criteria=(cv2.TERM_CRITERIA_COUNT, 2, 0))
    full = cv2.calibrateCamera(objp, imgp, size, None, None, criteria=BP._ZHANG_CRITERIA)
    assert short[0] > full[0] * (1 + 1e-4)  # two iterations are not enough here
    assert not BP._converged(BP._zhang_normal(objp, imgp, *short[1:], 0), len(objp))
    assert BP._converged(BP._zhang_normal(objp, imgp, *full[1:], 0), len(objp))

    calls = []
    real = cv2.calibrateCamera

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(cv2, "calibrateCamera", counting)
    rms, K, *_ = BP.calibrate_zhang(objp, imgp, size)
    assert len(calls) == 1 and rms == pytest.approx(full[0], rel=1e-6)  # converged at once: no restart


@pytest.mark.parametrize("cy", [1210.0, -130.0])
def test_zhang_calibrates_a_projector_whose_principal_point_lies_outside_its_image(cy):
    """Lens shift puts a projector's principal point beyond its bottom edge (or its top edge when it
    hangs from the ceiling). OpenCV refuses to start from such a guess ("Principal point must be within
    the image"); calibrate_zhang still recovers the intrinsics exactly from noise-free views."""
    import cv2

    from calib.models.camera import CameraModel
    from calib.paper.board_pose import calibrate_zhang, zhang_closed_form
    from calib.transforms import T_from_rvec_tvec

    K = np.array([[2300.0, 0, 975.0], [0, 2300.0, cy], [0, 0, 1]])
    dist = np.array([0.02, -0.03, 0.0, 0.0, 0.0])
    proj = CameraModel(1920, 1080, K, dist)
    X = np.array([[x, y, 0.0] for x in np.linspace(-200, 200, 9) for y in np.linspace(-150, 150, 7)])
    rng = np.random.default_rng(5)
    objp, imgp = [], []
    while len(objp) < 10:
        T = T_from_rvec_tvec(rng.normal(0, 0.3, 3), np.array([0, 540.0 - cy, 2300.0]) + rng.normal(0, 60, 3))
        uv = proj.project(transform_points(T, X))
        if np.all((uv > 0) & (uv < [1919, 1079])):
            objp.append(X.astype(np.float32))
            imgp.append(uv.astype(np.float32))
    K0 = zhang_closed_form(objp, imgp)
    with pytest.raises(cv2.error, match="Principal point must be within the image"):
        cv2.calibrateCamera(objp, imgp, (1920, 1080), K0, None, flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    rms, K_est, d_est, *_ = calibrate_zhang(objp, imgp, (1920, 1080))
    assert rms < 1e-3
    assert np.abs(K_est - K).max() < 0.05 and np.abs(d_est[:5] - dist).max() < 1e-4
