"""The projection uncertainty of a calibration as the panel shows it: per device (camera, projector) a heat
map of calibration.json's `projection_uncertainty` grid (how far a ray's pixel moves at 1 sigma, at each
place of the image; calib.quality.projection_uncertainty) with its colour scale in px, the median and the maximum,
and in plain words where it is large.

The words come from calib.quality.projection_uncertainty.summary_line (the rule `procam calibrate` prints: cells
above LARGE_SIGMA_PX, named by corner and edge), the heat map from the report's figure
(app.report.figures.projection_uncertainty_figure), so the panel, the summary and the report agree.

Pure functions of a CalibrationResult (no viser): the panel puts the text and the images in place.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from calib.quality.projection_uncertainty import LARGE_SIGMA_PX, summary_line

DEVICES = ("camera", "projector")
NOT_COMPUTED = ("Not computed for this calibration: the paper method gives no parameter covariance. The joint "
                "method (`--method joint`, the default) computes it.")


def device_grid(result, device: str) -> dict | None:
    """The device's grid when it has a finite 1-sigma to show (None: no grid, or the device held fixed)."""
    pu = getattr(result, "projection_uncertainty", None)
    g = pu.get(device) if isinstance(pu, dict) else None
    if not isinstance(g, dict) or g.get("fixed") or g.get("sigma_px") is None:
        return None
    try:
        s = np.asarray(g["sigma_px"], float)
    except (TypeError, ValueError):
        return None
    if s.ndim != 2 or s.size == 0 or not np.isfinite(s).any():
        return None
    return g


def grid_numbers(grid: dict) -> tuple[float, float]:
    """(median px, max px) of a grid's sigma, from the grid itself (a cell that is infinite counts as the
    largest)."""
    s = np.asarray(grid["sigma_px"], float)
    return float(np.median(s)), float(np.max(s))


def uncertainty_text(result, device: str, coverage: float | None = None) -> str:
    """The numbers and the plain-language line of one device (markdown). With the device's `coverage`
    (calib.quality.coverage) below 1, a small sigma is claimed only where the captures reach: elsewhere
    the model is extrapolated, and a small sigma there says nothing."""
    pu = getattr(result, "projection_uncertainty", None)
    if not isinstance(pu, dict):
        return NOT_COMPUTED if device == "camera" else ""
    g = pu.get(device)
    if isinstance(g, dict) and g.get("fixed"):
        return f"**{device}**: held fixed (its intrinsics were given), so this session says nothing new about it."
    grid = device_grid(result, device)
    if grid is None:
        return f"**{device}**: no grid in this calibration."
    med, top = grid_numbers(grid)
    top_s = f"{top:.3f} px" if math.isfinite(top) else "unbounded"
    line = summary_line(pu, device) or ""
    if "LARGE" in line:
        plain = "**Large** " + line.split("LARGE", 1)[1].strip()
    else:
        plain = f"Nowhere above {LARGE_SIGMA_PX:g} px: the captures constrain the whole {device} image."
        if coverage is not None and coverage < 1.0:
            plain = (f"Nowhere above {LARGE_SIGMA_PX:g} px where the captures reach ({device} coverage "
                     f"{coverage * 100:.0f}%); elsewhere the model is extrapolated, not measured.")
    return f"**{device}**: median **{med:.3f} px**, max **{top_s}** (1 sigma). {plain}"


def uncertainty_image(result, device: str) -> np.ndarray | None:
    """The device's heat map as an RGB image (the report's figure: colour scale in px, cells above
    LARGE_SIGMA_PX outlined), or None when there is nothing to draw or the figure cannot be made."""
    grid = device_grid(result, device)
    if grid is None:
        return None
    try:
        from app.report.figures import projection_uncertainty_figure

        data = projection_uncertainty_figure([(device, grid)], LARGE_SIGMA_PX)
    except (ImportError, KeyError, TypeError, ValueError):
        return None
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


INTRO = (f"How far the pixel of a ray moves at 1 sigma (worst direction), at each place of the image, from "
         f"the covariance of the calibration. Places above {LARGE_SIGMA_PX:g} px (outlined) had few or no "
         "observations: take views that reach them.")
