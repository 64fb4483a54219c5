"""The simulated devices implement the driver protocols the station codes against. These tests look at
the rendering and the operator, so they use the rig's ideal mode (no latency, a new frame per request);
its hardware-like timing is tested in tests/test_rig_timing.py."""

import numpy as np
import pytest

from calib.detection.detect import detect_board
from calib.errors import ProcamError, SpecError
from drivers.base import CameraDriver, Frame, Operator, ProjectorDriver
from drivers.errors import DeviceError
from drivers.sim import SimRig, get_scenario, open_sim_rig


@pytest.fixture(scope="module")
def rig():
    r = open_sim_rig("nonoverlap-136", seed=0, quality="live", read_noise_dn=0.0, electrons_per_dn=0.0,
                     blur_sigma_px=0.0, ideal=True)
    r.camera.start()
    return r


def test_devices_satisfy_the_protocols(rig):
    assert isinstance(rig.camera, CameraDriver)
    assert isinstance(rig.projector, ProjectorDriver)
    assert isinstance(rig.operator, Operator)
    assert rig.camera.size == (1280, 800) and rig.projector.size == (1920, 1080)
    assert rig.camera.factory_intrinsics() is None
    exposed = open_sim_rig("direct", expose_intrinsics=True)
    assert np.allclose(exposed.camera.factory_intrinsics().K, exposed.ground_truth().camera.K)
    s = rig.camera.settings()
    assert s["driver"] == "sim" and s["scenario"] == "nonoverlap-136" and "ambient" in s


def test_frames_on_request_strictly_numbered(rig):
    f1 = rig.camera.get_frame()
    f2 = rig.camera.get_frame()
    assert isinstance(f1, Frame) and f1.image.shape == (800, 1280, 3) and f1.image.dtype == np.uint8
    assert f2.frame_number > f1.frame_number and f2.timestamp_ms > f1.timestamp_ms
    f3 = rig.camera.get_frame(newer_than=f2.frame_number + 10)
    assert f3.frame_number > f2.frame_number + 10
    f4 = rig.camera.get_frame(newer_than=0)
    assert f4.frame_number > f3.frame_number


def test_camera_must_be_started():
    r = open_sim_rig("direct")
    with pytest.raises(DeviceError, match="start"):
        r.camera.get_frame()
    r.camera.start()
    r.camera.get_frame()
    r.camera.stop()
    with pytest.raises(ProcamError):
        r.camera.get_frame()


def test_projector_shows_what_it_is_given(rig):
    W, H = rig.projector.size
    img = np.zeros((H, W), np.uint8)
    img[100:200, 300:400] = 255
    t1 = rig.projector.show(img)
    assert np.array_equal(rig.projector.image, img)
    t2 = rig.projector.show(np.dstack([img] * 3))
    assert t2 > t1 and isinstance(rig.projector.wait_presented(t2), float)
    assert np.array_equal(rig.projector.image, img)
    with pytest.raises(DeviceError, match="1920x1080"):
        rig.projector.show(np.zeros((720, 1280), np.uint8))
    with pytest.raises(DeviceError):
        rig.projector.show(np.zeros((H, W), np.float32))


def test_operator_places_the_scripted_poses(rig):
    sc = rig.scenario
    text = rig.operator.request_pose("projector", 5, 2)
    assert "position 6 of 13" in text and "pose 3" in text
    expected = [T for p, T in sc.projector_poses if p == 5][2]
    assert np.allclose(rig.board.T_cam_board, expected)
    # the frame shows the board through the mirror, where the ground truth puts it
    W, H = rig.projector.size
    rig.projector.show(np.zeros((H, W), np.uint8))
    obs = detect_board(rig.camera.get_frame().image, sc.projector_board, mirrored=True)
    assert obs and len(obs.ids) >= 30
    # beyond the scripted count: further valid, deterministic poses
    rig.operator.request_pose("projector", 5, 9)
    T9 = rig.board.T_cam_board.copy()
    rig.operator.request_pose("projector", 5, 9)
    assert np.allclose(rig.board.T_cam_board, T9)
    assert not any(np.allclose(T9, T) for p, T in sc.projector_poses)
    assert detect_board(rig.camera.get_frame().image, sc.projector_board, mirrored=True)
    # mirror and verification steps
    rig.operator.request_pose("mirror-real-virtual", None, 1)
    assert np.allclose(rig.board.T_cam_board, sc.mirror_poses[1])
    assert rig.board.layout.charuco == sc.mirror_board
    rig.operator.request_pose("mirror-real-mirror", None, 0)
    n, d = sc.rig.mirror.normal, sc.rig.mirror.d
    assert abs(n @ rig.board.T_cam_board[:3, 3] + d - 3.0) < 1e-6  # lying on the mirror, 3 mm thick
    rig.operator.request_pose("verification", None, 0)
    assert np.allclose(rig.board.T_cam_board, sc.verification_pose)
    with pytest.raises(SpecError):
        rig.operator.request_pose("dance", None, 0)


