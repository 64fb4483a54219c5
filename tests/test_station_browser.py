"""The panel in a real Chromium (Debian's, driven by playwright, 1600x1000): a session operated by its
buttons through to a verified calibration, what the panel shows on the way (the current step's controls
only, guidance, results at the top, the verified pixels and a clicked pixel with their verdicts, the
results zip downloaded through the button, every capture with a thumbnail), and the access-code lock
when the station is served on the network. A small configuration keeps it short: 1 board pose per
pattern position (13 projector captures) and 3 mirror captures. Screenshots are left in the test's
temporary folder (step 2, calibrated, from the camera, results, captures, done) for a person to judge."""

import json
import re
import time
import zipfile

import cv2
import numpy as np
import pytest
from playwright.sync_api import expect, sync_playwright

from app.station.panel_results import RESULT_FILES
from calib.formats.session import SessionStore
from _station_helpers import WAIT_MS, until, StationProcess, launch_chromium, live_image_updates, text_input

pytestmark = pytest.mark.browser

SMALL = ("--rig", "sim", "--poses-per-position", "1", "--mirror-captures", "3", "--method", "paper")


def click(page, name):
    print(f"{time.monotonic() - T0[0]:6.1f} s  click {name}")
    page.get_by_role("button", name=name, exact=True).click(timeout=WAIT_MS)  # a loaded machine is slow, not wrong


T0 = [time.monotonic()]


def see(page, pattern, timeout=WAIT_MS):
    print(f"{time.monotonic() - T0[0]:6.1f} s  waiting for {pattern}")
    expect(page.get_by_text(re.compile(pattern)).first).to_be_visible(timeout=timeout)



def scroll_panels_to_top(page):
    page.evaluate("""() => { for (const el of document.querySelectorAll('*')) {
        if (el.scrollHeight > el.clientHeight + 2 && getComputedStyle(el).overflowY !== 'visible') el.scrollTop = 0; } }""")


def colour_pixels(png_bytes, bgr, tol=40):
    """Pixels of a screenshot within `tol` of the colour `bgr`."""
    img = cv2.imdecode(np.frombuffer(png_bytes, np.uint8), cv2.IMREAD_COLOR)
    return int((np.abs(img.astype(int) - np.array(bgr)).max(axis=2) <= tol).sum())


