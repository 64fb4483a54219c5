"""The panel refuses foreign pages (Origin), the access code cannot be
brute-forced (a throttle across connections and addresses, every failure logged, nothing of the session
shown without the code), and the capture loop cannot die silently (the autocapture race fixed, the loop
supervised, a banner when the station process is gone).

The websocket clients are the `websockets` library viser itself depends on; the stations run on the
simulated rig on loopback (a subprocess where the command line matters, in-process where the test needs
to inject time or errors)."""

from __future__ import annotations

import logging
import re
import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from app.station.access import AccessGate, Backoff, new_access_code, normalize_code
from app.station.autocapture import AutoCapture, AutoCaptureSettings, LiveDetection
from app.station.machine import ActionRefused
from app.station.panel import DISCONNECT_TEXT, StationPanel
from calib.models.observations import BoardObservation
from _panel_helpers import sim_station, ws_try
from _station_helpers import WAIT_MS, StationProcess


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t



def wait_for(cond, timeout_s=20.0, what="condition"):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"{what} not met in {timeout_s} s")


# ---- item 2: Origin ---------------------------------------------------------------------------------
def test_foreign_origin_is_refused_and_the_panels_own_origin_works(tmp_path):
    folder = tmp_path / "session"
    st = StationProcess("--rig", "sim", "--session", str(folder))
    try:
        port = st.port
        ws = f"ws://127.0.0.1:{port}"
        # a page on another site, or one reaching the station through a rebinding name: 403, nothing sent
        for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{port + 1}",
                       "null", f"file://127.0.0.1:{port}"):
            status, body = ws_try(ws, origin)
            assert status == 403, origin
            assert str(folder).encode() not in body
        # a client without Origin (not a browser) needs the per-start secret printed at start
        assert ws_try(ws)[0] == 403
        secret = next(re.search(r"/code/(\S+)", ln).group(1) for ln in st.lines if "without a browser" in ln)
        status, first = ws_try(f"{ws}/code/{secret}")
        assert status == 101 and len(first) > 0
        # the panel's own origin, by every name of loopback, gets the panel
        for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}"):
            status, first = ws_try(ws, origin)
            assert status == 101 and len(first) > 0, origin
        # the page itself is served as before, and may not be framed by another site
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/") as r:
            assert r.status == 200 and r.headers["X-Frame-Options"] == "DENY"
    finally:
        st.stop()
    refused = [ln for ln in st.lines if "refused a websocket" in ln]
    assert any("evil.example" in ln for ln in refused) and any("no Origin header" in ln for ln in refused)


def test_origin_rules():
    gate = AccessGate("127.0.0.1")
    assert gate.origin_allowed("http://127.0.0.1:8080", 8080)
    assert gate.origin_allowed("https://localhost:8080", 8080)
    assert gate.origin_allowed("http://[::1]:8080", 8080)
    assert not gate.origin_allowed("http://127.0.0.1:8081", 8080)
    assert not gate.origin_allowed("http://127.0.0.1.evil.example:8080", 8080)
    assert not gate.origin_allowed("http://user@127.0.0.1:8080", 8080)
    assert not gate.origin_allowed("ftp://127.0.0.1:8080", 8080)
    assert not gate.origin_allowed("null", 8080)
    assert not gate.origin_allowed("http://[::1", 8080)
    named = AccessGate("rig-pc.lab")
    assert named.origin_allowed("http://rig-pc.lab:80", 80) and named.origin_allowed("http://rig-pc.lab", 80)
    everywhere = AccessGate("0.0.0.0")
    assert everywhere.origin_allowed(f"http://{socket.gethostname()}:8080", 8080)
    assert not everywhere.origin_allowed("http://evil.example:8080", 8080)


def test_a_page_retrying_is_logged_without_flooding_the_log():
    clock, lines = FakeClock(), []
    gate = AccessGate("127.0.0.1", clock=clock, log=lines.append)
    evil = {"Upgrade": "websocket", "Origin": "http://evil.example"}
    for _ in range(7):  # a foreign page retrying every second
        assert gate.check("/", evil, "127.0.0.1", 8080).status == 403
        clock.t += 1.0
    clock.t += 5.0
    assert gate.check("/", evil, "127.0.0.1", 8080).status == 403
    assert len(lines) == 2 and "evil.example" in lines[0] and "(6 more like it" in lines[1]
    assert gate.refused_origins == 8


