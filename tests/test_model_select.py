"""The wide-angle corner-poor scenario and the coverage-aware distortion model selection on it:
the scenario is listed and renders (board corners detected where the geometry puts them); on its
synthetic sessions the joint method drops the k3 that only the unobserved image corners would need, and
is then no worse over the image than OpenCV with k3 fixed; where k3 is real and constrained (the D455-like
camera of the default rig) it is kept."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from calib.detection.detect import detect_board, detect_real_mirror
from calib.paper.camera import calibrate_camera
from calib.pipeline import calibrate_observations
from calib.quality.metrics import distortion_error_over_image
from calib.synthetic import SyntheticSession, observe
from calib.transforms import transform_points
from drivers.sim.render import PlacedBoard, Renderer, RenderSettings, SceneState, layout_for
from drivers.sim.scenarios import get_scenario, scenario_names

NAME = "wideangle-realmirror"


def _obs(name: str, seed: int):
    sc = get_scenario(name, seed)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                          sc.mirror_method, sc.board_thickness_mm)
    return sc, observe(ss, 0.05, seed, circle_centroids=True)


def test_listed_by_procam_simulate():
    assert NAME in scenario_names()
    out = subprocess.run([sys.executable, "-m", "app", "simulate", "--list"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and NAME in out.stdout and "fx 700" in out.stdout
    sc = get_scenario(NAME)
    cam = sc.rig.camera
    assert cam.size == (1920, 1080) and abs(cam.fx - 700) < 5 and cam.dist[0] == pytest.approx(-0.2)
    assert sc.mirror_method == "real-mirror"


def test_corner_poor_and_renders():
    sc = get_scenario(NAME)
    rig, cam = sc.rig, sc.rig.camera
    # every observation of a session stays away from the image corners
    uv = np.concatenate([cam.project(transform_points(rig.S() @ T, sc.projector_board.corner_points()))
                         for _, T in sc.projector_poses]
                        + [cam.project(transform_points(T, sc.mirror_board.corner_points())) for T in sc.mirror_poses])
    W, H = cam.size
    corner_dist = np.min([np.hypot(uv[:, 0] - x, uv[:, 1] - y) for x in (0, W) for y in (0, H)], axis=0)
    assert corner_dist.min() > 0.1 * np.hypot(W, H) and np.median(corner_dist) > 0.25 * np.hypot(W, H)
    # rendered (live quality): the projector board through the mirror and a board lying on the mirror are
    # detected where the geometry puts them
    r = Renderer(rig.camera, rig.projector, rig.T_cam_proj, rig.mirror, rig.mirror_rect, RenderSettings(supersample=1))
    T = sc.projector_poses[0][1]
    obs = detect_board(r.render(SceneState((PlacedBoard(sc.layout, T),))), sc.projector_board, True)
    assert obs and len(obs.ids) >= 30
    exp = cam.project(transform_points(rig.S() @ T, sc.projector_board.corner_points()))[obs.ids]
    assert np.median(np.linalg.norm(obs.corners_px - exp, axis=1)) < 0.1
    spec = sc.mirror_board
    T = sc.mirror_poses[0]
    mv = detect_real_mirror(r.render(SceneState((PlacedBoard(layout_for(spec), T),))), spec)
    assert mv and len(mv.real.ids) >= 20
    exp = cam.project(transform_points(T, spec.corner_points()))[mv.real.ids]
    assert np.median(np.linalg.norm(mv.real.corners_px - exp, axis=1)) < 0.1


@pytest.mark.parametrize("seed", [0, 6])
def test_coverage_criterion_drops_the_unconstrained_k3(seed):
    sc, obs = _obs(NAME, seed)
    true = sc.rig.camera
    r = calibrate_observations(obs, "joint")
    ms = r.diagnostics["model_selection"]["camera"]
    assert ms["chosen"] == "4coef" and r.camera.dist[4] == 0.0
    assert "coverage criterion" in ms["reason"]
    cands = {c["model"]: c for c in ms["coverage"]["candidates"]}
    assert cands["5coef"]["var_px2"] > 1.2 * cands["4coef"]["var_px2"]  # k3 is not constrained over the image
    assert set(cands) == {"4coef", "5coef"}  # only the highest radial order is weighed
    without = calibrate_observations(obs, "joint", method_options={"coverage": False})
    assert without.diagnostics["model_selection"]["camera"]["chosen"] == "5coef"
    err = distortion_error_over_image(r.camera, true)
    assert err < distortion_error_over_image(without.camera, true)
    assert err <= distortion_error_over_image(calibrate_camera(obs, fix_k3=True).camera, true)


def test_a_constrained_k3_is_kept():
    sc, obs = _obs("nonoverlap-136", 0)
    r = calibrate_observations(obs, "joint")
    ms = r.diagnostics["model_selection"]["camera"]
    assert ms["chosen"] == "5coef"
    cands = {c["model"]: c for c in ms["coverage"]["candidates"]}
    assert cands["4coef"]["mse_px2"] > 10 * cands["5coef"]["mse_px2"]


SHRINK = {"shrinkage": True}


def test_k3_shrinkage_pulls_an_unconstrained_k3_toward_zero():
    """Seed 4 of the wide-angle scenario (true k3 = 0): the keep-or-drop rule keeps a k3 that only noise put
    there (z^2 1.9); the shrinkage prior multiplies it by 1 - 1/z^2, the other parameters following, which
    brings the error over the image down; its covariance carries the prior."""
    sc, obs = _obs(NAME, 4)
    true = sc.rig.camera
    kept = calibrate_observations(obs, "joint", method_options={"shrinkage": False})
    assert kept.diagnostics["model_selection"]["camera"]["chosen"] == "5coef"
    r = calibrate_observations(obs, "joint", method_options=SHRINK)
    ms = r.diagnostics["model_selection"]["camera"]
    sh = ms["coverage"]["shrinkage"]
    assert ms["chosen"] == "5coef" and "k3 shrinkage" in ms["reason"]
    w = sh["weight_to_zero"]
    assert w == pytest.approx(1 / sh["z2"]) and 0.3 < w < 0.8
    # the MAP under the prior is (1 - w) times the unshrunk k3 (the quadratic model's identity)
    assert r.camera.dist[4] == pytest.approx(sh["k3_final"])
    assert abs(sh["k3_final"] - (1 - w) * sh["k3_5coef"]) < 0.05 * sh["k3_sigma"]
    assert abs(r.camera.dist[4]) < 0.7 * abs(kept.camera.dist[4])
    # posterior 1-sigma of k3: sqrt(1 - w) of the data's
    assert r.uncertainty["camera"]["dist"][4] == pytest.approx(np.sqrt(1 - w) * sh["k3_sigma"], rel=0.1)
    assert distortion_error_over_image(r.camera, true) < 0.85 * distortion_error_over_image(kept.camera, true)


def test_k3_shrinkage_drops_k3_when_the_data_show_no_more_than_noise():
    sc, obs = _obs(NAME, 0)
    r = calibrate_observations(obs, "joint", method_options=SHRINK)
    ms = r.diagnostics["model_selection"]["camera"]
    sh = ms["coverage"]["shrinkage"]
    assert sh["z2"] <= 1 and sh["weight_to_zero"] == 1.0 and sh["precision"] == float("inf")
    assert ms["chosen"] == "4coef" and r.camera.dist[4] == 0.0
    assert "prior width set from the data is zero" in ms["reason"]


def test_k3_shrinkage_leaves_a_constrained_k3():
    """The D455-like camera of the default rig has a real k3 (-0.019) that its views constrain: the prior is
    wide and k3 is recovered as without it."""
    sc, obs = _obs("nonoverlap-136", 0)
    r = calibrate_observations(obs, "joint", method_options=SHRINK)
    ms = r.diagnostics["model_selection"]["camera"]
    sh = ms["coverage"]["shrinkage"]
    assert ms["chosen"] == "5coef" and sh["weight_to_zero"] < 0.01 and sh["prior_sigma"] > 10 * sh["k3_sigma"]
    true_k3 = sc.rig.camera.dist[4]
    assert true_k3 == pytest.approx(-0.019)
    assert abs(r.camera.dist[4] - true_k3) < 2 * r.uncertainty["camera"]["dist"][4]
    assert r.camera.dist[4] == pytest.approx(sh["k3_5coef"], rel=0.01)


def test_accuracy_table_has_the_distortion_error_over_the_image():
    from app.commands.bench import accuracy_table

    metrics = {k: 0.0 for k in ("distance", "angle_deg", "proj_k_px", "proj_d", "cam_k_px", "cam_d", "mirror_offset",
                                "mirror_angle_deg", "proj_rms_px")}
    metrics.update(cam_dist_img_px=0.123, proj_dist_img_px=0.045)
    run = {"scenario": NAME, "seed": 0, "method": "joint", "skipped": 0, "metrics": metrics, "timing_s": {"total": 1.0}}
    table = accuracy_table([run], 1)
    head, row = table.splitlines()[0], next(line for line in table.splitlines() if line.startswith(NAME))
    assert "CamDimg px" in head and "ProjDimg px" in head
    assert "0.123" in row and "0.045" in row
