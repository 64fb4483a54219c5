"""The rig factory (sim | realsense), the human operator, settle-time measurement on the simulated rig,
and the `procam devices` / `procam show-pattern` commands (under Xvfb where they need a display)."""

import json
import os
import queue
import subprocess
import sys
import threading

import numpy as np
import pytest

from _drivers_helpers import REPO, SoftwareRealSense, run_python, screenshot, xvfb
from calib.errors import SpecError
from calib.models.pattern import PatternSpec
from drivers.base import CameraDriver, Operator, ProjectorDriver
from drivers.errors import DeviceError
from drivers.factory import STEPS, HumanOperator, default_rig_kind, open_rig
from drivers.settle import measure_settle

# ---- operator -----------------------------------------------------------------------------------------


def test_human_operator_words_every_step_and_does_nothing_else():
    op = HumanOperator(pattern_positions=13)
    assert isinstance(op, Operator)
    texts = {s: op.request_pose(s, 4 if s == "projector" else None, 2) for s in STEPS}
    assert texts["projector"].startswith("Pattern position 5 of 13, pose 3:")
    assert "directly and in the mirror" in texts["mirror-real-virtual"]
    assert "flat on the mirror" in texts["mirror-real-mirror"]
    assert texts["verification"].startswith("Verification")
    assert len(set(texts.values())) == len(STEPS)
    with pytest.raises(SpecError, match="unknown step"):
        op.request_pose("calibrate", None, 0)
    with pytest.raises(SpecError, match="pattern position"):
        op.request_pose("projector", None, 0)


# ---- the simulated rig through the factory ---------------------------------------------------------------

def test_factory_opens_the_simulated_rig_and_settle_is_measured_on_it():
    rig = open_rig("sim", scenario="nonoverlap-136", seed=0, latency_ms=100.0)
    assert rig.kind == "sim"
    assert isinstance(rig.camera, CameraDriver) and isinstance(rig.projector, ProjectorDriver)
    assert isinstance(rig.operator, Operator)
    rig.camera.start()
    try:
        rig.camera.set_manual_exposure(1e6 / 60, 1.0)  # auto exposure would change the brightness too
        rig.operator.request_pose("projector", 6, 0)  # the board now catches the projector's light
        m = measure_settle(rig.projector, rig.camera)
        assert 0 < m.changed_fraction < 0.5 and len(m.samples_s) == 5
        true_s = [rig.projector.timeline.latency_s(t) for t in range(1, rig.projector.ticket + 1)]
        # the projector's real latency (100 ms +- 4 ms) is covered, without waiting a frame too long
        assert max(true_s) <= m.settle_s < max(true_s) + 0.08
        assert m.settle_s >= min(m.samples_s)
        rig.operator.move_out()  # nothing in view is lit by the projector any more
        with pytest.raises(DeviceError, match="does not see the projector change"):
            measure_settle(rig.projector, rig.camera, trials=1, observe_s=0.3, first_rest_s=0.2)
    finally:
        rig.camera.stop()


def test_factory_rejects_unknown_rigs_and_options():
    with pytest.raises(SpecError, match="unknown rig 'kinect'"):
        open_rig("kinect")
    with pytest.raises(SpecError, match="unknown option.*exposure"):
        open_rig("realsense", exposure=5)


def test_default_rig_kind_follows_connected_cameras():
    sw = SoftwareRealSense()
    assert default_rig_kind(context=sw) == "realsense"
    sw.unplug()
    assert default_rig_kind(context=sw) == "sim"


HARDWARE_RIG_SCRIPT = r"""
import json
import numpy as np
from _drivers_helpers import SoftwareRealSense
from drivers.factory import HumanOperator, open_rig
from drivers.projector_window import ProjectorWindow, run_projector_loop
from drivers.realsense import RealSenseCamera
from drivers import projector_images as pi

sw = SoftwareRealSense(640, 480, 30, extra_modes=())
rig = open_rig("realsense", context=sw, width=640, height=480, fps=30, projector_screen=0, settle_s=0.05)
out = {"kind": rig.kind, "camera": type(rig.camera).__name__, "projector": type(rig.projector).__name__,
       "operator": type(rig.operator).__name__, "proj_size": rig.projector.size, "settle": rig.projector.settle_s}

def worker():
    rig.camera.start()
    t = rig.projector.wait_presented(rig.projector.show(pi.white(rig.projector.size)), 5.0)
    img = np.full((480, 640, 3), 77, np.uint8)
    sw.push(img, 1, 10.0)
    f = rig.camera.get_frame(2.0)
    return {"frame_ok": bool(np.array_equal(f.image, img)), "presented": t > 0,
            "instruction": rig.operator.request_pose("projector", 0, 0)}

out.update(run_projector_loop(rig.projector, worker, close=False))
rig.close()
out["closed"] = rig.projector.closed and not rig.camera.running
print(json.dumps(out))
"""


