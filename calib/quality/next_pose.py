"""The next-best placement of a projector step: the pattern position whose part of the projector's image
a board would help most, from the projection-uncertainty grid of the calibration so far.

Each pattern position names where in the projector's image the board stands (the circle grid lands on its
blank area; a structured-light sequence is decoded over the whole board). A placement there adds points
over that area, so it reduces the projector's projection uncertainty (calib.quality.projection_uncertainty:
intrinsics and distortion, rotation-compensated) mostly there. The choice: for each candidate position,
the largest 1-sigma of the grid over the area a board at that position covers (the pattern's extent
widened by `BOARD_MARGIN` on every side), and the reduction one more placement would bring if the
information there grew like the count of placements over it, sigma * (1 - sqrt((n + 1) / (n + 2))) with n
the placements taken at that position. An image corner no placement reached has the grid's largest
sigma (distortion extrapolated), so it is chosen before a place already measured.

What it does not do: predict the board's view in the camera (a position's area in the camera image
follows from the mirror and the working distance) or choose a tilt; the pose index picks the operator's
variant for the position, as before. Pure computation: `next_position` is the entry point.
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
class NextPlacement:
    """The position chosen and why."""

    position: int
    sigma_px: float  # the grid's largest 1-sigma over the position's area
    where: str  # the part of the projector's image it is in (corner, edge, centre)
    taken: int  # placements already taken at that position

    def reason(self) -> str:
        return (f"pattern position {self.position + 1}, the {self.where} of the projector's image, where its "
                f"projection 1-sigma is largest ({self.sigma_px:.3f} px; {self.taken} placement"
                f"{'' if self.taken == 1 else 's'} there so far)")


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


def _gain(sigma: float, taken: int) -> float:
    return sigma * (1.0 - math.sqrt((taken + 1.0) / (taken + 2.0)))


def next_position(grid: Mapping | None, pattern, size: tuple[int, int], candidates: Iterable[int],
                  taken: Mapping[int, int]) -> NextPlacement | None:
    """The candidate position a placement would help most (ties: the earlier candidate), or None when the
    grid says nothing (no covariance, the projector held fixed) or there is no candidate."""
    if not grid or grid.get("fixed") or grid.get("sigma_px") is None:
        return None
    width, height = size
    best, best_gain = None, -math.inf
    for p in candidates:
        sigma = area_sigma(grid, position_area(pattern, width, height, p))
        if sigma is None:
            continue
        sigma = sigma if math.isfinite(sigma) else 1e9  # unconstrained there: first
        n = int(taken.get(p, 0))
        g = _gain(sigma, n)
        if g > best_gain:
            best, best_gain = (p, sigma, n), g
    if best is None:
        return None
    p, sigma, n = best
    where = _where(grid, position_area(pattern, width, height, p)) or "middle"
    return NextPlacement(p, sigma, where, n)


def _where(grid: Mapping, rect) -> str | None:
    """The part of the image (calib.quality.projection_uncertainty's words) holding the rectangle's
    largest 1-sigma."""
    s, rows, cols = _area_cells(grid, rect)
    sub = s[np.ix_(rows, cols)]
    i, j = np.unravel_index(int(np.argmax(np.where(np.isfinite(sub), sub, np.inf))), sub.shape)
    at = np.zeros(s.shape)
    at[rows[i], cols[j]] = 1.0
    return where_max({"sigma_px": at})
