"""On-site recalibration (issue 15): the bumped simulated rig, the check's verdicts, the re-estimate,
the comparison and the archive (docs/RECALIBRATION.md)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import SpecError
from calib.quality.metrics import compare
from drivers.sim.bump import BUMP_PARTS, bump_scenario
from drivers.sim.scenarios import get_scenario


# ---- the bumped simulated rig --------------------------------------------------------------------
def test_bumps_move_only_their_part_by_the_stated_amounts():
    sc = get_scenario("nonoverlap-136", 0)
    gt = sc.ground_truth()
    m = {p: compare(bump_scenario(sc, p, 0).ground_truth(), gt) for p in BUMP_PARTS}
    assert m["none"].distance == 0 and m["none"].angle_deg == 0 and m["none"].cam_k_px == 0
    assert 10.0 <= m["projector"].distance <= 20.0 and m["projector"].angle_deg == pytest.approx(1.0, abs=1e-9)
    assert m["projector"].cam_k_px == 0 and m["projector"].mirror_angle_deg == 0
    assert m["mirror"].mirror_angle_deg == pytest.approx(0.5, abs=1e-6) and m["mirror"].distance == 0
    cam0, cam1 = gt.camera, bump_scenario(sc, "camera", 0).ground_truth().camera
    assert cam1.fx / cam0.fx == pytest.approx(1.005) and cam1.fy / cam0.fy == pytest.approx(1.005)
    assert cam1.cx == cam0.cx and m["camera"].distance == 0 and m["camera"].mirror_angle_deg == 0


def test_bump_is_seeded_and_unknown_part_refused():
    sc = get_scenario("nonoverlap-136", 0)
    a, b = bump_scenario(sc, "projector", 3), bump_scenario(sc, "projector", 3)
    c = bump_scenario(sc, "projector", 4)
    assert np.array_equal(a.rig.T_cam_proj, b.rig.T_cam_proj)
    assert not np.allclose(a.rig.T_cam_proj, c.rig.T_cam_proj)
    with pytest.raises(SpecError, match="unknown bump"):
        bump_scenario(sc, "tripod", 0)


def test_open_sim_rig_renders_the_bumped_rig_and_says_so():
    from drivers.sim.rig import open_sim_rig

    rig = open_sim_rig("nonoverlap-136", 0, ideal=True, bump="mirror")
    try:
        gt = rig.ground_truth()
        assert compare(gt, get_scenario().ground_truth()).mirror_angle_deg == pytest.approx(0.5, abs=1e-6)
        assert np.allclose(rig.renderer.mirror.normal, gt.mirror.normal)
        assert rig.camera.settings()["bump"] == "mirror"
    finally:
        rig.close()


# ---- the check, the re-estimate, the comparison (exact geometry + Gaussian noise, no rendering) ----
from functools import lru_cache  # noqa: E402

from calib.recalib import (  # noqa: E402
    check_rig, compare_calibrations, merge_observations, previous_covariance, projection_difference, reestimate, targets_from,
)
from calib.synthetic import SyntheticSession, observe  # noqa: E402

NOISE_PX = 0.1


def _session(sc, n_projector: int, n_mirror: int, seed: int) -> SyntheticSession:
    pp = sc.projector_poses[::max(1, len(sc.projector_poses) // max(n_projector, 1))][:n_projector]
    mp = sc.mirror_poses_for("real-virtual", n_mirror, seed=sc.seed + 50 + seed) if n_mirror else []
    return SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, pp, mp, "real-virtual")


@lru_cache(maxsize=1)
def previous():
    """A full joint calibration of the unbumped rig (52 + 14 captures, 0.1 px noise), with its uncertainty."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from _joint_helpers import perturbed

    from calib.joint.method import JointOptions, refine_joint

    sc = get_scenario("nonoverlap-136", 0)
    obs = observe(_session(sc, 52, 14, 0), NOISE_PX, 1)
    return refine_joint(obs, perturbed(sc.ground_truth()), JointOptions(camera_model="5coef", projector_model="5coef",
                                                                                 pattern_model="point"))


@lru_cache(maxsize=8)
def check(part: str):
    """The check on the rig bumped at `part`: 2 real-virtual mirror captures + 2 projector captures."""
    b = bump_scenario(get_scenario("nonoverlap-136", 0), part, 0)
    return b, check_rig(previous(), observe(_session(b, 2, 2, 0), NOISE_PX, 7))