# ---- item 3: the access code ------------------------------------------------------------------------
def test_access_codes_are_long_and_forgiving_to_type():
    codes = {new_access_code() for _ in range(200)}
    assert len(codes) == 200
    for c in list(codes)[:20]:
        assert re.fullmatch(r"[a-z2-7]{4}(-[a-z2-7]{4}){3}", c)  # 16 base32 letters: 80 bits
    c = next(iter(codes))
    assert normalize_code(c.upper().replace("-", " ")) == normalize_code(c)


@pytest.fixture
def network_panel(tmp_path, caplog):
    """A station that needs the access code, with a back-off driven by a fake clock."""
    caplog.set_level(logging.WARNING, logger="procam.station")
    clock = FakeClock()
    code = new_access_code()
    gate = AccessGate("127.0.0.1", code, clock=clock, per_client=Backoff(3, 10.0, 600.0),
                      per_station=Backoff(6, 30.0, 60.0))
    st = sim_station(tmp_path)
    panel = StationPanel(st, "127.0.0.1", 0, access_code=code, gate=gate)
    try:
        yield panel, clock, code
    finally:
        panel.stop()


def test_brute_force_is_throttled_across_connections_and_logged(network_panel, caplog):
    panel, clock, code = network_panel
    ws = f"ws://127.0.0.1:{panel.port}"
    own = f"http://127.0.0.1:{panel.port}"
    # the panel's own origin without the code: refused, nothing of the session sent
    assert ws_try(ws, own)[0] == 403
    # three wrong codes, each on a new connection, are checked and refused
    for guess in ("aaaa-bbbb-cccc-dddd", "2222-3333-4444-5555", "zzzz"):
        assert ws_try(f"{ws}/code/{guess}", own)[0] == 403
    # the third earned a back-off: the next try is not even checked, not even the right code
    status, body = ws_try(f"{ws}/code/{code}", own)
    assert status == 429 and b"try again in 10 s" in body
    clock.t += 10.5
    assert ws_try(f"{ws}/code/wrong", own)[0] == 403  # checked again: wrong, and the wait doubles
    clock.t += 10.5
    assert ws_try(f"{ws}/code/{code}", own)[0] == 429
    clock.t += 10.0
    status, first = ws_try(f"{ws}/code/{code}", own)
    assert status == 101 and len(first) > 0
    # every failure is in the panel's log and in the process log
    texts = [e.text for e in panel.machine.events]
    assert sum("wrong access code from 127.0.0.1" in t for t in texts) == 4
    assert any("refused unchecked" in t for t in texts)
    assert sum("wrong access code" in r.getMessage() for r in caplog.records) == 4
    assert panel.gate.failed_tries == 6


def test_the_station_wide_limit_holds_across_client_addresses(network_panel):
    panel, clock, code = network_panel
    ws = f"ws://127.0.0.1:{panel.port}"
    # two wrong codes from each of three addresses: none is throttled by itself, the station is
    for k in (2, 3, 4):
        for guess in ("aaaa", "bbbb"):
            assert ws_try(f"{ws}/code/{guess}", source=f"127.0.0.{k}")[0] == 403
    assert ws_try(f"{ws}/code/{code}", source="127.0.0.9")[0] == 429
    clock.t += 31.0
    assert ws_try(f"{ws}/code/{code}", source="127.0.0.9")[0] == 101


def test_a_browser_without_the_code_gets_only_the_prompt(network_panel):
    panel, clock, code = network_panel
    base = f"http://127.0.0.1:{panel.port}"
    folder = str(panel.machine.store.folder)
    with urllib.request.urlopen(base + "/") as r:
        page = r.read().decode()
    assert "Access code" in page and folder not in page and "viser" not in page.lower()
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(base + "/unlock?code=nope")
    assert e.value.code == 403 and "Wrong access code" in e.value.read().decode()
    # the right code (typed with spaces and capitals) leads to the panel's address carrying it
    with urllib.request.urlopen(base + "/unlock?code=" + code.upper().replace("-", "+")) as r:
        assert r.url.endswith("/code/" + normalize_code(code)) and "Viser" in r.read().decode()


