"""The station's recalibration mode in a real Chromium: `procam station --recalibrate PREVIOUS` on the
simulated rig with its projector bumped, operated by the panel's buttons (Start check, Accept verdict)
through the checklist's three stages to the comparison and the files written. PREVIOUS is the cheap
synthetic joint calibration of tests/test_recalibrate.py (the unbumped default scenario, with its
uncertainty), so no full session is run first."""

import json
import re
import time

import pytest
from playwright.sync_api import expect, sync_playwright

from tests._station_helpers import StationProcess, launch_chromium

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def see(page, pattern, timeout=30_000):
    expect(page.get_by_text(re.compile(pattern)).first).to_be_visible(timeout=timeout)


def test_recalibration_checklist_from_the_panel(tmp_path):
    from tests.test_recalibrate import previous

    prev = tmp_path / "prev" / "calibration.json"
    prev.parent.mkdir()
    previous().save_json(prev)
    folder = tmp_path / "recal"
    st = StationProcess("--rig", "sim", "--sim-bump", "projector", "--recalibrate", str(prev.parent),
                        "--session", str(folder))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(st.url)
            see(page, r"Recalibration of")
            see(page, r"Recalibration mode.*follow the")  # not the normal session's "press Calibrate"
            see(page, r"press \*?Start check")
            assert not (folder / "recalibration.json").exists()
            page.get_by_role("button", name="Start check", exact=True).click()
            # the check's verdict waits for the operator, nothing is written before
            see(page, r"projector: moved", timeout=120_000)
            see(page, r"verdict: moved")
            expect(page.get_by_role("button", name="Accept verdict", exact=True)).to_be_visible()
            assert not (folder / "recalibration.json").exists()
            page.screenshot(path=str(tmp_path / "verdict.png"))
            page.get_by_role("button", name="Accept verdict", exact=True).click()
            see(page, r"Re-measure what moved.*projector")
            see(page, r"projector rot deg: 1-sigma \d+\.\d+ / target \d+\.\d+", timeout=120_000)
            see(page, r"Compare.*\(ok\)", timeout=180_000)
            see(page, r"projector moved \d+\.\d+ \w+ \(1-sigma \d+\.\d+\), turned (0\.9|1\.0)\d+ deg")
            see(page, r"files written: recalibration\.json, calibration\.json, previous/calibration\.json")
            page.screenshot(path=str(tmp_path / "compared.png"))
            browser.close()
    finally:
        st.stop()
    rec = json.loads((folder / "recalibration.json").read_text())
    assert rec["ok"] is True and rec["check"]["parts"]["projector"]["status"] == "moved"
    assert (folder / "previous" / "calibration.json").read_bytes() == prev.read_bytes()
    assert rec["comparison"]["projector"]["rotation_change_deg"] == pytest.approx(1.0, abs=0.1)
