"""The panel in a real Chromium (Debian's, driven by playwright): a session operated by its buttons
through to a verified calibration, what the panel shows on the way, and the access-code lock when the
station is served on the network. A small configuration keeps it short: 1 board pose per pattern
position (13 projector captures) and 3 mirror captures."""

import json
import re
import time

import pytest
from playwright.sync_api import expect, sync_playwright

from calib.session import SessionStore
from tests._station_helpers import StationProcess, launch_chromium, text_input

pytestmark = pytest.mark.browser

SMALL = ("--rig", "sim", "--poses-per-position", "1", "--mirror-captures", "3", "--method", "paper")


def click(page, name):
    print(f"{time.monotonic() - T0[0]:6.1f} s  click {name}")
    page.get_by_role("button", name=name, exact=True).click()


T0 = [time.monotonic()]


def see(page, pattern, timeout=30_000):
    print(f"{time.monotonic() - T0[0]:6.1f} s  waiting for {pattern}")
    expect(page.get_by_text(re.compile(pattern)).first).to_be_visible(timeout=timeout)


def live_image_sources(page, seconds=3.0):
    """Distinct sources the live camera image shows during `seconds` (each update is a new blob)."""
    img = page.locator("img[src^='blob:']").first
    seen = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        src = img.get_attribute("src")
        if not seen or seen[-1] != src:
            seen.append(src)
        time.sleep(0.02)
    return seen


def test_a_session_operated_from_the_browser(tmp_path):
    T0[0] = time.monotonic()
    folder = tmp_path / "session"
    st = StationProcess(*SMALL, "--session", str(folder))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1440, "height": 900})
            page.goto(st.url)
            see(page, r"Simulated rig")
            see(page, r"no RealSense camera is connected|Move board")
            see(page, r"Projector capture: 0 / 13 captures")
            # an impossible action is refused, with its reason shown
            click(page, "Calibrate")
            see(page, r"Refused: Calibrate\. Calibration comes after the captures")
            text_input(page, "Intrinsics file").fill(str(tmp_path / "nowhere.json"))
            click(page, "Skip camera step")
            see(page, r"Refused: Skip camera step\..*does not exist")
            click(page, "Check rig")
            see(page, r"Check the rig: camera ok; projector ok")
            click(page, "Start")
            see(page, r"Choose how to calibrate the mirror")
            click(page, "Next step")
            see(page, r"Refused: Next step\. Choose the mirror method")
            click(page, "Mirror: real-virtual")
            for k in range(1, 4):  # the simulated operator places the board; auto-capture takes it
                click(page, "Move board")
                see(page, rf"Mirror capture \(real-virtual\): {k} / 3 captures")
            # the live image keeps changing with detections drawn on it
            assert len(live_image_sources(page, 2.0)) >= 3
            click(page, "Next step")
            see(page, r"The projector shows the pattern at position 1 of 13")
            click(page, "Move board")
            see(page, r"Projector capture: 1 / 13 captures")
            # retake the last capture: deleted, and the same pose is asked for again
            click(page, "Retake last")
            see(page, r"Projector capture: 0 / 13 captures")
            click(page, "Move board")
            see(page, r"Projector capture: 1 / 13 captures")
            # from here the simulated operator follows the station by itself
            page.get_by_text("Simulated operator moves the board by itself").click()
            see(page, r"Projector capture: 13 / 13 captures, 13 / 13 pattern positions complete", timeout=90_000)
            see(page, r"covered by the pattern positions captured: \d+%")
            click(page, "Calibrate")
            see(page, r"Calibration \(paper", timeout=90_000)
            see(page, r"Projector in the camera frame")
            see(page, r"Mirror: normal")
            click(page, "Verify")
            see(page, r"Verification PASSED", timeout=60_000)
            # the live check of one pixel: its epipolar curve drawn, seen and measured
            click(page, "Check pixel")
            see(page, r"Check pixel: checking pixel \(640\.0, 400\.0\)")
            page.get_by_role("tab", name="Log").click()
            see(page, r"pixel check \(640\.0, 400\.0\): \d+\.\d+ camera px", timeout=60_000)
            page.get_by_role("tab", name="Live camera").click()
            click(page, "Finish")
            see(page, r"The session is complete")
            page.get_by_role("tab", name="Captures").click()
            see(page, r"16 captures")
            page.get_by_role("tab", name="Live camera").click()
            time.sleep(1.0)
            page.screenshot(path=str(tmp_path / "panel.png"))
            browser.close()
    finally:
        st.stop()
    man = SessionStore.open(folder).manifest
    assert man.state["step"] == "done"
    assert len(man.captures_of("projector")) == 13 and len(man.captures_of("mirror-real-virtual")) == 3
    assert json.loads((folder / "verification.json").read_text())["passed"] is True
    assert (folder / "calibration.json").exists() and (tmp_path / "panel.png").stat().st_size > 50_000


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
            expect(op.get_by_role("button", name="Check rig", exact=True)).to_be_visible(timeout=15_000)
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
