"""The activity model the panel's status lines follow (app/station/activity.py), and what the panel says
without a browser: a failed action's line replaced by its later success, a running line gone when the
action ends, the live image's banner before any detection, the uncertainty claim limited to where the
captures reach, and one coverage for the panel's guidance and the report."""

import threading
from types import SimpleNamespace

import numpy as np
import pytest

from app.station.activity import Activities, Status, activities_text, rig_findings
from app.station.machine import MIRROR_CAPTURE, RigCheck
from app.words import plural, signed
from calib.errors import CalibrationError


def test_a_failure_is_replaced_by_a_later_success_of_the_same_action():
    logged = []
    acts = Activities(log=logged.append)
    with pytest.raises(CalibrationError):
        with acts.running("Calibrate"):
            raise CalibrationError("only 2 usable projector images")
    assert "**Calibrate failed:** only 2 usable projector images" in activities_text(acts.all())
    gate = threading.Event()
    acts.start("Calibrate")
    worker = threading.Thread(target=lambda: acts.conclude("Calibrate", gate.wait, lambda out: "RMS 0.1 px"))
    worker.start()
    acts.progress("Calibrate", "projector 3 of 9", log=False)
    text = activities_text(acts.all())
    assert "Calibrate: running.** projector 3 of 9" in text and "failed" not in text
    gate.set()
    worker.join()
    text = activities_text(acts.all())
    assert text == "**Calibrate: done.** RMS 0.1 px"  # no running line, no old failure
    assert acts.get("Calibrate").status is Status.DONE and logged == []  # counters are not logged


def test_the_rig_checks_findings_are_said_and_logged():
    logged = []
    acts = Activities(log=logged.append)
    checks = [RigCheck("camera", True, "1280x800 frames streaming"),
              RigCheck("camera exposure", True, "8333 us (1.00 refresh periods), gain 2"),
              RigCheck("projector latency", True, "latency 50 ms")]
    with acts.running("Check rig", "camera: waiting for a frame") as act:
        acts.progress("Check rig", "projector latency: measuring")
        act.outcome = rig_findings(checks)
    line = acts.get("Check rig").text()
    assert line.startswith("**Check rig: done.** all 3 checks passed")
    assert "8333 us" in line and "gain 2" in line and "latency 50 ms" in line and "1280x800" not in line
    assert logged == ["Check rig: projector latency: measuring"]


def test_the_banner_says_what_waiting_means():
    from app.station.panel import StationPanel

    panel = SimpleNamespace(machine=SimpleNamespace(state=MIRROR_CAPTURE))
    assert StationPanel._banner(panel, None, None) == "no frame with the board detected yet"


def test_small_uncertainty_is_claimed_only_where_the_captures_reach():
    from app.station.panel_uncertainty import uncertainty_text

    grid = np.full((10, 16), 0.1)
    result = SimpleNamespace(projection_uncertainty={
        "camera": {"sigma_px": grid.tolist(), "median_px": 0.1, "max_px": 0.1, "large_fraction": 0.0}})
    assert "constrain the whole camera image" in uncertainty_text(result, "camera", 1.0)
    partial = uncertainty_text(result, "camera", 0.46)
    assert "where the captures reach (camera coverage 46%)" in partial and "whole" not in partial


def test_one_coverage_for_the_panel_and_the_report():
    from app.station.panel_guidance import coverage_grid, coverage_summary
    from calib.quality.coverage import coverage_fraction

    size = (1280, 800)
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(0, 700, 300), rng.uniform(0, 500, 300)]
    counts = coverage_grid([pts[:150], pts[150:]], size)
    shown = f"{coverage_fraction(pts, *size) * 100:.0f}%"
    assert f"coverage **{shown}**" in coverage_summary(counts)


def test_counts_and_signs_read_right():
    assert plural(1, "capture") == "1 capture" and plural(2, "capture") == "2 captures"
    assert signed(-0.001) == "+0.00" and signed(-0.4) == "-0.40" and signed(1.25) == "+1.25"


def test_verified_pixels_are_labelled_beside_their_strokes_with_a_unit():
    import cv2

    from app.station.panel_live import FONT, NOT_MEASURED, ORANGE, RED, check_label, draw_checks

    stroke = np.c_[np.full(50, 200.0), np.linspace(50, 350, 50)]  # vertical, through the pixel
    measured = SimpleNamespace(ok=True, pixel=(200.0, 200.0), distance_px=0.8, distance_proj_px=1.1,
                               predicted_curve=stroke + [1.0, 0.0], detected_curve=stroke)
    missed = SimpleNamespace(ok=False, pixel=(450.0, 120.0), distance_px=None, distance_proj_px=None,
                             predicted_curve=None, detected_curve=None)
    assert check_label(measured, True) == "1.10 proj px" and check_label(missed, False) == "not measured"
    img = np.zeros((400, 640, 3), np.uint8)
    draw_checks(img, [measured, missed], 1.0, 1.5, 2.0)
    # the label does not sit on the stroke: the stroke's column stays orange along the label's rows
    (tw, th), _ = cv2.getTextSize("1.10 proj px", FONT, 0.35, 1)
    column = img[150:250, 199:202].reshape(-1, 3)
    assert (np.abs(column.astype(int) - ORANGE).max(axis=1) < 60).mean() > 0.6
    # not measured: grey, not red (it is no failure)
    near = img[110:131, 440:461].reshape(-1, 3).astype(int)
    assert (np.abs(near - NOT_MEASURED).max(axis=1) < 30).sum() > 20
    assert not (np.abs(near - RED).max(axis=1) < 30).any()


def test_a_manual_capture_of_a_pose_auto_capture_refused_says_so():
    from app.station.panel_controls import PanelControls

    said = PanelControls._describe_outcome(None, "capture", SimpleNamespace(id="p0004", meta={"similar_to": "p0003"}))
    assert said.startswith("p0004 written to the session") and "close to p0003; taken as you asked" in said
    plain = PanelControls._describe_outcome(None, "capture", SimpleNamespace(id="p0005", meta={}))
    assert plain == "p0005 written to the session"
