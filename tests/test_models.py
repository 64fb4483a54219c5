"""Camera model, transforms, specs and the synthetic rig agree with OpenCV and with docs/GEOMETRY.md."""

import cv2
import numpy as np
import pytest

from calib.errors import FormatError, SpecError
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.pattern import PatternSpec
from calib.synthetic import d455_camera, make_direct_rig, make_rig, make_session, observe
from calib.transforms import FLIP_X, invert_T, make_T, reflection_T, rotation_about, transform_points


def test_project_matches_opencv(rng):
    cam = CameraModel(1280, 800, [[640, 0, 630], [0, 645, 410], [0, 0, 1]], [0.1, -0.2, 0.001, -0.002, 0.05])
    X = rng.uniform([-1, -1, 1], [1, 1, 2], (200, 3))
    ref = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    assert np.abs(cam.project(X) - ref).max() < 1e-9


def test_rays_invert_projection(rng):
    cam = d455_camera()
    X = rng.uniform([-1, -0.6, 1], [1, 0.6, 2], (500, 3))
    r = cam.rays(cam.project(X))
    assert np.abs(r / r[:, 2:] - X / X[:, 2:]).max() < 1e-9


def test_flipped_model_images_the_flipped_scene(rng):
    """docs/GEOMETRY.md: the flipped image is seen by V' with cx' = W-1-cx, p2' = -p2, and points x -> -x."""
    cam = CameraModel(1280, 800, [[640, 0, 600], [0, 645, 410], [0, 0, 1]], [0.1, -0.2, 0.003, -0.004, 0.05])
    X = rng.uniform([-1, -1, 1], [1, 1, 2], (200, 3))
    flipped = cam.flipped()
    assert flipped.cx == pytest.approx(1279 - 600)
    assert flipped.dist[3] == pytest.approx(0.004) and flipped.dist[2] == pytest.approx(0.003)
    assert np.abs(flipped.project(X * [-1, 1, 1]) - cam.flip_points(cam.project(X))).max() < 1e-9
    assert np.allclose(flipped.flipped().K, cam.K) and np.allclose(flipped.flipped().dist, cam.dist)


def test_reflection_is_improper_involution(rng):
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    S = reflection_T(n, 0.7)
    assert np.allclose(S @ S, np.eye(4))
    assert np.linalg.det(S[:3, :3]) == pytest.approx(-1)
    X = rng.normal(size=(10, 3))
    mid = (X + transform_points(S, X)) / 2
    assert np.allclose(mid @ n + 0.7, 0)


def test_board_pose_from_flipped_view_is_rigid(rng):
    """T_cam_board = S F T_V'_board is proper, and V' sees the flipped projection of the reflected board."""
    rig = make_rig(136)
    S = rig.mirror.reflection()
    T = make_T(rotation_about([0.3, 1, 0.2], 150), rig.board_target)
    T_V_board = FLIP_X @ S @ T
    assert np.linalg.det(T_V_board[:3, :3]) == pytest.approx(1)
    Xb = CharucoSpec(8, 6, "DICT_5X5_50", 50, 25).corner_points()
    seen = rig.camera.project(transform_points(S @ T, Xb))
    seen_flipped = rig.camera.flipped().project(transform_points(T_V_board, Xb))
    assert np.abs(rig.camera.flip_points(seen) - seen_flipped).max() < 1e-9
    assert np.allclose(S @ FLIP_X @ T_V_board, T)


def test_charuco_spec_parse_and_errors():
    s = CharucoSpec.parse("8x6:DICT_5X5_50:4.43", units="cm")
    assert (s.cols, s.rows, s.square_length, s.marker_length, s.units) == (8, 6, 4.43, 2.215, "cm")
    assert np.allclose(s.corner_points(), s.cv_board().getChessboardCorners(), atol=1e-6)
    for bad in ("8x6", "8x6:DICT_NOPE:4", "8:DICT_5X5_50:4", "8x6:DICT_5X5_50:4:5", "40x40:DICT_4X4_50:1"):
        with pytest.raises(SpecError):
            CharucoSpec.parse(bad)
    with pytest.raises(FormatError, match="projector_board.cols"):
        CharucoSpec.from_dict({"rows": 6}, "projector_board")


def test_rendered_charuco_corners_follow_pixel_centre_convention():
    spec = CharucoSpec(8, 6, "DICT_5X5_50", 40.0, 20.0)
    img = spec.render(px_per_unit=2.0, margin_px=30)
    corners, ids, *_ = cv2.aruco.CharucoDetector(spec.cv_board()).detectBoard(img)
    expected = spec.corner_points()[ids, :2] * 2.0 - 0.5 + 30
    assert len(ids) == spec.n_corners and np.abs(corners - expected).max() < 0.01


@pytest.mark.parametrize("kind", ["circles", "chessboard"])
@pytest.mark.parametrize("size", [(1920, 1080), (1280, 720)])
def test_pattern_points_are_where_opencv_finds_them(kind, size):
    spec = PatternSpec.default_for(*size, kind=kind)
    offsets = spec.offsets(*size)
    assert len(offsets) == 13
    for pos in range(spec.positions):
        img, pts = spec.render(*size, pos)
        found = spec.find(img)
        assert found is not None, f"position {pos}"
        assert np.abs(found - pts).max() < 0.05
    # the 13 positions reach the projector's corners: what is drawn touches the margin
    ys, xs = np.nonzero(spec.render(*size, 0)[0])
    assert xs.min() <= spec.margin_px + 1 and ys.min() <= spec.margin_px + 1
    ys, xs = np.nonzero(spec.render(*size, 8)[0])
    assert xs.max() >= size[0] - 2 - spec.margin_px and ys.max() >= size[1] - 2 - spec.margin_px


def test_pattern_spec_errors():
    with pytest.raises(SpecError):
        PatternSpec("dots")
    with pytest.raises(SpecError):
        PatternSpec("circles", 4, 9, spacing_px=10, radius_px=9)
    with pytest.raises(SpecError, match="does not fit"):
        PatternSpec("circles", 4, 9, spacing_px=200, radius_px=20).offsets(640, 480)


@pytest.mark.parametrize("angle", [90, 136, 180])
def test_synthetic_mirror_rig_is_non_overlapping_and_consistent(angle):
    rig = make_rig(angle)
    ss = make_session(rig, seed=3)
    obs = observe(ss)
    assert len(obs.projector_views) == 13 * 4 and len(obs.mirror_views) == 7
    # the camera cannot see the boards directly: direct projections fall outside the image
    for pos, T in ss.projector_T_cam_board:
        X = transform_points(T, ss.layout.charuco.corner_points())
        assert not np.any(rig.camera.in_image(rig.camera.project(X)))
    # projector pixels land back where they were drawn
    v = obs.projector_views[5]
    T = ss.projector_T_cam_board[5][1]
    from calib.synthetic import projector_points_on_board

    Xb = projector_points_on_board(rig, T, v.pattern_proj_px)
    X_proj = transform_points(invert_T(rig.T_cam_proj) @ T, Xb)
    assert np.abs(rig.projector.project(X_proj) - v.pattern_proj_px).max() < 1e-6
    assert abs(np.degrees(np.arccos(rig.T_cam_proj[2, 2])) - angle) < 6


def test_synthetic_direct_rig():
    obs = observe(make_session(make_direct_rig()))
    assert obs.view == "direct" and len(obs.projector_views) == 52 and obs.mirror_views == ()
