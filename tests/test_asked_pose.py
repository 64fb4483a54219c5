"""The board pose a projector step asks for (calib.asked_pose): candidates drawn through the
estimated rig, each one's effect on the step's 1-sigmas predicted, the least worst one chosen."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import numpy as np
import pytest

from calib.asked_pose import Candidate, ask_pose, candidate_poses, mirror_seen
from calib.joint.predict import predict_uncertainty
from calib.models.vocab import Step
from calib.pipeline import calibrate_observations
from calib.quality.confidence import confidence_of
from calib.synthetic import projector_pose_ok
from drivers.sim.scenarios import get_scenario
from _calib_helpers import placements_observations

SC = get_scenario("nonoverlap-136", 0)


@lru_cache(maxsize=None)
def _so_far():
    """The 14 mirror views and the structured step's first 4 placements (0.05 px), and their joint
    calibration."""
    obs = placements_observations("nonoverlap-136", 0, 4, 0.05)
    return obs, calibrate_observations(obs, "joint")


def _need(obs, est, cand) -> float:
    merged = replace(obs, projector_views=obs.projector_views + (cand.view,))
    conf = confidence_of(predict_uncertainty(merged, est), Step.PROJECTOR)
    return max(q.sigma / q.target for q in conf.quantities)


def test_candidates_are_poses_a_person_could_hold_through_the_estimated_rig():
    obs, est = _so_far()
    cands = candidate_poses(obs, est, SC.layout, SC.pattern, [0, 6, 12], np.random.default_rng(1), 2,
                            mirror_rect=SC.rig.mirror_rect)
    assert [c.position for c in cands] == [0, 0, 6, 6, 12, 12]
    est_rig = replace(SC.rig, camera=est.camera, projector=est.projector, T_cam_proj=np.asarray(est.T_cam_proj),
                      mirror=est.mirror)
    blank = [c.T_cam_board[:3, :3] @ SC.layout.blank_centre + c.T_cam_board[:3, 3] for c in cands]
    dist = [float(np.linalg.norm(b - np.asarray(est.T_cam_proj)[:3, 3])) for b in blank]
    for c in cands:
        assert projector_pose_ok(est_rig, SC.layout, SC.pattern, c.position, c.T_cam_board)
        assert len(c.view.pattern_proj_px) == len(SC.pattern.points_px(*SC.rig.projector.size, c.position))
        assert c.view.pattern_position == c.position
    # about the distance the boards stood at so far (the median, 15% either way)
    solved = est.diagnostics["board_poses"]
    so_far = [np.linalg.norm(np.asarray(solved[pv.capture_id])[:3, :3] @ SC.layout.blank_centre
                             + np.asarray(solved[pv.capture_id])[:3, 3] - np.asarray(est.T_cam_proj)[:3, 3])
              for pv in obs.projector_views]
    assert all(0.8 * np.median(so_far) < d < 1.2 * np.median(so_far) for d in dist)
    assert len({c.view.capture_id for c in cands}) == len(cands)


def test_the_candidate_leaving_the_least_worst_sigma_is_asked_for_and_said_why():
    obs, est = _so_far()
    cands = candidate_poses(obs, est, SC.layout, SC.pattern, [2, 9], np.random.default_rng(3), 2,
                            mirror_rect=SC.rig.mirror_rect)
    # the same pose with only 5 of its pattern points decoded: less information, never the choice
    c0 = cands[0]
    poor = Candidate(c0.position, c0.T_cam_board,
                     replace(c0.view, capture_id="poor", pattern_cam_px=c0.view.pattern_cam_px[:5],
                             pattern_proj_px=c0.view.pattern_proj_px[:5]))
    asked = ask_pose(obs, est, [poor] + cands)
    needs = [_need(obs, est, c) for c in cands]
    assert asked.candidate is cands[int(np.argmin(needs))]
    assert asked.need == pytest.approx(min(needs), rel=1e-9)
    assert _need(obs, est, poor) > _need(obs, est, c0)
    assert asked.considered == len(cands) + 1
    assert asked.sigma / asked.target == pytest.approx(asked.need)
    assert f"pattern position {asked.position + 1}" in asked.reason() and asked.worst in asked.reason()
    assert ask_pose(obs, est, []) is None


def test_the_mirror_seen_so_far_lies_on_the_mirror_and_holds_every_mirrored_observation():
    obs, est = _so_far()
    seen = mirror_seen(obs, est)
    true = SC.rig.mirror_rect
    corners = np.array([seen.centre + a * seen.size[0] / 2 * seen.axis_u + b * seen.size[1] / 2 * seen.axis_v
                        for a in (-1, 1) for b in (-1, 1)])
    assert true.contains(corners).all()  # no more than the mirror
    assert seen.size[0] * seen.size[1] > 0.2 * true.size[0] * true.size[1]  # and a good part of it
    # every board corner seen through the mirror, cast back, lands in it (true rig: the same to 1 mm)
    uv = np.concatenate([pv.board.corners_px for pv in obs.projector_views])
    rays = est.camera.rays(uv)
    n, d = est.mirror.normal, est.mirror.d
    X = rays * (-d / (rays @ n))[:, None]
    assert replace(seen, size=(seen.size[0] + 2, seen.size[1] + 2)).contains(X).all()
    wider = mirror_seen(obs, est, margin_mm=30.0)
    assert wider.size == pytest.approx((seen.size[0] + 60, seen.size[1] + 60))
    assert mirror_seen(obs, est.with_(mirror=None)) is None  # a direct rig: no mirror to bound


def test_mirror_step_candidates_are_its_own_kind_of_pose_through_the_estimated_rig():
    from calib.asked_pose import mirror_candidates
    from calib.errors import ProcamError
    from calib.synthetic import _real_virtual_ok

    obs, est = _so_far()
    seen = mirror_seen(obs, est)
    cands = mirror_candidates(obs, est, 4, np.random.default_rng(5), seen)
    assert len(cands) == 4 and all(c.position is None for c in cands)
    est_rig = replace(SC.rig, camera=est.camera, projector=est.projector, T_cam_proj=np.asarray(est.T_cam_proj),
                      mirror=est.mirror, mirror_rect=seen)
    for c in cands:  # seen directly and whole in the part of the mirror seen so far, unoccluded
        assert _real_virtual_ok(est_rig, SC.mirror_board, c.T_cam_board)
        assert c.view.method == Step.REAL_VIRTUAL and c.view.virtual.mirrored
        assert len(c.view.real.ids) == SC.mirror_board.n_corners
    asked = ask_pose(obs, est, cands, Step.REAL_VIRTUAL)
    needs = []
    for c in cands:
        merged = replace(obs, mirror_views=obs.mirror_views + (c.view,))
        needs.append(confidence_of(predict_uncertainty(merged, est), Step.REAL_VIRTUAL).quantities[0].sigma)
    assert asked.candidate is cands[int(np.argmin(needs))] and asked.worst == "mirror normal"
    assert asked.reason().startswith("a board, held at the pose shown")
    # a board lying on the mirror can only be asked for where the mirror was seen
    flat = replace(obs, mirror_views=tuple(replace(mv, method=Step.REAL_MIRROR, virtual=None) for mv in obs.mirror_views))
    with pytest.raises(ProcamError, match="inside the part of the mirror seen so far"):
        mirror_candidates(flat, est, 2, np.random.default_rng(0), None)


def test_a_board_held_on_the_mirror_stays_on_it():
    from calib.synthetic import held_mirror_pose

    sc = get_scenario("nonoverlap-136-realmirror", 0)
    rng = np.random.default_rng(2)
    for T in sc.mirror_poses[:4]:
        H = held_mirror_pose(sc.rig, sc.mirror_board, sc.mirror_method, T, 3.0, 10.0, rng)
        assert not np.allclose(H, T)
        # the same height above the mirror and the same face towards it: turned about its normal, slid along it
        assert sc.rig.mirror.signed_distance(H[:3, 3][None])[0] == pytest.approx(
            sc.rig.mirror.signed_distance(T[:3, 3][None])[0], abs=1e-6)
        assert np.allclose(H[:3, 2], T[:3, 2], atol=1e-9)
        assert sc.rig.mirror_rect.contains(H[:3, 3][None]).all()
    # a pose shown on an estimated mirror plane (0.5 mm and 1 deg off the true one) is laid on the true mirror
    from calib.transforms import make_T, rotation_about

    T = sc.mirror_poses[0]
    shown = make_T(rotation_about([1.0, 0.0, 0.0], 1.0) @ T[:3, :3], T[:3, 3] + 0.5 * sc.rig.mirror.normal)
    H = held_mirror_pose(sc.rig, sc.mirror_board, sc.mirror_method, shown, 0.0, 0.0, rng, thickness_mm=3.0)
    corners = (H[:3, :3] @ sc.mirror_board.corner_points().T).T + H[:3, 3]
    assert np.allclose(sc.rig.mirror.signed_distance(corners), 3.0, atol=1e-6)
    T = SC.mirror_poses[0]
    H = held_mirror_pose(SC.rig, SC.mirror_board, SC.mirror_method, T, 3.0, 10.0, rng)
    assert 0 < np.linalg.norm(H[:3, 3] - T[:3, 3]) < 80 and not np.allclose(H[:3, 2], T[:3, 2])
    assert np.array_equal(held_mirror_pose(SC.rig, SC.mirror_board, SC.mirror_method, T, 0, 0, rng), T)
