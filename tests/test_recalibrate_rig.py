"""Recalibration on a rig a person operates (issue 15, docs/RECALIBRATION.md): the boards of PREVIOUS, the
rig checked against it, the technician's prompts (a scripted operator function stands in for the person,
the simulated operator moves the board), a stop part-way and --resume, and the RealSense driver path
through librealsense's software device (--rig sim-realsense)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from calib.errors import SessionError
from calib.formats.session import RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.recalib import sha256_file
from drivers.sim.scenarios import get_scenario


def _procam(*args, stdin=subprocess.DEVNULL, input=None, timeout=600):
    kw = {"input": input} if input is not None else {"stdin": stdin}
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True, timeout=timeout, **kw)


def _previous_session(folder: Path, scenario: str, calibration=None) -> Path:
    """A previous calibration as a session folder: the session.json of the simulated `scenario` (its boards,
    pattern, rig request; no captures needed here) and a calibration.json (the scenario's truth unless given)."""
    sc = get_scenario(scenario, 0)
    cal = calibration or sc.ground_truth()
    man = SessionManifest(RigInfo(tuple(cal.camera.size), tuple(cal.projector.size), "mirror", {}, "sim"),
                          sc.layout.charuco, sc.pattern, sc.mirror_board)
    with SessionStore.create(folder, man) as store:
        store.update(state={"rig_request": {"kind": "sim", "scenario": scenario, "seed": 0, "quality": "live"}})
    cal.save_json(folder / "calibration.json")
    return folder


def _synthetic_previous(folder: Path, projector_target_scale: float = 1.0) -> Path:
    """The cheap joint calibration of tests/test_recalibrate.py (default scenario, with its uncertainty).
    `projector_target_scale` < 1 shrinks the projector's reported 1-sigma, the re-estimate's target (the
    check reads the covariance, not these values), so that a projector bump needs re-measure captures:
    this synthetic calibration's own targets are reached by the check's 4 captures alone."""
    sys.path.insert(0, str(Path(__file__).parent))
    from test_recalibrate import previous

    folder.mkdir(parents=True, exist_ok=True)
    cal = previous()
    if projector_target_scale != 1.0:
        u = json.loads(json.dumps(cal.uncertainty))
        u["T_cam_proj"]["t_total"] *= projector_target_scale
        u["T_cam_proj"]["rot_total_deg"] *= projector_target_scale
        cal = cal.with_(uncertainty=u)
    cal.save_json(folder / "calibration.json")
    return folder / "calibration.json"


# ---- the boards of PREVIOUS ------------------------------------------------------------------------
def test_session_boards_are_used_and_a_closed_input_stops_resumably(tmp_path):
    """PREVIOUS captured on the chessboard-pattern scenario: `--rig sim` without --auto and without
    --scenario records PREVIOUS's boards and pattern (not the default scenario's), prompts the first
    check capture, and a closed stdin stops with exit 4, the folder resumable (archive + sha256 in state)."""
    prev = _previous_session(tmp_path / "prev", "nonoverlap-136-chessboard")
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(prev), "--rig", "sim", "--sim-bump", "none", "--out", str(d))
    assert r.returncode == 4, r.stdout[-2000:] + r.stderr[-2000:]
    assert "Check, capture 1 of 4: Mirror capture 1 of 2: Hold the mirror board" in r.stdout
    assert f"procam recalibrate {prev} --out {d} --resume" in r.stdout
    new, old = json.loads((d / "session.json").read_text()), json.loads((prev / "session.json").read_text())
    for key in ("projector_board", "mirror_board", "pattern"):
        assert new[key] == old[key], key
    assert new["pattern"]["kind"] == "chessboard" and new["state"]["rig_request"]["scenario"] == "nonoverlap-136-chessboard"
    assert new["captures"] == []
    assert new["state"]["recalibration"]["previous_sha256"] == sha256_file(prev / "calibration.json")
    assert (d / "previous" / "calibration.json").read_bytes() == (prev / "calibration.json").read_bytes()
    assert not (d / "recalibration.json").exists()
    # the station's and the session's normal resume refuse it: it is a recalibration, and nothing changes
    before = (d / "session.json").read_bytes()
    for cmd in (("station", "--resume", str(d), "--port", "0"), ("session", "--resume", str(d), "--auto")):
        r = _procam(*cmd, timeout=120)
        assert r.returncode == 2 and f"is a recalibration: continue it with `procam recalibrate PREVIOUS --out {d} " \
            "--resume`" in r.stderr, (cmd, r.stderr[-800:])
    assert (d / "session.json").read_bytes() == before


