"""The station's recalibration mode in a real Chromium: `procam station --recalibrate PREVIOUS` on the
simulated rig with its projector bumped, operated by the panel's buttons (Start check, Accept verdict)
through the checklist's three stages to the comparison and the files written. PREVIOUS is the cheap
synthetic joint calibration of tests/test_recalibrate.py (the unbumped default scenario, with its
uncertainty), so no full session is run first."""

import json
import re
import time
from pathlib import Path

import pytest
from playwright.sync_api import expect, sync_playwright

from _station_helpers import WAIT_MS, until, StationProcess, launch_chromium

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def see(page, pattern, timeout=WAIT_MS):
    expect(page.get_by_text(re.compile(pattern)).first).to_be_visible(timeout=timeout)


def recalibration_station(tmp_path, folder, bump: str = "projector") -> tuple[StationProcess, Path]:
    """A station recalibrating a previous calibration (tmp_path/prev/calibration.json, returned with it) on a
    simulated rig with `bump` moved, writing the recalibration to `folder`."""
    from test_recalibrate import previous

    prev = tmp_path / "prev" / "calibration.json"
    prev.parent.mkdir()
    previous().save_json(prev)
    return StationProcess("--rig", "sim", "--sim-bump", bump, "--recalibrate", str(prev.parent),
                          "--session", str(folder)), prev


def test_recalibration_checklist_from_the_panel(tmp_path):
    folder = tmp_path / "recal"
    st, prev = recalibration_station(tmp_path, folder)
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
            see(page, r"projector: moved", timeout=WAIT_MS)
            see(page, r"verdict: moved")
            expect(page.get_by_role("button", name="Accept verdict", exact=True)).to_be_visible()
            assert not (folder / "recalibration.json").exists()
            page.screenshot(path=str(tmp_path / "verdict.png"))
            page.get_by_role("button", name="Accept verdict", exact=True).click()
            see(page, r"Re-measure what moved.*projector")
            see(page, r"projector rot deg: 1-sigma \d+\.\d+ / target \d+\.\d+", timeout=WAIT_MS)
            see(page, r"Compare.*\(ok\)", timeout=WAIT_MS)
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
    assert rec["sign_off"]["by"] == "operator" and rec["sign_off"]["button"] == "Accept verdict"
    assert rec["sign_off"]["verdict"] == "moved: projector"


def test_unchanged_signoff_from_the_panel(tmp_path):
    """`--sim-bump none`: the check ends "unchanged", the technician signs off with the button; what the
    sign-off writes: recalibration.json with the verdict and the operator's sign-off, calibration.json
    the previous calibration (verdict in its diagnostics, nothing re-estimated), no verification.json."""
    from calib.models.result import CalibrationResult
    folder = tmp_path / "recal"
    st, prev = recalibration_station(tmp_path, folder, bump="none")
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(st.url)
            see(page, r"press \*?Start check")
            page.get_by_role("button", name="Start check", exact=True).click()
            see(page, r"verdict: unchanged", timeout=WAIT_MS)
            for part in ("camera", "mirror", "projector"):
                see(page, rf"{part}: unchanged")
            sign = page.get_by_role("button", name="Sign off: unchanged", exact=True)
            expect(sign).to_be_visible()
            expect(page.get_by_role("button", name="Accept verdict", exact=True)).to_have_count(0)
            time.sleep(1.0)  # the flow waits for the technician: nothing is written before the sign-off
            assert not (folder / "recalibration.json").exists() and not (folder / "calibration.json").exists()
            sign.click()
            see(page, r"Compare.*unchanged \(ok\)", timeout=WAIT_MS)
            see(page, r"no part moved: calibration\.json is the previous calibration")
            see(page, r"files written: recalibration\.json, calibration\.json, previous/calibration\.json$")
            see(page, r"Recalibration of.*✔ done")
            expect(sign).to_have_count(0)
            page.screenshot(path=str(tmp_path / "signed-off.png"))
            browser.close()
    finally:
        st.stop()
    rec = json.loads((folder / "recalibration.json").read_text())
    assert rec["verdict"] == "unchanged" and rec["ok"] is True and rec["reestimate"] is None
    assert rec["comparison"] is None and rec["captures"]["total"] <= 4
    assert rec["sign_off"]["by"] == "operator" and rec["sign_off"]["verdict"] == "unchanged"
    assert rec["sign_off"]["button"] == "Sign off: unchanged" and rec["sign_off"]["at_utc"]
    assert rec["verification"]["previous"]["passed"] is True and "recalibrated" not in rec["verification"]
    assert not (folder / "verification.json").exists()
    assert (folder / "previous" / "calibration.json").read_bytes() == prev.read_bytes()
    new, old = CalibrationResult.load_json(folder / "calibration.json"), CalibrationResult.load_json(prev)
    assert new.diagnostics["recalibration"]["verdict"] == "unchanged"
    assert new.method == old.method and (new.camera.K == old.camera.K).all()
    assert (new.T_cam_proj == old.T_cam_proj).all() and (new.mirror.normal == old.mirror.normal).all()


