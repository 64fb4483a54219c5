"""Projected circles are not points: the centroid of an imaged circle is not the image of its centre
(docs/GEOMETRY.md). The bias is shown (its size, growing with the radius squared and with obliqueness),
and the joint refinement's conic model removes it where the point model does not."""

import numpy as np
import pytest

from _joint_helpers import ground_truth, observations, session
from calib.joint.conic import circle_boundary, circle_frame, ellipse_image_centre, polygon_centroid
from calib.joint.method import JointOptions, build_problem, refine_joint
from calib.models.pattern import PatternSpec
from calib.quality.metrics import compare
from calib.synthetic import imaged_circle_centroids, projector_points_on_board
from calib.transforms import rotation_about, transform_points

BIG = PatternSpec("circles", 4, 9, spacing_px=60.0, radius_px=24.0)


def _plane_homography(tilt_deg: float, f: float = 1000.0, distance: float = 1000.0) -> np.ndarray:
    """Pixels of a camera (f, principal point 0) looking at a plane tilted by tilt_deg about x, from
    plane coordinates (mm, origin on the optical axis)."""
    R = rotation_about([1, 0, 0], tilt_deg)
    K = np.diag([f, f, 1.0])
    return K @ np.column_stack([R[:, 0], R[:, 1], [0, 0, distance]])


def _bias_px(H: np.ndarray, radius: float, centre=(0.0, 0.0)) -> tuple[float, float]:
    """(|polygon centroid - image of the centre|, |conic centre - polygon centroid|) in pixels."""
    ring = circle_boundary(np.array([centre]), radius, 512)[0]
    img = np.c_[ring, np.ones(len(ring))] @ H.T
    poly = img[:, :2] / img[:, 2:]
    cen = polygon_centroid(poly)
    c = H @ [centre[0], centre[1], 1.0]
    conic = ellipse_image_centre(H @ circle_frame(np.array(centre), np.eye(2), radius))
    return float(np.linalg.norm(cen - c[:2] / c[2])), float(np.linalg.norm(conic - cen))


def test_bias_grows_with_radius_squared_and_with_obliqueness():
    tilts = (0, 15, 30, 45)
    biases = [_bias_px(_plane_homography(t), 20.0)[0] for t in tilts]
    assert biases[0] < 1e-9  # fronto-parallel: an ellipse centred on the image of the centre
    assert all(b2 > 1.1 * b1 for b1, b2 in zip(biases[1:], biases[2:])) and biases[1] > 0.05
    # it follows sin(2 tilt) (the image also shrinks as cos(tilt)): relative to the blob it keeps growing
    assert np.allclose(np.array(biases[1:]) / np.sin(np.radians(2 * np.array(tilts[1:]))), biases[-1], rtol=0.02)
    for t in (20, 40, 60):
        small, _ = _bias_px(_plane_homography(t), 10.0)
        big, _ = _bias_px(_plane_homography(t), 20.0)
        assert big / small == pytest.approx(4.0, rel=0.05)
    # the centre of the mapped conic IS the area centroid of the imaged circle (no distortion)
    for t in (20, 60):
        b, conic_err = _bias_px(_plane_homography(t), 20.0, centre=(30.0, -10.0))
        assert conic_err < 1e-4 * b


def test_bias_in_a_session_is_small_but_systematic():
    """Through projector, board, mirror and camera (with distortion), at the default radius (12.6 px
    in a 1920x1080 projector) the bias is a few thousandths of a pixel, 4x that at twice the radius."""
    ss = session()
    rig = ss.rig
    b1, b2 = [], []
    for pos, T in ss.projector_T_cam_board[::4]:
        q = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)
        centre = rig.camera.project(transform_points(rig.S() @ T, projector_points_on_board(rig, T, q)))
        b1.append(np.linalg.norm(imaged_circle_centroids(rig, T, q, ss.pattern.radius_px) - centre, axis=1))
        b2.append(np.linalg.norm(imaged_circle_centroids(rig, T, q, 2 * ss.pattern.radius_px) - centre, axis=1))
    b1, b2 = np.concatenate(b1), np.concatenate(b2)
    assert 5e-4 < b1.mean() < 0.01 and b1.max() < 0.02
    assert b2.mean() / b1.mean() == pytest.approx(4.0, rel=0.1)
    # the option of calib.synthetic.observe reports exactly these centroids
    obs = observations(circle_centroids=True)
    pv, (pos, T) = obs.projector_views[8], ss.projector_T_cam_board[8]
    assert np.allclose(pv.pattern_cam_px, imaged_circle_centroids(rig, T, pv.pattern_proj_px, ss.pattern.radius_px))


def test_conic_model_explains_the_observed_centroids():
    """At the true parameters the conic model predicts biased observations 6x better than the point
    model; with the 32-point centroid correction (the lens distortions' curvature across a blob),
    over 50x better."""
    kw = dict(pattern=BIG)
    obs = observations(circle_centroids=True, **kw)
    prob, _ = build_problem(obs, ground_truth(**kw), JointOptions(pattern_model="conic"), "5coef", "5coef")
    x = prob.x0()
    _, uv_conic = prob.predict(x, "conic")
    _, uv_point = prob.predict(x, "point")
    rms_conic = np.sqrt(np.mean((uv_conic - prob.pattern.uv) ** 2))
    rms_point = np.sqrt(np.mean((uv_point - prob.pattern.uv) ** 2))
    assert rms_point > 2e-3 and rms_conic < rms_point / 4
    prob.update_centroid_correction(x)
    _, uv_corr = prob.predict(x, "conic")
    assert np.sqrt(np.mean((uv_corr - prob.pattern.uv) ** 2)) < rms_point / 50


def test_joint_refinement_with_the_conic_model_is_unbiased():
    """Exact (noise-free) but biased observations of a large-circle pattern: the point model converges
    to a biased calibration, the conic model to the truth."""
    kw = dict(pattern=BIG)
    obs = observations(circle_centroids=True, **kw)
    gt = ground_truth(**kw)
    opts = dict(camera_model="5coef", projector_model="k1k2", uncertainty=False)
    point = compare(refine_joint(obs, gt, JointOptions(pattern_model="point", **opts)), gt)
    conic = compare(refine_joint(obs, gt, JointOptions(pattern_model="conic", **opts)), gt)
    assert point.proj_k_px > 0.05 and point.angle_deg > 1e-4
    assert conic.proj_k_px < point.proj_k_px / 20 and conic.distance < point.distance / 20
    assert conic.angle_deg < point.angle_deg / 20
