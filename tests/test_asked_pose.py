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
