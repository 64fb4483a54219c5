"""Helpers for the station tests: small session stores and stand-in calibration/verification callables
for tests of the state machine's logic (the end-to-end tests use the real pipeline on the sim rig)."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib.formats.session import RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.observations import VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.synthetic import make_rig

REPO = Path(__file__).resolve().parents[1]
CAM_SIZE = (1280, 800)
PROJ_SIZE = (1920, 1080)
TINY = np.zeros((6, 8, 3), np.uint8)


def make_store(folder, view: str = VIEW_MIRROR, positions: int = 13) -> SessionStore:
    man = SessionManifest(
        RigInfo(CAM_SIZE, PROJ_SIZE, view, {}, "test"),
        CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0),
        PatternSpec.default_for(*PROJ_SIZE, positions=positions),
        CharucoSpec(8, 6, "DICT_5X5_50", 22.0, 11.0) if view == VIEW_MIRROR else None,
    )
    return SessionStore.create(folder, man)


@dataclass
class FakeReport:
    mean_px: float
    worst_px: float
    threshold_px: float = 2.0

    @property
    def passed(self) -> bool:
        return self.worst_px <= self.threshold_px


class Recorder:
    """Calibration / verification stand-ins that record their calls and return ground truth."""

    def __init__(self, fail_calibration: str | None = None):
        self.calibrations = []
        self.verifications = []
        self.fail_calibration = fail_calibration

    def calibrate(self, folder, intrinsics, progress):
        from calib.errors import CalibrationError

        self.calibrations.append((Path(folder), intrinsics, len(SessionStore.open(folder).manifest.captures)))
        if self.fail_calibration:
            raise CalibrationError(self.fail_calibration)
        return make_rig(136).ground_truth().with_(method="stand-in", rms={"camera": 0.1, "projector": 0.2})

    def verify(self, result, **kw):
        self.verifications.append(result)
        return FakeReport(0.4, 0.9)


def run_procam(*args, timeout=300, env_extra=None, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
    return subprocess.run([sys.executable, "-m", "app", *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout, **kw)


def popen_procam(*args, env_extra=None) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1", **(env_extra or {}))
    return subprocess.Popen([sys.executable, "-m", "app", *args], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


# ---- the station as a process, for the browser tests --------------------------------------------------
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class StationProcess:
    """`procam station` in a subprocess; its output lines are collected in a thread."""

    def __init__(self, *args, timeout_s: float = 90.0):
        import re
        import threading
        import time

        self.port = free_port()
        self.proc = popen_procam("station", "--port", str(self.port), *args)
        self.lines: list[str] = []
        self.url = None
        self.code = None
        done = threading.Event()

        def read():
            for line in self.proc.stdout:
                self.lines.append(line.rstrip("\n"))
                m = re.search(r"panel at (http://\S+)", line)
                if m:
                    self.url = m.group(1)
                    if not any("access code" in ln for ln in self.lines) and "--host" not in args:
                        done.set()
                m = re.search(r"access code: ([a-z2-7-]+)", line)
                if m:
                    self.code = m.group(1)
                    done.set()
            done.set()

        threading.Thread(target=read, daemon=True).start()
        end = time.monotonic() + timeout_s
        while not done.wait(0.2):
            if time.monotonic() > end:
                self.stop()
                raise AssertionError("the station did not start:\n" + "\n".join(self.lines))
        if self.url is None:
            raise AssertionError("the station did not start:\n" + "\n".join(self.lines))

    def stop(self):
        import signal

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except Exception:
                self.proc.kill()
                self.proc.wait(10)


#: how long a browser test waits for a state: a wait ends as soon as the state is reached, so only a
#: broken feature ever waits this long (a loaded machine is slow, not wrong)
WAIT_MS = 240_000


def launch_chromium(playwright):
    from playwright.sync_api import expect

    expect.set_options(timeout=WAIT_MS)  # every expect(...) waits on state, not on a 5 s default
    return playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)


def until(condition, timeout_s: float = WAIT_MS / 1000, every_s: float = 0.1):
    """Poll `condition()` until it returns a true value (returned) or `timeout_s` passes (AssertionError)."""
    import time

    end = time.monotonic() + timeout_s
    while True:
        got = condition()
        if got:
            return got
        if time.monotonic() > end:
            raise AssertionError(f"not reached within {timeout_s:g} s: {getattr(condition, '__doc__', None) or condition}")
        time.sleep(every_s)


def text_input(page, label: str):
    """viser's text input of the given label (its <label> does not point at the input)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input").first


