"""Epipolar curves (calib.epipolar) against analytic cases and the synthetic rigs' ground truth."""

import numpy as np
import pytest

from calib.models.camera import CameraModel
from calib.epipolar import (
    camera_curve_for_projector_pixel,
    camera_ray,
    default_depth_range,
    distance_to_polyline,
    epipolar_curve,
    epipolar_curve_samples,
    fundamental_matrix,
    predicted_camera_curve,
)
from calib.synthetic import make_direct_rig, make_rig, make_session, projector_points_on_board
from calib.transforms import invert_T, make_T, rotation_about, transform_points

RIGS = {"90": lambda **kw: make_rig(90, **kw), "136": lambda **kw: make_rig(136, **kw),
        "180": lambda **kw: make_rig(180, **kw), "direct": lambda **kw: make_direct_rig(**kw)}


def _no_distortion(model: CameraModel) -> CameraModel:
    return model.with_params(dist=np.zeros(5))


def _proj_px_of(result, X_cam):
    return result.projector.project(transform_points(invert_T(result.T_cam_proj), X_cam))


def _cam_px_of(result, X_cam):
    S = np.eye(4) if result.mirror is None else result.mirror.reflection()
    return result.camera.project(transform_points(S, X_cam))


@pytest.mark.parametrize("name", sorted(RIGS))
def test_without_distortion_the_curve_is_the_fundamental_matrix_line(name, rng):
    rig = RIGS[name]()
    res = rig.ground_truth().with_(camera=_no_distortion(rig.camera), projector=_no_distortion(rig.projector))
    F = fundamental_matrix(res)
    n_checked = 0
    for u in rng.uniform([100, 80], [1180, 720], (60, 2)):
        q = epipolar_curve(res, u, tol_px=1e-9)
        if len(q) == 0:
            continue
        n_checked += 1
        line = F @ np.array([u[0], u[1], 1.0])
        d = (q @ line[:2] + line[2]) / np.linalg.norm(line[:2])
        assert np.abs(d).max() < 1e-6
        # a straight line: no subdivision was needed beyond the initial samples
        assert len(q) == 64
        # its ends are on the projector image border or at the depth limits
        assert np.all(res.projector.in_image(q))
    assert n_checked >= 6


@pytest.mark.parametrize("name", sorted(RIGS))
def test_with_distortion_the_curve_passes_through_every_projected_ray_point(name, rng):
    rig = RIGS[name]()
    res = rig.ground_truth()
    n_checked = 0
    for u in rng.uniform([100, 80], [1180, 720], (40, 2)):
        c = epipolar_curve_samples(res, u, tol_px=1e-8)
        if len(c) == 0:
            continue
        n_checked += 1
        if n_checked > 6:
            break
        ray = camera_ray(res, u)
        t = rng.uniform(c.depths[0], c.depths[-1], 50)
        X = ray.points(t)
        # the sampled points are really seen at u
        assert np.abs(_cam_px_of(res, X) - u).max() < 1e-6
        d = distance_to_polyline(_proj_px_of(res, X), c.px)
        assert d.distance.max() < 1e-6
        # and the polyline is genuinely curved (distortion): the F-line misses some samples
        line = fundamental_matrix(res) @ np.array([u[0], u[1], 1.0])
        off = np.abs(c.px @ line[:2] + line[2]) / np.linalg.norm(line[:2])
        assert off.max() > 1e-3
    assert n_checked > 6


@pytest.mark.parametrize("name", sorted(RIGS))
def test_ground_truth_curve_passes_through_the_true_board_point(name):
    rig = RIGS[name]()
    res = rig.ground_truth()
    ss = make_session(rig, per_position=1, seed=2)
    worst = 0.0
    for pos, T in ss.projector_T_cam_board:
        q = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)[::11]
        Xb = projector_points_on_board(rig, T, q)  # board points lit by q
        u = _cam_px_of(res, transform_points(T, Xb))  # where the camera sees them
        for ui, qi in zip(u, q):
            worst = max(worst, distance_to_polyline(qi, epipolar_curve(res, ui, tol_px=1e-8)).distance[0])
    assert worst < 1e-6


def test_depth_range_default_and_limits():
    rig = make_rig(136)
    res = rig.ground_truth()
    lo, hi = default_depth_range("mm")
    assert (lo, hi) == (200.0, 5000.0)
    c = epipolar_curve_samples(res, (640, 400))
    assert lo <= c.depths.min() and c.depths.max() <= hi + 1e-9
    assert np.all(np.diff(c.depths) > 0)
    # the ray is clipped where it leaves the projector image (not at the far depth here: 136 deg rig)
    on_border = ~res.projector.in_image(c.px[[0, -1]], margin_px=1e-6)
    assert on_border.any()
    # a narrower depth range gives a sub-curve
    c2 = epipolar_curve_samples(res, (640, 400), depth_range=(1000.0, 1500.0), tol_px=1e-8)
    assert c2.depths[0] == pytest.approx(1000.0) and c2.depths[-1] == pytest.approx(1500.0)
    assert distance_to_polyline(c2.px, c.px).distance.max() < 1e-2
    # units: the same rig in metres gives the same curve
    T = np.array(res.T_cam_proj)
    T[:3, 3] /= 1000.0
    from calib.models.result import MirrorPlane

    res_m = res.with_(T_cam_proj=T, mirror=MirrorPlane(res.mirror.normal, res.mirror.d / 1000.0), units="m")
    cm = epipolar_curve_samples(res_m, (640, 400))
    assert cm.depths[-1] == pytest.approx(c.depths[-1] / 1000.0)
    assert distance_to_polyline(cm.px, c.px).distance.max() < 1e-2