def test_previous_calibration_uncertainty_is_read_as_covariances():
    prev = previous()
    for part, k in (("camera", 4), ("mirror", 3), ("projector", 6)):
        C = previous_covariance(prev, part)
        assert C.shape == (k, k) and np.all(np.diag(C) > 0)
    # the stored translation sigma is the projector block's translation part
    C = previous_covariance(prev, "projector")
    assert np.sqrt(np.trace(C[3:, 3:])) == pytest.approx(prev.uncertainty["T_cam_proj"]["t_total"], rel=1e-9)
    assert targets_from(prev)["projector_t"] == pytest.approx(prev.uncertainty["T_cam_proj"]["t_total"])


@pytest.mark.parametrize("part,moved", [("none", ()), ("projector", ("projector",)), ("mirror", ("mirror",)),
                                        ("camera", ("camera",))])
def test_check_names_the_part_that_moved_and_only_it(part, moved):
    _, rep = check(part)
    assert rep.moved == moved, {p: (c.status, c.mahalanobis2) for p, c in rep.parts.items()}
    assert rep.verdict == ("unchanged" if not moved else "moved: " + ", ".join(moved))
    for p, c in rep.parts.items():
        assert c.captures >= 2 and c.threshold > 0
        assert (c.mahalanobis2 > c.threshold) == (p in moved)


def test_check_without_mirror_captures_says_the_mirror_was_not_checked():
    b = bump_scenario(get_scenario("nonoverlap-136", 0), "none", 0)
    rep = check_rig(previous(), observe(_session(b, 2, 0, 0), NOISE_PX, 7))
    assert rep.parts["mirror"].status == "not checked" and rep.verdict == "incomplete"
    assert "between camera and mirror" in rep.parts["mirror"].reason


def _reestimated(part: str, n_projector: int, n_mirror: int, intrinsics: str = "prior", previous_cal=None):
    """The check's captures and `n_projector` + `n_mirror` more, re-estimating what the check found moved."""
    b, rep = check(part)
    o1 = observe(_session(b, 2, 2, 0), NOISE_PX, 7)
    o2 = observe(_session(b, n_projector, n_mirror, 1), NOISE_PX, 8)
    start = rep.current if previous_cal is None else previous_cal
    re = reestimate(start, merge_observations(o1, o2), rep.moved, intrinsics=intrinsics)
    return b, rep, re


def test_recalibrated_result_carries_this_sessions_residuals_not_the_previous_ones():
    """The result written states the RMS, per-view residuals, worst views and degrees of freedom of the
    recalibration's own captures (the previous session's capture names never appear)."""
    from calib.recalib import with_own_residuals

    b, rep = check("projector")
    obs = merge_observations(observe(_session(b, 2, 2, 0), NOISE_PX, 7), observe(_session(b, 8, 0, 1), NOISE_PX, 8))
    re = reestimate(rep.current, obs, rep.moved, intrinsics="held")
    res = with_own_residuals(re.result, obs, True)
    ids = [v.capture_id for v in obs.mirror_views] + [v.capture_id for v in obs.projector_views]
    assert [p["capture_id"] for p in res.per_view] == ids
    assert {w["capture_id"] for w in res.diagnostics["worst_views"]} <= set(ids)
    assert "board_poses" not in res.diagnostics and "worst_points" not in res.diagnostics
    # 0.1 px noise per coordinate: a point's residual about 0.14 px
    assert 0.05 < res.rms["joint"] < 0.3 and 0.05 < res.rms["pattern"] < 0.3
    n_res = sum(2 * p["n_points"] for p in res.per_view)
    assert res.uncertainty["dof"] == n_res - 6 * len(ids)
    assert res.uncertainty["variance_factor"] == pytest.approx(1.0, abs=0.5)  # whitened by the class sigma
    assert res.rms != previous().rms
    kept = with_own_residuals(previous(), obs, False)  # nothing re-estimated: the covariance is the previous one's
    assert kept.uncertainty["dof"] == previous().uncertainty["dof"] and kept.per_view != previous().per_view


