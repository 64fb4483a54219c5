"""Coverage: one definition for the panel and the report. The image is cut into a grid of square-ish
cells, GRID_COLUMNS across (rows in proportion to its height); an image's coverage is the share of its
cells that hold at least one observed point. The camera's points are the board corners detected in it;
the projector's are the pattern points captured on the board. Cells without a point are where a model
is extrapolated, not measured (their corners constrain the higher distortion terms most).
"""

from __future__ import annotations

import numpy as np

GRID_COLUMNS = 16
#: how the panel and the report name it, with its definition in a few words
COVERAGE_WORDS = f"coverage (share of the image's {GRID_COLUMNS}-column grid cells holding a point)"


def grid_shape(width: int, height: int, nx: int = GRID_COLUMNS) -> tuple[int, int]:
    """(columns, rows) of the coverage grid of a width x height image."""
    return nx, max(2, round(nx * height / width))


def cell_counts(uv, width: int, height: int, nx: int = GRID_COLUMNS) -> np.ndarray:
    """Points per cell, (rows, columns); pixel (0, 0) is the centre of the top-left pixel."""
    nx, ny = grid_shape(width, height, nx)
    uv = np.asarray(uv, float).reshape(-1, 2)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    ix = np.clip((uv[:, 0] + 0.5) / width * nx, 0, nx - 1e-9).astype(int)
    iy = np.clip((uv[:, 1] + 0.5) / height * ny, 0, ny - 1e-9).astype(int)
    counts = np.zeros((ny, nx), int)
    np.add.at(counts, (iy, ix), 1)
    return counts


def coverage_fraction(uv, width: int, height: int, nx: int = GRID_COLUMNS) -> float:
    """Coverage of a width x height image by the points `uv` (N, 2): the share of cells holding one."""
    return float((cell_counts(uv, width, height, nx) > 0).mean())
