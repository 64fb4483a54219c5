"""Per-point weights: a structured-light point's own sigma (its local-homography fit's covariance,
carried into camera pixels by calib.detection.structured_view.camera_sigma_px) weighs it in the joint
adjustment relative to its class (calib.joint.assembly.relative_noise); points without one are alike."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from _joint_helpers import ground_truth, observations
from calib.detection.structured_view import camera_sigma_px
from calib.joint.assembly import REL_MAX, REL_MIN, relative_noise
from calib.joint.method import JointOptions, build_problem, refine_joint
from calib.joint.robust import class_sigmas
from calib.models.observations import ProjectorView
from calib.pipeline import calibrate_observations
from calib.quality.metrics import compare


def test_camera_sigma_is_the_projector_covariance_through_the_maps_jacobian():
    H = np.array([[1.7, 0.2, 300.0], [-0.1, 1.5, 120.0], [2e-4, -1e-4, 1.0]])
    rng = np.random.default_rng(0)
    proj = rng.uniform([50, 50], [1200, 750], (40, 2))
    cam = cv2.perspectiveTransform(proj[:, None], H)[:, 0]
    A = rng.normal(size=(40, 2, 2)) * 0.01
    cov = A @ np.transpose(A, (0, 2, 1)) + 1e-5 * np.eye(2)
    s = camera_sigma_px(cam, proj, cov)
    for i in range(40):  # the Jacobian by central differences
        J = np.zeros((2, 2))
        for k in range(2):
            d = np.zeros(2)
            d[k] = 1e-4
            J[:, k] = (cv2.perspectiveTransform((proj[i] + d)[None, None], H)[0, 0]
                       - cv2.perspectiveTransform((proj[i] - d)[None, None], H)[0, 0]) / 2e-4
        assert s[i] == pytest.approx(np.sqrt(np.trace(J @ cov[i] @ J.T) / 2), rel=1e-5)


def test_relative_noise_is_against_the_median_and_bounded():
    rel = relative_noise(np.array([0.01, 0.02, 0.02, 0.04, 1.0, 1e-6, np.nan]))
    assert rel[:4] == pytest.approx([0.5, 1.0, 1.0, 2.0])
    assert rel[4] == REL_MAX and rel[5] == REL_MIN and rel[6] == 1.0
    assert np.all(relative_noise(np.full(5, np.nan)) == 1.0)


def test_a_view_refuses_sigmas_it_cannot_use():
    pv = observations().projector_views[0]
    n = len(pv.pattern_cam_px)
    for bad in (np.ones(n - 1), np.zeros(n), np.full(n, np.nan)):
        with pytest.raises(ValueError, match="pattern_sigma_px"):
            ProjectorView(pv.capture_id, pv.board, pv.pattern_cam_px, pv.pattern_proj_px, None, bad)


def _mixed_noise(obs, seed: int, low: float, high: float):
    """Every view's pattern points, a random half with `high` px noise and the rest `low`; returns the
    observations with and without the points' sigmas."""
    rng = np.random.default_rng(seed)
    weighted, plain = [], []
    for pv in obs.projector_views:
        n = len(pv.pattern_cam_px)
        s = np.where(rng.random(n) < 0.5, high, low)
        uv = np.asarray(pv.pattern_cam_px) + rng.normal(size=(n, 2)) * s[:, None]
        weighted.append(replace(pv, pattern_cam_px=uv, pattern_sigma_px=s))
        plain.append(replace(pv, pattern_cam_px=uv))
    return replace(obs, projector_views=tuple(weighted)), replace(obs, projector_views=tuple(plain))


def test_the_class_sigma_is_that_of_the_median_point():
    """At the true calibration the residuals are the points' noise: whitened by each point's relative
    noise, the pattern class's sigma is the median point's, and each point's weight is its own."""
    w, _ = _mixed_noise(observations(0.02, 1), 1, 0.1, 0.35)
    prob, _ = build_problem(w, ground_truth(), JointOptions(pattern_model="point"), "5coef", "k1k2")
    sig = class_sigmas(prob, prob.raw_residuals(prob.x0()), JointOptions(), robust=False)
    own = np.concatenate([v.pattern_sigma_px for v in w.projector_views])
    assert sig["pattern"] == pytest.approx(np.median(own), rel=0.1)
    prob.set_class_sigmas(sig)
    assert prob.point_sigma[len(prob.corners):] == pytest.approx(sig["pattern"] * relative_noise(own))
    for name, m in prob.class_masks().items():  # corners: their class's sigma alone
        if name != "pattern":
            assert prob.point_sigma[m] == pytest.approx(sig[name])


def test_points_weighed_by_their_sigma_give_a_better_projector():
    """Half of the pattern points 4 times noisier than the rest: with each point's sigma the projector's
    intrinsics and pose come out closer to the truth than with every point alike (means of three noise
    draws; the gain is modest, about 10 %, because the board poses' corner noise limits them too, and
    without the sigmas the robust pass rejects the noisiest points instead of weighing them)."""
    gt = ground_truth()
    err = {"weighted": [], "plain": []}
    for s in range(3):
        w, p = _mixed_noise(observations(0.05, s), s, 0.1, 0.4)
        init = calibrate_observations(p, "paper")
        for name, obs in (("weighted", w), ("plain", p)):
            m = compare(refine_joint(obs, init, JointOptions(uncertainty=False)), gt)
            err[name].append((m.proj_k_px, m.distance))
    wk, wd = np.mean(err["weighted"], axis=0)
    pk, pd = np.mean(err["plain"], axis=0)
    assert wk < pk and wd < pd, (wk, pk, wd, pd)
