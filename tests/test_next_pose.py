"""The next-best placement (calib.quality.next_pose): the pattern position whose area of the projector's
image has the largest remaining projection uncertainty, discounted by the placements already there."""

from __future__ import annotations

from collections import Counter
from functools import lru_cache

import numpy as np

from calib.pipeline import calibrate_observations
from calib.quality.next_pose import area_sigma, next_position, position_area
from calib.quality.projection_uncertainty import grid_pixels
from calib.synthetic import SyntheticSession, observe
from drivers.sim.scenarios import get_scenario

SC = get_scenario("nonoverlap-136", 0)
SIZE = (SC.rig.projector.width, SC.rig.projector.height)


def _grid(sigma: np.ndarray) -> dict:
    xs, ys = grid_pixels(*SIZE)
    return {"x_px": xs.tolist(), "y_px": ys.tolist(), "sigma_px": sigma.tolist(), "fixed": False}


def test_the_position_over_the_largest_sigma_is_chosen_and_said_where():
    s = np.full((10, 16), 0.1)
    s[-2:, -3:] = 1.0  # the bottom-right corner unconstrained
    best = next_position(_grid(s), SC.pattern, SIZE, range(SC.pattern.positions), {})
    x0, y0, x1, y1 = position_area(SC.pattern, *SIZE, best.position)
    assert x1 > 0.9 * SIZE[0] and y1 > 0.9 * SIZE[1]
    assert best.sigma_px == 1.0 and best.where == "bottom-right corner"
    assert "bottom-right corner" in best.reason() and "1.000 px" in best.reason()


def test_equal_sigmas_go_to_the_place_with_fewest_placements_and_a_large_one_is_revisited():
    s = np.full((10, 16), 0.2)
    taken = {p: 1 for p in range(13)}
    taken[5] = 0
    assert next_position(_grid(s), SC.pattern, SIZE, range(13), taken).position == 5
    # once there, a place with twice the sigma is worth a second placement
    s2 = s.copy()
    s2[:2, :3] = 0.4
    best = next_position(_grid(s2), SC.pattern, SIZE, range(13), {p: 1 for p in range(13)})
    assert best.position == 0 and best.taken == 1


def test_only_candidates_are_chosen_and_nothing_without_a_grid():
    s = np.full((10, 16), 0.1)
    s[:2, :3] = 5.0
    assert next_position(_grid(s), SC.pattern, SIZE, [4, 7], {}).position in (4, 7)
    assert next_position(None, SC.pattern, SIZE, range(13), {}) is None
    assert next_position({"fixed": True, "sigma_px": None}, SC.pattern, SIZE, range(13), {}) is None
    assert next_position(_grid(s), SC.pattern, SIZE, [], {}) is None
    s[:] = np.inf  # unconstrained everywhere: still a choice
    assert next_position(_grid(s), SC.pattern, SIZE, [3], {}).position == 3


def test_an_area_between_cell_centres_takes_the_nearest_cell():
    s = np.arange(160, dtype=float).reshape(10, 16)
    g = _grid(s)
    xs, ys = g["x_px"], g["y_px"]
    x, y = (xs[3] + xs[4]) / 2, (ys[6] + ys[7]) / 2
    assert area_sigma(g, (x - 1, y - 1, x + 1, y + 1)) in (s[6, 3], s[6, 4], s[7, 3], s[7, 4])


@lru_cache(maxsize=2)
def _result_without(drop: tuple[int, ...]):
    poses = [(p, T) for p, T in SC.projector_poses if p not in drop]
    ss = SyntheticSession(SC.rig, SC.layout, SC.mirror_board, SC.pattern, poses, SC.mirror_poses, SC.mirror_method,
                          SC.board_thickness_mm)
    return calibrate_observations(observe(ss, 0.1, 0, circle_centroids=True), "joint"), Counter(p for p, _ in poses)


def test_a_calibration_that_never_reached_a_corner_asks_for_it():
    """The joint adjustment's own grid: with no placement at an image corner, that corner's distortion is
    extrapolated, and the choice is the position there."""
    for drop, where in (((8,), "bottom-right corner"), ((0, 2), "top-left corner")):
        result, taken = _result_without(drop)
        best = next_position(result.projection_uncertainty["projector"], SC.pattern, SIZE, range(13), taken)
        assert best.position in drop and best.where == where and best.taken == 0, (drop, best)
