"""`procam board` and assets/: printed boards at true scale, detected by the project's own detector, and
the committed assets equal to a fresh regeneration."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.board_sheet import BlankArea, Sheet, Fill, board_rects, layout_sheet, spec_argument
from app.cli import main
from app.commands.board import PATTERN_SIZES, asset_files
from app.sheet_writers import rasterise, sheet_pdf, sheet_svg
from calib.detection.detect import detect_board
from calib.errors import SpecError
from calib.models.boards import CharucoSpec
from calib.models.pattern import PatternSpec
from calib.synthetic import BoardLayout
from drivers.projector_images import pattern_image
from drivers.sim.scenarios import default_mirror_board, default_projector_board

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT / "assets"


def _pdftoppm(pdf: Path, dpi: int) -> np.ndarray:
    exe = shutil.which("pdftoppm")
    assert exe, "pdftoppm is missing: apt-get install poppler-utils (.ci/run installs it)"
    out = pdf.with_suffix("")
    subprocess.run([exe, "-gray", "-r", str(dpi), "-singlefile", str(pdf), str(out)], check=True)
    img = cv2.imread(str(out) + ".pgm", cv2.IMREAD_GRAYSCALE)
    assert img is not None
    return img


def _measured_square_mm(img: np.ndarray, spec: CharucoSpec, dpi: float):
    """(detection, square side in mm): the mean distance between neighbouring detected corners."""
    obs = detect_board(img, spec, mirrored=False)
    assert obs, f"the detector did not find the printed board: {getattr(obs, 'reason', '')}"
    assert len(obs.ids) == spec.n_corners
    pos = {int(i): c for i, c in zip(obs.ids, obs.corners_px)}
    n = spec.cols - 1
    d = [np.linalg.norm(pos[i + 1] - pos[i]) for i in pos if (i + 1) % n and i + 1 in pos]
    d += [np.linalg.norm(pos[i + n] - pos[i]) for i in pos if i + n in pos]
    return obs, float(np.mean(d)) / (dpi / 25.4)


def _scale_bar_mm(img: np.ndarray, dpi: float) -> float:
    """Length of the one dark bar 3-5 mm tall and 90-110 mm long, from the darkness along a row of its
    lower half (the notches cut only the upper half)."""
    s = dpi / 25.4
    n, _, stats, _ = cv2.connectedComponentsWithStats((img < 128).astype(np.uint8), connectivity=8)
    bars = [st for st in stats[1:] if 3 * s <= st[3] <= 5 * s and 90 * s <= st[2] <= 110 * s]
    assert len(bars) == 1, f"expected one scale bar, found {len(bars)}"
    x, y, w, h, _ = bars[0]
    row = img[y + int(0.75 * h), x - 3 : x + w + 3].astype(float)
    return float(np.sum(255.0 - row) / 255.0) / s


def _unit_mm(spec):
    return {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}[spec.units]


# ---- the board geometry is OpenCV's -----------------------------------------------------------------
@pytest.mark.parametrize("text, units, px_per_unit", [
    ("8x6:DICT_4X4_50:22:13.2", "mm", 10), ("8x6:DICT_4X4_50:50:30", "mm", 4), ("7x5:DICT_6X6_250:40", "mm", 2),
    ("5x7:DICT_5X5_100:3:1.5", "cm", 28),
])
def test_board_rectangles_are_opencvs_board_pixel_for_pixel(text, units, px_per_unit):
    # where every cell edge falls on a pixel edge, the rectangles rasterised must equal OpenCV's own
    # image of the board the detector uses (CharucoBoard.generateImage)
    spec = CharucoSpec.parse(text, units)
    w, h = spec.size
    sheet = Sheet("custom", w, h, (Fill(tuple(board_rects(spec)), 0.0),), "t", (0.0, 0.0), 1.0)
    ours = rasterise(sheet, px_per_unit * 25.4)
    ref = spec.render(px_per_unit)
    assert ours.shape == ref.shape
    assert np.array_equal(ours, ref)


# ---- generated boards, detected --------------------------------------------------------------------
def test_png_board_is_detected_at_its_true_size(tmp_path, capsys):
    spec = default_mirror_board()
    out = tmp_path / "mirror.png"
    assert main(["board", "--board", spec_argument(spec), "--out", str(out), "--dpi", "150", "--paper", "a4"]) == 0
    assert "A4 landscape" in capsys.readouterr().out
    data = out.read_bytes()
    ppm = int(round(150 / 0.0254))
    assert data[37:41] == b"pHYs" and int.from_bytes(data[41:45], "big") == ppm  # viewers know its dpi
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (round(210 / 25.4 * 150), round(297 / 25.4 * 150))
    obs, square_mm = _measured_square_mm(img, spec, 150)
    assert square_mm == pytest.approx(22.0, rel=2e-4)
    # every corner where the sheet says the board is (pixel centres at (x s - 0.5, y s - 0.5))
    sheet = layout_sheet(spec, None, "a4")
    s = 150 / 25.4
    expected = (np.asarray(sheet.board_origin_mm) + spec.corner_points()[obs.ids, :2]) * s - 0.5
    assert np.abs(expected - obs.corners_px).max() < 0.05
    assert _scale_bar_mm(img, 150) == pytest.approx(100.0, abs=0.05)


@pytest.mark.parametrize("text, units, dpi", [("8x6:DICT_5X5_50:4.43", "cm", 100), ("5x4:DICT_4X4_50:7.3", "mm", 300)])
def test_pdf_board_rasterised_by_poppler_is_detected_at_its_true_size(tmp_path, text, units, dpi):
    spec = CharucoSpec.parse(text, units)
    pdf = tmp_path / "board.pdf"
    assert main(["board", "--board", text, "--units", units, "--out", str(pdf)]) == 0
    img = _pdftoppm(pdf, dpi)
    _, square_mm = _measured_square_mm(img, spec, dpi)
    assert square_mm == pytest.approx(spec.square_length * _unit_mm(spec), rel=1e-3)
    # poppler snaps the edges of filled rectangles to pixel edges: the bar is exact to about a pixel
    assert _scale_bar_mm(img, dpi) == pytest.approx(100.0, abs=1.5 * 25.4 / dpi)
    content = pdf.read_bytes()
    assert b"CreationDate" not in content and b"/ID" not in content  # nothing that changes between runs
    m = re.search(rb"\(Board spec for the station: --board (\S+) --units (\w+)\) Tj", content)
    assert m, "the station's board spec is not written on the sheet"
    assert CharucoSpec.parse(m.group(1).decode(), m.group(2).decode()) == spec


def test_svg_is_true_size_and_has_the_pdfs_rectangles():
    spec = CharucoSpec.parse("6x4:DICT_4X4_50:30:18")
    sheet = layout_sheet(spec, BlankArea(100, 10), "a3")
    svg, pdf = sheet_svg(sheet), sheet_pdf(sheet).decode("latin-1")
    assert re.search(r'width="420mm" height="297mm" viewBox="0 0 420 297"', svg)
    assert re.search(r"/MediaBox \[0 0 1190\.5512 841\.8898\]", pdf)  # 420 x 297 mm in points
    svg_rects = [tuple(float(v) for v in r) for r in
                 re.findall(r"M(-?[\d.]+) (-?[\d.]+)h(-?[\d.]+)v(-?[\d.]+)h-?[\d.]+z", svg)]
    pdf_rects = [tuple(float(v) for v in r) for r in re.findall(r"(-?[\d.]+) (-?[\d.]+) (-?[\d.]+) (-?[\d.]+) re", pdf)]
    assert len(svg_rects) == sum(len(i.rects) for i in sheet.items if isinstance(i, Fill)) > 0
    assert svg_rects == pdf_rects


def test_spec_argument_round_trips():
    for spec in (CharucoSpec(8, 6, "DICT_5X5_50", 4.43, 2.215, "cm"), CharucoSpec(9, 7, "DICT_4X4_250", 22.123456789, 13.1, "mm"),
                 default_projector_board(), default_mirror_board()):
        assert CharucoSpec.parse(spec_argument(spec), spec.units) == spec


# ---- assets/ ---------------------------------------------------------------------------------------
def test_committed_assets_equal_a_fresh_regeneration():
    fresh = asset_files()
    committed = {p.relative_to(ASSETS).as_posix() for p in ASSETS.rglob("*") if p.is_file()} - {"README.md"}
    assert committed == set(fresh), "assets/ is stale: run procam board --assets assets"
    for rel, data in fresh.items():
        assert (ASSETS / rel).read_bytes() == data, f"assets/{rel} differs from a regeneration: run procam board --assets assets"


def test_pattern_pngs_are_the_pattern_codes_images():
    for w, h in PATTERN_SIZES:
        spec = PatternSpec.default_for(w, h)
        assert (spec.kind, spec.cols, spec.rows, spec.positions) == ("circles", 4, 9, 13)
        files = sorted((ASSETS / "patterns" / f"{w}x{h}").glob("*.png"))
        assert len(files) == 13
        for k, f in enumerate(files):
            img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            expected, points = pattern_image(spec, (w, h), k)
            assert img.shape == (h, w) and np.array_equal(img, expected), f"{f.name}"
        found = spec.find(img)  # the last one: the pattern finder sees the grid where the code put it
        assert found is not None and np.abs(found - points).max() < 0.1


def test_committed_projector_board_is_the_default_with_its_blank_area(tmp_path):
    spec = default_projector_board()
    pdf = tmp_path / "p.pdf"
    shutil.copy(ASSETS / "projector-board.pdf", pdf)
    dpi = 30
    img = _pdftoppm(pdf, dpi)
    obs, square_mm = _measured_square_mm(img, spec, dpi)
    assert square_mm == pytest.approx(50.0, rel=2e-3)
    # the blank area, located from the detected corners through the board's own layout, is white
    layout = BoardLayout(spec)
    A = cv2.estimateAffinePartial2D(spec.corner_points()[obs.ids, :2].astype(np.float32),
                                    obs.corners_px.astype(np.float32))[0]
    x0, y0, x1, y1 = layout.blank_rect
    (u0, v0), (u1, v1) = (A @ np.array([[x0, y0, 1.0], [x1, y1, 1.0]]).T).T
    blank = img[int(np.ceil(v0)) + 1 : int(v1) - 1, int(np.ceil(u0)) + 1 : int(u1) - 1]
    assert blank.shape[1] == pytest.approx((x1 - x0) * dpi / 25.4, abs=4) and blank.min() >= 250
    m = re.search(rb"--board (\S+) --units (\w+)\) Tj", pdf.read_bytes())
    assert CharucoSpec.parse(m.group(1).decode(), m.group(2).decode()) == spec
    mirror = re.search(rb"--mirror-board (\S+) --units (\w+)\) Tj", (ASSETS / "mirror-board.pdf").read_bytes())
    assert CharucoSpec.parse(mirror.group(1).decode(), mirror.group(2).decode()) == default_mirror_board()


# ---- bad input ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["--board", "8x6:DICT_5X5_50"], "does not parse"),
    (["--board", "8x6:DICT_9X9_50:20"], "unknown ArUco dictionary 'DICT_9X9_50'"),
    (["--board", "8x6:DICT_4X4_50:20:25"], "need 0 < marker_length < square_length"),
    (["--board", "20x20:DICT_4X4_50:10"], "needs 200 markers; DICT_4X4_50 has 50"),
    (["--board", "8x6:DICT_4X4_50:20", "--units", "furlong"], "unknown length unit 'furlong'"),
    (["--board", "8x6:DICT_4X4_50:20", "--blank-area", "wide"], "blank area 'wide' does not parse"),
    (["--board", "8x6:DICT_4X4_50:20", "--blank-area", "-5"], "need WIDTH > 0"),
    (["--board", "8x6:DICT_4X4_50:50", "--paper", "a4"], "does not fit A4 (210 x 297 mm); the smallest sheet it fits: A2"),
    (["--board", "8x6:DICT_4X4_50:20", "--paper", "letter"], "unknown paper 'letter'"),
    (["--board", "8x6:DICT_4X4_50:20", "--dpi", "100"], "--dpi applies to PNG output only"),
    (["--blank-area", "300"], "give the board: --board"),
])
def test_bad_input_is_one_clear_line_and_writes_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "b.pdf"
    assert main(["board", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("procam board: error:") and "\n" not in err and message in err, err
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("out, message", [("b.jpg", "must end in .pdf, .svg, .png"), ("missing/b.pdf", "does not exist"),
                                          ("x.pdf", "is a folder")])
def test_bad_out_is_refused(tmp_path, capsys, out, message):
    (tmp_path / "x.pdf").mkdir()
    argv = ["board", "--board", "8x6:DICT_4X4_50:20", "--out", str(tmp_path / out)]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert main(["board", "--board", "8x6:DICT_4X4_50:20", "--out", str(tmp_path / "b.png"), "--dpi", "5"]) == 2
    assert "between 10 and 2400" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["x.pdf"] and not any((tmp_path / "x.pdf").iterdir())


def test_procam_board_command_writes_an_svg(tmp_path):
    out = tmp_path / "b.svg"
    r = subprocess.run([sys.executable, "-m", "app", "board", "--board", "8x6:DICT_5X5_50:4.43", "--units", "cm",
                        "--blank-area", "30:2", "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stdout and "A1 landscape" in r.stdout
    svg = out.read_text()
    assert "--board 8x6:DICT_5X5_50:4.43:2.215 --units cm" in svg and "blank area 30 x 26.58 cm, 2 cm right" in svg


@pytest.mark.parametrize("text, units, blank, paper", [
    ("3x3:DICT_4X4_50:5", "mm", None, "a4"), ("8x6:DICT_5X5_50:4.43", "cm", "30", "a1"),
    ("12x9:DICT_5X5_100:30", "mm", "200:10", "a1"), ("40x30:DICT_6X6_1000:3", "cm", None, "custom"),
    ("8x6:DICT_4X4_50:2:1.2", "in", None, "a2"),
])
def test_sheet_is_the_smallest_that_holds_everything_inside_the_margins(text, units, blank, paper):
    spec = CharucoSpec.parse(text, units)
    sheet = layout_sheet(spec, BlankArea.parse(blank, units) if blank else None)
    assert sheet.paper == paper
    m = 7.0  # app.board_sheet.PAGE_MARGIN_MM: printers leave the paper's edge blank
    for item in sheet.items:
        for x, y, w, h in getattr(item, "rects", ()):
            assert m <= x and x + w <= sheet.width_mm - m and m <= y and y + h <= sheet.height_mm - m
        if hasattr(item, "text"):
            assert m <= item.x <= sheet.width_mm - m and item.y <= sheet.height_mm - m
    if paper != "a4":  # the next smaller sheet is refused, naming the one that fits
        smaller = {"a1": "a2", "a2": "a3", "custom": "a0"}[paper]
        with pytest.raises(SpecError, match=f"does not fit {smaller.upper()}"):
            layout_sheet(spec, BlankArea.parse(blank, units) if blank else None, smaller)


def test_a_board_of_implausible_size_is_drawn_with_a_warning_naming_the_unit(tmp_path, capsys):
    """`--board 8x6:DICT_5X5_50:4.43` without `--units cm` is a 35 x 27 mm board: drawn (the operator may
    mean it) but with a warning that names the unit and the fix; a realistic size gets none."""
    from app.cli import main

    assert main(["board", "--board", "8x6:DICT_5X5_50:4.43", "--out", str(tmp_path / "small.svg")]) == 0
    err = capsys.readouterr().err
    assert "warning: squares of 4.43 mm make a board of 35.44 x 26.58 mm" in err and "add --units cm" in err
    assert (tmp_path / "small.svg").exists()
    assert main(["board", "--board", "8x6:DICT_5X5_50:4.43", "--units", "cm", "--out", str(tmp_path / "ok.svg")]) == 0
    assert "warning" not in capsys.readouterr().err
    assert main(["board", "--board", "2x2:DICT_5X5_50:600", "--out", str(tmp_path / "big.svg")]) == 0
    err = capsys.readouterr().err
    assert "larger than any calibration board" in err and "add --units" not in err
    # a page beyond 2 m is refused (tests/test_cli_options.py), not drawn with a warning
    help_text = subprocess.run([sys.executable, "-m", "app", "board", "--help"], capture_output=True, text=True,
                               timeout=60).stdout
    assert "8x6:DICT_5X5_50:44.3 (squares of 44.3 mm" in " ".join(help_text.split())