def test_a_session_operated_from_the_browser(tmp_path):
    T0[0] = time.monotonic()
    folder = tmp_path / "session"
    st = StationProcess(*SMALL, "--session", str(folder))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000}, accept_downloads=True)
            page.set_default_timeout(WAIT_MS)  # clicks and the download wait on state (report.html is written first)
            page.goto(st.url)
            see(page, r"Simulated rig")
            see(page, r"no RealSense camera is connected|Check rig")
            see(page, r"Projector capture: 0 / 13 captures")
            see(page, r"Step 1 of 6: Check the rig")
            # the other steps' controls are out of the way until asked for
            expect(page.get_by_role("button", name="Calibrate", exact=True)).to_have_count(0)
            page.get_by_text("Show every step's controls").click(timeout=WAIT_MS)
            # an impossible action is refused, with its reason shown
            click(page, "Calibrate")
            see(page, r"Refused: Calibrate\. Calibration comes after the captures")
            page.get_by_text("Show every step's controls").click(timeout=WAIT_MS)
            expect(page.get_by_role("button", name="Calibrate", exact=True)).to_have_count(0)
            text_input(page, "Intrinsics file").fill(str(tmp_path / "nowhere.json"))
            click(page, "Skip camera step")
            see(page, r"Refused: Skip camera step\..*does not exist")
            click(page, "Check rig")
            see(page, r"Check the rig: camera ok; projector ok")
            see(page, r"Check rig: done\. all \d+ checks passed")  # successes are said too, not only refusals
            click(page, "Start")
            see(page, r"Choose how to calibrate the mirror")
            click(page, "Next step")
            see(page, r"Refused: Next step\. Choose the mirror method")
            click(page, "Mirror: real-virtual")
            for k in range(1, 4):  # the simulated operator places the board; auto-capture takes it
                click(page, "Move board")
                see(page, rf"Mirror capture \(real-virtual\): {k} / 3 captures")
                if k == 2:  # guidance: camera coverage, bars with their targets, where to hold the board next
                    see(page, r"Camera: coverage \d+% \(board corners\); \d of 4 image corners reached")
                    see(page, r"position x: \d+% \(.*; (target: a range of 45% of the width|✔ target met)\)")
                    see(page, r"Hold the board next towards")
                    page.screenshot(path=str(tmp_path / "mirror-step.png"))
            # the live image keeps changing with detections drawn on it
            assert len(live_image_updates(page, 3)) >= 3
            click(page, "Next step")
            see(page, r"The projector shows the pattern at position 1 of 13")
            click(page, "Move board")
            see(page, r"Projector capture: 1 / 13 captures")
            # retake the last capture: deleted, and the board must take another pose (the simulated
            # operator holds it differently) before it is captured again
            click(page, "Retake last")
            see(page, r"Retake last: p\d+ deleted; the simulated operator holds the board in another pose")
            see(page, r"Projector capture: 1 / 13 captures")
            # from here the simulated operator follows the station by itself
            page.get_by_text("Simulated operator moves the board by itself").click(timeout=WAIT_MS)
            see(page, r"Projector capture: 13 / 13 captures, 13 / 13 pattern positions complete", timeout=WAIT_MS)
            see(page, r"Projector: coverage \d+% \(pattern points captured")
            # the capture to change defaults to the newest one (Delete selected removes what was just taken)
            page.get_by_text("Change captures", exact=True).click(timeout=WAIT_MS)
            newest = json.loads((folder / "session.json").read_text())["captures"][-1]["id"]
            expect(text_input(page, "Capture to change")).to_have_value(newest)
            # Calibrate is possible; the note under it names the diversity targets not met yet
            see(page, r"Possible now\. Diversity targets not met yet: .*the target is a range of")
            click(page, "Calibrate")
            see(page, r"Calibrate: running.*Diversity targets not met yet: ")
            see(page, r"Calibration\*? \(paper", timeout=WAIT_MS)
            see(page, r"Projector in the camera frame")
            # the results are at the top: visible without scrolling, with the Download button
            scroll_panels_to_top(page)
            time.sleep(0.5)
            expect(page.get_by_text(re.compile(r"RMS reprojection error")).first).to_be_in_viewport()
            expect(page.get_by_role("button", name="Download results (zip)")).to_be_in_viewport()
            page.screenshot(path=str(tmp_path / "calibrated.png"))
            see(page, r"camera: k1 [+-]\d")  # distortion coefficients shown
            see(page, r"fx px")
            # the worst views by reprojection RMS, and every file written, listed
            page.get_by_text("Worst views (reprojection RMS)", exact=True).click(timeout=WAIT_MS)
            expect(page.get_by_role("cell", name=re.compile(r"^(p|mrv)\d{4}$")).first).to_be_visible()
            page.get_by_text("Files written", exact=True).click(timeout=WAIT_MS)
            see(page, r"calibration\.yaml \(\d+(\.\d)? (bytes|kB)\)")
            see(page, r"images/: 16 files")
            click(page, "Verify")
            see(page, r"Verification PASSED", timeout=WAIT_MS)
            # every verified pixel is drawn on the live image with its distance and verdict
            see(page, r"Verified pixels")
            see(page, r"\(\d+\.\d, \d+\.\d\): \d+\.\d+ camera px = \d+\.\d+ projector px: pass")
            live_img = page.locator("img[src^='blob:']").first

            def strokes_and_markers():
                """the live image shows orange detected strokes and green (pass) pixel markers"""
                shot = live_img.screenshot()
                return colour_pixels(shot, (30, 140, 255)) > 50 and colour_pixels(shot, (60, 210, 60), tol=30) > 20

            until(strokes_and_markers)
            # click on the camera image in the 3D view to check that pixel
            click(page, "View from the camera")
            time.sleep(1.5)
            page.screenshot(path=str(tmp_path / "from-camera.png"))
            canvas = page.locator("canvas").first
            box = canvas.bounding_box()
            live = page.locator("img[src^='blob:']").first.bounding_box()
            panel_right = live["x"] + live["width"] + 20
            x = (panel_right + box["x"] + box["width"] * 0.75) / 2
            page.mouse.click(x, box["y"] + box["height"] / 2)
            see(page, r"Check pixel: checking pixel \(\d+\.\d, \d+\.\d\) camera px")
            see(page, r"Pixel check \(\d+\.\d, \d+\.\d\): \d+\.\d+ camera px.*: (pass|FAIL)", timeout=WAIT_MS)
            print("clicked at", x, box["y"] + box["height"] / 2, "canvas", box)
            time.sleep(1.5)
            page.screenshot(path=str(tmp_path / "clicked.png"))
            # the results leave the browser: a zip of exactly the result files the session has
            with page.expect_download(timeout=WAIT_MS) as dl:
                click(page, "Download results (zip)")
            zpath = tmp_path / "results.zip"
            dl.value.save_as(zpath)
            page.screenshot(path=str(tmp_path / "panel-results.png"))
            click(page, "Finish")
            see(page, r"The session is complete")
            page.get_by_role("tab", name="Captures").click(timeout=WAIT_MS)
            see(page, r"16 captures")
            expect(page.locator("img[alt^='p']")).to_have_count(13)  # every capture listed, with a thumbnail
            expect(page.locator("img[alt^='mrv']")).to_have_count(3)
            page.screenshot(path=str(tmp_path / "captures.png"))
            page.get_by_role("tab", name="Live camera").click(timeout=WAIT_MS)
            time.sleep(1.0)
            page.screenshot(path=str(tmp_path / "panel.png"))
            browser.close()
    finally:
        st.stop()
    man = SessionStore.open(folder).manifest
    assert man.state["step"] == "done"
    assert len(man.captures_of("projector")) == 13 and len(man.captures_of("mirror-real-virtual")) == 3
    retaken = [c for c in man.captures_of("projector") if c.meta.get("retake")]
    assert len(retaken) == 1 and retaken[0].meta["operator_pose_index"] >= 100  # another pose than the deleted one
    assert json.loads((folder / "verification.json").read_text())["passed"] is True
    with zipfile.ZipFile(zpath) as z:
        expected = [n for n in RESULT_FILES if (folder / n).is_file()]
        names = z.namelist()
        assert names[:len(expected)] == expected and "calibration.yaml" in expected
        # and, by default, every export under exports/ (the dropdown's "all exports")
        assert "exports/calibration-camera.cameramodel" in names and "exports/calibration-unity.json" in names
        assert all(n.startswith("exports/") for n in names[len(expected):])
        assert z.read("calibration.json") == (folder / "calibration.json").read_bytes()
        assert z.read("verification.json") == (folder / "verification.json").read_bytes()
    assert (tmp_path / "panel.png").stat().st_size > 50_000