# ---- item 8: the capture loop -------------------------------------------------------------------------
def test_autocapture_history_survives_concurrent_resets():
    """The race that killed the loop: update() on the loop thread, reset() from a button."""
    ac = AutoCapture(AutoCaptureSettings(still_frames=6))
    obs = BoardObservation(np.arange(20), np.random.default_rng(0).uniform(0, 500, (20, 2)), False)
    det = LiveDetection("projector", 0, (640, 480), board=obs, failure="pattern: not found")
    errors, stop = [], threading.Event()

    def feed():
        try:
            while not stop.is_set():
                ac.update(det)
        except Exception as e:  # the bug: IndexError in motion()
            errors.append(e)

    def press():
        while not stop.is_set():
            ac.reset()

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible: the race shows within a second
    try:
        threads = [threading.Thread(target=feed), threading.Thread(target=press)]
        for t in threads:
            t.start()
        end = time.monotonic() + 1.5
        while time.monotonic() < end and not errors:
            time.sleep(0.01)
        stop.set()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert errors == []
    h = ac.history()
    assert len(h) <= 6 and all(x is obs for x in h)


def test_button_presses_during_the_loop_do_not_kill_it(tmp_path):
    """Move board and Capture pressed from four threads while the loop runs on the simulated rig. (The
    race itself is proven by the test above, which fails without the fix; here the whole station must go
    on: no loop error, the history consistent, every capture in the session once.)"""
    st = sim_station(tmp_path, auto_capture=True, follow_operator=False)
    m = st.machine
    st.check_rig()
    m.start_session()
    m.choose_mirror_method("real-virtual")
    st.start_loop()
    try:
        wait_for(lambda: st.live is not None and st.live.detection is not None, what="a first detection")
        stop, unexpected = threading.Event(), []

        def press(action):
            while not stop.is_set():
                try:
                    action()
                except ActionRefused:
                    pass
                except Exception as e:
                    unexpected.append(e)
                time.sleep(0.002)  # a few hundred presses a second per thread, the loop still gets frames

        presses = [threading.Thread(target=press, args=(a,)) for a in
                   (st.request_pose, st.capture_now, st.request_pose, st.capture_now)]
        old = sys.getswitchinterval()
        sys.setswitchinterval(1e-5)  # switch threads often, so that a race has its chance
        try:
            frame0 = st.live.frame_number
            for t in presses:
                t.start()
            time.sleep(3.0)
            stop.set()
            for t in presses:
                t.join()
        finally:
            sys.setswitchinterval(old)
        frame = st.live.frame_number
        assert frame > frame0 + 5  # the loop detected frames all along the presses
        wait_for(lambda: st.live.frame_number > frame + 2, what="the loop going on after the presses")
        assert unexpected == [] and st.frames.loop_errors == [] and st.frames.loop_stopped is None
        assert st.frames.loop_thread.is_alive()
        h = st.autocap.history()
        assert len(h) <= st.options.autocapture.still_frames
        assert all(isinstance(x, BoardObservation) for x in h)
        # the captures the presses took are all in the session, each once
        ids = [c.id for c in m.manifest.captures]
        assert len(ids) == len(set(ids))
    finally:
        st.stop_loop()


def test_an_unexpected_error_is_logged_shown_and_the_loop_restarts(tmp_path, caplog):
    caplog.set_level(logging.ERROR, logger="procam.station")
    st = sim_station(tmp_path, auto_capture=False)
    st.frames.loop_backoff_s = (0.05, 0.2)
    m = st.machine
    st.check_rig()
    m.start_session()
    m.choose_mirror_method("real-virtual")
    real_tick, calls = st._tick, []

    def failing_tick():
        calls.append(1)
        if len(calls) in (3, 4):
            raise IndexError("injected for the test")
        return real_tick()

    st._tick = failing_tick
    panel = StationPanel(st, "127.0.0.1", 0)
    st.start_loop()
    panel.start()
    try:
        wait_for(lambda: len(st.frames.loop_errors) == 2, what="two loop errors")
        frame = st.live.frame_number if st.live else -1
        wait_for(lambda: st.live is not None and st.live.frame_number > frame + 3, what="frames after the errors")
        assert st.frames.loop_thread.is_alive() and st.frames.loop_stopped is None
        # logged with the traceback: the panel's log tab and the process log
        failed = [e.text for e in m.events if e.text.startswith("capture loop failed")]
        assert len(failed) == 2 and "Traceback" in failed[0] and "IndexError: injected for the test" in failed[0]
        assert "failing_tick" in failed[0]
        assert "IndexError: injected" in panel.log_text() and "```" in panel.log_text()
        recs = [r for r in caplog.records if "capture loop failed" in r.getMessage()]
        assert len(recs) == 2 and recs[0].exc_info is not None
        # shown to the operator: the banner over the panel
        panel.refresh()
        assert "failed and was restarted" in panel.h_alert.content and panel.h_alert.visible
    finally:
        st.stop_loop()
        panel.stop()


