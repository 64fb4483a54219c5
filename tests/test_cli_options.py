"""Options that hung, crashed or wrote unusable sessions, and the panel's
websocket under malformed input. Grouped by input; every command runs in a subprocess with a timeout,
so a hang fails the test instead of the suite."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
from pathlib import Path

import msgspec
import pytest
from websockets.sync.client import connect

from app.cli import main
from app.station.panel import StationPanel
from _station_helpers import StationProcess, free_port, run_procam
from _panel_helpers import PROTOCOL, sim_station, ws_try

#: far longer than any refusal takes; a command that did not refuse runs into it (and fails the test)
TIMEOUT_S = 120


def refused(*args) -> str:
    """Run `procam ARGS`; it must exit 2 with one error line (no traceback, nothing "unexpected"); that line."""
    try:
        r = run_procam(*args, timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"procam {' '.join(args)} did not finish in {TIMEOUT_S} s (a hang, or no refusal)")
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, (args, r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    assert lines[0].startswith(f"procam {args[0]}: error: ") and "unexpected" not in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A tiny simulated session with a calibration.json (its ground truth), as a finished one holds."""
    folder = tmp_path_factory.mktemp("hostile_options") / "S"
    assert main(["simulate", "direct", "--out", str(folder), "--per-position", "1", "--mirror-count", "1",
                 "--quality", "live", "--workers", "1", "--no-progress"]) == 0
    shutil.copy(folder / "ground_truth.json", folder / "calibration.json")
    return folder


# ---- numbers: ports, counts, noise, seeds --------------------------------------------------------------
NUMBERS = [
    (["station", "--port", "99999"], "--port"),
    (["station", "--port", "-1"], "--port"),
    (["station", "--port", "http"], "--port"),
    (["session", "--rig", "sim", "--auto", "--mirror-captures", "-1"], "--mirror-captures"),
    (["session", "--rig", "sim", "--auto", "--poses-per-position", "0"], "--poses-per-position"),
    (["session", "--rig", "sim", "--auto", "--mirror-frames", "0"], "--mirror-frames"),
    (["session", "--rig", "sim", "--auto", "--mirror-frames", "65"], "--mirror-frames"),
    (["session", "--rig", "sim", "--auto", "--projector-pattern", "structured", "--placements", "0"], "--placements"),
    (["simulate", "direct", "--blur", "nan"], "--blur"),
    (["simulate", "direct", "--shot", "nan"], "--shot"),
    (["simulate", "direct", "--noise", "nan"], "--noise"),
    (["simulate", "direct", "--seed", "-1"], "--seed"),
    (["simulate", "direct", "--blur", "1e9"], "--blur"),
]


@pytest.mark.parametrize("args, option", NUMBERS, ids=[" ".join(a[0:1] + a[-2:]) for a, _ in NUMBERS])
def test_absurd_numbers_are_refused_naming_the_option_before_any_folder(tmp_path, args, option):
    out = tmp_path / "new"
    folder_opt = {"station": "--session", "session": "--out", "simulate": "--out"}[args[0]]
    line = refused(*args, folder_opt, str(out))
    assert f"argument {option}: must be" in line
    assert not out.exists()


@pytest.mark.parametrize("command, folder_opt", [("session", "--out"), ("simulate", "--out")])
def test_placements_without_the_structured_step_are_refused_before_any_folder(tmp_path, command, folder_opt):
    out = tmp_path / "new"
    args = [command, "--rig", "sim", "--auto"] if command == "session" else [command, "direct"]
    line = refused(*args, "--placements", "4", folder_opt, str(out))
    assert "--placements counts structured-light placements: give it with --projector-pattern structured" in line
    assert not out.exists()


def test_a_recalibration_refuses_the_structured_step(session, tmp_path):
    out = tmp_path / "new"
    line = refused("station", "--recalibrate", str(session), "--projector-pattern", "structured",
                   "--session", str(out), "--port", "0")
    assert "a recalibration re-measures with PREVIOUS's own" in line and not out.exists()


