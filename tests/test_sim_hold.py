"""How still the simulated operator keeps a board (drivers/sim/hold.py), and the motion check that has to
tell a board held by hand from one on a stand (calib.detection.structured_view.board_motion_px)."""

import numpy as np
import pytest

from calib.detection import detect as D
from calib.detection.structured_view import MAX_MOTION_PX, board_motion_px
from calib.errors import SpecError
from calib.models.observations import BoardObservation
from calib.transforms import rotation_angle_deg, transform_points
from drivers.clock import SimClock
from drivers.sim.hold import HOLD_MODELS, Hold, held_offset
from drivers.sim.rig import SimRig
from drivers.sim.scenarios import get_scenario


def _poses(hold=None, step="mirror-real-virtual", frames=30, on_stand=False, ideal=False):
    """The true board pose of `frames` consecutive frames (one second at 30 fps) after a placement."""
    rig = SimRig(get_scenario("nonoverlap-136", 0), "live", clock=SimClock(realtime=False), hold=hold, ideal=ideal)
    rig.camera.start()
    rig.operator.request_pose(step, 0 if step == "projector" else None, 0, on_stand=on_stand)
    out, last = [], None
    for _ in range(frames):
        f = rig.camera.get_frame(newer_than=last)
        last = f.frame_number
        out.append(np.array(f.meta["T_cam_board"]))
    return rig, out


def _spread_mm(poses):
    t = np.array([T[:3, 3] for T in poses])
    return float(np.linalg.norm(t - t[0], axis=1).max())


def test_a_hand_held_board_sways_a_board_on_a_stand_barely_moves_one_on_the_mirror_lies_still():
    _, hand = _poses()
    _, stand = _poses(on_stand=True)
    _, mirror = _poses(step="mirror-real-mirror")
    _, ideal = _poses(ideal=True)
    assert 0.1 < _spread_mm(hand) < 3.0  # a person's sway over one second: tenths of a millimetre
    assert _spread_mm(stand) < 0.02
    assert _spread_mm(mirror) == 0.0 and _spread_mm(ideal) == 0.0
    # the hand-held board also turns a little, about its centre
    assert 0.001 < max(rotation_angle_deg(T[:3, :3] @ hand[0][:3, :3].T) for T in hand) < 0.5


def test_the_offset_is_a_function_of_the_placement_and_time():
    m = HOLD_MODELS[Hold.HAND]
    c = np.array([50.0, 40.0, 0.0])
    a = held_offset(m, (0, 1, 2), 0.7, c)
    assert np.array_equal(a, held_offset(m, (0, 1, 2), 0.7, c))  # a frame rendered again shows the same pose
    assert not np.allclose(a, held_offset(m, (0, 1, 3), 0.7, c))  # another placement, another sway
    assert not np.allclose(a, held_offset(m, (0, 1, 2), 0.8, c))
    assert np.array_equal(held_offset(HOLD_MODELS[Hold.STILL], (0, 1, 2), 0.7, c), np.eye(4))


def test_a_forced_hold_applies_to_every_step_and_a_bad_one_is_refused():
    _, hand_projector = _poses(hold="hand", step="projector", on_stand=True)
    assert _spread_mm(hand_projector) > 0.1  # the rig's hold wins over the stand asked for
    with pytest.raises(SpecError, match="unknown hold"):
        SimRig(get_scenario("nonoverlap-136", 0), "live", hold="glued")


def test_motion_check_tells_a_still_board_from_a_hand_held_one():
    rig, hand = _poses(frames=9)
    sc = rig.scenario
    cam, spec = sc.rig.camera, sc.mirror_board
    X = spec.corner_points()
    ids = np.arange(len(X))

    def seen(T, noise, rng):
        uv = cam.project(transform_points(T, X))
        return BoardObservation(ids, uv + rng.normal(0, noise, uv.shape), False)

    rng = np.random.default_rng(3)
    pairs = [(seen(hand[0], 0.15, rng), seen(hand[0], 0.15, rng)) for _ in range(40)]
    # corner noise alone (0.15 px, the noisiest real-virtual views) never reads as motion, where the
    # largest single corner's displacement would have called some of these still boards moved
    assert max(board_motion_px(a, b) for a, b in pairs) < MAX_MOTION_PX
    assert max(np.hypot(*(a.corners_px - b.corners_px).T).max() for a, b in pairs) > MAX_MOTION_PX
    true = float(np.hypot(*(cam.project(transform_points(hand[-1], X)) - cam.project(transform_points(hand[0], X))).T).max())
    est = [board_motion_px(seen(hand[0], 0.08, rng), seen(hand[-1], 0.08, rng)) for _ in range(10)]
    assert true > MAX_MOTION_PX and np.median(np.abs(np.array(est) - true)) < 0.1
    # detected in rendered frames, the board out of view is inf
    assert board_motion_px(seen(hand[0], 0.0, rng), None) == float("inf")
    img = rig.camera.get_frame().image
    view = D.detect_real_virtual(img, spec)
    assert not isinstance(view, D.DetectionFailure)
    assert board_motion_px(view.real, view.real) == pytest.approx(0.0, abs=1e-9)
