"""detect_session on a session rendered by the simulator (drivers/sim): realistic images (room, lens
distortion, blur, noise, projector falloff), exact ground truth from its scene.json."""

from dataclasses import replace

import numpy as np
import pytest

from app.commands.simulate import simulate_session
from calib.detection.detect import detect_session
from drivers.sim.scenarios import get_scenario
from drivers.sim.scene_file import expected_points


@pytest.mark.slow
@pytest.mark.parametrize("name", ["nonoverlap-136", "direct"])
def test_detect_session_on_a_simulated_session(tmp_path, name):
    sc = replace(get_scenario(name, seed=3), per_position=1, mirror_count=2)
    store = simulate_session(sc, tmp_path / "s", quality="live", workers=1, progress=False)
    obs = detect_session(store, workers=2)
    truth = expected_points(tmp_path / "s")
    assert not obs.skipped, obs.skipped
    assert len(obs.projector_views) == 13 and len(obs.mirror_views) == (2 if sc.mirror_method else 0)
    board_err, pattern_err, mirror_err = [], [], []
    for v in obs.projector_views:
        corners, points, _ = truth[v.capture_id]
        assert v.board.mirrored == (name != "direct") and len(v.board.ids) >= 24
        board_err.append(np.linalg.norm(v.board.corners_px - corners[v.board.ids], axis=1))
        pattern_err.append(np.linalg.norm(v.pattern_cam_px - points, axis=1))
    for mv in obs.mirror_views:
        real, _, virt = truth[mv.capture_id]
        mirror_err.append(np.linalg.norm(mv.real.corners_px - real[mv.real.ids], axis=1))
        mirror_err.append(np.linalg.norm(mv.virtual.corners_px - virt[mv.virtual.ids], axis=1))
    board_err, pattern_err = np.concatenate(board_err), np.concatenate(pattern_err)
    # single-sample rendering with noise: a tenth of a pixel is the scale; a wrong flip would be >= 1 px
    assert np.median(board_err) < 0.12 and np.percentile(board_err, 95) < 0.35
    assert np.median(pattern_err) < 0.12 and np.percentile(pattern_err, 95) < 0.3
    if mirror_err:
        mirror_err = np.concatenate(mirror_err)
        assert np.median(mirror_err) < 0.15 and np.percentile(mirror_err, 90) < 0.4