def test_pixel_that_misses_the_mirror_gives_an_empty_curve():
    rig = make_rig(136)
    res = rig.ground_truth()
    # tilt the mirror so that it faces away from some pixels' rays: the plane is behind the camera
    from calib.models.result import MirrorPlane

    away = res.with_(mirror=MirrorPlane(np.array([0.0, 0.0, 1.0]), 100.0))  # plane z = -100 mm
    assert camera_ray(away, (640, 400)) is None
    assert epipolar_curve(away, (640, 400)).shape == (0, 2)


@pytest.mark.parametrize("name", ["136", "direct"])
def test_inverse_curve_is_consistent(name, rng):
    """q on the epipolar curve of u  <=>  u on the camera curve of q."""
    rig = RIGS[name]()
    res = rig.ground_truth()
    centre = _cam_px_of(res, rig.board_target[None])[0]  # the middle of where the projector lights
    for u in centre + rng.uniform(-100, 100, (4, 2)):
        c = epipolar_curve_samples(res, u)
        assert len(c) > 0
        for q in c.px[len(c) // 4 :: max(1, len(c) // 3)]:
            back = camera_curve_for_projector_pixel(res, q, tol_px=1e-8)
            assert len(back) > 0
            assert distance_to_polyline(u, back.px).distance[0] < 1e-3  # q is only known to tol_px
            # the inverse curve's points are lit by q and seen where it says
            assert np.abs(_proj_px_of(res, back.points) - q).max() < 1e-6
            assert np.abs(_cam_px_of(res, back.points) - back.px).max() < 1e-6


@pytest.mark.parametrize("name", ["136", "direct"])
def test_predicted_camera_curve_is_the_image_of_the_drawn_curve_on_the_board(name, rng):
    rig = RIGS[name]()
    res = rig.ground_truth()
    ss = make_session(rig, per_position=1, seed=4)
    pos, T = ss.projector_T_cam_board[6]
    q0 = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)[10]
    u = _cam_px_of(res, transform_points(T, projector_points_on_board(rig, T, q0[None])))[0]
    pred = predicted_camera_curve(res, u, T, tol_px=1e-8)
    assert len(pred) > 10
    assert distance_to_polyline(u, pred).distance[0] < 1e-6
    # every drawn projector pixel lands on the board where the camera sees it on the predicted curve
    q = epipolar_curve(res, u)
    Xb = projector_points_on_board(rig, T, q)
    seen = _cam_px_of(res, transform_points(T, Xb))
    seen = seen[res.camera.in_image(seen)]
    assert len(seen) > 10
    assert distance_to_polyline(seen, pred).distance.max() < 1e-3
    # the plane given as (n, offset) is the same thing
    n = T[:3, 2]
    pred2 = predicted_camera_curve(res, u, (2 * n, -2 * n @ T[:3, 3]), tol_px=1e-8)
    assert distance_to_polyline(pred2, pred).distance.max() < 1e-6


def test_a_perturbed_calibration_misses_the_true_pixel():
    rig = make_rig(136)
    res = rig.ground_truth()
    ss = make_session(rig, per_position=1, seed=2)
    pos, T = ss.projector_T_cam_board[0]
    q = ss.pattern.points_px(rig.projector.width, rig.projector.height, pos)[17]
    u = _cam_px_of(res, transform_points(T, projector_points_on_board(rig, T, q[None])))[0]
    Tp = np.array(res.T_cam_proj)
    Tp = Tp @ make_T(rotation_about([1, 0, 0], 0.5), np.zeros(3))  # 0.5 deg about the projector's x
    bad = res.with_(T_cam_proj=Tp)
    assert distance_to_polyline(q, epipolar_curve(bad, u)).distance[0] > 5.0


def test_distance_to_polyline_is_exact(rng):
    poly = np.cumsum(rng.normal(size=(30, 2)) * 5, axis=0)
    P = rng.uniform(poly.min(0) - 5, poly.max(0) + 5, (80, 2))
    d = distance_to_polyline(P, poly)
    # brute force: dense points on each segment
    s = np.linspace(0, 1, 2001)
    dense = (poly[:-1, None, :] * (1 - s)[None, :, None] + poly[1:, None, :] * s[None, :, None]).reshape(-1, 2)
    brute = np.min(np.linalg.norm(P[:, None] - dense[None], axis=2), axis=1)
    assert np.abs(d.distance - brute).max() < 5e-3
    assert np.all(d.distance <= brute + 1e-12)
    assert np.allclose(np.linalg.norm(P - d.closest, axis=1), d.distance)
    # signs and interior on a simple case: a line along +x
    line = np.array([[0.0, 0.0], [10.0, 0.0]])
    r = distance_to_polyline([[5, 2], [5, -3], [12, 0.5], [-1, 0]], line)
    assert np.allclose(r.distance, [2, 3, np.hypot(2, 0.5), 1])
    assert np.allclose(r.signed[:2], [2, -3])
    assert r.interior.tolist() == [True, True, False, False]
    with pytest.raises(ValueError):
        distance_to_polyline([[0, 0]], np.zeros((0, 2)))