@pytest.mark.parametrize("option", ["--stop-on-confidence", "--next-best", "--ask-pose", "--mirror-frames=4"])
def test_a_recalibration_refuses_a_new_sessions_plan_switches(session, tmp_path, option):
    out = tmp_path / "new"
    line = refused("station", "--recalibrate", str(session), option, "--session", str(out), "--port", "0")
    assert "plan a new session's capture steps" in line and not out.exists()


@pytest.mark.parametrize("option", ["--next-best", "--ask-pose"])
def test_choosing_the_next_pose_without_stopping_on_confidence_is_refused_before_any_folder(tmp_path, option):
    out = tmp_path / "new"
    line = refused("session", "--rig", "sim", "--auto", option, "--out", str(out))
    assert f"{option} chooses each pose" in line and "only --stop-on-confidence computes: give both" in line
    assert not out.exists()


def test_asking_for_the_pose_and_the_next_best_position_together_is_refused(tmp_path):
    out = tmp_path / "new"
    line = refused("session", "--rig", "sim", "--auto", "--stop-on-confidence", "--ask-pose", "--next-best",
                   "--out", str(out))
    assert "both choose where the board goes next: give one" in line and not out.exists()


@pytest.mark.parametrize("args, says", [
    (["--rig", "sim", "--auto", "--blank-area", "300:20"], "the simulated rig's board is its scenario's"),
    (["--rig", "realsense", "--board", "8x6:DICT_5X5_50:44.3", "--blank-area", "300:x"],
     "blank area '300:x' does not parse"),
    (["--rig", "realsense", "--board", "8x6:DICT_5X5_50:44.3", "--blank-area", "-5"], "need WIDTH > 0"),
])
def test_a_blank_area_the_session_cannot_use_is_refused_before_any_folder(tmp_path, args, says):
    out = tmp_path / "new"
    line = refused("session", *args, "--out", str(out))
    assert says in line and not out.exists()


def test_a_resumed_session_keeps_its_blank_area(session):
    line = refused("session", "--auto", "--resume", str(session), "--blank-area", "300:20")
    assert "a resumed session keeps its own" in line


def test_verify_seed_names_the_option(session):
    line = refused("verify", str(session), "--seed", "-1")
    assert "argument --seed: must be a whole number from 0" in line


# ---- hosts: not this machine, not a host name ---------------------------------------------------------
@pytest.mark.parametrize("host, says", [("203.0.113.7", "not an address of this machine"),
                                        ("not a host!", "host name or an IP address")])
def test_a_host_the_station_cannot_serve_on_is_one_line_and_no_folder(tmp_path, host, says):
    out = tmp_path / "new"
    line = refused("station", "--rig", "sim", "--host", host, "--port", str(free_port()), "--session", str(out))
    assert "--host" in line and says in line
    assert not out.exists()


def test_serving_on_the_network_says_the_traffic_is_plain_http(tmp_path):
    st = StationProcess("--rig", "sim", "--host", "0.0.0.0", "--session", str(tmp_path / "s"))
    try:
        assert st.code is not None
    finally:
        st.stop()
    assert any("plain HTTP" in ln and "not encrypted" in ln for ln in st.lines), st.lines


# ---- folders: a new session inside another session ----------------------------------------------------
def test_a_new_session_inside_another_sessions_folder_is_refused(session):
    before = sorted(p.name for p in (session / "images").iterdir())
    for args in (["session", "--rig", "sim", "--auto", "--out", str(session / "images" / "new")],
                 ["station", "--rig", "sim", "--port", str(free_port()), "--session", str(session / "images" / "new")],
                 ["recalibrate", str(session), "--rig", "sim", "--auto", "--out", str(session / "images" / "rc")]):
        line = refused(*args)
        assert f"is inside the session {session}" in line, line
    assert sorted(p.name for p in (session / "images").iterdir()) == before