def tick_until_projector_captures(station, machine, n: int, max_ticks: int = 300) -> None:
    """Start a real-virtual session and let the station tick (the simulated operator moving the board)
    until `n` projector captures are taken, or `max_ticks` have passed."""
    from calib.models.observations import STEP_PROJECTOR

    machine.start_session()
    machine.choose_mirror_method("real-virtual")
    for _ in range(max_ticks):
        if len(machine.captures_of(STEP_PROJECTOR)) >= n:
            return
        if machine.target is None:
            machine.proceed()
        station.tick()


def assert_within_its_uncertainty(session, k: float = 3.0):
    """A live session's calibration against the simulator's truth, each error bounded by `k` times the
    1-sigma the calibration reports for it. One short live session is one noise draw whose outcome
    depends on which frames the loop happened to take, so a fixed bound near the typical error fails
    now and then on a correct run; the reported sigma is what that draw should scatter by. The sigmas
    themselves must be a good session's (a wrong frame inflates the residuals and with them the sigmas)."""
    import json

    from calib.formats.session_files import CALIBRATION, GROUND_TRUTH
    from calib.models.result import CalibrationResult
    from calib.quality.metrics import compare

    session = Path(session)
    m = compare(CalibrationResult.load_json(session / CALIBRATION), CalibrationResult.load_json(session / GROUND_TRUTH))
    u = json.loads((session / CALIBRATION).read_text())["uncertainty"]
    pose, proj = u["T_cam_proj"], u["projector"]
    proj_k_sigma = float(np.sqrt(sum(proj[p] ** 2 for p in ("fx", "fy", "cx", "cy"))))
    assert pose["t_total"] < 1.0 and pose["rot_total_deg"] < 0.1 and proj_k_sigma < 3.0, u
    assert m.distance < k * pose["t_total"], (m.distance, pose)
    assert m.angle_deg < k * pose["rot_total_deg"], (m.angle_deg, pose)
    assert m.proj_k_px < k * proj_k_sigma, (m.proj_k_px, proj)
    return m


def snapshot(folder):
    """{path: (mode, bytes or link target)} of everything under `folder`."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = os.path.join(root, name)
            st = os.lstat(p)
            out[p] = (st.st_mode, os.readlink(p) if os.path.islink(p) else
                      (open(p, "rb").read() if stat.S_ISREG(st.st_mode) else None))
    return out


def live_image_updates(page, n=3):
    """Wait until the live camera image has shown `n` distinct sources (each update is a new blob)."""
    img = page.locator("img[src^='blob:']").first
    seen = []

    def updated():
        """the live image updates"""
        src = img.get_attribute("src")
        if not seen or seen[-1] != src:
            seen.append(src)
        return len(seen) >= n

    until(updated, every_s=0.02)
    return seen


def station_on_sim(folder, plan, *, projector_pattern=None, rig_options=None, scenario="nonoverlap-136", seed=0,
                   kind="sim", **station_options):
    """A new session in `folder` on the simulated rig (by default nonoverlap-136, seed 0; `kind` another
    simulated camera path, e.g. "sim-realsense") and the Station driving it: (rig, machine, station, the
    station's log lines)."""
    from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
    from app.station.station import Station, StationOptions

    req = RigRequest(kind, scenario, seed)
    rig = open_requested_rig(req, **(rig_options or {}))
    m = make_machine(create_session(folder, rig, req, plan, projector_pattern=projector_pattern), rig, plan)
    lines = []
    return rig, m, Station(rig, m, StationOptions(**station_options), log=lines.append), lines


def tick_until(st, cond, max_ticks: int) -> None:
    """Tick the station until `cond()` holds; fails after `max_ticks` ticks (frames, not seconds)."""
    for _ in range(max_ticks):
        if cond():
            return
        st.tick()
    raise AssertionError(f"not reached in {max_ticks} ticks; state {st.machine.state}")