def test_projector_reestimate_with_exact_held_parts_is_within_05mm_005deg():
    """With the held parts exact (the unbumped truth carrying the previous calibration's uncertainty),
    the re-estimated pose alone reaches the bumped truth; error from held parts is the next test's."""
    b = bump_scenario(get_scenario("nonoverlap-136", 0), "projector", 0)
    exact = get_scenario().ground_truth().with_(uncertainty=previous().uncertainty)
    obs = merge_observations(observe(_session(b, 2, 2, 0), NOISE_PX, 7), observe(_session(b, 8, 0, 1), NOISE_PX, 8))
    re = reestimate(exact, obs, ("projector",), intrinsics="held")
    m = compare(re.result, b.ground_truth())
    assert m.distance < 0.5 and m.angle_deg < 0.05, (m.distance, m.angle_deg)
    assert m.cam_k_px == 0 and m.mirror_angle_deg == 0


def test_projector_reestimate_holds_the_rest_and_reports_the_change():
    b, rep, re = _reestimated("projector", 8, 0, intrinsics="held")
    m0 = compare(previous(), get_scenario().ground_truth())  # the previous calibration's own error
    m = compare(re.result, b.ground_truth())
    assert m.distance < m0.distance + 0.5 and m.angle_deg < m0.angle_deg + 0.05
    assert re.parts == ("projector",) and re.reached, re.missing
    # held parts are the previous calibration's, bit for bit
    assert np.array_equal(re.result.camera.K, previous().camera.K)
    assert np.array_equal(re.result.mirror.normal, previous().mirror.normal)
    cmp = compare_calibrations(previous(), re.result, re.sigma)
    true_shift = np.linalg.norm(b.rig.T_cam_proj[:3, 3] - get_scenario().rig.T_cam_proj[:3, 3])
    assert cmp["projector"]["position_change_mm"] == pytest.approx(true_shift, abs=1.0)
    assert cmp["projector"]["rotation_change_deg"] == pytest.approx(1.0, abs=0.1)
    assert cmp["projector"]["position_sigma_mm"] > 0
    assert cmp["mirror"]["normal_change_deg"] == 0 and cmp["camera"]["projection_difference"]["max_px"] < 1e-9


def test_mirror_reestimate_normal_within_005_deg():
    b, rep, re = _reestimated("mirror", 0, 4)
    m = compare(re.result, b.ground_truth())
    assert m.mirror_angle_deg < 0.05 and re.parts == ("mirror",)
    cmp = compare_calibrations(previous(), re.result, re.sigma)
    assert cmp["mirror"]["normal_change_deg"] == pytest.approx(0.5, abs=0.06)


def test_camera_reestimate_recovers_the_focal_length():
    b, rep, re = _reestimated("camera", 4, 4)
    true_fx = b.ground_truth().camera.fx
    assert abs(re.result.camera.fx - true_fx) < 0.5 < abs(previous().camera.fx - true_fx)
    cmp = compare_calibrations(previous(), re.result, re.sigma)
    assert cmp["camera"]["fx_change_px"] == pytest.approx(true_fx - previous().camera.fx, abs=0.5)
    assert cmp["camera"]["projection_difference"]["max_px"] > 2.0


# ---- the intrinsics prior (the previous covariance) -----------------------------------------------
from calib.recalib import PRIOR_EIG_FLOOR, RecalibrationRecord, intrinsics_prior  # noqa: E402


def _stored(prev):
    cv = prev.uncertainty["covariance"]
    return list(cv["names"]), np.array(cv["matrix"])


def test_prior_residual_is_the_mahalanobis_distance_to_the_previous_intrinsics():
    prev = previous()
    pr = intrinsics_prior(prev, prev)
    names, M = _stored(prev)
    order = [n for b in pr.blocks for n in pr.params[b]]
    assert pr.blocks == ("cam_intr", "proj_intr") and order[:4] == ["cam.fx", "cam.fy", "cam.cx", "cam.cy"]
    assert all(n.startswith(("cam.", "proj.")) for n in order) and len(order) == 4 + 5 + 4 + 5
    ii = [names.index(n) for n in order]
    C = M[np.ix_(ii, ii)]
    rng = np.random.default_rng(0)
    d = rng.multivariate_normal(np.zeros(len(C)), C)
    blocks = {"cam_intr": d[:9], "proj_intr": d[9:]}
    assert np.allclose(pr.offset, 0) and pr.floored == 0
    assert pr.residual(blocks) @ pr.residual(blocks) == pytest.approx(d @ np.linalg.solve(C, d), rel=1e-6)
    # started elsewhere (a model whose camera fx is 1 px off the previous value): the offset says so
    K = np.array(prev.camera.K)
    K[0, 0] += 1.0
    assert intrinsics_prior(prev, prev.with_(camera=prev.camera.with_params(K=K))).offset[0] == pytest.approx(1.0)