def test_network_panel_needs_the_access_code(tmp_path):
    # no --rig: without a RealSense connected the station takes the simulated rig, and says so
    st = StationProcess("--host", "0.0.0.0", "--session", str(tmp_path / "s"))
    try:
        assert st.code and re.fullmatch(r"[a-z2-7]{4}(-[a-z2-7]{4}){3}", st.code)  # 80 random bits
        assert st.url.endswith("/code/" + st.code)  # the printed address carries the code
        url = f"http://127.0.0.1:{st.port}"
        with sync_playwright() as p:
            browser = launch_chromium(p)
            # a browser without the code sees a prompt for it and nothing of the session
            guest = browser.new_context().new_page()
            guest.goto(url)
            see(guest, r"Enter the access code printed in the station's terminal")
            assert str(tmp_path) not in guest.content()
            assert guest.get_by_text("Checklist").count() == 0
            guest.get_by_label("Access code").fill("aaaa-bbbb-cccc-dddd")
            click(guest, "Open the panel")
            see(guest, r"Wrong access code")
            assert guest.get_by_role("button", name="Check rig", exact=True).count() == 0
            # the operator types the code (in capitals, without dashes): the panel with its controls
            op = browser.new_context().new_page()
            op.goto(url)
            op.get_by_label("Access code").fill(st.code.upper().replace("-", ""))
            click(op, "Open the panel")
            see(op, r"no RealSense camera is connected, so the station uses the simulated rig")
            see(op, r"only browsers that gave the access code see this panel")
            expect(op.get_by_role("button", name="Check rig", exact=True)).to_be_visible(timeout=WAIT_MS)
            click(op, "Check rig")
            see(op, r"Check the rig: camera ok")
            # a second browser opening the printed address gets in at once, and sees what the operator did
            tablet = browser.new_context().new_page()
            tablet.goto(st.url)
            see(tablet, r"Check the rig: camera ok")
            # the guest still has nothing, and its failure is in the log
            assert guest.get_by_text("Checklist").count() == 0
            tablet.get_by_role("tab", name="Log").click()
            see(tablet, r"wrong access code from 127\.0\.0\.1")
            browser.close()
    finally:
        st.stop()
    assert any("access code" in ln for ln in st.lines)
    assert any("wrong access code from 127.0.0.1" in ln for ln in st.lines)  # the process log too


