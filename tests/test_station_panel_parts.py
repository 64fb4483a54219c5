"""The panel's computations without a browser: the pixel a click on the camera image in the 3D view
points at, the results zip, the parameter text ("fixed" for a given camera, distortion), guidance (the
coverage grid, where to hold the board next, unmet targets), the banner that wraps instead of being cut,
and the retake rule of auto-capture (the deleted pose is not captured again)."""

import json
import zipfile

import numpy as np
import pytest

from app.station.autocapture import AutoCapture, AutoCaptureSettings, Bar, diversity_bars
from app.station.panel_guidance import coverage_grid, suggest_next, unmet_targets
from app.station.panel_live import FONT, image_plane, pixel_of_click, wrap
from app.station.panel_results import (
    EXPORTS_ALL, EXPORTS_NONE, RESULT_FILES, export_choices, export_names, parameters_text, results_zip,
    worst_views_text,
)
from calib.errors import ProcamError
from calib.synthetic import make_rig
from test_station_autocapture import board_at, det, observe

CAM = make_rig(136).ground_truth().camera


@pytest.mark.parametrize("origin", [(0.0, 0.0, 0.0), (-0.4, -0.7, -0.9)])
def test_a_click_on_the_image_plane_gives_the_pixel_under_it(origin):
    depth = 0.3
    centre, w, h, _ = image_plane(CAM, depth)
    for u, v in ((0.0, 0.0), (CAM.width - 1.0, 17.0), (640.5, 399.25), (CAM.cx, CAM.cy)):
        # the point of the plane showing pixel (u, v): its centre plus the offset of the pixel
        target = np.array([(u - CAM.cx) / CAM.fx * depth, (v - CAM.cy) / CAM.fy * depth, depth])
        d = target - np.array(origin)
        got = pixel_of_click(CAM, depth, origin, tuple(d / np.linalg.norm(d)))
        assert got == pytest.approx((u, v), abs=1e-6)
    # the plane is as wide as the image at that depth, centred on the image's middle pixel
    assert w == pytest.approx(CAM.width / CAM.fx * depth) and centre[2] == depth
    # rays that miss the image, or point away from it, give no pixel
    assert pixel_of_click(CAM, depth, (0, 0, 0), (0.9, 0.0, 0.1)) is None
    assert pixel_of_click(CAM, depth, (0, 0, 0), (0.0, 0.0, -1.0)) is None


def test_results_zip_carries_exactly_the_result_files_there(tmp_path):
    with pytest.raises(ProcamError, match="calibrate first"):
        results_zip(tmp_path)
    res = make_rig(136).ground_truth()
    res.save_json(tmp_path / "calibration.json")
    (tmp_path / "verification.json").write_text(json.dumps({"passed": True}))
    (tmp_path / "session.json").write_text("{}")  # not a result: stays out
    data, names = results_zip(tmp_path)
    assert names == ["calibration.json", "verification.json"]
    zpath = tmp_path / "out.zip"
    zpath.write_bytes(data)
    with zipfile.ZipFile(zpath) as z:
        assert z.namelist() == names
        assert z.read("calibration.json") == (tmp_path / "calibration.json").read_bytes()
    assert set(names) <= set(RESULT_FILES)


