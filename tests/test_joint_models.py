"""Distortion model selection: the true model is found on data generated with it (no distortion, and a
5-coefficient lens), the rational model is not picked for a Brown-Conrady lens, a forced model is
kept, and the report says what was chosen and why."""

import numpy as np
import pytest

from _joint_helpers import ground_truth, observations, perturbed
from calib.joint.method import JointOptions, refine_joint
from calib.joint.model_select import bic

STRONG_CAM = (-0.12, 0.09, 0.002, -0.0015, -0.04)
STRONG_PROJ = (0.03, -0.05, 0.003, -0.002, 0.08)


def test_no_distortion_selects_none():
    kw = dict(per_position=2, camera_dist=(), projector_dist=())
    res = refine_joint(observations(0.1, 0, **kw), perturbed(ground_truth(**kw)), JointOptions(uncertainty=False))
    ms = res.diagnostics["model_selection"]
    assert ms["camera"]["chosen"] == "none" and ms["projector"]["chosen"] == "none"
    assert not np.any(res.camera.dist) and not np.any(res.projector.dist)
    assert "lowest BIC" in ms["camera"]["reason"] and ms["refit"]["kept"]


@pytest.mark.parametrize("selection", ["bic", "lrt"])
def test_five_coefficient_lenses_select_5coef_not_rational(selection):
    kw = dict(per_position=2, camera_dist=STRONG_CAM, projector_dist=STRONG_PROJ)
    gt = ground_truth(**kw)
    res = refine_joint(observations(0.1, 1, **kw), perturbed(gt), JointOptions(selection=selection, uncertainty=False))
    ms = res.diagnostics["model_selection"]
    assert ms["camera"]["chosen"] == "5coef" and ms["projector"]["chosen"] == "5coef"
    assert res.camera.dist.size == 5 and np.abs(res.camera.dist - gt.camera.dist).max() < 0.02
    for dev in ("camera", "projector"):
        cands = {c["model"]: c for c in ms[dev]["candidates"]}
        assert set(cands) == {"none", "k1", "k1k2", "5coef", "rational"}
        if selection == "bic":
            assert cands["rational"]["delta_bic"] > 0 and cands["k1k2"]["delta_bic"] > 0
        else:
            assert cands["k1k2"]["p_value"] < 0.05 and cands["rational"]["p_value"] >= 0.001
            assert "p =" in ms[dev]["reason"]


def test_k1k2_projector_is_recognised():
    """The default rig's projector has k1, k2 only: it is simplified, the 5-coefficient camera is not."""
    kw = dict(per_position=2)
    res = refine_joint(observations(0.05, 2, **kw), perturbed(ground_truth(**kw)), JointOptions(uncertainty=False))
    assert res.diagnostics["camera_model"] == "5coef" and res.diagnostics["projector_model"] == "k1k2"
    assert np.all(res.projector.dist[2:] == 0)


def test_forced_models_are_kept():
    kw = dict(per_position=2)
    res = refine_joint(observations(0.1, 3, **kw), perturbed(ground_truth(**kw)),
                       JointOptions(camera_model="rational", projector_model="k1"))
    ms = res.diagnostics["model_selection"]
    assert ms["camera"] == {"chosen": "rational", "forced": True, "reason": "forced by the user"}
    assert ms["projector"]["chosen"] == "k1" and ms["projector"]["forced"]
    assert res.camera.dist.size == 8 and np.all(res.projector.dist[1:] == 0) and res.projector.dist[0] != 0
    assert len(res.uncertainty["camera"]["dist"]) == 8 and res.uncertainty["projector"]["dist"][1] == 0.0


def test_unknown_model_is_an_actionable_error():
    from calib.errors import CalibrationError

    kw = dict(per_position=1)
    with pytest.raises(CalibrationError, match="one of auto, none, k1, k1k2, 4coef, 5coef, rational"):
        refine_joint(observations(**kw), ground_truth(**kw), JointOptions(camera_model="fisheye"))


def test_bic_penalises_parameters_and_floors_exact_fits():
    assert bic(100.0, 1000, 10) < bic(100.0, 1000, 11)
    assert bic(100.0, 1000, 10) < bic(101.0, 1000, 10)
    assert bic(0.0, 1000, 10) == bic(1e-9, 1000, 10)


def test_chi2_survival_function_matches_scipy():
    from scipy.stats import chi2

    from calib.joint.model_select import chi2_sf

    for k in range(1, 13):
        for x in (1e-8, 0.01, 0.5, 1.0, 3.84, 7.8, 15.0, 40.0, 120.0, 400.0):
            assert chi2_sf(x, k) == pytest.approx(chi2.sf(x, k), rel=1e-10, abs=1e-300)
    assert chi2_sf(0.0, 3) == 1.0
    with pytest.raises(ValueError):
        chi2_sf(1.0, 0)


@pytest.mark.parametrize("solver", ["lm", "scipy"])
def test_a_prior_on_k3_shrinks_it_by_the_expected_fraction(solver):
    """The solver's zero-mean Gaussian prior (prob.prior, what the k3 shrinkage sets): with a precision equal
    to the data's own for k3, the estimate is halved (the quadratic model's identity: the prior moves k3 by
    var / (var + tau^2)) by both solvers, and the covariance's k3 variance is halved too."""
    from calib.joint.method import build_problem, solve
    from calib.joint.uncertainty import marginal_covariance

    kw = dict(per_position=1)
    obs = observations(0.1, 6, **kw)
    prob, _ = build_problem(obs, perturbed(ground_truth(**kw)), JointOptions(pattern_model="point"), "5coef", "k1k2")
    x, _ = solve(prob, "linear", 1.0, 100, 1e-12, "lm")
    k = prob.global_names.index("cam.dist4")
    k3, x0 = x[k], x.copy()
    cov, s2, _ = marginal_covariance(prob, x)
    var_unit = cov[k, k] / s2
    prob.prior = {"cam.dist4": 1.0 / var_unit}
    xp, _ = solve(prob, "linear", 1.0, 100, 1e-12, solver)
    assert abs(k3) > 3 * np.sqrt(cov[k, k])  # a k3 the data show
    assert xp[k] == pytest.approx(0.5 * k3, rel=0.02)
    assert not np.allclose(xp[:k], x0[:k])  # the other parameters follow
    cov_p, _, _ = marginal_covariance(prob, xp)
    assert cov_p[k, k] == pytest.approx(0.5 * cov[k, k], rel=0.05)
