"""`procam verify SESSION --rig sim`: exit codes (0 pass, 1 fail, 2 could not run) and verification.json."""

import json
import subprocess
import sys

import pytest

from app.cli import main
from app.verification import perturbed
from drivers.sim.scenarios import get_scenario
from _epipolar_helpers import make_sim_session


def test_correct_calibration_passes_and_writes_the_report(tmp_path, capsys):
    sc = get_scenario("nonoverlap-136", 0)
    make_sim_session(tmp_path, calibration=sc.ground_truth())
    assert main(["verify", str(tmp_path), "--rig", "sim", "--grid", "3x2"]) == 0
    out = capsys.readouterr().out
    assert "PASS" in out and "mean" in out and "worst" in out
    d = json.loads((tmp_path / "verification.json").read_text())
    assert d["passed"] is True and d["n_checks"] == 6 and d["n_measured"] == 6
    assert d["settings"]["grid"] == [3, 2] and d["calibration"]["path"].endswith("calibration.json")
    # it records which calibration it verified (the file's hash) and says its pixels are the camera's
    import hashlib

    assert d["calibration"]["sha256"] == hashlib.sha256((tmp_path / "calibration.json").read_bytes()).hexdigest()
    assert 0 <= d["mean_camera_px"] <= d["worst_camera_px"]
    # the session's board was found: every check carries the predicted curve for the panel's overlay
    assert d["settings"]["board_pose_known"] and all(len(c["predicted_curve"]) > 10 for c in d["checks"])
    # the frames were read as light: this session recorded no response, the simulated camera knows its own
    assert d["response"] == {"model": "bt709", "gamma": 2.2, "from": "camera"}
    # a recorded one is the one used
    from dataclasses import replace

    from calib.formats.session import SessionStore

    store = SessionStore.open(tmp_path)
    store.update(rig=replace(store.manifest.rig, camera_settings={**store.manifest.rig.camera_settings,
                                                                  "response": {"model": "bt709", "gamma": 2.1}}))
    assert main(["verify", str(tmp_path), "--rig", "sim", "--grid", "3x1"]) == 0
    assert "gamma 2.1 as the session recorded" in capsys.readouterr().err
    d = json.loads((tmp_path / "verification.json").read_text())
    assert d["response"] == {"model": "bt709", "gamma": 2.1, "from": "session"}


def test_perturbed_calibration_fails_with_exit_1(tmp_path, capsys):
    sc = get_scenario("nonoverlap-136", 0)
    make_sim_session(tmp_path, calibration=perturbed(sc.ground_truth(), principal_shift_px=(5.0, 0.0)))
    assert main(["verify", str(tmp_path), "--rig", "sim", "--grid", "3x1"]) == 1
    out = capsys.readouterr().out
    assert "FAIL" in out
    d = json.loads((tmp_path / "verification.json").read_text())
    assert d["passed"] is False and d["mean_proj_px"] > 1.5
    # a looser threshold lets the same calibration pass, and --out puts the report elsewhere
    other = tmp_path / "other.json"
    assert main(["verify", str(tmp_path), "--rig", "sim", "--grid", "3x1", "--threshold", "8", "--out", str(other)]) == 0
    assert json.loads(other.read_text())["threshold_px"] == 8.0


def test_could_not_run_exits_2(tmp_path, capsys):
    sc = get_scenario("nonoverlap-136", 0)
    no_cal = tmp_path / "no_cal"
    make_sim_session(no_cal)
    assert main(["verify", str(no_cal), "--rig", "sim"]) == 2
    assert "procam calibrate" in capsys.readouterr().err
    real = tmp_path / "real"
    make_sim_session(real, calibration=sc.ground_truth(), driver="realsense")
    assert main(["verify", str(real), "--rig", "sim"]) == 2
    assert "--scenario" in capsys.readouterr().err
    # ... unless the scenario is named
    assert main(["verify", str(real), "--rig", "sim", "--scenario", "nonoverlap-136", "--grid", "3x1"]) == 0
    assert main(["verify", str(tmp_path / "missing"), "--rig", "sim"]) == 2
    # a calibration of another rig's size
    other = tmp_path / "other"
    make_sim_session(other, "nonoverlap-136-720p", calibration=sc.ground_truth())
    assert main(["verify", str(other), "--rig", "sim"]) == 2
    assert "differs" in capsys.readouterr().err