def test_results_zip_carries_the_exports_chosen(tmp_path):
    from calib.export.registry import EXPORTERS, write_exports

    res = make_rig(136).ground_truth()
    res.save_json(tmp_path / "calibration.json")
    assert export_choices()[:2] == (EXPORTS_ALL, EXPORTS_NONE) and set(export_choices()[2:]) == set(EXPORTERS)
    ref = tmp_path / "ref"
    ref.mkdir()
    write_exports(res, tuple(EXPORTERS), ref, "calibration")
    data, names = results_zip(tmp_path, export_names(EXPORTS_ALL))
    want = sorted(f"exports/{p.name}" for p in ref.iterdir())
    assert names[0] == "calibration.json" and sorted(n for n in names if n.startswith("exports/calibration")) == want
    assert "exports/calibration-camera.cameramodel" in names and "exports/calibration-projector.ros.yaml" in names
    zpath = tmp_path / "out.zip"
    zpath.write_bytes(data)
    with zipfile.ZipFile(zpath) as z:
        for n in want:  # the bytes `procam export` writes
            assert z.read(n) == (ref / n.split("/", 1)[1]).read_bytes(), n
    assert not (tmp_path / "exports").exists()  # written elsewhere, never into the session folder
    assert results_zip(tmp_path, export_names("ros"))[1] == ["calibration.json", "exports/calibration-camera.ros.yaml",
                                                             "exports/calibration-projector.ros.yaml"]
    assert results_zip(tmp_path, export_names(EXPORTS_NONE))[1] == ["calibration.json"]
    # a calibration the trust check rejects leaves with a note instead of exports
    trust = {"passed": False, "reasons": [{"code": "rms_high", "message": "residuals of 9 px"}]}
    res.with_(diagnostics={"trust": trust}).save_json(tmp_path / "calibration.json")
    data, names = results_zip(tmp_path, export_names(EXPORTS_ALL))
    assert names == ["calibration.json", "exports/NOTES.txt"]
    zpath.write_bytes(data)
    with zipfile.ZipFile(zpath) as z:
        assert "trust check rejects" in z.read("exports/NOTES.txt").decode() and "rms_high" in z.read("exports/NOTES.txt").decode()


