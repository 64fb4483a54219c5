"""The reported 1-sigma values are honest: over repeated noise draws the true error is within 3 sigma
for at least 95 % of the parameters; the pose-marginalised covariance is the exact block of the full
inverse; the key layout of result.uncertainty is the documented one (docs/JOINT.md)."""

import numpy as np
import pytest

from _joint_helpers import ground_truth, observations, parameter_errors, perturbed
from calib.joint.method import JointOptions, build_problem, refine_joint, solve
from calib.joint.uncertainty import marginal_covariance


@pytest.mark.parametrize("rig", ["136", "direct"])
def test_three_sigma_coverage_over_seeds(rig):
    kw = dict(rig=rig, per_position=2)
    gt = ground_truth(**kw)
    z = []
    for seed in range(5):
        res = refine_joint(observations(0.2, 100 + seed, **kw), gt,
                           JointOptions(camera_model="5coef", projector_model="5coef"))
        errs = parameter_errors(res, gt)
        z += [e / s for _, e, s in errs]
    z = np.array(z)
    assert len(z) >= 5 * 24
    assert np.mean(z <= 3) >= 0.95
    # and the sigmas are not merely inflated: about two thirds of the errors are within 1 sigma
    assert 0.5 < np.mean(z <= 1) < 0.85


def test_marginal_covariance_is_the_block_of_the_full_inverse():
    kw = dict(per_position=1)
    obs = observations(0.2, 1, **kw)
    prob, _ = build_problem(obs, perturbed(ground_truth(**kw)), JointOptions(pattern_model="point"), "5coef", "k1k2")
    x, _ = solve(prob, "linear", 1.0)
    cov, s2, dof = marginal_covariance(prob, x)
    J = prob.jacobian(x).toarray()
    r = prob.residuals(x)
    full = np.linalg.inv(J.T @ J) * (r @ r) / (len(r) - J.shape[1])
    G = prob.n_global
    assert dof == len(r) - J.shape[1] and s2 == pytest.approx((r @ r) / dof)
    assert np.allclose(cov, full[:G, :G], rtol=1e-6, atol=1e-12 * np.abs(full[:G, :G]).max())


def test_uncertainty_key_layout():
    kw = dict(per_position=1)
    res = refine_joint(observations(0.1, 2, **kw), perturbed(ground_truth(**kw)))
    u = res.uncertainty
    assert u["schema"] == "procam-uncertainty-1" and u["units"] == "mm"
    for dev in ("camera", "projector"):
        assert set(u[dev]) >= {"fx", "fy", "cx", "cy", "dist"} and all(u[dev][k] > 0 for k in ("fx", "fy", "cx", "cy"))
        model = res.camera if dev == "camera" else res.projector
        assert len(u[dev]["dist"]) == model.dist.size
    T = u["T_cam_proj"]
    assert len(T["t"]) == 3 and len(T["rot_deg"]) == 3
    assert T["t_total"] == pytest.approx(np.linalg.norm(T["t"]))
    assert T["rot_total_deg"] == pytest.approx(np.linalg.norm(T["rot_deg"]))
    assert set(u["mirror"]) == {"normal_deg", "d", "normal_deg_given_camera", "normal_deg_with_more_mirror",
                                "normal_deg_with_more_projector"} and u["mirror"]["normal_deg"] > 0
    names = u["covariance"]["names"]
    C = np.array(u["covariance"]["matrix"])
    assert C.shape == (len(names), len(names)) and np.allclose(C, C.T)
    assert np.sqrt(C[names.index("proj.fx"), names.index("proj.fx")]) == pytest.approx(u["projector"]["fx"])
    assert 0.5 < u["variance_factor"] < 2.0


def _outlook_problem(mirror_method: str, drop_mirror: int = 0):
    kw = dict(per_position=1, mirror_method=mirror_method)
    obs = observations(0.2, 3, **kw)
    if drop_mirror:
        from dataclasses import replace
        obs = replace(obs, mirror_views=obs.mirror_views[:-drop_mirror])
    return obs, ground_truth(**kw)