def test_prior_of_an_ill_conditioned_covariance_is_floored_weaker_never_stronger():
    prev = previous()
    names, M = _stored(prev)
    i, j = names.index("proj.dist0"), names.index("proj.dist1")
    M[j, :], M[:, j] = M[i, :] * 2.0, M[:, i] * 2.0  # dist1 = 2 dist0 exactly: a singular covariance
    M[j, j] = 4.0 * M[i, i]
    bad = prev.with_(uncertainty=dict(prev.uncertainty, covariance=dict(prev.uncertainty["covariance"],
                                                                        matrix=M.tolist())))
    pr = intrinsics_prior(bad, bad, ("proj",))
    assert pr.floored >= 1 and np.all(np.isfinite(pr.W))
    order = list(pr.params["proj_intr"])
    ii = [names.index(n) for n in order]
    C = M[np.ix_(ii, ii)]
    v = np.zeros(len(order))  # the direction the covariance says is exact: dist1 - 2 dist0 != 0
    v[order.index("proj.dist0")], v[order.index("proj.dist1")] = 1.0, -0.5
    v *= np.sqrt(M[i, i])
    r = pr.residual({"proj_intr": v})
    # a finite penalty (no infinite pull), bounded by the floor: |r|^2 <= |v|^2 / (floor * lambda_max) in
    # the Jacobi-scaled coordinates
    assert 0 < r @ r < 10.0 / PRIOR_EIG_FLOOR
    # along a well-determined direction the prior is the covariance's own (fx alone)
    u = np.zeros(len(order))
    u[0] = 1.0
    e = pr.residual({"proj_intr": u})
    assert e @ e == pytest.approx(u @ np.linalg.pinv(C) @ u, rel=0.05)


def test_prior_reestimate_propagates_the_intrinsics_uncertainty_into_the_pose():
    """Held intrinsics ignore their own uncertainty; under the prior the pose's 1-sigma carries it, and
    the intrinsics move (within their previous 1-sigma) where the new captures ask for it."""
    b, rep, held = _reestimated("projector", 8, 0, intrinsics="held")
    _, _, pri = _reestimated("projector", 8, 0, intrinsics="prior")
    assert held.intrinsics == "held" and pri.intrinsics == "prior" and "18 parameters" in pri.intrinsics_note
    sh, sp = held.sigma["projector"], pri.sigma["projector"]
    assert sp["t_mm"] > 1.1 * sh["t_mm"] and sp["rot_deg"] > 1.5 * sh["rot_deg"]
    m = compare(pri.result, b.ground_truth())
    assert m.distance < 3 * sp["t_mm"] and m.angle_deg < 3 * sp["rot_deg"], (m.distance, m.angle_deg, sp)
    u = previous().uncertainty
    dfx = pri.result.projector.fx - previous().projector.fx
    assert 0 < abs(dfx) < 3 * u["projector"]["fx"]
    assert abs(pri.result.camera.fx - previous().camera.fx) < 3 * u["camera"]["fx"]
    assert pri.sigma["projector_intrinsics"]["fx_px"] <= u["projector"]["fx"] * (1 + 1e-6)
    # the result's uncertainty is the re-estimate's, and says how it was made
    ru = pri.result.uncertainty
    assert ru["T_cam_proj"]["t_total"] == pytest.approx(sp["t_mm"], rel=1e-6)
    assert ru["T_cam_proj"]["rot_total_deg"] == pytest.approx(sp["rot_deg"], rel=1e-6)
    assert ru["recalibration"]["intrinsics"] == "prior"
    assert held.result.uncertainty["T_cam_proj"]["t_total"] == pytest.approx(sh["t_mm"], rel=1e-6)
    assert pri.result.diagnostics["trust"]["quality"]["low"] is False
    # recalibration.json records the mode
    d = RecalibrationRecord("p", "0" * 64, "previous/calibration.json", rep, pri, None).to_dict()
    assert d["intrinsics"] == "prior" and d["reestimate"]["intrinsics"] == "prior"


