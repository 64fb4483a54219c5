"""The next-best placement (calib.quality.next_pose): the pattern position where a board lands on the
largest remaining projection uncertainty (against each device's target), discounted by the placements
already there."""

from __future__ import annotations

from collections import Counter
from functools import lru_cache

import numpy as np

from calib.pipeline import calibrate_observations
from calib.quality.next_pose import DeviceGrid, area_sigma, next_position, position_area
from calib.quality.projection_uncertainty import grid_pixels
from calib.synthetic import SyntheticSession, observe
from drivers.sim.scenarios import get_scenario

SC = get_scenario("nonoverlap-136", 0)
SIZE = (SC.rig.projector.width, SC.rig.projector.height)
POSITIONS = range(SC.pattern.positions)
AREAS = {p: position_area(SC.pattern, *SIZE, p) for p in POSITIONS}


def _grid(sigma: np.ndarray, size=SIZE) -> dict:
    xs, ys = grid_pixels(*size)
    return {"x_px": xs.tolist(), "y_px": ys.tolist(), "sigma_px": sigma.tolist(), "fixed": False}


def _proj(sigma, target=1.0) -> DeviceGrid:
    return DeviceGrid("projector", _grid(sigma), AREAS, target)


def test_the_position_over_the_largest_sigma_is_chosen_and_said_where():
    s = np.full((10, 16), 0.1)
    s[-2:, -3:] = 1.0  # the bottom-right corner unconstrained
    best = next_position([_proj(s, 0.5)], POSITIONS, {})
    x0, y0, x1, y1 = AREAS[best.position]
    assert x1 > 0.9 * SIZE[0] and y1 > 0.9 * SIZE[1]
    assert best.sigma_px == 1.0 and best.target_px == 0.5 and best.where == "bottom-right corner"
    assert best.device == "projector"
    assert "bottom-right corner of the projector's image" in best.reason() and "1.000 px, target 0.5" in best.reason()


def test_equal_sigmas_go_to_the_place_with_fewest_placements_and_a_large_one_is_revisited():
    s = np.full((10, 16), 0.2)
    taken = {p: 1 for p in POSITIONS}
    taken[5] = 0
    assert next_position([_proj(s)], POSITIONS, taken).position == 5
    # once there, a place with twice the sigma is worth a second placement
    s2 = s.copy()
    s2[:2, :3] = 0.4
    best = next_position([_proj(s2)], POSITIONS, {p: 1 for p in POSITIONS})
    assert best.position == 0 and best.taken == 1


def test_the_device_furthest_from_its_target_decides():
    """Two grids: the projector's hot at its top-left, another device's (3x its target) where a board at
    position 8 lands in its image: that device decides; with its target 10x larger, the projector does."""
    cam_size = (1280, 800)
    s_p = np.full((10, 16), 0.1)
    s_p[:2, :3] = 1.0
    s_c = np.full((10, 16), 0.1)
    s_c[:2, -3:] = 3.0  # the camera's top-right corner
    cam_areas = {p: (0.0, 0.0, 100.0, 100.0) for p in POSITIONS}
    cam_areas[8] = (1100.0, 0.0, 1279.5, 150.0)
    grids = [_proj(s_p, 1.0), DeviceGrid("camera", _grid(s_c, cam_size), cam_areas, 1.0)]
    best = next_position(grids, POSITIONS, {})
    assert (best.position, best.device, best.where) == (8, "camera", "top-right corner")
    # with the camera's target 10x larger, the projector's need is the larger
    grids[1] = DeviceGrid("camera", _grid(s_c, cam_size), cam_areas, 10.0)
    assert next_position(grids, POSITIONS, {}).device == "projector"


def test_only_candidates_are_chosen_and_nothing_without_a_grid():
    s = np.full((10, 16), 0.1)
    s[:2, :3] = 5.0
    assert next_position([_proj(s)], [4, 7], {}).position in (4, 7)
    assert next_position([], POSITIONS, {}) is None
    assert next_position([DeviceGrid("projector", {"fixed": True, "sigma_px": None}, AREAS, 1.0)], POSITIONS, {}) is None
    assert next_position([_proj(s)], [], {}) is None
    s[:] = np.inf  # unconstrained everywhere: still a choice
    assert next_position([_proj(s)], [3], {}).position == 3


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


def test_a_calibration_that_never_reached_a_projector_corner_asks_for_it():
    """The joint adjustment's own grid: with no placement at a projector image corner, that corner's
    distortion is extrapolated, and the choice is the position there."""
    for drop, where in (((8,), "bottom-right corner"), ((0, 2), "top-left corner")):
        result, taken = _result_without(drop)
        grid = DeviceGrid("projector", result.projection_uncertainty["projector"], AREAS, 1.0)
        best = next_position([grid], POSITIONS, taken)
        assert best.position in drop and best.where == where and best.taken == 0, (drop, best)
