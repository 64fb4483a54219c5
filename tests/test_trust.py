"""The trust check (calib/quality/trust.py): degenerate sessions fail with their reasons (stable codes), through
both methods, `procam calibrate` and the station; full simulated sessions of every scenario pass."""

import dataclasses
import json

import numpy as np
import pytest

from _calib_helpers import observations
from calib.errors import CalibrationError, UntrustedCalibration
from calib.models.observations import BoardObservation, ProjectorView
from calib.models.result import CalibrationResult, MirrorPlane
from calib.pipeline import calibrate_observations
from calib.quality.trust import CODES, TrustThresholds, check_calibration, field_of_view_deg, radial_fold_fraction
from calib.synthetic import SyntheticSession, make_rig, observe

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


#: the copied-capture session's projector: fy of -5e7 px (the issue's run) or of 2.5e5 px, by the run
ABSURD_FOCAL = {"focal_out_of_range", "focal_nonpositive"}


# ---- degenerate sessions, built from a synthetic one (no rendering) ----------------------------------
def _normal():
    return observations("136", 0.2, 1, per_position=2)  # 26 projector views: quicker, still a full rig


def _copied_capture():
    """The same projector image over every projector capture: one board pose and one set of pattern
    blobs, while each capture still says which pattern position it showed."""
    obs = _normal()
    pv0 = obs.projector_views[0]
    views = tuple(ProjectorView(pv.capture_id, pv0.board, pv0.pattern_cam_px, pv.pattern_proj_px,
                                pv.pattern_position) for pv in obs.projector_views)
    return dataclasses.replace(obs, projector_views=views)


def _identical_pattern_points():
    """Every capture claims the first capture's pattern points (projector pixels)."""
    obs = _normal()
    pv0 = obs.projector_views[0]
    views = tuple(ProjectorView(pv.capture_id, pv.board, pv.pattern_cam_px, pv0.pattern_proj_px,
                                pv0.pattern_position) for pv in obs.projector_views)
    return dataclasses.replace(obs, projector_views=views)


def _with_nan(where: str):
    obs = _normal()
    views = list(obs.projector_views)
    pv = views[5]
    if where == "pattern":
        uv = np.array(pv.pattern_cam_px)
        uv[3, 0] = np.nan
        views[5] = ProjectorView(pv.capture_id, pv.board, uv, pv.pattern_proj_px, pv.pattern_position)
    else:
        c = np.array(pv.board.corners_px)
        c[2, 1] = np.inf
        views[5] = ProjectorView(pv.capture_id, BoardObservation(pv.board.ids, c, pv.board.mirrored),
                                 pv.pattern_cam_px, pv.pattern_proj_px, pv.pattern_position)
    return dataclasses.replace(obs, projector_views=tuple(views)), pv.capture_id


@pytest.mark.parametrize("method", ["paper", "joint"])
def test_copied_projector_capture_is_rejected(method):
    with pytest.raises(UntrustedCalibration) as ei:
        calibrate_observations(_copied_capture(), method)
    e = ei.value
    assert set(e.codes) <= set(CODES)
    if method == "paper":  # it runs to the end with an absurd projector: fy ~ 2.5e5 px, stereo RMS ~ 33 px
        assert {"focal_out_of_range", "aspect_ratio", "rms_high"} <= set(e.codes)
        pj = e.result.projector
        assert field_of_view_deg(pj.fy, pj.cy, pj.height) < TrustThresholds().fov_min_deg
    else:  # the refinement meets NaN from that starting point: no crash, the reason, the start kept
        # (OpenCV's threads make the degenerate starting point vary from run to run: the refinement either
        # meets NaN and reports its absurd start, or ends absurd itself)
        assert ABSURD_FOCAL & set(e.codes)
        if "non_finite" in e.codes:
            assert e.codes[0] == "non_finite" and "joint_error" in e.result.diagnostics
    assert e.code == "untrusted" and isinstance(e, CalibrationError)
    assert e.report.reasons[0].message in str(e)
    assert e.result is not None


@pytest.mark.parametrize("method", ["paper", "joint"])
def test_identical_pattern_points_are_rejected(method):
    with pytest.raises(UntrustedCalibration) as ei:
        calibrate_observations(_identical_pattern_points(), method)
    codes = ei.value.codes
    if method == "paper" or "non_finite" in codes:  # the paper result (or the joint's start) does not fit
        assert "rms_high" in codes
    else:  # the joint fits it (RMS 0.04 px in the case) but nothing pins the projector down
        assert {"uncertainty_pose", "uncertainty_intrinsics", "ill_conditioned"} & set(codes)