def test_prior_does_not_hide_a_refocus_and_falls_back_without_a_covariance():
    # the check runs first, with the same rule in both modes: a refocus is found, and the camera re-fitted
    b, rep, re = _reestimated("camera", 4, 4, intrinsics="prior")
    assert rep.moved == ("camera",) and re.parts == ("camera",)
    assert abs(re.result.camera.fx - b.ground_truth().camera.fx) < 0.5
    # no stored covariance (another method, an old file): the intrinsics can only be held, and it says so
    prev = previous()
    bare = prev.with_(uncertainty={k: v for k, v in prev.uncertainty.items() if k != "covariance"})
    _, rep, re = _reestimated("projector", 8, 0, intrinsics="prior", previous_cal=bare)
    assert re.intrinsics == "held" and "no covariance" in re.intrinsics_note
    assert np.array_equal(re.result.camera.K, prev.camera.K)
    with pytest.raises(Exception, match="unknown intrinsics mode"):
        reestimate(prev, observe(_session(b, 2, 2, 0), NOISE_PX, 7), ("projector",), intrinsics="free")


def inflated(prev, k: float):
    """`prev` with every 1-sigma k times larger (covariance k^2): trusted, but far more uncertain than a
    full session (the quality gate's LOW QUALITY), with its trust report and projection grids to match."""
    from calib.quality.projection_uncertainty import projection_uncertainty
    from calib.quality.trust import check_calibration

    u = dict(prev.uncertainty)
    for dev in ("camera", "projector"):
        u[dev] = {key: ([k * x for x in v] if isinstance(v, list) else k * v) for key, v in u[dev].items()}
    t = u["T_cam_proj"]
    u["T_cam_proj"] = {key: ([k * x for x in v] if isinstance(v, list) else k * v) for key, v in t.items()}
    u["mirror"] = {key: ([k * x for x in v] if isinstance(v, list) else k * v) for key, v in u["mirror"].items()}
    u["covariance"] = dict(u["covariance"], matrix=(k * k * np.array(u["covariance"]["matrix"])).tolist())
    out = prev.with_(uncertainty=u)
    out = out.with_(projection_uncertainty=projection_uncertainty(out))
    return out.with_(diagnostics=dict(out.diagnostics or {}, trust=check_calibration(out).to_dict()))


def test_quality_gate_of_the_recalibrated_result_is_its_own():
    """A recalibration from a previous calibration far more uncertain than a full session reaches its
    (loose) targets at once, and its result says LOW QUALITY; from a good one it does not."""
    low = inflated(previous(), 10.0)
    assert low.diagnostics["trust"]["passed"] and low.diagnostics["trust"]["quality"]["low"]
    b, rep = check("projector")
    obs = observe(_session(b, 2, 2, 0), NOISE_PX, 7)
    start = low.with_(T_cam_proj=rep.current.T_cam_proj)
    for mode in ("held", "prior"):
        re = reestimate(start, obs, ("projector",), intrinsics=mode)
        q = re.result.diagnostics["trust"]["quality"]
        assert re.reached and q["low"], mode
    good = reestimate(rep.current, obs, ("projector",))
    assert good.result.diagnostics["trust"]["passed"] and not good.result.diagnostics["trust"]["quality"]["low"]


def test_prior_stops_where_more_captures_cannot_lower_the_1_sigma():
    """Under the prior the pose's 1-sigma has a floor, the previous intrinsics' uncertainty: a target
    between the captures' own share (what held intrinsics report) and the total is met as far as
    captures can meet it (reached, the floor said), a target below the captures' own share is not."""
    b, rep, held = _reestimated("projector", 8, 0, intrinsics="held")
    sh = held.sigma["projector"]
    o1 = observe(_session(b, 2, 2, 0), NOISE_PX, 7)
    obs = merge_observations(o1, observe(_session(b, 8, 0, 1), NOISE_PX, 8))
    total = reestimate(rep.current, obs, ("projector",), intrinsics="prior").sigma["projector"]
    assert total["t_mm"] > 1.1 * sh["t_mm"] and total["rot_deg"] > 1.5 * sh["rot_deg"]
    between = {"projector_t": (sh["t_mm"] + total["t_mm"]) / 2, "projector_rot_deg": (sh["rot_deg"] + total["rot_deg"]) / 2}
    re = reestimate(rep.current, obs, ("projector",), targets=between, intrinsics="prior")
    assert re.reached and not re.missing and len(re.floor) == 2
    assert "projector rotation 1-sigma" in re.floor[0] + re.floor[1] and "previous intrinsics" in re.floor[0]
    assert re.to_dict()["limited_by_previous_intrinsics"] == list(re.floor)
    below = {"projector_t": 0.5 * sh["t_mm"], "projector_rot_deg": 0.5 * sh["rot_deg"]}
    re = reestimate(rep.current, obs, ("projector",), targets=below, intrinsics="prior")
    assert not re.reached and len(re.missing) == 2 and not re.floor


