"""Issue 28, section 2, in a real Chromium: what the panel says after each action is still true. An
unreadable intrinsics file is refused in words (the "done" of the action before is gone from the message
line) and a good one outside the session is copied into it; the rig check says what it found (exposure,
gain, latency) in the panel and the log; after a calibration no "running" or "busy" line is left, the
Calibrate line says done, and the verdict (trust check + quality gate) is the first thing in the results;
coverage is named as the report names it; the download says what it sent; the log keeps more than 10
events; one capture is "1 capture". Small session (13 projector, 3 mirror captures, paper method)."""

import json
import re

import pytest
from playwright.sync_api import expect, sync_playwright

from _station_helpers import WAIT_MS, StationProcess, launch_chromium, text_input

pytestmark = [pytest.mark.browser, pytest.mark.slow]

SMALL = ("--rig", "sim", "--poses-per-position", "1", "--mirror-captures", "3", "--method", "paper")


def see(page, pattern, timeout=WAIT_MS):
    expect(page.get_by_text(re.compile(pattern)).first).to_be_visible(timeout=timeout)


def gone(page, pattern):
    expect(page.get_by_text(re.compile(pattern))).to_have_count(0)


def click(page, name):
    page.get_by_role("button", name=name, exact=True).click(timeout=WAIT_MS)  # a loaded machine is slow, not wrong


def message_line(page, pattern):
    """The message line under "Next:" (the paragraph that starts with the action's bold label)."""
    return page.locator("p", has_text=re.compile(pattern)).first


def test_the_panel_says_what_is_true_after_each_action(tmp_path):
    folder = tmp_path / "session"
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "folder.json").mkdir()
    zipped = outside / "packed.json"
    zipped.write_bytes(b"PK\x03\x04" + bytes(range(256)))
    st = StationProcess(*SMALL, "--session", str(folder))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000}, accept_downloads=True)
            page.goto(st.url)
            see(page, r"Step 1 of 6: Check the rig")
            # the rig check: its findings in the panel (the line that followed it, the checklist) and the log
            click(page, "Check rig")
            see(page, r"Check rig: done\. all \d+ checks passed\. camera exposure: \d+(\.\d+)? us .*gain .*"
                      r"projector latency: latency \d+ ms")
            see(page, r"camera exposure ok \(\d+(\.\d+)? us .*gain")
            gone(page, r"Check rig: running")
            # a bad intrinsics file: refused, named, and the "done" above leaves the message line
            for path, words in ((outside / "folder.json", "is a folder, not a file"),
                                (zipped, r"is not a text file \(a zip\?\)"),
                                ("/etc/passwd", "is not an intrinsics file")):
                text_input(page, "Intrinsics file").fill(str(path))
                click(page, "Skip camera step")
                see(page, rf"Refused: Skip camera step\. Intrinsics file {re.escape(str(path))}: {words}")
            expect(message_line(page, r"^Check rig: done")).to_have_count(0)
            # a good one outside the session: copied in, recorded by the copy
            rig_camera = json.loads((folder / "session.json").read_text())["rig"]["camera"]
            size = (rig_camera["width"], rig_camera["height"])
            cam = {"width": size[0], "height": size[1], "K": [[900.0, 0, size[0] / 2], [0, 900.0, size[1] / 2],
                                                              [0, 0, 1]], "dist": [0.0, 0.0, 0.0, 0.0, 0.0]}
            good = outside / "camera.json"
            good.write_text(json.dumps({"camera": cam}))
            text_input(page, "Intrinsics file").fill(str(good))
            click(page, "Skip camera step")
            see(page, r"camera from given_camera\.json \(given\)")
            assert (folder / "given_camera.json").read_bytes() == good.read_bytes()
            assert json.loads((folder / "session.json").read_text())["state"]["camera_intrinsics"] == "given_camera.json"
            click(page, "Calibrate camera from captures")
            see(page, r"camera from the captures")
            click(page, "Start")
            click(page, "Mirror: real-virtual")
            click(page, "Move board")
            see(page, r"Mirror capture \(real-virtual\): 1 / 3 captures")
            tab = page.get_by_role("tab", name="Captures")
            expect(tab).to_be_visible()  # (the docked window redraws while captures arrive)
            tab.click(timeout=WAIT_MS)
            see(page, r"^1 capture \(newest first\)$")
            page.get_by_role("tab", name="Live camera").click(timeout=WAIT_MS)
            page.get_by_text("Simulated operator moves the board by itself").click(timeout=WAIT_MS)
            see(page, r"Mirror capture \(real-virtual\): 3 / 3 captures")
            click(page, "Next step")
            see(page, r"Projector capture: 13 / 13 captures")
            see(page, r"Camera: coverage \d+% \(board corners\); \d of 4 image corners reached")
            see(page, r"Projector: coverage \d+% \(pattern points captured")
            click(page, "Calibrate")
            see(page, r"Calibrate: done\. RMS reprojection error", timeout=WAIT_MS)
            # once it ended: nothing says it runs or that the station is busy; the verdict comes first
            gone(page, r"Calibrate: running")
            gone(page, r"busy \(calibrating\)")
            verdict = page.get_by_text(re.compile(r"Verdict: (TRUSTED|LOW QUALITY|NOT TRUSTED)")).first
            expect(verdict).to_be_visible()
            rms = page.get_by_text(re.compile(r"RMS reprojection error: ")).first
            assert verdict.bounding_box()["y"] < rms.bounding_box()["y"]
            # the download says what it sent, after it sent it
            with page.expect_download(timeout=WAIT_MS):
                click(page, "Download results (zip)")
            see(page, r"Download results \(zip\): done\. session-results\.zip sent \(\d+ kB\)")
            # the log keeps every event (more than the 10 it used to), newest first
            page.get_by_role("tab", name="Log").click(timeout=WAIT_MS)
            see(page, r"^\d+ events, newest first")
            see(page, r"rig check: projector latency ok: latency \d+ ms")
            see(page, r"Check rig: projector latency: measuring")
            n = int(re.match(r"(\d+)", page.get_by_text(re.compile(r"^\d+ events, newest first")).first.inner_text())[1])
            assert n > 10
            page.screenshot(path=str(tmp_path / "after.png"))
            browser.close()
    finally:
        st.stop()
