"""Auto-capture logic on exact synthetic observations: pose features, stillness, novelty, bars."""

import numpy as np
import pytest

from app.station.autocapture import (
    AutoCapture,
    AutoCaptureSettings,
    LiveDetection,
    PoseFeatures,
    diversity_bars,
    pose_distance,
    pose_features,
)
from calib.models.boards import CharucoSpec
from calib.models.observations import BoardObservation
from calib.synthetic import d455_camera
from calib.transforms import make_T, rotation_about, transform_points

BOARD = CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0)
CAM = d455_camera()


def board_at(tilt_deg=0.0, axis=(0, 1, 0), centre=(0.0, 0.0, 900.0), spin_deg=0.0):
    """T_cam_board of the board centred on `centre`, facing the camera, tilted about `axis`."""
    R = rotation_about(axis, tilt_deg) @ rotation_about([0, 0, 1], spin_deg)
    w, h = BOARD.size
    return make_T(R, np.array(centre) - R @ np.array([w / 2, h / 2, 0.0]))


def observe(T, noise=0.0, rng=None, mirrored=False):
    uv = CAM.project(transform_points(T, BOARD.corner_points()))
    if noise:
        uv = uv + rng.normal(0, noise, uv.shape)
    if mirrored:  # seen through a mirror (here the plane x = 0): the image of the reflected board
        uv = CAM.project(transform_points(T, BOARD.corner_points()) * [-1, 1, 1])
    return BoardObservation(np.arange(BOARD.n_corners), uv, mirrored)


def det(obs, frame=0, failure=None):
    return LiveDetection("projector", frame, CAM.size, board=obs, features=pose_features(obs, BOARD, CAM),
                         failure=failure)


@pytest.mark.parametrize("tilt", [0.0, 15.0, 35.0])
def test_pose_features_measure_tilt_size_and_centre(tilt):
    f = pose_features(observe(board_at(tilt)), BOARD, CAM)
    # the board's normal against the line of sight to its centre (on the optical axis here)
    assert f.tilt_deg == pytest.approx(tilt, abs=0.5)
    assert f.centre[0] == pytest.approx(CAM.cx / CAM.width, abs=0.02)
    near = pose_features(observe(board_at(tilt, centre=(0, 0, 600.0))), BOARD, CAM)
    assert near.size > f.size * 1.3


def test_mirrored_view_gives_the_same_tilt():
    T = board_at(25.0, axis=(1, 0, 0))
    a = pose_features(observe(T), BOARD, CAM)
    b = pose_features(observe(T, mirrored=True), BOARD, CAM)
    assert b.tilt_deg == pytest.approx(a.tilt_deg, abs=0.5)


def test_pose_distance():
    a = pose_features(observe(board_at(10.0)), BOARD, CAM)
    b = pose_features(observe(board_at(22.0)), BOARD, CAM)
    assert pose_distance(a, b)["rotation_deg"] == pytest.approx(12.0, abs=0.5)
    assert pose_distance(a, a)["rotation_deg"] == pytest.approx(0.0, abs=1e-3)
    rt = PoseFeatures.from_dict(a.to_dict())
    assert pose_distance(a, rt)["rotation_deg"] < 0.01 and rt.tvec is not None


def test_captures_only_when_still(rng):
    ac = AutoCapture(AutoCaptureSettings(still_frames=3, still_px=1.0))
    # the board sweeps across: never captured however long it moves
    for i in range(8):
        d = ac.update(det(observe(board_at(10.0, centre=(i * 15.0, 0, 900.0)), 0.1, rng), i))
        assert not d.capture and not d.still and "still" in d.message
    # it stops (sensor noise only): captured on the third still frame
    decisions = [ac.update(det(observe(board_at(10.0, centre=(120.0, 0, 900.0)), 0.1, rng), 10 + i)) for i in range(3)]
    assert [d.capture for d in decisions] == [False, False, True]
    assert decisions[-1].motion_px < 1.0


def test_no_capture_without_a_usable_detection(rng):
    ac = AutoCapture()
    for i in range(5):
        d = ac.update(det(observe(board_at(5.0), 0.05, rng), i, failure="pattern: pattern not found"))
        assert not d.capture and d.message == "pattern: pattern not found"
    d = ac.update(LiveDetection("projector", 9, CAM.size, failure="board: board not found"))
    assert not d.capture and not d.still


def test_a_pose_like_one_taken_is_not_captured_again(rng):
    ac = AutoCapture()
    taken = pose_features(observe(board_at(12.0)), BOARD, CAM)
    ac.reset([("p0001", taken)])
    for i in range(5):
        d = ac.update(det(observe(board_at(13.0), 0.05, rng), i))
        assert not d.capture
    assert d.still and not d.novel and d.similar_to == "p0001" and "too close to p0001" in d.message
    # tilted further: a new pose
    ac.reset()
    ds = [ac.update(det(observe(board_at(12.0 + 15.0, axis=(1, 0, 0)), 0.05, rng), 10 + i)) for i in range(3)]
    assert ds[-1].capture and ds[-1].novel


def test_diversity_bars_fill_up():
    poses = [board_at(t, axis=a, centre=c) for t, a, c in [
        (5.0, (0, 1, 0), (0, 0, 900.0)), (30.0, (1, 0, 0), (-250, -120, 800.0)), (20.0, (0, 1, 0), (260, 140, 1300.0))]]
    feats = [pose_features(observe(T), BOARD, CAM) for T in poses]
    one = diversity_bars(feats[:1])
    three = diversity_bars(feats)
    assert all(b.fraction == 0.0 for b in one)
    assert [b.name for b in three] == ["position x", "position y", "size", "tilt"]
    assert all(b3.fraction > b1.fraction for b1, b3 in zip(one, three))
    assert all(0.0 <= b.fraction <= 1.0 for b in three)
    assert diversity_bars([])[0].detail == "no poses yet"