# ---- files: a device or a FIFO as the camera intrinsics ------------------------------------------------
def test_camera_intrinsics_that_are_not_a_regular_file_are_named_so(session, tmp_path):
    fifo = tmp_path / "intrinsics.json"
    os.mkfifo(fifo)
    for path, kind in (("/dev/zero", "a device"), (str(fifo), "a FIFO")):
        line = refused("calibrate", str(session), "--camera-intrinsics", path)
        assert f"argument --camera-intrinsics: {path} is {kind}" in line and "not a regular file" in line
        out = tmp_path / "new"
        line = refused("session", "--rig", "sim", "--auto", "--out", str(out), "--camera-intrinsics", path)
        assert f"{path} is {kind}" in line and not out.exists()


# ---- board sizes -------------------------------------------------------------------------------------
def test_a_board_too_large_to_print_is_refused(tmp_path):
    out = tmp_path / "board.pdf"
    line = refused("board", "--board", "8x6:DICT_4X4_50:400", "--out", str(out))  # a 3.6 m page
    assert "--board" in line and "2000 mm" in line and "--units" in line
    assert not out.exists()
    line = refused("board", "--board", "8x6:DICT_4X4_50:1e12", "--out", str(out))  # beyond any board
    assert "--board" in line and "--units" in line
    assert not out.exists()


# ---- the panel's websocket ---------------------------------------------------------------------------
@pytest.fixture
def panel(tmp_path):
    p = StationPanel(sim_station(tmp_path), "127.0.0.1", 0)
    try:
        yield p
    finally:
        p.stop()


def test_malformed_websocket_messages_are_one_log_line_each(panel, caplog):
    caplog.set_level(logging.WARNING)  # websockets logs a handler's failure at ERROR, with its traceback
    url, origin = f"ws://127.0.0.1:{panel.port}", f"http://127.0.0.1:{panel.port}"
    deep = b"\x91" * 200_000 + b"\xc0"  # 200k nested one-element arrays
    messages = [os.urandom(64) + b"\xc1", "a text frame", msgspec.msgpack.encode({"type": "NoSuchMessage"}), deep,
                bytes(40 * 1024 * 1024)]
    for msg in messages:
        with connect(url, subprotocols=PROTOCOL, origin=origin, open_timeout=30, max_size=None) as c:
            c.recv(timeout=30)
            c.send(msg)
            with pytest.raises(Exception):  # the station closes this connection
                while True:
                    c.recv(timeout=60)
    lines = [r for r in caplog.records if r.name == "procam.station" and "malformed message" in r.getMessage()]
    assert len(lines) == len(messages), [r.getMessage() for r in caplog.records]
    assert all("\n" not in r.getMessage() for r in lines)
    assert not [r for r in caplog.records if r.exc_info or "connection handler failed" in r.getMessage()]
    status, first = ws_try(url, origin)  # and the panel still serves its own page's websocket
    assert status == 101 and len(first) > 0


def test_two_origin_headers_are_refused_with_403(panel):
    own, foreign = f"http://127.0.0.1:{panel.port}", "http://evil.example"
    request = (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{panel.port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
               f"Sec-WebSocket-Protocol: {PROTOCOL[0]}\r\nOrigin: {own}\r\nOrigin: {foreign}\r\n\r\n")
    with socket.create_connection(("127.0.0.1", panel.port), timeout=30) as s:
        s.sendall(request.encode())
        status_line = s.makefile("rb").readline().decode()
    assert status_line.split()[1] == "403", status_line


def test_bench_placements_refuses_an_unknown_mirror_hold_before_any_work():
    r = run_procam("bench", "placements", "--mirror-hold", "../etc", "--mirror-frames", "4", timeout=TIMEOUT_S)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert lines[0].startswith("procam bench placements: error: argument --mirror-hold: invalid choice")
    assert "'still', 'person'" in lines[0] and "rendered" not in r.stderr  # refused before any rendering
