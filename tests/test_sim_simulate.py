"""`procam simulate` writes sessions in the live capture format, with ground truth and the scene."""

import json

import numpy as np
import pytest

from app.cli import main
from calib.detection.detect import detect_board
from calib.formats.session import SessionStore
from calib.models.result import CalibrationResult
from calib.quality.metrics import PAPER_HEADLINE, compare
from drivers.sim.scenarios import get_scenario, list_scenarios


def test_list(capsys):
    assert main(["simulate", "--list"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split()[0] for ln in lines] == [n for n, _ in list_scenarios()]
    assert all(len(ln.split(None, 1)) == 2 for ln in lines)


def test_errors(tmp_path, capsys):
    assert main(["simulate", "nope", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scenario" in capsys.readouterr().err
    assert main(["simulate", "direct"]) == 2
    assert "--out" in capsys.readouterr().err


def test_simulated_session_reads_like_a_live_one(tmp_path):
    out = tmp_path / "s"
    rc = main(["simulate", "nonoverlap-136", "--out", str(out), "--seed", "4", "--per-position", "1",
               "--mirror-count", "2", "--quality", "live", "--noise", "0", "--blur", "0", "--workers", "2",
               "--no-progress"])
    assert rc == 0
    store = SessionStore.open(out)
    m = store.manifest
    sc = get_scenario("nonoverlap-136", 4)
    assert m.rig.driver == "sim" and m.rig.view == "mirror" and m.rig.camera_size == (1280, 800)
    assert m.projector_board == sc.projector_board and m.mirror_board == sc.mirror_board
    assert m.pattern == sc.pattern and m.mirror_method == "real-virtual" and m.board_thickness == 0.0
    proj = m.captures_of("projector")
    assert len(proj) == 13 and len(m.captures_of("mirror-real-virtual")) == 2
    for c in proj:
        assert np.allclose(c.pattern_points_px, sc.pattern.points_px(1920, 1080, c.pattern_position))
    assert sorted(c.pattern_position for c in proj) == list(range(13))
    gt = CalibrationResult.load_json(out / "ground_truth.json")
    assert gt.units == "mm" and np.allclose(gt.T_cam_proj, sc.rig.T_cam_proj)
    assert np.allclose(gt.mirror.normal, sc.rig.mirror.normal)
    scene = json.loads((out / "scene.json").read_text())
    assert scene["name"] == "nonoverlap-136" and scene["seed"] == 4 and scene["mirror_rect"]["size_mm"] == [620.0, 420.0]
    assert scene["render_used"]["read_noise_dn"] == 0.0 and scene["render_used"]["supersample"] == 1
    caps = {c["id"]: c for c in scene["captures"]}
    assert set(caps) == {c.id for c in m.captures}
    # the recorded board pose is the one in the image
    c = proj[3]
    T = np.array(caps[c.id]["T_cam_board"])
    img = store.load_image(c)
    obs = detect_board(img, m.projector_board, mirrored=True)
    from calib.transforms import transform_points

    expected = sc.rig.camera.project(transform_points(sc.rig.S() @ T, m.projector_board.corner_points()))[obs.ids]
    assert np.median(np.linalg.norm(obs.corners_px - expected, axis=1)) < 0.1
    # same seed, same images (whatever the process that rendered them)
    out2 = tmp_path / "s2"
    main(["simulate", "nonoverlap-136", "--out", str(out2), "--seed", "4", "--per-position", "1", "--mirror-count", "2",
          "--quality", "live", "--noise", "0", "--blur", "0", "--workers", "1", "--no-progress"])
    assert np.array_equal(store.load_image(c), SessionStore.open(out2).load_image(c))
    # an existing session is not overwritten by accident
    assert main(["simulate", "direct", "--out", str(out), "--no-progress"]) == 2


@pytest.mark.slow
def test_simulate_then_calibrate_reproduces_ground_truth(tmp_path):
    """The default scenario, full protocol (7 real-virtual + 13 x 4 captures, camera noise and blur on,
    session quality), calibrated by `procam calibrate` with the default and with the paper's method:
    errors no worse than the paper's synthetic headline numbers (docs/GEOMETRY.md)."""
    out = tmp_path / "s"
    assert main(["simulate", "nonoverlap-136", "--out", str(out), "--no-progress"]) == 0
    gt = CalibrationResult.load_json(out / "ground_truth.json")
    for extra in ([], ["--method", "paper"]):
        target = out / f"calibration{'-'.join([''] + extra[1:])}.json"
        assert main(["calibrate", str(out), "--no-progress", "--out", str(target), *extra]) == 0
        m = compare(CalibrationResult.load_json(target), gt)
        assert m.distance < PAPER_HEADLINE["distance"], extra
        assert m.angle_deg < PAPER_HEADLINE["angle_deg"], extra
        assert m.proj_k_px < PAPER_HEADLINE["proj_k_px"], extra
        assert m.proj_d < PAPER_HEADLINE["proj_d"], extra
        assert m.mirror_offset < PAPER_HEADLINE["mirror_offset"], extra
        assert m.mirror_angle_deg < PAPER_HEADLINE["mirror_angle_deg"], extra
        assert m.cam_k_px < 2.0, extra