@pytest.mark.display
def test_factory_opens_the_hardware_rig_with_a_software_camera():
    with xvfb((1280, 720)) as display:
        r = run_python(HARDWARE_RIG_SCRIPT, display)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert (out["kind"], out["camera"], out["projector"], out["operator"]) == (
        "realsense", "RealSenseCamera", "ProjectorWindow", "HumanOperator")
    assert out["proj_size"] == [1280, 720] and out["settle"] == pytest.approx(0.05)
    assert out["frame_ok"] and out["presented"] and out["instruction"].startswith("Pattern position 1")
    assert out["closed"]


# ---- procam devices -----------------------------------------------------------------------------------------

def cli(args, display, timeout=120):
    code = "import sys; from app.cli import main; sys.exit(main(sys.argv[1:]))"
    return run_python(code, display, timeout=timeout, args=args)


def test_devices_without_a_display_is_not_an_error():
    r = cli(["devices"], None)
    assert r.returncode == 0, r.stderr
    assert "RealSense cameras:" in r.stdout
    assert "none: DISPLAY is not set" in r.stdout
    j = json.loads(cli(["devices", "--json"], None).stdout)
    assert j["screens"] == [] and "DISPLAY" in j["display_error"] and isinstance(j["realsense"], list)


@pytest.mark.display
def test_devices_lists_screens_and_cameras(monkeypatch, capsys):
    with xvfb((1280, 720)) as display:
        r = cli(["devices", "--json"], display)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["screens"] == [{"index": 0, "name": "screen", "primary": False, "x": 0, "y": 0,
                                                "width": 1280, "height": 720, "refresh_hz": None}]
    # the camera list as librealsense reports a (software) D455
    import drivers.realsense as realsense
    from app.cli import main

    sw = SoftwareRealSense()
    real = realsense.list_realsense_devices
    monkeypatch.setattr(realsense, "list_realsense_devices", lambda context=None: real(context=sw))
    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["devices"]) == 0
    text = capsys.readouterr().out
    assert "SW-D455-0001  Intel RealSense D455 (software)  firmware 5.16.0.1  USB 3.2" in text


# ---- procam show-pattern ------------------------------------------------------------------------------------

class Running:
    """`procam show-pattern` in a subprocess, its stdout lines in a queue."""

    def __init__(self, args, display):
        env = dict(os.environ, DISPLAY=display, PYTHONPATH=str(REPO))
        self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", "show-pattern", *args], cwd=str(REPO), env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.lines.put(line.strip())

    def wait_line(self, prefix, timeout=60):
        while True:
            line = self.lines.get(timeout=timeout)
            if line.startswith(prefix):
                return line

    def finish(self, timeout=60):
        self.proc.wait(timeout)
        return self.proc.returncode, self.proc.stderr.read()


@pytest.mark.display
def test_show_pattern_shows_the_pattern_pixel_exact():
    W, H = 1280, 720
    circles = PatternSpec.default_for(W, H, "circles")
    chess = PatternSpec.default_for(W, H, "chessboard")
    with xvfb((W, H)) as display:
        run = Running(["--screen", "0", "--position", "12", "--duration", "3"], display)
        head = run.wait_line("screen 0")
        assert "1280x720 circles 4x9" in head and "Esc or q quits" in head
        assert run.wait_line("showing") == "showing position 12 (13 of 13)"
        expected = circles.render(W, H, 12)[0]
        assert np.array_equal(screenshot(display), np.repeat(expected[:, :, None], 3, 2))
        assert run.finish()[0] == 0

        run = Running(["--screen", "0", "--pattern", "chessboard", "--cycle", "1.0", "--duration", "3.5"], display)
        for k in range(3):
            assert run.wait_line("showing") == f"showing position {k} ({k + 1} of 13)"
            expected = chess.render(W, H, k)[0]
            assert np.array_equal(screenshot(display)[:, :, 1], expected), f"position {k}"
        assert run.finish()[0] == 0

        run = Running(["--screen", "0", "--size", "800x600", "--position", "4", "--duration", "2"], display)
        run.wait_line("showing")
        small = PatternSpec.default_for(800, 600, "circles").render(800, 600, 4)[0]
        shot = screenshot(display)
        assert np.array_equal(shot[:600, :800, 0], small) and shot[600:].max() == 0
        assert run.finish()[0] == 0

        bad = cli(["show-pattern", "--screen", "0", "--position", "13"], display)
        assert bad.returncode == 2 and "pattern position 13 out of range 0..12" in bad.stderr
        bad = cli(["show-pattern", "--screen", "3"], display)
        assert bad.returncode == 2 and "no screen 3" in bad.stderr
    r = cli(["show-pattern", "--screen", "0"], None)
    assert r.returncode == 2 and "DISPLAY is not set" in r.stderr