def test_reestimate_says_which_target_is_not_reached_yet():
    b, rep = check("camera")
    re = reestimate(rep.current, observe(_session(b, 2, 2, 0), NOISE_PX, 7), rep.moved)
    target = targets_from(previous())["camera_f_px"]
    assert max(re.sigma["camera"]["fx_px"], re.sigma["camera"]["fy_px"]) > target
    assert not re.reached and len(re.missing) == 1 and "camera focal length 1-sigma" in re.missing[0]


def test_projection_difference_of_a_focal_change_is_its_radial_scale():
    cam = get_scenario().rig.camera
    K = np.array(cam.K)
    K[0, 0] *= 1.005
    K[1, 1] *= 1.005
    pd = projection_difference(cam, cam.with_params(K=K), grid=(5, 4))
    w, h = cam.size
    xs, ys = np.linspace(0.05 * w, 0.95 * w, 5), np.linspace(0.05 * h, 0.95 * h, 4)
    expect = np.array([[0.005 * np.hypot(x - cam.cx, y - cam.cy) for x in xs] for y in ys])
    assert np.allclose(pd["px"], expect, atol=1e-3)
    assert pd["max_px"] == pytest.approx(expect.max(), abs=1e-3)


# ---- the archive and the command -----------------------------------------------------------------
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from calib.errors import SessionError  # noqa: E402


def test_archive_copies_with_its_hash_and_never_overwrites(tmp_path):
    from app.recalibration import archive_previous, find_previous
    from calib.recalib import sha256_file

    src_dir = tmp_path / "old"
    src_dir.mkdir()
    get_scenario().ground_truth().save_json(src_dir / "calibration.json")
    src = find_previous(src_dir)  # a session folder is accepted
    assert src == src_dir / "calibration.json" and find_previous(src) == src
    out = tmp_path / "new"
    dest, digest = archive_previous(src, out)
    assert dest == out / "previous" / "calibration.json"
    assert dest.read_bytes() == src.read_bytes() and digest == sha256_file(src)
    before = dest.read_bytes()
    other = tmp_path / "other.json"
    bump_scenario(get_scenario(), "projector", 0).ground_truth().save_json(other)
    with pytest.raises(SessionError, match="never overwrites"):
        archive_previous(other, out)
    assert dest.read_bytes() == before
    with pytest.raises(SessionError, match="no previous calibration"):
        find_previous(tmp_path / "missing")


def _procam(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True, timeout=timeout)


def test_recalibrate_refuses_a_missing_previous_and_a_used_folder(tmp_path):
    r = _procam("recalibrate", str(tmp_path / "nope"), "--rig", "sim", "--auto", "--out", str(tmp_path / "d"))
    assert r.returncode == 2 and "no previous calibration" in r.stderr and not (tmp_path / "d").exists()
    get_scenario().ground_truth().save_json(tmp_path / "c.json")
    used = tmp_path / "used"
    used.mkdir()
    (used / "keep.txt").write_text("x")
    r = _procam("recalibrate", str(tmp_path / "c.json"), "--rig", "sim", "--auto", "--out", str(used))
    assert r.returncode == 2 and "not empty" in r.stderr and sorted(p.name for p in used.iterdir()) == ["keep.txt"]


@pytest.mark.slow
def test_recalibrate_after_a_projector_bump_end_to_end(tmp_path):
    """A full simulated session, then `procam recalibrate --sim-bump projector` on it."""
    from calib.models.result import CalibrationResult
    from calib.recalib import sha256_file

    full = tmp_path / "full"
    r = _procam("session", "--rig", "sim", "--auto", "--out", str(full))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    prev_bytes = (full / "calibration.json").read_bytes()
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(full), "--rig", "sim", "--auto", "--sim-bump", "projector", "--out", str(d))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rec = json.loads((d / "recalibration.json").read_text())
    parts = rec["check"]["parts"]
    assert parts["projector"]["status"] == "moved"
    assert parts["mirror"]["status"] == "unchanged" and parts["camera"]["status"] == "unchanged"
    assert rec["captures"]["total"] <= 12
    assert rec["previous"]["sha256"] == sha256_file(full / "calibration.json")
    assert (d / "previous" / "calibration.json").read_bytes() == prev_bytes == (full / "calibration.json").read_bytes()
    res, gt = CalibrationResult.load_json(d / "calibration.json"), CalibrationResult.load_json(d / "ground_truth.json")
    m = compare(res, gt)
    assert m.distance < 0.5 and m.angle_deg < 0.05
    assert json.loads((d / "session.json").read_text())["state"]["recalibration"]["sim_bump"] == "projector"
    assert rec["comparison"]["projector"]["rotation_change_deg"] == pytest.approx(1.0, abs=0.05)
    # the epipolar verification: the previous calibration fails on the bumped rig, the recalibrated one passes
    assert rec["verification"]["previous"]["passed"] is False
    assert rec["verification"]["recalibrated"]["passed"] is True
    assert json.loads((d / "verification.json").read_text())["passed"] is True