def test_a_loop_failing_again_and_again_stops_with_a_clear_banner(tmp_path):
    st = sim_station(tmp_path)
    st.frames.loop_backoff_s = (0.01, 0.02)
    st.frames.loop_give_up = (4, 60.0)

    def broken():
        raise KeyError("always")

    st._tick = broken
    panel = StationPanel(st, "127.0.0.1", 0)
    st.start_loop()
    try:
        wait_for(lambda: st.frames.loop_stopped is not None, what="the loop giving up")
        st.frames.loop_thread.join(5.0)
        assert not st.frames.loop_thread.is_alive() and len(st.frames.loop_errors) == 4
        panel.refresh()
        assert "The capture loop stopped" in panel.h_alert.content and "--resume" in panel.h_alert.content
        assert "restart the station" in st.instruction()
        with pytest.raises(ActionRefused, match="capture loop stopped"):
            st.capture_now()
    finally:
        st.stop_loop()
        panel.stop()


@pytest.mark.browser
def test_the_page_says_so_when_the_station_process_is_gone(tmp_path):
    from playwright.sync_api import expect, sync_playwright

    from _station_helpers import launch_chromium

    st = StationProcess("--rig", "sim", "--session", str(tmp_path / "s"))
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(st.url)
            expect(page.get_by_text(re.compile("Checklist")).first).to_be_visible(timeout=WAIT_MS)
            banner = page.get_by_text(DISCONNECT_TEXT[:40])
            time.sleep(7.0)  # longer than the banner's delay: the heartbeat keeps it hidden while alive
            expect(banner).to_be_hidden()
            st.stop()
            expect(banner).to_be_visible(timeout=WAIT_MS)
            page.screenshot(path=str(tmp_path / "gone.png"))
            browser.close()
    finally:
        st.stop()
    assert Path(tmp_path / "gone.png").stat().st_size > 10_000


@pytest.mark.browser
def test_the_operator_sees_a_loop_failure_in_the_browser(tmp_path):
    from playwright.sync_api import expect, sync_playwright

    from _station_helpers import launch_chromium

    st = sim_station(tmp_path)
    st.frames.loop_backoff_s = (0.05, 0.2)
    real_tick, failed = st._tick, []

    def failing_tick():
        if panel.controls.clients and not failed:  # once, when the browser is there
            failed.append(1)
            raise ZeroDivisionError("injected for the test")
        return real_tick()

    st._tick = failing_tick
    panel = StationPanel(st, "127.0.0.1", 0)
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            st.start_loop()
            panel.start()
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(panel.url)
            expect(page.get_by_text("Checklist").first).to_be_visible(timeout=WAIT_MS)
            # a notification and a banner, and the traceback in the Log tab
            expect(page.get_by_text("Capture loop failed").first).to_be_visible(timeout=WAIT_MS)
            expect(page.get_by_text("The capture loop failed and was restarted").first).to_be_visible()
            page.get_by_role("tab", name="Log").click()
            expect(page.get_by_text(re.compile(r"ZeroDivisionError: injected for the test")).first).to_be_visible()
            expect(page.get_by_text(re.compile(r"Traceback \(most recent call last\)")).first).to_be_visible()
            page.screenshot(path=str(tmp_path / "loop.png"))
            browser.close()
        assert st.frames.loop_thread.is_alive() and len(st.frames.loop_errors) == 1
    finally:
        st.stop_loop()
        panel.stop()