def test_a_realsense_without_a_recorded_response_has_it_measured(tmp_path, monkeypatch):
    """`procam verify --rig sim-realsense|realsense` on a session that recorded no response (the RealSense
    driver does not know its curve): measured as the station's rig check does, after the recorded (here
    searched) exposure; the exposure and gain are back after. A recorded one is used without measuring;
    a failed measurement is a warning and the check goes on uncorrected."""
    from dataclasses import replace

    import drivers.exposure
    from app.commands.verify import _apply_recorded, camera_response
    from calib.formats.session import SessionStore
    from drivers.errors import DeviceError
    from drivers.factory import open_rig

    make_sim_session(tmp_path, calibration=get_scenario("nonoverlap-136", 0).ground_truth())
    man = SessionStore.open(tmp_path).manifest
    rig = open_rig("sim-realsense", scenario="nonoverlap-136", seed=0, quality="live", latency_ms=0.0)
    try:
        rig.camera.start()
        rig.operator.request_pose("verification", None, 0)
        applied, _ = _apply_recorded(rig, man)
        assert not callable(getattr(rig.camera, "response", None))
        response, record, line = camera_response(rig, man, applied)
        assert record["from"] == "measured" and record["source"] == "measured" and "measured now" in line
        assert response.gamma == pytest.approx(rig.sim.camera.response()["gamma"], abs=0.1)
        dev = rig.device.options()
        assert (dev["exposure_us"], dev["gain"]) == (applied["exposure_us"], applied["gain"])
        assert rig.sim.camera.settings_timeline.current["gain"] == rig.device.sim_gain(applied["gain"])

        def never(*a, **k):
            raise AssertionError("measured although the session recorded a response")

        monkeypatch.setattr(drivers.exposure, "measure_response", never)
        recorded = replace(man, rig=replace(man.rig, camera_settings={"response": record}))
        assert camera_response(rig, recorded, applied)[:2] == (response, {**response.to_dict(), "from": "session"})

        def fails(*a, **k):
            rig.camera.set_manual_exposure(applied["exposure_us"], 128.0)  # the bracket ran partly
            raise DeviceError("too few dim pixels in view to measure the camera's response")

        monkeypatch.setattr(drivers.exposure, "measure_response", fails)
        response, record, line = camera_response(rig, man, applied)
        assert response is None and record is None
        assert line.startswith("warning:") and "too few dim pixels" in line and "uncorrected" in line
        assert rig.device.options()["gain"] == applied["gain"]
    finally:
        rig.close()


def test_bad_arguments_exit_2(tmp_path):
    for args in (["--grid", "4"], ["--grid", "0x3"], ["--threshold", "-1"], []):
        r = subprocess.run([sys.executable, "-m", "app", "verify", str(tmp_path), *args],
                           capture_output=True, text=True)
        assert r.returncode == 2, (args, r.stderr)


@pytest.mark.slow
def test_simulate_calibrate_verify_end_to_end(tmp_path):
    """The whole chain on the simulated rig: a `procam calibrate` result passes `procam verify`."""
    folder = tmp_path / "s"
    run = lambda *a: subprocess.run([sys.executable, "-m", "app", *a], capture_output=True, text=True)  # noqa: E731
    r = run("simulate", "nonoverlap-136", "--out", str(folder), "--quality", "live", "--no-progress")
    assert r.returncode == 0, r.stderr
    r = run("calibrate", str(folder), "--no-progress")
    assert r.returncode == 0, r.stderr
    r = run("verify", str(folder), "--rig", "sim")
    assert r.returncode == 0, r.stdout + r.stderr
    d = json.loads((folder / "verification.json").read_text())
    assert d["passed"] and d["n_measured"] >= 10 and d["mean_proj_px"] < 0.5