@pytest.mark.parametrize("method", ["paper", "joint"])
@pytest.mark.parametrize("where", ["pattern", "board"])
def test_non_finite_observation_is_a_calibration_error(method, where):
    obs, cid = _with_nan(where)
    with pytest.raises(CalibrationError) as ei:
        calibrate_observations(obs, method)
    assert ei.value.code == "non_finite" and cid in str(ei.value)


def test_refine_joint_reports_non_finite_instead_of_crashing():
    """NaN reaching the solver itself (not via the pipeline's input check) becomes a CalibrationError."""
    from calib.joint.method import refine_joint

    obs, _ = _with_nan("pattern")
    init = calibrate_observations(_normal(), "paper")
    with pytest.raises(CalibrationError) as ei:
        refine_joint(obs, init)
    assert ei.value.code == "non_finite"


# ---- single checks on an exact result ---------------------------------------------------------------
@pytest.fixture(scope="module")
def truth():
    return make_rig(136).ground_truth()


def _codes(result):
    return check_calibration(result).codes


def test_ground_truth_passes(truth):
    assert check_calibration(truth).passed
    assert radial_fold_fraction(truth.camera) is None and radial_fold_fraction(truth.projector) is None


@pytest.mark.parametrize("change, code", [
    (lambda t: t.with_(projector=t.projector.with_params(K=np.diag([2300.0, -5e7, 1.0]))), "focal_nonpositive"),
    (lambda t: t.with_(camera=t.camera.with_params(K=[[6e4, 0, 640], [0, 6e4, 400], [0, 0, 1]])), "focal_out_of_range"),
    (lambda t: t.with_(camera=t.camera.with_params(K=[[640, 0, 640], [0, 900, 400], [0, 0, 1]])), "aspect_ratio"),
    (lambda t: t.with_(projector=t.projector.with_params(K=[[2300, 0, 9000], [0, 2300, 500], [0, 0, 1]])),
     "principal_point"),
    (lambda t: t.with_(camera=t.camera.with_params(dist=[-0.45, 0.0, 0, 0, 0])), "distortion_folds"),
    (lambda t: t.with_(mirror=MirrorPlane([0, 0, 1.0], 300.0)), "mirror_behind_camera"),
    (lambda t: t.with_(T_cam_proj=np.array(t.T_cam_proj) + np.pad([[0, 0, 0, 2e4]], ((0, 3), (0, 0)))),
     "projector_too_far"),
    (lambda t: t.with_(rms={"joint": 330.0}, method="joint"), "rms_high"),
    (lambda t: t.with_(camera=t.camera.with_params(K=[[np.nan, 0, 640], [0, 640, 400], [0, 0, 1]])), "non_finite"),
])
def test_each_check_fires(truth, change, code):
    assert code in CODES
    assert code in _codes(change(truth))


def test_fold_is_within_the_image_only(truth):
    """A k1 that folds the mapping beyond the image corners is fine; one that folds inside is not."""
    cam = truth.camera
    assert radial_fold_fraction(cam.with_params(dist=[-0.1, 0, 0, 0, 0])) is None  # folds at r ~ 1.83 > 1.17
    f = radial_fold_fraction(cam.with_params(dist=[-0.3, 0, 0, 0, 0]))  # r_d peaks at 0.70 < 1.17
    assert f == pytest.approx(0.70 / 1.1734, abs=0.02)


def test_uncertainty_and_conditioning_checks(truth):
    th = TrustThresholds()
    cov = np.eye(3)
    unc = {"T_cam_proj": {"t_total": th.sigma_t_mm * 24, "rot_total_deg": 0.01},
           "camera": {"fx": 0.2, "fy": 0.2, "cx": 0.3, "cy": 0.2},
           "projector": {"fx": max(th.sigma_intrinsics_px, th.sigma_intrinsics_fraction * truth.projector.fx) * 2,
                         "fy": 1, "cx": 1, "cy": 1},
           "mirror": {"normal_deg": 0.03, "d": 0.1}, "covariance": {"matrix": cov.tolist()}}
    rep = check_calibration(truth.with_(uncertainty=unc))
    assert rep.codes == ["uncertainty_pose", "uncertainty_intrinsics"]
    assert rep.reasons[0].value == pytest.approx(th.sigma_t_mm * 24)
    # a cm session: the same number is 10x the length
    unc_cm = dict(unc, T_cam_proj={"t_total": th.sigma_t_mm / 5, "rot_total_deg": 0.01},
                  projector={"fx": 1, "fy": 1, "cx": 1, "cy": 1})
    T_cm = np.array(truth.T_cam_proj, float)
    T_cm[:3, 3] /= 10.0  # the same rig, its lengths in cm
    truth_cm = truth.with_(T_cam_proj=T_cm, mirror=MirrorPlane(truth.mirror.normal, truth.mirror.d / 10.0), units="cm")
    assert check_calibration(truth_cm.with_(uncertainty=unc_cm)).codes == ["uncertainty_pose"]
    assert check_calibration(truth.with_(uncertainty=unc_cm)).passed
    # a covariance that could not be computed (NaN) fails, it does not pass silently
    unc_nan = dict(unc_cm, T_cam_proj={"t_total": float("nan"), "rot_total_deg": 0.01},
                   covariance={"matrix": [[1.0, float("nan")], [float("nan"), 1.0]]})
    assert check_calibration(truth.with_(uncertainty=unc_nan)).codes == ["uncertainty_pose", "ill_conditioned"]
    nearly_singular = np.array([[1.0, 1 - 1e-12], [1 - 1e-12, 1.0]])
    unc_sing = dict(unc_cm, covariance={"matrix": nearly_singular.tolist()})
    assert check_calibration(truth.with_(uncertainty=unc_sing)).codes == ["ill_conditioned"]


