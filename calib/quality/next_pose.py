"""The next-best placement of a projector step: the pattern position where a board would reduce the
largest remaining uncertainty, from the projection-uncertainty grids of the calibration so far.

Each pattern position names where in the projector's image the board stands (the circle grid lands on its
blank area; a structured-light sequence is decoded over the whole board). A placement there adds points
over that area, so it reduces the device's projection uncertainty (calib.quality.projection_uncertainty:
intrinsics and distortion, rotation-compensated) mostly there. For each candidate position and each
device grid given (`DeviceGrid`: the station gives the projector's): the grid's largest 1-sigma over the
board's area in that device's image, divided by the device's target (calib.quality.confidence's "over
its image" targets); the worst is the position's need, and the choice is the position whose need one
more placement would reduce most if the information there grew like the count of placements over it,
need * (1 - sqrt((n + 1) / (n + 2))), n the placements taken at that position. An image corner no board
reached has its grid's largest sigma (distortion extrapolated), so it is chosen before a place already
measured. The area in the projector's image: the pattern's extent widened by `BOARD_MARGIN` on every side.

What it does not do: predict the projector's pose or intrinsics (what these grids leave out), the
camera's view of the board (which side of the blank area a person holds the printed part is theirs to
choose, so the board's place in the camera's image is known only to about a board), or choose a tilt;
the pose index picks the operator's variant for the position, as before. benchmarks/next_pose.py
measures it against the plan's order. Pure computation: `next_position` is the entry point.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from calib.quality.projection_uncertainty import where_max

#: how far beyond the pattern's points a board at a position reaches, as a share of the pattern's extent
BOARD_MARGIN = 0.25


@dataclass(frozen=True)
class DeviceGrid:
    """One device's grid (calib.quality.projection_uncertainty), the board's area in its image at each
    candidate position (x0, y0, x1, y1 pixels), and the device's target 1-sigma (px)."""

    device: str  # "projector" / "camera"
    grid: Mapping
    areas: Mapping[int, tuple[float, float, float, float]]
    target_px: float


@dataclass(frozen=True)
class NextPlacement:
    """The position chosen and why."""

    position: int
    device: str  # whose grid needs the placement most
    sigma_px: float  # that grid's largest 1-sigma over the board's area there
    target_px: float
    where: str  # the part of that device's image it is in (corner, edge, centre)
    taken: int  # placements already taken at that position

    def reason(self) -> str:
        return (f"pattern position {self.position + 1}, at the {self.where} of the {self.device}'s image, where its "
                f"projection 1-sigma is largest against its target ({self.sigma_px:.3f} px, target "
                f"{self.target_px:.3g}; {self.taken} placement{'' if self.taken == 1 else 's'} there so far)")


def position_area(pattern, width: int, height: int, position: int) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) projector pixels a board at `position` covers: the pattern's points widened by
    BOARD_MARGIN of their extent on every side, clipped to the image."""
    pts = pattern.points_px(width, height, position)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = BOARD_MARGIN * (hi - lo)
    x0, y0 = np.maximum(lo - pad, -0.5)
    x1, y1 = np.minimum(hi + pad, (width - 0.5, height - 0.5))
    return float(x0), float(y0), float(x1), float(y1)


def _area_cells(grid: Mapping, rect):
    """(sigma grid, rows, cols) of the cells whose centres lie in `rect` (the nearest row / column when
    none does); None when the grid has no sigmas."""
    s = grid.get("sigma_px")
    if s is None:
        return None
    s = np.asarray(s, float)
    xs, ys = np.asarray(grid["x_px"], float), np.asarray(grid["y_px"], float)
    if s.shape != (len(ys), len(xs)) or not s.size:
        return None
    x0, y0, x1, y1 = rect
    cols = np.flatnonzero((xs >= x0) & (xs <= x1))
    rows = np.flatnonzero((ys >= y0) & (ys <= y1))
    if not len(cols):
        cols = np.array([int(np.argmin(np.abs(xs - (x0 + x1) / 2)))])
    if not len(rows):
        rows = np.array([int(np.argmin(np.abs(ys - (y0 + y1) / 2)))])
    return s, rows, cols


def area_sigma(grid: Mapping, rect) -> float | None:
    """The largest 1-sigma of a device grid (calib.quality.projection_uncertainty) over the cells whose
    centres lie in `rect`; the nearest cell's when none does. None when the grid has no sigmas."""
    cells = _area_cells(grid, rect)
    if cells is None:
        return None
    s, rows, cols = cells
    return float(np.max(s[np.ix_(rows, cols)]))


def _usable(g: DeviceGrid) -> bool:
    return bool(g.grid) and not g.grid.get("fixed") and g.grid.get("sigma_px") is not None and g.target_px > 0


def next_position(grids: Iterable[DeviceGrid], candidates: Iterable[int], taken: Mapping[int, int]) \
        -> NextPlacement | None:
    """The candidate position a placement would help most (ties: the earlier candidate), or None when no
    grid says anything (no covariance, the devices held fixed) or there is no candidate."""
    grids = [g for g in grids if _usable(g)]
    best, best_gain = None, -math.inf
    for p in candidates:
        need = None
        for g in grids:
            if p not in g.areas:
                continue
            sigma = area_sigma(g.grid, g.areas[p])
            if sigma is None:
                continue
            sigma = sigma if math.isfinite(sigma) else 1e9  # unconstrained there: first
            if need is None or sigma / g.target_px > need[0]:
                need = (sigma / g.target_px, g, sigma)
        if need is None:
            continue
        n = int(taken.get(p, 0))
        gain = need[0] * (1.0 - math.sqrt((n + 1.0) / (n + 2.0)))
        if gain > best_gain:
            best, best_gain = (p, need[1], need[2], n), gain
    if best is None:
        return None
    p, g, sigma, n = best
    return NextPlacement(p, g.device, sigma, g.target_px, _where(g.grid, g.areas[p]) or "middle", n)


def _where(grid: Mapping, rect) -> str | None:
    """The part of the image (calib.quality.projection_uncertainty's words) holding the rectangle's
    largest 1-sigma."""
    s, rows, cols = _area_cells(grid, rect)
    sub = s[np.ix_(rows, cols)]
    i, j = np.unravel_index(int(np.argmax(np.where(np.isfinite(sub), sub, np.inf))), sub.shape)
    at = np.zeros(s.shape)
    at[rows[i], cols[j]] = 1.0
    return where_max({"sigma_px": at})
