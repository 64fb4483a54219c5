"""The 3D view's geometry: board poses from the corners the station stored, before calibration (virtual
images behind the mirror) and after (reflected to where the boards were), the mirror and the rays."""

import numpy as np

from app.station.autocapture import approximate_camera
from app.station.rigview import rig_scene
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL
from calib.synthetic import make_rig, make_session, observe
from calib.transforms import transform_points
from _station_helpers import TINY, make_store


def store_with_captures(tmp_path, n_proj=5, n_mirror=3):
    rig = make_rig(136)
    ss = make_session(rig, per_position=1)
    obs = observe(ss)
    store = make_store(tmp_path / "s")

    # the synthetic session's boards, not the helper's defaults
    store.update(projector_board=ss.layout.charuco, mirror_board=ss.mirror_board, pattern=ss.pattern)
    for v in obs.projector_views[:n_proj]:
        store.add_capture(STEP_PROJECTOR, TINY, v.pattern_position, v.pattern_proj_px,
                          {"board_ids": v.board.ids.tolist(), "board_px": v.board.corners_px.tolist()})
    for v in obs.mirror_views[:n_mirror]:
        store.add_capture(STEP_REAL_VIRTUAL, TINY, None, None,
                          {"board_ids": v.real.ids.tolist(), "board_px": v.real.corners_px.tolist()})
    return rig, ss, store


def test_boards_are_reflected_into_place_once_calibrated(tmp_path):
    rig, ss, store = store_with_captures(tmp_path)
    truth = rig.ground_truth()
    sc = rig_scene(store.manifest, truth, approximate_camera(rig.camera.size))
    w, h = ss.layout.charuco.size
    corners = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float)
    proj = [b for b in sc.boards if b.step == STEP_PROJECTOR]
    assert len(proj) == 5 and not any(b.virtual for b in proj)
    for b, (_, T) in zip(proj, ss.projector_T_cam_board):
        assert np.abs(b.outline - transform_points(T, corners)).max() < 1e-3  # mm
    mirror = [b for b in sc.boards if b.step == STEP_REAL_VIRTUAL]
    wm, hm = ss.mirror_board.size
    mc = np.array([[0, 0, 0], [wm, 0, 0], [wm, hm, 0], [0, hm, 0]], float)
    for b, T in zip(mirror, ss.mirror_T_cam_board):
        assert np.abs(b.outline - transform_points(T, mc)).max() < 1e-3
    # the mirror quad lies on the plane, the virtual camera is the camera's reflection
    assert np.abs(truth.mirror.signed_distance(sc.mirror_quad)).max() < 1e-6
    S = truth.mirror.reflection()
    assert np.allclose(sc.virtual_camera.T_cam_dev[:3, 3], S[:3, 3])
    assert np.linalg.det(sc.virtual_camera.T_cam_dev[:3, :3]) > 0
    # one ray per projector board, from the projector to the pattern's centre on the board
    assert sc.rays.shape == (5, 2, 3)
    assert np.allclose(sc.rays[:, 0], truth.T_cam_proj[:3, 3])
    for ray, (_, T) in zip(sc.rays, ss.projector_T_cam_board):
        assert abs((ray[1] - T[:3, 3]) @ T[:3, 2]) < 1e-6  # ends on the board's plane


def test_before_calibration_the_boards_are_seen_in_the_mirror(tmp_path):
    rig, ss, store = store_with_captures(tmp_path, n_mirror=0)
    sc = rig_scene(store.manifest, None, rig.camera)  # exact intrinsics, no mirror known yet
    assert sc.projector is None and sc.mirror_quad is None and len(sc.rays) == 0
    S = rig.mirror.reflection()
    w, h = ss.layout.charuco.size
    corners = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float)
    for b, (_, T) in zip(sc.boards, ss.projector_T_cam_board):
        assert b.virtual
        # where the camera sees the board: its mirror image
        assert np.abs(b.outline - transform_points(S @ T, corners)).max() < 1e-3