# ---- full sessions of every simulator scenario pass (exact geometry + blob-centroid bias + noise) -----
def _scenario_obs(name):
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario(name, 0)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                          sc.mirror_method, sc.board_thickness_mm)
    return observe(ss, 0.3, 0, circle_centroids=True)


def _scenario_names():
    from drivers.sim.scenarios import scenario_names

    return scenario_names()


@pytest.mark.parametrize("name", _scenario_names())
def test_full_sessions_of_every_scenario_pass(name):
    obs = _scenario_obs(name)
    for method in ("paper", "joint"):
        res = calibrate_observations(obs, method)  # raises UntrustedCalibration if rejected
        trust = res.diagnostics["trust"]
        assert trust["passed"] and trust["reasons"] == []
        if method == "joint":  # the uncertainty checks did run, well inside their limits
            th = TrustThresholds()
            assert trust["metrics"]["sigma.t_mm"] < th.sigma_t_mm / 5
            assert trust["metrics"]["condition"] < th.condition_max / 100


def test_accept_mode_keeps_the_result_with_its_reasons():
    res = calibrate_observations(_copied_capture(), "paper", trust="accept")
    trust = res.diagnostics["trust"]
    assert not trust["passed"] and trust["accepted_by_user"]
    assert "rms_high" in [r["code"] for r in trust["reasons"]]


# ---- the command line and the station ----------------------------------------------------------------
@pytest.fixture
def empty_session(tmp_path):
    """A session folder whose detection is replaced by given observations (no images to render)."""
    from calib.formats.session import RigInfo, SessionManifest, SessionStore

    obs = _normal()
    manifest = SessionManifest(rig=RigInfo(obs.camera_size, obs.projector_size, obs.view, driver="test"),
                               projector_board=obs.projector_board, pattern=obs.pattern,
                               mirror_board=obs.mirror_board, mirror_method="real-virtual")
    SessionStore.create(tmp_path / "s", manifest)
    return tmp_path / "s"


def _detect_returns(monkeypatch, obs):
    import calib.detection.detect

    monkeypatch.setattr(calib.detection.detect, "detect_session", lambda *a, **k: obs)