def test_asked_for_a_pose_the_operator_holds_it_a_few_degrees_and_millimetres_off(rig):
    """A person holding a board on a shown outline: off by SimOperator.FOLLOW_DEG / FOLLOW_MM (1-sigma),
    always a valid placement, the same for the same request, and never a pose that is not finite."""
    from calib.synthetic import projector_pose_ok
    from calib.transforms import rotation_angle_deg

    sc = rig.scenario
    T = [T for p, T in sc.projector_poses if p == 6][0]
    centre = lambda P: P[:3, :3] @ sc.layout.blank_centre + P[:3, 3]  # noqa: E731
    degs, mms = [], []
    for index in range(12):
        text = rig.operator.request_pose("projector", 6, index, asked=T)
        held = rig.board.T_cam_board
        assert "the pose asked for" in text and "dashed outline" in text
        assert np.allclose(held, rig.operator.last_pose) and projector_pose_ok(sc.rig, sc.layout, sc.pattern, 6, held)
        degs.append(rotation_angle_deg(held[:3, :3] @ T[:3, :3].T))
        mms.append(float(np.linalg.norm(centre(held) - centre(T))))
    # rotation about a random axis, 1-sigma FOLLOW_DEG; shift 1-sigma FOLLOW_MM per axis (~1.6x in 3D)
    assert 0.3 * rig.operator.FOLLOW_DEG < np.median(degs) < 3 * rig.operator.FOLLOW_DEG
    assert 0.5 * rig.operator.FOLLOW_MM < np.median(mms) < 3 * rig.operator.FOLLOW_MM
    again = rig.operator.request_pose("projector", 6, 11, asked=T) and rig.board.T_cam_board
    assert np.allclose(again, held)
    with pytest.raises(SpecError, match="not a finite 4x4"):
        rig.operator.request_pose("projector", 6, 0, asked=np.full((4, 4), np.nan))
    with pytest.raises(SpecError):
        rig.operator.request_pose("projector", 13, 0)


def test_move_out_empties_the_view(rig):
    rig.operator.request_pose("projector", 0, 0)
    with_board = rig.camera.get_frame().image
    rig.operator.move_out()
    assert rig.board is None
    empty = rig.camera.get_frame().image
    assert not np.array_equal(with_board, empty)
    assert not detect_board(empty, rig.scenario.projector_board, mirrored=True)
    assert rig.camera.get_frame().meta["T_cam_board"] is None


def test_settling_frames_show_motion_then_stillness():
    r = open_sim_rig("nonoverlap-136", settling_frames=3, read_noise_dn=0.0, electrons_per_dn=0.0, ideal=True)
    r.camera.start()
    r.operator.request_pose("projector", 4, 0)
    r.operator.request_pose("projector", 4, 1)
    frames = [r.camera.get_frame() for _ in range(6)]
    assert [f.meta["moving"] for f in frames] == [True, True, True, False, False, False]
    imgs = [f.image.astype(int) for f in frames]
    for a, b in zip(imgs[:3], imgs[1:4]):
        assert np.abs(a - b).max() > 50  # the board moved between these frames
    assert np.array_equal(imgs[3], imgs[4]) and np.array_equal(imgs[4], imgs[5])
    assert np.allclose(frames[-1].meta["T_cam_board"], [T for p, T in r.scenario.projector_poses if p == 4][1])


def test_noise_is_reproducible_per_frame_number():
    a = open_sim_rig("direct", seed=3, ideal=True)
    b = open_sim_rig("direct", seed=3, ideal=True)
    for r in (a, b):
        r.camera.start()
        r.operator.request_pose("projector", 0, 0)
    fa, fb = a.camera.get_frame(), b.camera.get_frame()
    assert np.array_equal(fa.image, fb.image)
    assert not np.array_equal(fa.image, a.camera.get_frame().image)  # fresh noise in the next frame


def test_ground_truth_and_direct_rig():
    r = open_sim_rig("direct")
    gt = r.ground_truth()
    assert gt.mirror is None and gt.units == "mm"
    assert np.allclose(gt.T_cam_proj, get_scenario("direct").rig.T_cam_proj)
    with pytest.raises(DeviceError, match="no mirror"):
        r.operator.request_pose("mirror-real-virtual", None, 0)
    with pytest.raises(SpecError):
        open_sim_rig("direct", quality="ultra")
    with pytest.raises(SpecError, match="unknown render setting"):
        open_sim_rig("direct", ambiance=0.3)
    assert isinstance(SimRig(get_scenario("direct"), "live"), SimRig)