def test_a_scenario_or_board_other_than_previous_is_refused(tmp_path):
    prev = _previous_session(tmp_path / "prev", "nonoverlap-136")
    man = json.loads((prev / "session.json").read_text())
    man["projector_board"]["cols"], man["projector_board"]["rows"] = 7, 5  # a board the scenario does not render
    (prev / "session.json").write_text(json.dumps(man))
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(prev), "--rig", "sim", "--auto", "--out", str(d))
    assert r.returncode == 2 and "choose the scenario PREVIOUS was captured on" in r.stderr and "7x5" in r.stderr
    assert not d.exists()
    r = _procam("recalibrate", str(prev), "--rig", "sim", "--auto", "--board", "8x6:DICT_4X4_50:50:30", "--out", str(d))
    assert r.returncode == 2 and "is not the board PREVIOUS was captured with" in r.stderr and not d.exists()


def test_bare_calibration_without_boards_is_refused_on_a_real_rig(tmp_path):
    """A calibration.json records the devices' sizes and units, not the boards: on the real rig the
    command asks for --board before any device is opened (the station's recalibration mode too)."""
    cal = get_scenario().ground_truth()
    bare = tmp_path / "bare.json"
    cal.with_(diagnostics={"session": "/data/site-7/session-1"}).save_json(bare)
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(bare), "--rig", "realsense", "--out", str(d))
    assert r.returncode == 2 and not d.exists()
    assert "does not record the boards" in r.stderr and "add --board COLSxROWS:DICT:SQUARE[:MARKER]" in r.stderr
    assert "/data/site-7/session-1" in r.stderr  # where it says it came from
    assert len(r.stderr.strip().splitlines()) == 1
    r = _procam("station", "--rig", "realsense", "--recalibrate", str(bare), "--session", str(d), "--port", "0",
                timeout=120)
    assert r.returncode == 2 and "add --board" in r.stderr and not d.exists()


def test_board_options_for_a_bare_calibration_and_their_checks():
    from app.recalibration import previous_board_specs

    cal = get_scenario().ground_truth()  # 1920x1080 projector, mm, with a mirror
    s = previous_board_specs("x/calibration.json", cal, board="8x6:DICT_5X5_50:40:30")
    assert s.board == CharucoSpec(8, 6, "DICT_5X5_50", 40.0, 30.0, "mm") and s.mirror_board == s.board
    assert s.pattern.positions > 1 and s.view == "mirror"
    s = previous_board_specs("x/calibration.json", cal, board="8x6:DICT_5X5_50:40:30", mirror_board="5x4:DICT_4X4_50:20:12")
    assert s.mirror_board == CharucoSpec(5, 4, "DICT_4X4_50", 20.0, 12.0, "mm")
    with pytest.raises(SessionError, match="--units mm"):
        previous_board_specs("x/calibration.json", cal, board="8x6:DICT_5X5_50:4:3", units="cm")
    assert previous_board_specs("x/calibration.json", cal, simulated=True) is None  # the scenario's boards


def test_the_connected_rig_must_be_the_one_previous_calibrated():
    from app.recalibration import check_rig_matches

    cal = get_scenario().ground_truth()  # camera 1280x800, projector 1920x1080

    def rig(cam, proj):
        return SimpleNamespace(kind="realsense", camera=SimpleNamespace(size=cam), projector=SimpleNamespace(size=proj))

    check_rig_matches(cal, None, rig((1280, 800), (1920, 1080)))
    with pytest.raises(SessionError, match="projector screen is 1280x720 but PREVIOUS calibrated a 1920x1080"):
        check_rig_matches(cal, None, rig((1280, 800), (1280, 720)))
    with pytest.raises(SessionError, match="camera streams 1920x1080 but PREVIOUS's camera model is for 1280x800"):
        check_rig_matches(cal, None, rig((1920, 1080), (1920, 1080)))