@pytest.mark.parametrize("method", ["paper", "joint"])
def test_cli_exits_non_zero_and_writes_no_calibration(empty_session, monkeypatch, capsys, method):
    from app.cli import main

    _detect_returns(monkeypatch, _copied_capture())
    rc = main(["calibrate", str(empty_session), "--method", method, "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0
    assert not (empty_session / "calibration.json").exists() and not (empty_session / "calibration.yaml").exists()
    assert any(f"[{c}]" in err for c in ABSURD_FOCAL)
    assert err.strip().splitlines()[-1].startswith("procam calibrate: error: the calibration is not trustworthy")
    rejected = json.loads((empty_session / "calibration.rejected.json").read_text())
    assert rejected["diagnostics"]["trust"]["passed"] is False
    assert rejected["diagnostics"]["trust"]["reasons"][0]["code"] in CODES


def test_cli_accept_untrusted_writes_with_the_reasons(empty_session, monkeypatch, capsys):
    from app.cli import main

    _detect_returns(monkeypatch, _copied_capture())
    rc = main(["calibrate", str(empty_session), "--method", "paper", "--no-progress", "--accept-untrusted"])
    err = capsys.readouterr().err
    assert rc == 0 and "WARNING" in err and "[rms_high]" in err
    res = CalibrationResult.load_json(empty_session / "calibration.json")
    assert res.diagnostics["trust"]["accepted_by_user"] is True


def test_cli_normal_session_passes(empty_session, monkeypatch, capsys):
    from app.cli import main

    _detect_returns(monkeypatch, _normal())
    rc = main(["calibrate", str(empty_session), "--method", "paper", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    res = CalibrationResult.load_json(empty_session / "calibration.json")
    assert res.diagnostics["trust"]["passed"] is True
    assert not (empty_session / "calibration.rejected.json").exists()


def test_station_shows_the_reasons_and_keeps_no_result(tmp_path):
    """The station's calibration step: the failure and its reasons reach the machine's error (what the
    panel and the instruction line show) and its log; calibration.json is not written."""
    from app.station.machine import CALIBRATION, Plan, RigCheck, SessionMachine
    from app.station.session_calibration import keep_rejected
    from _station_helpers import TINY, make_store

    def calibrate_fn(folder, camera_intrinsics, progress=None):  # the pipeline, on a degenerate session
        return calibrate_observations(_copied_capture(), "paper")

    plan = Plan(poses_per_position=2, real_virtual_captures=4, real_mirror_captures=2, min_real_virtual=3,
                min_projector_captures=6)
    m = SessionMachine(make_store(tmp_path / "s", "mirror", 5), plan, calibrate_fn=calibrate_fn)
    m.start_session([RigCheck("camera", True, "streaming"), RigCheck("projector", True, "up")])
    m.choose_mirror_method("real-virtual")
    while m.target is not None:
        m.record_capture(TINY)
    m.proceed()
    while m.target is not None:
        m.record_capture(TINY)
    with pytest.raises(UntrustedCalibration):
        m.calibrate()
    folder = m.store.folder
    assert m.state == CALIBRATION and m.busy is None
    assert "not trustworthy" in m.calibration_error and "stereo RMS" in m.calibration_error
    assert m.result is None and not (folder / "calibration.json").exists()
    assert json.loads((folder / "calibration.rejected.json").read_text())["diagnostics"]["trust"]["passed"] is False
    assert any("calibration failed" in e.text and "RMS" in e.text for e in m.events)
    assert keep_rejected(folder, lambda: 7) == 7


# ---- end to end: a rendered session, made degenerate the way the issue found it -----------------------
@pytest.fixture(scope="module")
def rendered_small(tmp_path_factory):
    """13 projector + 5 real-virtual images of the 136 degree rig, rendered (detection included)."""
    from _calib_helpers import write_session
    from calib.synthetic import make_session

    folder = tmp_path_factory.mktemp("trust") / "session"
    write_session(folder, make_session(make_rig(136), per_position=1, mirror_count=5, seed=2), k=1)
    return folder


def _run_calibrate(folder, *args):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "app", "calibrate", str(folder), "--no-progress", *args],
                          capture_output=True, text=True, timeout=600)


def _degenerate_copy(src, dst, mode: str):
    import shutil

    shutil.copytree(src, dst)
    data = json.loads((dst / "session.json").read_text())
    proj = [c for c in data["captures"] if c["step"] == "projector"]
    for c in proj[1:]:
        if mode == "copied image":
            shutil.copyfile(dst / proj[0]["image"], dst / c["image"])
        else:
            c["pattern_points_px"] = proj[0]["pattern_points_px"]
    (dst / "session.json").write_text(json.dumps(data))
    return dst


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["copied image", "identical pattern points"])
def test_rendered_degenerate_session_fails_in_the_cli(rendered_small, tmp_path, mode):
    folder = _degenerate_copy(rendered_small, tmp_path / "s", mode)
    for method in ("paper", "joint"):
        proc = _run_calibrate(folder, "--method", method)
        assert proc.returncode == 2, proc.stderr
        assert not (folder / "calibration.json").exists() and not (folder / "calibration.yaml").exists()
        assert "Traceback" not in proc.stderr
        if mode == "copied image":  # copies count once (calib.detection.detect): too few images to start
            assert "only 1 usable projector image" in proc.stderr and "p0001 is a copy of p0000" in proc.stderr
            continue
        assert "not trustworthy" in proc.stderr
        rejected = json.loads((folder / "calibration.rejected.json").read_text())
        codes = [r["code"] for r in rejected["diagnostics"]["trust"]["reasons"]]
        assert codes and set(codes) <= set(CODES) and all(f"[{c}]" in proc.stderr for c in codes)


@pytest.mark.slow
def test_rendered_normal_session_passes_in_the_cli(rendered_small, tmp_path):
    import shutil

    folder = tmp_path / "s"
    shutil.copytree(rendered_small, folder)
    proc = _run_calibrate(folder)
    assert proc.returncode == 0, proc.stderr
    res = CalibrationResult.load_json(folder / "calibration.json")
    assert res.diagnostics["trust"]["passed"] and not (folder / "calibration.rejected.json").exists()
