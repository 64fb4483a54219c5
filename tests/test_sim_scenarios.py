"""Named scenarios: the paper's set-ups, valid board poses, ground truth."""

import numpy as np
import pytest

from calib.errors import SpecError
from calib.models.result import CalibrationResult
from calib.synthetic import projector_points_on_board
from calib.transforms import rotation_angle_deg, transform_points
from drivers.sim.scenarios import DEFAULT_SCENARIO, get_scenario, list_scenarios

REQUIRED = ["direct", "nonoverlap-90", "nonoverlap-136", "nonoverlap-180", "nonoverlap-136-realmirror",
            "nonoverlap-136-720p", "nonoverlap-136-chessboard", "shortthrow"]


def test_library_names_and_default():
    names = [n for n, _ in list_scenarios()]
    assert names[0] == DEFAULT_SCENARIO == "nonoverlap-136"
    assert set(REQUIRED) <= set(names)
    assert all(desc for _, desc in list_scenarios())
    with pytest.raises(SpecError, match="unknown scenario"):
        get_scenario("nonoverlap-45")
    assert get_scenario("nonoverlap-136-720p").rig.projector.size == (1280, 720)
    assert get_scenario("nonoverlap-136-chessboard").pattern.kind == "chessboard"
    rm = get_scenario("nonoverlap-136-realmirror")
    assert rm.mirror_method == "real-mirror" and rm.board_thickness_mm == 3.0
    d = get_scenario("direct")
    assert d.rig.mirror is None and d.mirror_method is None and d.mirror_poses == []


@pytest.mark.parametrize("name", REQUIRED)
def test_ground_truth_and_non_overlap(name):
    sc = get_scenario(name)
    gt = sc.ground_truth()
    assert isinstance(gt, CalibrationResult) and gt.units == "mm"
    assert np.allclose(gt.T_cam_proj, sc.rig.T_cam_proj)
    cam, proj = gt.camera, gt.projector
    assert proj.cx != pytest.approx((proj.width - 1) / 2, abs=5)  # principal point shifted, as projectors have
    assert np.any(cam.dist != 0) and np.any(proj.dist != 0)
    if name == "direct":
        return
    angle = rotation_angle_deg(gt.T_cam_proj[:3, :3])
    assert abs(angle - sc.rig.angle_deg) < 8
    # the projector lights boards the camera sees only through the mirror
    for pos, T in sc.projector_poses[::5]:
        X = transform_points(T, sc.projector_board.corner_points())
        assert not np.any(cam.in_image(cam.project(X)))


@pytest.mark.parametrize("name", REQUIRED)
def test_projector_poses_follow_the_protocol(name):
    """13 pattern positions x 4 poses; the pattern lands inside the blank region; the board's corners
    are imaged (through the mirror rectangle, for a mirrored rig) with the printed face towards the
    viewer; poses vary like a person holds a board (tilts and distances)."""
    sc = get_scenario(name)
    rig, cam = sc.rig, sc.rig.camera
    poses = sc.projector_poses
    positions = [p for p, _ in poses]
    assert len(poses) == 52 and all(positions.count(p) == 4 for p in range(13))
    x0, y0, x1, y1 = sc.layout.blank_rect
    S = rig.S()
    tilts, dists = [], []
    for pos, T in poses:
        q = sc.pattern.points_px(*rig.projector.size, pos)
        Xb = projector_points_on_board(rig, T, q)
        assert np.all((Xb[:, 0] > x0) & (Xb[:, 0] < x1) & (Xb[:, 1] > y0) & (Xb[:, 1] < y1))
        X = transform_points(T, sc.projector_board.corner_points())
        assert np.all(cam.in_image(cam.project(transform_points(S, X))))
        if rig.mirror is not None:
            # the ray to each virtual corner crosses the mirror plane inside the rectangle
            Xv = transform_points(S, X)
            t = -rig.mirror.d / (Xv @ rig.mirror.normal)
            assert np.all((t > 0) & (t < 1)) and np.all(rig.mirror_rect.contains(t[:, None] * Xv))
        # printed face (-z of the board) towards the projector and the (virtual) camera
        P = rig.T_cam_proj[:3, 3]
        V = transform_points(S, np.zeros((1, 3)))[0]
        c = X.mean(axis=0)
        assert -T[:3, 2] @ (P - c) > 0 and -T[:3, 2] @ (V - c) > 0
        tilts.append(np.degrees(np.arccos(-T[:3, 2] @ (P - c) / np.linalg.norm(P - c))))
        dists.append(np.linalg.norm(P - c))
    assert np.ptp(tilts) > 15 and np.ptp(dists) > 100


def test_poses_depend_on_the_seed_only():
    a, b, c = get_scenario("nonoverlap-136", 1), get_scenario("nonoverlap-136", 1), get_scenario("nonoverlap-136", 2)
    assert all(np.allclose(x[1], y[1]) for x, y in zip(a.projector_poses, b.projector_poses))
    assert not np.allclose(a.projector_poses[0][1], c.projector_poses[0][1])
    assert all(np.allclose(x, y) for x, y in zip(a.mirror_poses, b.mirror_poses))


@pytest.mark.parametrize("name", ["nonoverlap-90", "nonoverlap-136", "nonoverlap-180"])
def test_real_virtual_placements_show_both_views_apart(name):
    sc = get_scenario(name)
    rig, cam, S = sc.rig, sc.rig.camera, sc.rig.S()
    assert len(sc.mirror_poses) == sc.mirror_count == 14  # as the published recordings (52 + 14)
    for T in sc.mirror_poses:
        X = transform_points(T, sc.mirror_board.corner_points())
        real, virt = cam.project(X), cam.project(transform_points(S, X))
        assert np.all(cam.in_image(real)) and np.all(cam.in_image(virt))
        assert np.all(rig.mirror.signed_distance(X) > 0)  # in front of the mirror
        # the two views do not touch in the image
        gap = np.linalg.norm(real[:, None] - virt[None], axis=2).min()
        assert gap > 20


def test_verification_pose_is_calm_and_central():
    for name in ("nonoverlap-136", "direct"):
        sc = get_scenario(name)
        rig = sc.rig
        T = sc.verification_pose
        P = rig.T_cam_proj[:3, 3]
        c = transform_points(T, sc.layout.blank_centre[None])[0]
        to_p = (P - c) / np.linalg.norm(P - c)
        assert np.degrees(np.arccos(-T[:3, 2] @ to_p)) < 25  # about frontal to the projector
        q = rig.projector.project(transform_points(np.linalg.inv(rig.T_cam_proj), c[None]))[0]
        assert np.linalg.norm(q - [(rig.projector.width - 1) / 2, (rig.projector.height - 1) / 2]) < 60
        X = transform_points(rig.S() @ T, sc.projector_board.corner_points())
        assert np.all(rig.camera.in_image(rig.camera.project(X)))
