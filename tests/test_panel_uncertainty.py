"""The panel's projection-uncertainty part (app/station/panel_uncertainty.py) on constructed grids: its
numbers are the grid's, its words follow the calibration summary's LARGE rule, and it draws a heat map
only where there is a grid to draw."""

import numpy as np

from app.station.panel_uncertainty import NOT_COMPUTED, uncertainty_image, uncertainty_text
from calib.quality.projection_uncertainty import GRID, LARGE_SIGMA_PX, grid_pixels, large_regions
from calib.synthetic import make_rig


def result_with(camera_sigma, projector=None):
    base = make_rig(136).ground_truth()

    def grid(model, s):
        xs, ys = grid_pixels(model.width, model.height, GRID)
        s = np.asarray(s, float)
        return {"width": model.width, "height": model.height, "grid": list(GRID), "x_px": xs.tolist(),
                "y_px": ys.tolist(), "sigma_px": s.tolist(), "median_px": float(np.median(s)),
                "max_px": float(s.max()), "large_fraction": float(np.mean(s > LARGE_SIGMA_PX)), "fixed": False}

    pu = {"schema": "procam-projection-uncertainty-1", "method": "test", "large_sigma_px": LARGE_SIGMA_PX,
          "camera": grid(base.camera, camera_sigma),
          "projector": projector if projector is not None else grid(base.projector, np.full(GRID[::-1], 0.1))}
    return base.with_(projection_uncertainty=pu)


def corners_large():
    s = np.full(GRID[::-1], 0.04)
    s[0, 0], s[-1, -1] = 1.234, 0.8
    return s


def test_numbers_and_the_large_places_in_words():
    r = result_with(corners_large())
    text = uncertainty_text(r, "camera")
    assert "median **0.040 px**, max **1.234 px**" in text
    where = large_regions(r.projection_uncertainty["camera"])
    assert where == ["top-left corner", "bottom-right corner"]
    assert "**Large** (> 0.5 px) over 1% of the image: top-left corner, bottom-right corner" in text
    assert "few or no observations there" in text
    calm = uncertainty_text(r, "projector")
    assert "max **0.100 px**" in calm and "Nowhere above 0.5 px" in calm and "Large" not in calm


def test_heat_map_is_drawn_with_the_grid_in_it():
    r = result_with(corners_large())
    img = uncertainty_image(r, "camera")
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[1] >= 300
    # another grid draws another picture
    flat = result_with(np.full(GRID[::-1], 0.04))
    assert np.abs(img.astype(int) - uncertainty_image(flat, "camera").astype(int)).sum() > 0


def test_nothing_to_draw_is_said_so():
    base = make_rig(136).ground_truth()
    assert base.projection_uncertainty is None
    assert uncertainty_text(base, "camera") == NOT_COMPUTED and uncertainty_image(base, "camera") is None
    fixed = result_with(np.full(GRID[::-1], 0.04), projector={"fixed": True, "sigma_px": None})
    assert "held fixed" in uncertainty_text(fixed, "projector") and uncertainty_image(fixed, "projector") is None
    broken = result_with(np.full(GRID[::-1], np.inf))
    assert uncertainty_image(broken, "camera") is None