def test_one_browser_drives_the_others_watch(tmp_path):
    """Two browsers on one station: the first drives, the second watches (its controls disabled) until it
    takes control; after each hand-over the other one watches, and the log names who did what."""
    st = StationProcess(*SMALL, "--session", str(tmp_path / "session"))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            one = browser.new_context(viewport={"width": 1600, "height": 1000}).new_page()
            one.set_default_timeout(WAIT_MS)
            one.goto(st.url)
            see(one, r"Connected: browser 1 \(drives\) = this browser\. This browser drives the station")
            two = browser.new_context(viewport={"width": 1600, "height": 1000}).new_page()
            two.set_default_timeout(WAIT_MS)
            two.goto(st.url)
            see(two, r"Connected: browser 1 \(drives\), browser 2 = this browser\. This browser is watching")
            see(one, r"Connected: browser 1 \(drives\) = this browser, browser 2\. This browser drives")
            expect(two.get_by_role("button", name="Check rig", exact=True)).to_be_disabled()
            expect(one.get_by_role("button", name="Take control", exact=True)).to_have_count(0)
            click(two, "Take control")
            see(two, r"This browser drives the station")
            see(one, r"This browser is watching")
            expect(one.get_by_role("button", name="Check rig", exact=True)).to_be_disabled()
            expect(two.get_by_role("button", name="Take control", exact=True)).to_have_count(0)
            click(two, "Check rig")
            see(one, r"Check the rig: camera ok; projector ok")
            click(one, "Take control")
            see(two, r"This browser is watching")
            expect(two.get_by_role("button", name="Start", exact=True)).to_be_disabled()
            click(one, "Start")
            see(two, r"Choose how to calibrate the mirror")
            one.get_by_role("tab", name="Log").click()
            see(one, r"browser 2 took control from browser 1")
            see(one, r"browser 2: pressed Check rig")
            see(one, r"browser 1 took control from browser 2")
            see(one, r"browser 1: pressed Start")
            one.screenshot(path=str(tmp_path / "driving.png"))
            two.screenshot(path=str(tmp_path / "watching.png"))
            browser.close()
    finally:
        st.stop()
