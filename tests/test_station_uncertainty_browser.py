"""The projection uncertainty in the panel, in a real Chromium (Debian's, through playwright): a simulated
station runs a small session by itself (--auto, 13 projector and 3 mirror captures, the joint method) to
a calibration; the panel's results then show, per device, the heat map of calibration.json's
projection-uncertainty grid and its median and maximum, which must be the grid's own numbers."""

import json
import re

import cv2
import numpy as np
import pytest
from playwright.sync_api import expect, sync_playwright

from calib.quality.projection_uncertainty import large_regions
from _station_helpers import WAIT_MS, until, StationProcess, launch_chromium

pytestmark = [pytest.mark.browser, pytest.mark.slow]

NUMBERS = r"{dev}: median ([0-9.]+) px, max ([0-9.]+) px \(1 sigma\)\. (.*)"


def test_projection_uncertainty_is_shown_after_a_calibration(tmp_path):
    folder = tmp_path / "session"
    st = StationProcess("--rig", "sim", "--auto", "--poses-per-position", "1", "--mirror-captures", "3",
                        "--method", "joint", "--session", str(folder))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(st.url)
            shown = {}
            for dev in ("camera", "projector"):
                line = page.get_by_text(re.compile(NUMBERS.format(dev=dev))).first
                expect(line).to_be_visible(timeout=WAIT_MS)
                shown[dev] = re.search(NUMBERS.format(dev=dev), line.inner_text()).groups()
                # the heat map under its label: a real picture, not the 8x8 placeholder
                img = page.locator(f"xpath=//p[normalize-space()='{dev} projection uncertainty']"
                                   "/following-sibling::div//img").first
                expect(img).to_be_visible(timeout=WAIT_MS)
                img.scroll_into_view_if_needed()
                assert img.evaluate("e => e.naturalWidth") >= 300
                pix = cv2.imdecode(np.frombuffer(img.screenshot(), np.uint8), cv2.IMREAD_COLOR)
                hot = (pix[:, :, 2].astype(int) - pix[:, :, 0] > 60) & (pix[:, :, 1] < 200)  # magma's reds/oranges
                assert hot.sum() > 200, "no heat map drawn"
            page.screenshot(path=str(tmp_path / "uncertainty.png"))
            browser.close()
    finally:
        st.stop()
    pu = json.loads((folder / "calibration.json").read_text())["projection_uncertainty"]
    for dev, (median, top, words) in shown.items():
        s = np.asarray(pu[dev]["sigma_px"], float)
        assert s.shape == (10, 16)
        assert median == f"{np.median(s):.3f}" and top == f"{s.max():.3f}"
        assert top == f"{pu[dev]['max_px']:.3f}" and median == f"{pu[dev]['median_px']:.3f}"
        # the plain-language part follows the summary's LARGE rule
        where = large_regions(pu[dev])
        if where:
            assert words.startswith("Large (> 0.5 px)") and all(w in words for w in where)
        else:
            assert s.max() <= pu["large_sigma_px"] and words.startswith("Nowhere above 0.5 px")