def green(locator) -> bool:
    """The button is drawn green (the highlighted next action)."""
    r, g, b = (int(v) for v in re.findall(r"\d+", locator.evaluate("e => getComputedStyle(e).backgroundColor"))[:3])
    return g > r + 40 and g > b + 40


def test_recalibration_mode_shows_its_own_controls_numbers_and_files(tmp_path):
    """After each action of a projector recalibration, the panel shows only this mode's controls with the
    next one highlighted, the verdict's movement in mm and degrees, this recalibration's own RMS and worst
    views, the files as they are, a download with recalibration.json and calibration.yaml, and a live
    image (with a true frame rate) that keeps updating once it is over."""
    import zipfile

    from calib.formats.session import SessionStore
    from _station_helpers import live_image_updates

    folder = tmp_path / "recal"
    st, prev = recalibration_station(tmp_path, folder)
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000}, accept_downloads=True)
            page.set_default_timeout(WAIT_MS)  # clicks and the download wait on state
            page.goto(st.url)
            see(page, r"press \*?Start check")
            start = page.get_by_role("button", name="Start check", exact=True)
            expect(start).to_be_visible()
            assert green(start)
            for normal in ("Calibrate", "Next step", "Back", "Check rig"):  # the normal flow's controls are gone
                expect(page.get_by_role("button", name=normal, exact=True)).to_have_count(0)
            see(page, r"camera (?!0\.0 )\d+(\.\d)? frames/s")  # the preview runs before the flow ticks the station
            start.click()
            expect(start).to_have_count(0)
            see(page, r"projector: moved \(turned (0\.9|1\.0)\d+ deg, shifted \d+\.\d+ mm \(1-sigma \d+\.\d+ deg, "
                      r"\d+\.\d+ mm\); change \d+\.\d+ > \d+\.\d+ \(chi-square", timeout=WAIT_MS)
            accept = page.get_by_role("button", name="Accept verdict", exact=True)
            expect(accept).to_be_visible()
            assert green(accept)
            accept.click()
            expect(accept).to_have_count(0)
            see(page, r"Compare.*\(ok\)", timeout=WAIT_MS)
            see(page, r"files written: recalibration\.json, calibration\.json")
            see(page, r"Recalibration of.*✔ done")
            download = page.get_by_role("button", name="Download results (zip)", exact=True)
            expect(download).to_be_visible()
            until(lambda: green(download))
            page.get_by_text("Files written", exact=True).click()
            see(page, r"recalibration\.json \(\d+(\.\d)? (bytes|kB)\)")
            see(page, r"calibration\.yaml \(\d+(\.\d)? (bytes|kB)\)")
            # this recalibration's own numbers: its RMS and worst views name its captures only
            ids = {c.id for c in SessionStore.open(folder).manifest.captures}
            saved = json.loads((folder / "calibration.json").read_text())
            assert {pv["capture_id"] for pv in saved["per_view"]} == ids
            see(page, rf"RMS reprojection error: joint {saved['rms']['joint']:.3f} px")
            page.get_by_text("Worst views (reprojection RMS)", exact=True).click()
            cells = page.get_by_role("cell", name=re.compile(r"^(p|mrv)\d{4}$"))
            expect(cells.first).to_be_visible()
            assert set(cells.all_inner_texts()) <= ids
            with page.expect_download() as dl:  # report.html is written first
                download.click()
            zpath = tmp_path / "results.zip"
            dl.value.save_as(zpath)
            # the live image keeps updating once the flow is over, and its frame rate says so
            assert len(live_image_updates(page, 3)) >= 3
            see(page, r"camera (?!0\.0 )\d+(\.\d)? frames/s")
            page.screenshot(path=str(tmp_path / "done.png"))
            browser.close()
    finally:
        st.stop()
    with zipfile.ZipFile(zpath) as z:
        names = z.namelist()
        assert "recalibration.json" in names and "calibration.yaml" in names
        assert z.read("recalibration.json") == (folder / "recalibration.json").read_bytes()