# ---- the technician's prompts ----------------------------------------------------------------------
@pytest.mark.slow
def test_scripted_operator_is_prompted_through_check_and_remeasure(tmp_path):
    """`--rig sim` without --auto, in process: the prompt function (here a script standing in for the
    person; the simulated operator moves the board) is called once before every capture, naming the step."""
    import argparse

    from app.commands.recalibrate import open_recalibration, prepare
    from app.recalibration import rig_verify_fn, run_recalibration

    prev = _synthetic_previous(tmp_path / "prev", projector_target_scale=0.5)
    d = tmp_path / "recal"
    args = argparse.Namespace(previous=str(prev), out=str(d), resume=False, rig="sim", auto=False, scenario=None,
                              seed=None, quality=None, sim_latency_ms=None, sim_bump="projector", board=None,
                              mirror_board=None, units=None, serial=None, projector_screen=None, settle_s=None,
                              max_captures=None, workers=2)
    said = []
    ready = prepare(args, said.append)
    rig = ready.open_rig()
    prompts = []

    def operator(text):
        prompts.append((text, len(machine.manifest.captures)))

    try:
        store, machine, station = open_recalibration(args, ready, rig, said.append)
        out = run_recalibration(prev, station, machine, log=said.append, prompt=operator,
                                verify=rig_verify_fn(rig, d))
    finally:
        rig.close()
    assert out.ok and out.record["check"]["parts"]["projector"]["status"] == "moved", out.message
    n = out.record["captures"]["total"]
    verifying = [t for t, _ in prompts if t.startswith("Epipolar verification")]
    assert [t.split(":")[0] for t in verifying] == ["Epipolar verification of the previous calibration",
                                                   "Epipolar verification of the recalibrated calibration"]
    assert "set the projector board on a stand, facing the projector" in verifying[0]
    prompts = [(t, k) for t, k in prompts if not t.startswith("Epipolar verification")]
    assert len(prompts) == n and [k for _, k in prompts] == list(range(n))  # one prompt before each capture
    texts = [t for t, _ in prompts]
    assert texts[0].startswith("Check, capture 1 of 4: Mirror capture 1 of 2: Hold the mirror board")
    assert texts[1].startswith("Check, capture 2 of 4: Mirror capture 2 of 2")
    assert all(t.startswith(f"Check, capture {i + 1} of 4: The projector shows the pattern at position")
               for i, t in zip((2, 3), texts[2:4]))
    assert n > 4 and all(t.startswith("Re-measure projector (round ") and "The projector shows the pattern" in t
                         for t in texts[4:])
    assert "tilt it differently" in texts[4]
    got = [s for s in said if s.startswith("got ")]
    assert len(got) == n and "board corners" in got[0] and "in the mirror" in got[0] and "the pattern (36 points)" in got[-1]