def test_view_information_adds_up_to_the_pose_marginalised_information():
    from calib.joint.solver import prior_terms
    from calib.joint.uncertainty import _mean_view_information, _schur_terms
    from calib.models.vocab import Step

    obs, gt = _outlook_problem("real-virtual")
    prob, _ = build_problem(obs, perturbed(gt), JointOptions(pattern_model="point"), "5coef", "k1k2")
    x, _ = solve(prob, "linear", 1.0)
    Jg, w, B, D, schur, _ = _schur_terms(prob, x)
    total = np.zeros_like(schur)
    for is_step in (lambda s: s.is_mirror, lambda s: s == Step.PROJECTOR):
        views = [v for v, ps in enumerate(prob.poses) if is_step(Step(ps.role))]
        total += len(views) * _mean_view_information(prob, Jg, w, B, D, views)
    pi, pl = prior_terms(prob)
    total[pi, pi] += pl
    assert np.allclose(total, schur, rtol=1e-8, atol=1e-9 * np.abs(schur).max())


@pytest.mark.parametrize("method", ["real-virtual", "real-mirror"])
def test_mirror_outlook_predicts_the_placements_added(method):
    """The normal's 1-sigma predicted with 4 more mirror placements is what adding 4 of the session's own
    gives, within a fifth; the mirror views' own share (the camera known) is below the whole."""
    full_obs, gt = _outlook_problem(method)
    part_obs, _ = _outlook_problem(method, drop_mirror=4)
    opts = JointOptions(camera_model="5coef", projector_model="5coef")
    part = refine_joint(part_obs, gt, opts).uncertainty["mirror"]
    full = refine_joint(full_obs, gt, opts).uncertainty["mirror"]
    more = part["normal_deg_with_more_mirror"]
    assert len(more) == 16 and all(a >= b for a, b in zip([part["normal_deg"]] + more, more))
    assert more[3] == pytest.approx(full["normal_deg"], rel=0.2)
    assert 0 < part["normal_deg_given_camera"] < part["normal_deg"]
    assert len(part["normal_deg_with_more_projector"]) == 16


def test_boards_on_the_mirror_lower_the_normal_less_per_placement():
    """Most of the normal's 1-sigma is the camera's intrinsics' in both mirror methods. Boards seen directly
    and in the mirror also constrain the camera; boards lying on the mirror all lie in one plane and
    hardly do, so each further one lowers the normal's 1-sigma less."""
    opts = JointOptions(camera_model="5coef", projector_model="5coef")
    gain = {}
    for method in ("real-virtual", "real-mirror"):
        obs, gt = _outlook_problem(method)
        u = refine_joint(obs, gt, opts).uncertainty["mirror"]
        assert u["normal_deg_given_camera"] < 0.5 * u["normal_deg"]
        gain[method] = 1 - u["normal_deg_with_more_mirror"][3] / u["normal_deg"]
    assert 0 < gain["real-mirror"] < gain["real-virtual"]


def test_a_failing_outlook_leaves_the_uncertainty_whole(monkeypatch):
    import calib.joint.uncertainty as U

    def singular(*a):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(U, "_mirror_outlook", singular)
    obs, gt = _outlook_problem("real-virtual")
    u = refine_joint(obs, gt, JointOptions(camera_model="5coef", projector_model="5coef")).uncertainty
    assert set(u["mirror"]) == {"normal_deg", "d"} and u["mirror"]["normal_deg"] > 0


def test_with_the_camera_given_the_normal_is_all_the_mirror_views_own():
    from calib.quality.confidence import mirror_outlook

    obs, gt = _outlook_problem("real-virtual")
    res = refine_joint(obs, gt, JointOptions(camera_model="5coef", projector_model="5coef", fix_camera=True))
    m = res.uncertainty["mirror"]
    assert m["normal_deg_given_camera"] == pytest.approx(m["normal_deg"])
    assert "(nearly all of it)" in mirror_outlook(res)
