"""Projection uncertainty over the image (calib.quality.projection_uncertainty): the grid against a Monte-Carlo
of the covariance, large where the session has no data, stored in calibration.json and read back."""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np
import pytest

from calib.errors import FormatError
from calib.joint.lens import distort
from calib.models.result import CalibrationResult
from calib.pipeline import calibrate_observations
from calib.quality import projection_uncertainty as PU
from calib.synthetic import SyntheticSession, observe
from drivers.sim.scenarios import get_scenario
from _joint_helpers import observations


@lru_cache(maxsize=2)
def joint_result(kind: str) -> CalibrationResult:
    if kind == "default":  # the 136 deg mirrored rig, D455-like camera
        obs = observations(0.05, 0, circle_centroids=True)
    else:  # the wide-angle camera whose image corners see nothing
        sc = get_scenario("wideangle-realmirror", 0)
        ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, sc.projector_poses, sc.mirror_poses,
                              sc.mirror_method, sc.board_thickness_mm)
        obs = observe(ss, 0.05, 0, circle_centroids=True)
    return calibrate_observations(obs, "joint")


def _monte_carlo_sigma(model, cov, names, prefix, uv, n=4000, seed=1):
    """Worst-direction 1-sigma of the pixel motion of the rays through uv over samples of the intrinsics
    drawn from cov, each sample's field freed of its best-fitting rotation (the definition the module
    implements to first order), by the nonlinear projection."""
    rows, cols = PU._param_columns(names, prefix)
    C = np.asarray(cov)[np.ix_(rows, rows)]
    base = np.r_[model.K[0, 0], model.K[1, 1], model.K[0, 2], model.K[1, 2], np.pad(model.dist, (0, 8 - model.dist.size))]
    rng = np.random.default_rng(seed)
    theta = np.tile(base, (n, 1))
    theta[:, cols] += rng.multivariate_normal(np.zeros(len(rows)), C, size=n)
    xy = model.undistort_normalized(uv)
    x, y = xy[None, :, 0], xy[None, :, 1]
    xd, yd = distort(x, y, [theta[:, 4 + i, None] for i in range(8)])
    px = np.stack([theta[:, 0, None] * xd + theta[:, 2, None], theta[:, 1, None] * yd + theta[:, 3, None]], axis=-1)
    d = (px - uv[None]).reshape(n, -1)  # (n, 2N)
    R = PU.rotation_jacobian(model, uv).reshape(-1, 3)
    d = d - (d @ np.linalg.pinv(R).T) @ R.T
    d = d.reshape(n, -1, 2)
    d -= d.mean(axis=0)
    Cq = np.einsum("sni,snj->nij", d, d) / n
    return np.sqrt(np.linalg.eigvalsh(Cq)[:, 1])


@pytest.mark.parametrize("device,prefix", [("camera", "cam"), ("projector", "proj")])
def test_grid_matches_monte_carlo_of_the_covariance(device, prefix):
    r = joint_result("default")
    g = r.projection_uncertainty[device]
    names, cov = r.uncertainty["covariance"]["names"], r.uncertainty["covariance"]["matrix"]
    X, Y = np.meshgrid(g["x_px"], g["y_px"])
    uv = np.column_stack([X.ravel(), Y.ravel()])
    model = r.camera if device == "camera" else r.projector
    mc = _monte_carlo_sigma(model, cov, names, prefix, uv)
    grid = np.asarray(g["sigma_px"]).ravel()
    assert grid.shape == (16 * 10,)
    rel = np.abs(grid - mc) / mc
    assert np.median(rel) < 0.04 and rel.max() < 0.12, (np.median(rel), rel.max())
    # the fixed-ray motion without the rotation removed is far larger at the centre: the removal matters
    assert grid.min() < 0.5 * np.sqrt(np.asarray(cov)[names.index(f"{prefix}.cx")][names.index(f"{prefix}.cx")])


def test_large_in_the_corners_without_data_and_said_so():
    r = joint_result("wide")
    g = r.projection_uncertainty["camera"]
    s = np.asarray(g["sigma_px"])
    centre = s[3:7, 5:11].max()
    corners = np.array([s[0, 0], s[0, -1], s[-1, 0], s[-1, -1]])
    assert np.all(corners > 4 * centre), (corners, centre)
    assert corners.max() > PU.LARGE_SIGMA_PX and g["large_fraction"] > 0
    line = PU.summary_line(r.projection_uncertainty, "camera")
    assert "LARGE" in line and "corner" in line and PU.where_max(g).endswith("corner")
    # a grid large only at its centre says "centre"
    assert PU.large_regions({"sigma_px": [[0, 0, 0, 0], [0, 0.9, 0.9, 0], [0, 0.9, 0.9, 0], [0, 0, 0, 0]]}) == ["centre"]
    from app.commands.calibrate import format_summary

    assert line in format_summary(r)


def test_round_trip_and_old_files(tmp_path):
    r = joint_result("default")
    p = tmp_path / "calibration.json"
    r.save_json(p)
    back = CalibrationResult.load_json(p)
    for dev in ("camera", "projector"):
        a, b = r.projection_uncertainty[dev], back.projection_uncertainty[dev]
        assert a["grid"] == b["grid"] == [16, 10]
        assert np.allclose(a["sigma_px"], b["sigma_px"])
    assert back.projection_uncertainty["method"] == PU.METHOD
    d = json.loads(p.read_text())
    del d["projection_uncertainty"]  # a file written before the key existed
    old = tmp_path / "old.json"
    old.write_text(json.dumps(d))
    assert CalibrationResult.load_json(old).projection_uncertainty is None


@pytest.mark.parametrize("bad,field", [
    ("text", "projection_uncertainty"),
    ({"camera": {"grid": [16], "sigma_px": []}}, "projection_uncertainty.camera.grid"),
    ({"camera": {"grid": [2, 2], "sigma_px": [[1, 2], [3]]}}, "projection_uncertainty.camera.sigma_px"),
    ({"camera": {"grid": [2, 1], "sigma_px": [[1, -2]]}}, "projection_uncertainty.camera.sigma_px"),
    ({"projector": {"grid": [1, 1], "sigma_px": [["x"]]}}, "projection_uncertainty.projector.sigma_px"),
])
def test_malformed_grid_is_a_format_error(tmp_path, bad, field):
    p = tmp_path / "c.json"
    joint_result("default").save_json(p)
    d = json.loads(p.read_text())
    d["projection_uncertainty"] = bad
    p.write_text(json.dumps(d))
    with pytest.raises(FormatError) as e:
        CalibrationResult.load_json(p)
    assert field in str(e.value)


def test_paper_method_has_no_grid():
    r = calibrate_observations(observations(0.05, 0, circle_centroids=True), "paper")
    assert r.projection_uncertainty is None
    assert PU.projection_uncertainty(r) is None
