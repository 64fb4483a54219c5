"""The command line under misuse: outputs that
would destroy a session are refused before any work, options are checked before detection, progress
never writes bar codes into a log, unexpected exceptions become one line plus a traceback file, and a
second calibration method never replaces the first one's result silently."""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import calib.detection.detect
import calib.pipeline
from app.cli import main
from app.commands._progress import BARS, LINES, OFF, Progress, progress_mode
from app.verification import VerificationReport, verification_is_stale
from calib.models.result import CalibrationResult
from calib.recalib import sha256_file

SIM_ARGS = ["--per-position", "2", "--mirror-count", "3", "--quality", "live", "--workers", "1"]


@pytest.fixture(scope="module")
def sim_session(tmp_path_factory):
    """A small simulated session (26 projector + 3 mirror images, live quality), calibrated once (joint; with
    13 projector images the quality gate finds it LOW QUALITY (projector orientation) and the command exits 3):
    the folder holds session.json, images/, detections.json, calibration.json/.yaml, ground_truth.json."""
    folder = tmp_path_factory.mktemp("cli_hardening") / "s"
    assert main(["simulate", "nonoverlap-136", "--out", str(folder), *SIM_ARGS, "--no-progress"]) == 0
    assert main(["calibrate", str(folder), "--no-progress", "--workers", "1"]) == 0
    assert (folder / "detections.json").exists() and (folder / "calibration.json").exists()
    return folder


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under `folder` (relative path) and the SHA-256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def count_detection(monkeypatch):
    """Counts calls of the detector (calib.pipeline imports detect_session from calib.detection.detect at call time)."""
    calls = []
    real = calib.detection.detect.detect_session

    def counting(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(calib.detection.detect, "detect_session", counting)
    return calls


def one_error_line(err: str, command: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"procam {command}: error: "), err
    return lines[0]


def _emulate_read_only(monkeypatch, folder: Path):
    """Make `folder` unwritable: chmod for a normal user; root ignores permissions, so for root the OS's
    answer (EACCES) is given for files created in that folder."""
    folder.chmod(0o555)
    if os.geteuid() != 0:
        return
    real = tempfile.mkstemp

    def mkstemp(*a, dir=None, **kw):
        if dir is not None and Path(dir).resolve() == folder.resolve():
            raise PermissionError(errno.EACCES, "Permission denied", str(folder))
        return real(*a, dir=dir, **kw)

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)


# ---- --out traps (issue 13 item 5) ------------------------------------------------------------------
def test_calibrate_out_traps_are_refused_before_detection(sim_session, tmp_path, capsys, count_detection, monkeypatch):
    S = sim_session
    before = snapshot(S)
    first_image = sorted((S / "images").iterdir())[0]
    a_file = tmp_path / "plain.txt"
    a_file.write_text("x")
    traps = {
        str(S / "session.json"): "manifest",
        str(S / "detections.json"): "detection cache",
        str(S / "images" / "new.json"): "images folder",
        str(first_image.with_suffix(".json")): "images folder",
        str(S / ".session.lock.json"): "lock",
        str(S / "ground_truth.json"): "ground truth",
        str(tmp_path / "res.yaml"): "YAML export",
        str(tmp_path / "res.yml"): "YAML export",
        str(S): "is a folder",
        str(a_file / "under.json"): "is a file, not a folder",
        str(tmp_path / "result.txt"): "*.json",
    }
    for out, expected in traps.items():
        rc = main(["calibrate", str(S), "--out", out, "--no-progress"])
        line = one_error_line(capsys.readouterr().err, "calibrate")
        assert rc == 2 and expected in line, (out, line)
    # the intrinsics file given on the command line is an input too
    cam = tmp_path / "cam.json"
    shutil.copy(S / "ground_truth.json", cam)
    cam_hash = sha256_file(cam)
    assert main(["calibrate", str(S), "--camera-intrinsics", str(cam), "--out", str(cam), "--no-progress"]) == 2
    assert "also an input" in one_error_line(capsys.readouterr().err, "calibrate")
    assert sha256_file(cam) == cam_hash
    # a read-only folder
    ro = tmp_path / "ro"
    ro.mkdir()
    _emulate_read_only(monkeypatch, ro)
    try:
        assert main(["calibrate", str(S), "--out", str(ro / "cal.json"), "--no-progress"]) == 2
        line = one_error_line(capsys.readouterr().err, "calibrate")
        assert f"cannot write in {ro}" in line and "Permission denied" in line
    finally:
        ro.chmod(0o755)
    assert count_detection == []  # every refusal came before detection
    assert snapshot(S) == before  # and the session is byte for byte what it was
    assert list(ro.iterdir()) == [] and not (tmp_path / "res.json").exists()