@pytest.mark.slow
def test_a_structured_light_session_is_recalibrated_with_its_own_step(tmp_path):
    """PREVIOUS measured its projector with the structured-light sequence: the recalibration's projector
    captures are structured placements too (each the whole coded sequence), the check finds the bumped
    projector and the re-estimate lands on the bumped truth."""
    from calib.models.result import CalibrationResult
    from calib.formats.session import SessionStore

    full = tmp_path / "full"
    r = _procam("session", "--rig", "sim", "--auto", "--projector-pattern", "structured", "--placements", "4",
                "--mirror-captures", "4", "--out", str(full))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(full), "--rig", "sim", "--auto", "--sim-bump", "projector", "--out", str(d))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    man = SessionStore.open(d).manifest
    assert man.pattern.kind == "structured"
    proj = man.captures_of("projector")
    assert proj and all(c.structured for c in proj)
    assert all(len(c.frames) == len(SessionStore.open(full).manifest.captures_of("projector")[0].frames) for c in proj)
    rec = json.loads((d / "recalibration.json").read_text())
    assert rec["check"]["parts"]["projector"]["status"] == "moved"
    assert rec["check"]["parts"]["camera"]["status"] == "unchanged"
    m = compare(CalibrationResult.load_json(d / "calibration.json"), CalibrationResult.load_json(d / "ground_truth.json"))
    assert m.distance < 0.5 and m.angle_deg < 0.05
    assert rec["verification"]["recalibrated"]["passed"] is True

@pytest.mark.slow
def test_recalibrate_exit_code_3_for_a_low_quality_calibration_0_for_a_good_one(tmp_path):
    """`--sim-bump none` from a previous calibration far more uncertain than a full session: the
    calibration written (the previous one) fails the quality gate, exit 3 with the reasons, as
    `procam calibrate` / `session`; the same flow from the good calibration exits 0."""
    low, good = tmp_path / "low.json", tmp_path / "good.json"
    inflated(previous(), 10.0).save_json(low)
    previous().save_json(good)
    for prev, code in ((low, 3), (good, 0)):
        d = tmp_path / f"recal-{code}"
        r = _procam("recalibrate", str(prev), "--rig", "sim", "--auto", "--sim-bump", "none", "--out", str(d))
        assert r.returncode == code, r.stdout[-3000:] + r.stderr[-2000:]
        rec = json.loads((d / "recalibration.json").read_text())
        assert rec["ok"] is True and rec["verdict"] == "unchanged" and (d / "calibration.json").exists()
        assert rec["sign_off"] is None and rec["intrinsics"] is None  # headless: nobody asked; nothing re-fitted
        assert ("LOW QUALITY" in r.stdout and "[quality_" in r.stdout) == (code == 3)


def test_station_recalibration_mode_refuses_a_missing_previous_and_a_used_folder(tmp_path):
    r = _procam("station", "--rig", "sim", "--port", "0", "--recalibrate", str(tmp_path / "nope"),
                "--session", str(tmp_path / "d"), timeout=120)
    assert r.returncode == 2 and "no previous calibration" in r.stderr and not (tmp_path / "d").exists()
    get_scenario().ground_truth().save_json(tmp_path / "c.json")
    used = tmp_path / "used"
    used.mkdir()
    (used / "keep.txt").write_text("x")
    r = _procam("station", "--rig", "sim", "--port", "0", "--recalibrate", str(tmp_path / "c.json"),
                "--session", str(used), timeout=120)
    assert r.returncode == 2 and "not empty" in r.stderr and sorted(p.name for p in used.iterdir()) == ["keep.txt"]