def test_parameters_show_fixed_for_a_given_camera_and_the_distortion():
    res = make_rig(136).ground_truth()
    unc = {"camera": {"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0, "dist": [0.0] * 5, "fixed": True},
           "projector": {"fx": 1.5, "fy": 1.4, "cx": 0.8, "cy": 0.9, "dist": [0.001] * 5}}
    text = parameters_text(res.with_(uncertainty=unc), given_camera=True)
    cam_row = next(ln for ln in text.splitlines() if ln.startswith("| camera"))
    assert "(fixed)" in cam_row and "± 0.00" not in cam_row
    proj_row = next(ln for ln in text.splitlines() if ln.startswith("| projector"))
    assert "± 1.50" in proj_row and "fixed" not in proj_row
    assert f"k1 {res.camera.dist[0]:+.5f}" in text and "fx px" in text
    # worst views from the calibration's diagnostics
    worst = res.with_(diagnostics={"worst_views": [{"capture_id": "p0007", "step": "projector", "rms_px": 0.91}]})
    assert "| p0007 | projector | 0.910 |" in worst_views_text(worst)


def test_coverage_and_the_next_pose_goes_where_nothing_landed_yet():
    size = (1280, 800)
    # corners only in the right half of the image
    xs, ys = np.meshgrid(np.linspace(700, 1270, 12), np.linspace(10, 790, 10))
    corners = [np.c_[xs.ravel(), ys.ravel()]]
    counts = coverage_grid(corners, size)
    assert counts[:, :8].sum() == 0 and counts.sum() == len(corners[0])
    s = suggest_next(counts, [], diversity_bars([]))
    assert s.rect[2] <= 0.6  # the box lies in the empty left half
    assert "left" in s.text and s.tilt_deg is not None  # no poses yet: the tilt target is not met


def test_the_asked_pose_is_dashed_on_the_live_image_along_its_outline():
    from types import SimpleNamespace

    from app.station.panel_live import draw_asked_outline

    img = np.zeros((400, 640, 3), np.uint8)
    quad = np.array([[0.25, 0.4], [0.75, 0.4], [0.75, 0.8], [0.25, 0.8]])  # fractions of the image
    draw_asked_outline(img, SimpleNamespace(outline=quad))
    white = (img == 255).all(axis=2)
    for (ax, ay), (bx, by) in zip(quad, np.roll(quad, -1, axis=0)):  # dashes along every edge
        t = np.linspace(0.1, 0.9, 40)
        xs = np.round((ax + (bx - ax) * t) * 640 - 0.5).astype(int)
        ys = np.round((ay + (by - ay) * t) * 400 - 0.5).astype(int)
        hits = [white[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2].any() for x, y in zip(xs, ys)]
        assert 0.3 < np.mean(hits) < 0.95  # dashed: lit along about half of it, not all of it
    assert not white[200:300, 200:440].any()  # nothing inside it
    assert white[:150].any()  # the label above it
    blank = np.zeros_like(img)
    draw_asked_outline(blank, None)
    assert not blank.any()


def test_unmet_targets_name_the_bar():
    bars = [Bar("size", 0.3, "24-31% of the image", "25% of the image"), Bar("tilt", 1.0, "0-40 deg", "25 deg")]
    unmet = unmet_targets(bars)
    assert len(unmet) == 1 and unmet[0].startswith("size spans 24-31% of the image, the target is a range of 25%")


def test_the_banner_wraps_instead_of_cutting():
    import cv2

    text = ("board 35 corners | mirror image 33 | this pose is too close to mrv0001: move or tilt the board "
            "further away from where it was")
    lines = wrap(text, 620)
    assert len(lines) >= 2 and " ".join(lines).split() == text.split()
    assert all(cv2.getTextSize(ln, FONT, 0.45, 1)[0][0] <= 620 for ln in lines)


def test_after_a_retake_the_same_still_pose_is_not_captured_again(rng):
    ac = AutoCapture(AutoCaptureSettings(still_frames=3, still_px=1.0))
    same = det(observe(board_at(10.0), 0.1, rng))
    ac.avoid("p0001 (deleted)", same.features)
    ac.reset([])  # the station resets on the new target: the avoided pose stays
    for i in range(6):  # the board stays where it was: never captured
        d = ac.update(det(observe(board_at(10.0), 0.1, rng), i))
        assert not d.capture and d.similar_to == "p0001 (deleted)"
    assert d.still and "too close to p0001" in d.message
    # moved and tilted to a new pose: captured once still, and the rule is spent
    out = [ac.update(det(observe(board_at(30.0, centre=(150.0, 0, 900.0)), 0.1, rng), 10 + i)) for i in range(3)]
    assert out[-1].capture and ac.avoided == []


def test_the_zip_goes_out_even_when_the_report_fails(tmp_path, monkeypatch):
    import sys
    import types

    from app.station.panel_results import write_report_if_available

    make_rig(136).ground_truth().save_json(tmp_path / "calibration.json")
    fake = types.ModuleType("app.report")

    def broken(session_dir, out_path=None):
        raise ImportError("cannot import name 'x'")

    fake.write_report = broken
    monkeypatch.setitem(sys.modules, "app.report", fake)
    path, why = write_report_if_available(tmp_path)
    assert path is None and "ImportError" in why
    assert results_zip(tmp_path)[1] == ["calibration.json"]

    def works(session_dir, out_path=None):
        out_path.write_text("<html></html>")
        return out_path

    fake.write_report = works
    path, why = write_report_if_available(tmp_path)
    assert why is None and path == tmp_path / "report.html"
    assert results_zip(tmp_path)[1] == ["calibration.json", "report.html"]


def test_the_asked_outline_uses_the_blank_area_the_session_records():
    from types import SimpleNamespace

    from app.station.asked import DEFAULT_BLANK_MM, board_layout
    from calib.models.boards import CharucoSpec

    mm = CharucoSpec(8, 6, "DICT_5X5_50", 44.3, 22.15, "mm")
    given = board_layout(None, SimpleNamespace(projector_board=mm, blank_area=(250.0, 15.0)))
    w, h = mm.size
    assert given.blank_rect == (w + 15.0, 0.0, w + 265.0, h)  # --blank-area 250:15, as session.json has it
    scenario = SimpleNamespace(layout=SimpleNamespace(blank_rect="the scenario's"))
    assert board_layout(SimpleNamespace(scenario=scenario), SimpleNamespace(projector_board=mm, blank_area=None)) \
        is scenario.layout
    cm = CharucoSpec(8, 6, "DICT_5X5_50", 4.43, 2.215, "cm")
    default = board_layout(None, SimpleNamespace(projector_board=cm, blank_area=None))
    assert default.blank_width == pytest.approx(DEFAULT_BLANK_MM[0] / 10) and default.gap == pytest.approx(2.0)