def test_out_json_gets_its_yaml_beside_it_and_a_full_disk_is_one_line(sim_session, tmp_path, capsys, monkeypatch):
    gt = CalibrationResult.load_json(sim_session / "ground_truth.json")
    monkeypatch.setattr(calib.pipeline, "calibrate_session", lambda *a, **kw: gt)  # the writing is under test
    out = tmp_path / "res.json"
    assert main(["calibrate", str(sim_session), "--out", str(out), "--no-progress"]) == 0
    assert json.loads(out.read_text())["method"] == gt.method
    assert (tmp_path / "res.yaml").read_text().startswith("%YAML")
    capsys.readouterr()

    def full(self, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(CalibrationResult, "save_json", full)
    assert main(["calibrate", str(sim_session), "--out", str(tmp_path / "r2.json"), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err, "calibrate")
    assert "cannot write" in line and "r2.json" in line and "No space left on device" in line


def test_simulate_import_and_bench_outputs_are_checked_first(sim_session, tmp_path, capsys, monkeypatch):
    S = sim_session
    before = snapshot(S)
    a_file = tmp_path / "f"
    a_file.write_text("x")
    renders = []
    import app.commands.simulate as simulate

    monkeypatch.setattr(simulate, "simulate_session", lambda *a, **kw: renders.append(1))
    for out, expected in ((S / "images" / "x", "inside the session"), (a_file, "is a file"),
                          (a_file / "sub", "is a file, not a folder")):
        assert main(["simulate", "direct", "--out", str(out), "--no-progress"]) == 2
        assert expected in one_error_line(capsys.readouterr().err, "simulate")
    ro = tmp_path / "ro"
    ro.mkdir()
    _emulate_read_only(monkeypatch, ro)
    try:
        assert main(["simulate", "direct", "--out", str(ro / "new"), "--no-progress"]) == 2
        assert "cannot write in" in one_error_line(capsys.readouterr().err, "simulate")
    finally:
        ro.chmod(0o755)
    assert renders == []
    # import-procamcalib: never into its own inputs or a session
    rec, pat = tmp_path / "rec", tmp_path / "Asym_4_9"
    rec.mkdir()
    pat.mkdir()
    for out, expected in ((rec / "session", "inside the input folder"), (pat, "also an input"),
                          (S / "images", "inside the session")):
        assert main(["import-procamcalib", str(rec), str(pat), "--board", "8x6:DICT_5X5_50:4.43", "--out", str(out),
                     "--no-progress"]) == 2
        assert expected in one_error_line(capsys.readouterr().err, "import-procamcalib")
    # bench: --json and --keep are checked before any session is simulated
    import app.commands.bench as bench

    monkeypatch.setattr(bench, "accuracy_runs", lambda *a, **kw: renders.append(1) or [])
    assert main(["bench", "accuracy", "--scenarios", "direct", "--json", str(S / "session.json")]) == 2
    assert "manifest" in one_error_line(capsys.readouterr().err, "bench")
    assert main(["bench", "accuracy", "--scenarios", "direct", "--keep", str(S / "images")]) == 2
    assert "inside the session" in one_error_line(capsys.readouterr().err, "bench")
    assert renders == [] and snapshot(S) == before


# ---- options before work (issue 17 item 2) -------------------------------------------------------------
def test_option_errors_come_before_detection(tmp_path, capsys, count_detection):
    S = tmp_path / "s"
    assert main(["simulate", "direct", "--out", str(S), *SIM_ARGS, "--no-progress"]) == 0
    capsys.readouterr()
    junk = tmp_path / "junk.json"
    junk.write_text("{")
    other_size = tmp_path / "720p.json"  # intrinsics of another resolution than the session's 1280x800
    gt = CalibrationResult.load_json(S / "ground_truth.json")
    gt.with_(camera=gt.camera.__class__(1280, 720, gt.camera.K, gt.camera.dist)).save_json(other_size)
    cases = [
        (["--method", "jiont"], "unknown calibration method 'jiont'"),
        (["--camera-intrinsics", str(tmp_path / "missing.yaml")], "does not exist"),
        (["--camera-intrinsics", str(tmp_path)], "is a folder"),
        (["--camera-intrinsics", str(junk)], "not valid JSON"),
        (["--camera-intrinsics", str(other_size)], "is for 1280x720 images but the session's are 1280x800"),
        (["--method", "paper", "--camera-model", "k1"], "--method joint only"),
        (["--workers", "0"], "--workers"),
    ]
    for extra, expected in cases:
        assert main(["calibrate", str(S), "--no-progress", *extra]) == 2
        assert expected in one_error_line(capsys.readouterr().err, "calibrate"), extra
    assert count_detection == [] and not (S / "detections.json").exists()


# ---- progress (issue 17 item 1) ---------------------------------------------------------------------
class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_is_bars_on_a_terminal_and_lines_in_a_log():
    assert progress_mode(False, _Terminal()) == BARS
    assert progress_mode(False, io.StringIO()) == LINES
    assert progress_mode(True, _Terminal()) == OFF
    term = _Terminal()
    p = Progress(BARS, term)
    cb = p.callback("detect", unit="images")
    for i in range(4):
        cb(i, 3, f"p{i}")
    p.close()
    assert "\r" in term.getvalue()  # a real tqdm bar
    log = io.StringIO()
    p = Progress(LINES, log)
    det, cal = p.callback("detect", unit="images"), p.callback("calibrate", stages=True)
    for i in range(67):
        det(i, 66, f"p{i}")
    for i, label in enumerate(["starting", "camera", "mirror", "projector"]):
        cal(i, 3, label)
    assert log.getvalue().splitlines() == [
        "detect: 66 images", *[ln for ln in log.getvalue().splitlines() if ln.startswith("detect: 66/66 images done")],
        "calibrate: starting (0/3)", "calibrate: camera (1/3)", "calibrate: mirror (2/3)", "calibrate: projector (3/3)"]


def test_no_bars_when_stderr_is_a_file(sim_session, tmp_path):
    log = tmp_path / "log"
    with open(log, "w") as f:
        r = subprocess.run([sys.executable, "-m", "app", "calibrate", str(sim_session), "--method", "paper",
                            "--redetect", "--out", str(tmp_path / "c.json"), "--workers", "1"],
                           stdout=subprocess.PIPE, stderr=f, text=True)
    assert r.returncode == 0
    text = log.read_text()
    assert "\r" not in text and "\x1b" not in text and "it/s" not in text
    lines = text.splitlines()
    assert lines[0] == "detect: 29 images" and re.fullmatch(r"detect: 29/29 images done in [\d.]+ s", lines[1])
    assert lines[2:] == ["calibrate: starting (0/3)", "calibrate: camera (1/3)", "calibrate: mirror (2/3)",
                         "calibrate: projector (3/3)"]


# ---- version, help, messages (issue 17 items 3-5) -----------------------------------------------------
def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"procam {version('procam-station')} ")
    r = subprocess.run([sys.executable, "-m", "app", "--version"], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.startswith("procam ")


def test_simulate_help_states_the_defaults_it_uses(capsys):
    from app.commands.simulate import capture_plan
    from drivers.sim.scenarios import get_scenario

    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    sc = get_scenario("nonoverlap-136", 0)
    n_mirror = sum(1 for j in capture_plan(sc) if j["step"] != "projector")  # what simulate writes
    assert f"mirror-calibration captures (default: the scenario's, {n_mirror})" in help_text
    assert f"board poses per pattern position (default: the scenario's, {sc.per_position} " in help_text


def test_messages(sim_session, tmp_path, capsys):
    S = sim_session
    assert main(["calibrate", str(S / "session.json")]) == 2
    line = one_error_line(capsys.readouterr().err, "calibrate")
    assert "session.json is the session's manifest file; give its folder" in line and f"calibrate {S}" in line
    assert main(["calibrate", str(S / "scene.json")]) == 2
    assert "is a file, not a session folder" in one_error_line(capsys.readouterr().err, "calibrate")
    assert main(["calibrate", str(tmp_path / "none")]) == 2
    assert "does not exist" in one_error_line(capsys.readouterr().err, "calibrate")
    # evaluate: a folder instead of a file, and swapped arguments
    assert main(["evaluate", str(S), str(S / "ground_truth.json")]) == 2
    line = one_error_line(capsys.readouterr().err, "evaluate")
    assert "is a folder, not a file" in line and str(S / "calibration.json") in line
    assert main(["evaluate", str(S / "ground_truth.json"), str(S / "calibration.json")]) == 2
    line = one_error_line(capsys.readouterr().err, "evaluate")
    assert "swapped" in line and f"procam evaluate {S / 'calibration.json'} {S / 'ground_truth.json'}" in line
    assert main(["evaluate", str(S / "calibration.json"), str(S / "ground_truth.json")]) == 0
    capsys.readouterr()


def test_simulate_says_wrote_on_stdout_and_the_rms_line_has_units(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["simulate", "direct", "--out", str(out), *SIM_ARGS, "--no-progress"]) == 0
    o = capsys.readouterr()
    assert o.out.startswith(f"wrote {out}:") and "wrote" not in o.err
    gt = CalibrationResult.load_json(out / "ground_truth.json")
    from app.commands.calibrate import format_rms

    line = format_rms(gt.with_(method="paper", rms={"camera": 0.1, "mirror_plane": 0.02, "projector": 0.3,
                                                   "stereo": 0.2}))
    assert line.startswith("RMS: camera 0.100 px, mirror_plane 0.020 mm, projector 0.300 projector px, stereo 0.200 px")
    line = format_rms(gt.with_(method="joint", rms={"joint": 0.04, "board": 0.05}))
    assert "joint 0.040 px, board 0.050 px" in line and "camera pixels" in line
    for part in line.split(": ", 1)[1].split(" (")[0].split(", "):
        assert part.split()[-1] in ("px", "mm"), part


def test_verification_json_names_the_image_of_its_pixels(tmp_path):
    old = {"schema": "procam-verification", "version": 1, "passed": True, "threshold_px": 1.5, "checks": [],
           "mean_px": 0.2, "worst_px": 0.5, "mean_proj_px": 0.8, "worst_proj_px": 2.0}
    rep = VerificationReport.from_dict(old)  # a file written before the rename still loads
    assert rep.mean_px == 0.2 and rep.worst_px == 0.5
    d = rep.to_dict()
    assert d["mean_camera_px"] == 0.2 and d["worst_camera_px"] == 0.5 and "mean_px" not in d
    assert VerificationReport.from_dict(d).mean_px == 0.2


# ---- unexpected exceptions (issue 13 item 9) ----------------------------------------------------------
def test_unexpected_exception_is_one_line_with_a_traceback_file(sim_session, capsys, monkeypatch):
    import calib.quality.metrics

    def broken(*a, **kw):
        raise RuntimeError("boom in compare")

    monkeypatch.setattr(calib.quality.metrics, "compare", broken)
    rc = main(["evaluate", str(sim_session / "calibration.json"), str(sim_session / "ground_truth.json")])
    line = one_error_line(capsys.readouterr().err, "evaluate")
    assert rc == 2 and "unexpected RuntimeError: boom in compare" in line
    path = Path(re.search(r"full traceback in (\S+)", line).group(1))
    try:
        text = path.read_text()
        assert "Traceback (most recent call last)" in text and "boom in compare" in text and "def broken" not in text
        assert "in broken" in text  # the frame where it was raised
    finally:
        path.unlink()

    def oserror(*a, **kw):
        raise OSError(errno.EIO, "Input/output error", "/some/file")

    monkeypatch.setattr(calib.quality.metrics, "compare", oserror)
    assert main(["evaluate", str(sim_session / "calibration.json"), str(sim_session / "ground_truth.json")]) == 2
    line = one_error_line(capsys.readouterr().err, "evaluate")
    assert "cannot access /some/file: Input/output error" in line
    Path(re.search(r"full traceback in (\S+)", line).group(1)).unlink()

    def interrupted(*a, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(calib.quality.metrics, "compare", interrupted)
    assert main(["evaluate", str(sim_session / "calibration.json"), str(sim_session / "ground_truth.json")]) == 130
    assert capsys.readouterr().err.strip() == "procam evaluate: interrupted"


# ---- a second method (issue 17 item 6) --------------------------------------------------------------
def test_a_second_method_keeps_the_first_and_a_replaced_calibration_makes_the_verification_stale(
        sim_session, tmp_path, capsys):
    S = tmp_path / "s"
    shutil.copytree(sim_session, S)
    main_cal = S / "calibration.json"
    assert json.loads(main_cal.read_text())["method"] == "joint"
    # a verification of this calibration.json (as `procam verify` writes it: the hash of the file it checked)
    report = {"schema": "procam-verification", "version": 1, "passed": True, "threshold_px": 1.5, "checks": [],
              "calibration": {"path": str(main_cal), "method": "joint", "sha256": sha256_file(main_cal)}}
    (S / "verification.json").write_text(json.dumps(report))
    assert verification_is_stale(S / "verification.json", main_cal) is False
    joint_hash = sha256_file(main_cal)

    assert main(["calibrate", str(S), "--method", "paper", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert sha256_file(main_cal) == joint_hash  # the joint result is untouched
    paper = CalibrationResult.load_json(S / "calibration-paper.json")
    assert paper.method == "paper" and (S / "calibration-paper.yaml").exists()
    assert f"{main_cal} holds the joint calibration and was kept" in out and "stale" not in out
    assert verification_is_stale(S / "verification.json", main_cal) is False

    # the same method again on the same captures gives the same result: the file and its verification are
    # kept (issue 28: re-running changed nothing, so nothing needs verifying again)
    assert main(["calibrate", str(S), "--method", "joint", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert sha256_file(main_cal) == joint_hash and f"kept {main_cal}: the result is the one it holds" in out
    assert "stale" not in out and verification_is_stale(S / "verification.json", main_cal) is False

    # a calibration.json the captures do not give (edited here) is replaced; its verification is stale, and
    # the hint names the rig the session recorded
    cal = json.loads(main_cal.read_text())
    cal["camera"]["K"][0][0] += 1.0
    main_cal.write_text(json.dumps(cal))
    report["calibration"]["sha256"] = sha256_file(main_cal)
    (S / "verification.json").write_text(json.dumps(report))
    edited_hash = sha256_file(main_cal)
    assert main(["calibrate", str(S), "--method", "joint", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert sha256_file(main_cal) != edited_hash
    assert "verification.json verified the calibration this one replaced, so it is stale" in out
    assert f"`procam verify {S} --rig sim` again" in out
    assert verification_is_stale(S / "verification.json", main_cal) is True

    # --out names the main file on purpose: it is replaced, the other method's file stays
    assert main(["calibrate", str(S), "--method", "paper", "--out", str(main_cal), "--no-progress"]) == 0
    assert CalibrationResult.load_json(main_cal).method == "paper" and "stale" in capsys.readouterr().out


def test_verify_out_is_checked_before_measuring(sim_session, capsys, monkeypatch):
    import app.verification

    measured = []
    monkeypatch.setattr(app.verification, "verify", lambda *a, **kw: measured.append(1))
    before = snapshot(sim_session)
    for out, expected in ((sim_session / "session.json", "manifest"), (sim_session / "calibration.json", "also an input"),
                          (sim_session, "is a folder")):
        assert main(["verify", str(sim_session), "--rig", "sim", "--out", str(out)]) == 2
        assert expected in one_error_line(capsys.readouterr().err, "verify")
    assert measured == [] and snapshot(sim_session) == before


def test_board_out_never_replaces_a_session_image(sim_session, capsys):
    before = snapshot(sim_session)
    image = sorted((sim_session / "images").iterdir())[0]
    assert image.suffix == ".png"
    assert main(["board", "--board", "8x6:DICT_5X5_50:4.43", "--out", str(image)]) == 2
    assert "images folder" in one_error_line(capsys.readouterr().err, "board")
    assert main(["board", "--assets", str(sim_session / "images" / "assets")]) == 2
    assert "inside the session" in one_error_line(capsys.readouterr().err, "board")
    assert snapshot(sim_session) == before


def test_error_lines_never_carry_terminal_control_characters(tmp_path, capsys):
    """A file name (or a session file's value) quoted in an error is shown with its control characters
    escaped: it cannot clear the screen, colour the terminal or overwrite the line with a carriage return."""
    from app.cli import main

    hostile = str(tmp_path / "no\x1b[2J\rsuch\x07")
    assert main(["calibrate", hostile]) == 2
    err = capsys.readouterr().err
    assert "\\x1b[2J\\rsuch\\x07" in err
    assert not any(ord(c) < 32 and c not in "\n\t" for c in err) and "\x9b" not in err


def test_a_held_mirror_placement_sways_through_its_frames_and_a_moved_one_is_taken_again():
    """procam bench placements --mirror-hold person: a hand-held real-virtual board moves from frame to
    frame, within what the station allows over the frames it keeps (else they are taken again, counted);
    a board laid on the mirror lies still."""
    import numpy as np

    import app.commands.simulate as sim
    from app.station.mirror_frames import MAX_MEAN_MOTION_PX
    from calib.transforms import transform_points
    from drivers.sim.scenarios import get_scenario

    for name, moves in (("nonoverlap-136", True), ("nonoverlap-136-realmirror", False)):
        sc = get_scenario(name, 0)
        sim._init_worker(sc, "live")
        try:
            rig = sim._worker_rig
            X = sc.mirror_board.corner_points()
            refused_total, swayed = 0, 0.0
            for job in [j for j in sim.capture_plan(sc, mirror_frames=8, mirror_hold="person") if j["step"] != "projector"]:
                rig.operator.request_pose(job["step"], job["position"], job["index"])
                poses, refused = sim.held_frames(rig, job, 8)
                assert len(poses) == 8 and 0 <= refused <= sim.MAX_HOLD_ATTEMPTS
                a, b = (sc.rig.camera.project(transform_points(P, X)) for P in (poses[0], poses[-1]))
                moved = float(np.hypot(*(b - a).T).max())
                if refused < sim.MAX_HOLD_ATTEMPTS:
                    assert moved <= MAX_MEAN_MOTION_PX
                refused_total += refused
                swayed = max(swayed, float(np.abs(poses[3][:3, 3] - poses[0][:3, 3]).max()))
                assert sim.held_frames(rig, job, 8)[1] == refused  # deterministic per placement
            if moves:
                assert swayed > 0.005 and refused_total > 0  # it moves, and some averages are taken again
                # the capture is the mean of the frames rendered where the board was at each
                job = next(j for j in sim.capture_plan(sc, mirror_frames=8, mirror_hold="person") if j["step"] != "projector")
                _, mean, _, _, refused = sim._render_job(job)
                poses, _ = sim.held_frames(rig, job, 8)
                frames = [rig.render_still(sim.FRAME_KEY_BASE * (1 + job["key"]) + f, T).astype(float)
                          for f, T in enumerate(poses)]
                assert np.array_equal(mean, np.clip(np.rint(sum(frames) / 8), 0, 255).astype(np.uint8))
                still = sim._render_job(dict(job, hold="still"))[1]
                assert not np.array_equal(mean, still)
            else:
                assert swayed == 0.0 and refused_total == 0
        finally:
            sim._worker_rig = None


def test_a_mirror_capture_of_several_frames_is_their_mean_each_its_own_noise(tmp_path, monkeypatch):
    """procam bench placements --mirror-frames N: each mirror capture the mean of N renders of the still
    board, each with its own noise draw (less noise than one), recorded in the capture's meta."""
    import numpy as np

    import app.commands.simulate as sim
    from calib.formats.session import SessionStore
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", 0)
    jobs = sim.capture_plan(sc, mirror_frames=4)
    mirror = [j for j in jobs if j["step"] != "projector"]
    assert mirror and all(j["frames"] == 4 for j in mirror)
    sim._init_worker(sc, "live")
    try:
        job = dict(mirror[0])
        _, mean, _, _, refused = sim._render_job(job)
        assert refused == 0  # a still board: nothing to refuse
        rig = sim._worker_rig
        frames = [rig.render_still(sim.FRAME_KEY_BASE * (1 + job["key"]) + f).astype(float) for f in range(4)]
        assert np.array_equal(mean, np.clip(np.rint(sum(frames) / 4), 0, 255).astype(np.uint8))
        assert not np.array_equal(frames[0], frames[1])  # each frame its own noise draw
        one = sim._render_job(dict(job, frames=1))[1].astype(float)
        still = np.mean(frames, axis=0)
        assert np.std(mean - still) < np.std(one - still)  # the mean is nearer the noiseless image
    finally:
        sim._worker_rig = None
    # a session of one mirror and one projector capture: the mirror one records its frames
    plan = sim.capture_plan

    def two(scenario, structured, frames, hold="still"):
        js = plan(scenario, structured, frames, hold)
        few = [next(j for j in js if j["step"] != "projector"), next(j for j in js if j["step"] == "projector")]
        return [dict(j, key=i) for i, j in enumerate(few)]

    monkeypatch.setattr(sim, "capture_plan", two)
    sim.simulate_session(sc, tmp_path / "S", quality="live", workers=1, progress=False, mirror_frames=3)
    caps = SessionStore.open(tmp_path / "S").manifest.captures
    assert [c.meta.get("frames_averaged") for c in caps] == [3, None]