# ---- stop and resume ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_resume_on_sim_realsense_keeps_the_captures_and_reaches_unchanged(tmp_path):
    """Through the RealSense driver and librealsense's software device (--rig sim-realsense): three
    prompts answered, then the input closes (exit 4); --resume refuses another PREVIOUS, then continues on
    the stopped run's rig and bump with the 3 captures kept, and the verdict is "unchanged" in 4."""
    prev = _synthetic_previous(tmp_path / "prev")
    d = tmp_path / "recal"
    r = _procam("recalibrate", str(prev), "--rig", "sim-realsense", "--sim-bump", "none", "--out", str(d),
                input="\n\n\n")
    assert r.returncode == 4, r.stdout[-2000:] + r.stderr[-2000:]
    taken = {p.name: p.read_bytes() for p in (d / "images").iterdir()}
    assert sorted(taken) == ["mrv0000.png", "mrv0001.png", "p0000.png"]
    manifest = (d / "session.json").read_bytes()
    # another PREVIOUS: refused, nothing touched
    other = tmp_path / "other.json"
    data = json.loads(prev.read_text())
    data["camera"]["K"][0][0] += 1.0
    other.write_text(json.dumps(data))
    r = _procam("recalibrate", str(other), "--out", str(d), "--resume", "--auto")
    assert r.returncode == 2 and "is not the calibration the recalibration" in r.stderr and "sha256" in r.stderr
    assert (d / "session.json").read_bytes() == manifest
    # the same PREVIOUS: continues (the rig, scenario and bump are the stopped one's) and finishes
    r = _procam("recalibrate", str(prev), "--out", str(d), "--resume", "--auto")
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    rec = json.loads((d / "recalibration.json").read_text())
    assert rec["verdict"] == "unchanged" and rec["ok"] is True and rec["resumed"] is True
    assert rec["captures"]["total"] == 4 and rec["verification"]["previous"]["passed"] is True
    for name, data in taken.items():
        assert (d / "images" / name).read_bytes() == data
    assert rec["previous"]["sha256"] == sha256_file(prev)
    man = json.loads((d / "session.json").read_text())
    assert man["rig"]["driver"] == "sim-realsense" and man["state"]["rig_request"]["kind"] == "sim-realsense"
    r = _procam("recalibrate", str(prev), "--out", str(d), "--resume", "--auto")
    assert r.returncode == 2 and "is finished" in r.stderr


# ---- the station's recalibration mode ----------------------------------------------------------------
@pytest.mark.slow
def test_station_checklist_prompts_the_operator_on_sim_realsense(tmp_path):
    """`procam station --recalibrate PREV --rig sim-realsense` as its command builds it (prepare,
    open_recalibration, the panel's checklist), driven by the checklist's own actions (Start check,
    Sign off): every capture is announced in the checklist's *Now* line before it is taken."""
    import argparse
    import time

    from app.commands.recalibrate import open_recalibration, prepare
    from app.recalibration import rig_verify_fn
    from app.station.panel import StationPanel
    from app.station.panel_recal import RecalibrationPanel

    prev = _synthetic_previous(tmp_path / "prev")
    d = tmp_path / "recal"
    args = argparse.Namespace(previous=str(prev), out=str(d), resume=False, rig="sim-realsense", auto=False,
                              scenario=None, seed=None, quality=None, sim_latency_ms=None, sim_bump="none", board=None,
                              mirror_board=None, units=None, serial=None, projector_screen=None, settle_s=None,
                              max_captures=None, workers=2)
    ready = prepare(args, lambda text: None)
    rig = ready.open_rig()
    panel = None
    try:
        store, machine, station = open_recalibration(args, ready, rig, lambda text: None)
        panel = StationPanel(station, "127.0.0.1", 0)
        rp = RecalibrationPanel(panel, prev, verify=rig_verify_fn(rig, d))
        shown = []
        show = rp._prompt

        def prompt(text):  # what the checklist shows when the flow prompts (before the capture)
            show(text)
            shown.append((rp.text(), len(machine.manifest.captures)))

        rp._prompt = prompt
        rp.start_check()
        t_end = time.monotonic() + 300
        while rp.stage not in ("verdict", "failed") and time.monotonic() < t_end:
            time.sleep(0.2)
        assert rp.stage == "verdict", rp.error
        assert rp.accept_label() == "Sign off: unchanged"
        rp.accept()
        while rp.stage not in ("done", "failed") and time.monotonic() < t_end:
            time.sleep(0.2)
        assert rp.stage == "done", rp.error
    finally:
        if panel is not None:
            panel.stop()
        rig.close()
    assert [k for _, k in shown] == [0, 1, 2, 3, 4]  # the 4 check captures, then the verification
    assert "**Now:** Epipolar verification of the previous calibration" in shown[4][0]
    assert "**Now:** Check, capture 1 of 4: Mirror capture 1 of 2: Hold the mirror board" in shown[0][0]
    assert "**Now:** Check, capture 3 of 4: The projector shows the pattern" in shown[2][0]
    assert "**Now:**" not in rp.text() and "3. **Compare**: unchanged (ok)" in rp.text()
    rec = json.loads((d / "recalibration.json").read_text())
    assert rec["verdict"] == "unchanged" and json.loads((d / "session.json").read_text())["rig"]["driver"] == "sim-realsense"
