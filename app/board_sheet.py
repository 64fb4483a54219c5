"""The printed sheet of a board: what `procam board` draws, as a list of filled rectangles and text
lines in millimetres on a page (y down, origin at the page's top-left corner).

The board's black squares and marker cells come from the same `CharucoSpec.cv_board()` the detector
uses (its marker corners, ids and dictionary), so the station's board spec and the printed file have one
definition. The projector board's blank area (where the projected circle grid lands) is
`calib.synthetic.BoardLayout`, the definition the simulated rig renders. app/sheet_writers.py turns a
Sheet into PDF, SVG or PNG.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import SpecError
from calib.models.boards import MM_PER_UNIT, CharucoSpec
from calib.models.vocab import LengthUnit
from calib.synthetic import BoardLayout


#: ISO 216 sheets, (short side, long side) in mm, smallest first
PAPERS = {"a4": (210.0, 297.0), "a3": (297.0, 420.0), "a2": (420.0, 594.0), "a1": (594.0, 841.0),
          "a0": (841.0, 1189.0)}
PAPER_CHOICES = (*PAPERS, "auto")

PAGE_MARGIN_MM = 7.0  # nothing printed closer to the paper's edge (most printers leave 3-5 mm blank)
CROP_GAP_MM = 1.0  # crop marks start this far outside the board's outline...
CROP_LEN_MM = 4.0  # ...and are this long
CROP_WIDTH_MM = 0.15
SCALE_BAR_MM = 100.0  # the 10 cm bar
SCALE_BAR_HEIGHT_MM = 4.0
NOTCH_WIDTH_MM = 0.3  # white notches cut into the bar's top half at every centimetre
SPEC_FONT_MM = 3.5
TEXT_FONT_MM = 2.6
LINE_SPACING = 1.45
CHAR_WIDTH_EM = 0.56  # a generous average Helvetica advance, for line wrapping only


@dataclass(frozen=True)
class Fill:
    """Axis-aligned rectangles (x, y, w, h) in mm, filled with one grey level (0 black, 1 white) as one
    path: they never overlap, so a renderer shows no seams between neighbours."""

    rects: tuple
    gray: float = 0.0


@dataclass(frozen=True)
class Text:
    """One line of text; (x, y) is the start of its baseline in mm. `size_mm` is the font size (em)."""

    x: float
    y: float
    size_mm: float
    text: str
    bold: bool = False
    anchor: str = "start"  # "start" | "middle"


@dataclass(frozen=True)
class Sheet:
    """A page: paper name ("a4", ..., or "custom"), size in mm, and what is printed on it, in paint order."""

    paper: str
    width_mm: float
    height_mm: float
    items: tuple
    title: str
    board_origin_mm: tuple  # page position of the board frame's origin (top-left outer ChArUco corner)
    mm_per_unit: float

    @property
    def orientation(self) -> str:
        return "landscape" if self.width_mm > self.height_mm else "portrait"

    def describe(self) -> str:
        name = self.paper.upper() if self.paper != "custom" else "custom"
        return f"{name} {self.orientation} ({_num(self.width_mm)} x {_num(self.height_mm)} mm)"


@dataclass(frozen=True)
class BlankArea:
    """The projector board's blank area: `width` to the right of the ChArUco squares, after `gap`, as
    tall as the squares (board units)."""

    width: float
    gap: float

    @classmethod
    def parse(cls, text: str, units: str) -> "BlankArea":
        """'WIDTH[:GAP]' in board units; GAP defaults to 20 mm in those units."""
        parts = str(text).strip().split(":")
        try:
            if len(parts) not in (1, 2):
                raise ValueError
            width = float(parts[0])
            gap = float(parts[1]) if len(parts) == 2 else 20.0 / MM_PER_UNIT[units]
        except (ValueError, KeyError):
            raise SpecError(f"blank area '{text}' does not parse; expected WIDTH[:GAP] in board units, e.g. "
                            "320:20") from None
        if not (np.isfinite(width) and np.isfinite(gap) and width > 0 and gap >= 0):
            raise SpecError(f"blank area '{text}': need WIDTH > 0 and GAP >= 0 (board units)")
        return cls(width, gap)


def spec_argument(spec: CharucoSpec) -> str:
    """The --board string that parses back to `spec` (with --units spec.units)."""
    return f"{spec.cols}x{spec.rows}:{spec.dictionary}:{_exact(spec.square_length)}:{_exact(spec.marker_length)}"


def _exact(v: float) -> str:
    """The shortest text that parses back to exactly `v` (50.0 -> '50')."""
    r = repr(float(v))
    return r[:-2] if r.endswith(".0") else r


def _num(v: float, digits: int = 6) -> str:
    return format(float(v), f".{digits}g")


# ---- the board ----------------------------------------------------------------------------------------
def board_rects(spec: CharucoSpec) -> list[tuple[float, float, float, float]]:
    """The black parts of the printed board as (x, y, w, h) in board units, in the board frame: the
    chessboard squares that hold no marker, and every marker's black cells (one rectangle per run of
    black cells in a row), from OpenCV's board of `spec` (the detector's)."""
    board = spec.cv_board()
    dictionary = board.getDictionary()
    n_cells = dictionary.markerSize + 2  # one border cell each side: the detector's markerBorderBits = 1
    s = spec.square_length
    occupied = set()
    rects = []
    for marker_id, corners in zip(board.getIds().ravel(), board.getObjPoints()):
        c = np.asarray(corners, float)[:, :2]
        x0, y0 = c[0]
        side = c[1, 0] - c[0, 0]
        if not (np.allclose(c[1], (x0 + side, y0)) and np.allclose(c[2], (x0 + side, y0 + side))
                and np.allclose(c[3], (x0, y0 + side))):
            raise SpecError(f"marker {marker_id} of {spec} is not an upright square in OpenCV's board")
        occupied.add((int((x0 + side / 2) // s), int((y0 + side / 2) // s)))
        cells = dictionary.generateImageMarker(int(marker_id), n_cells, borderBits=1) < 128  # True = black
        cell = side / n_cells
        for i, row in enumerate(cells):
            j = 0
            while j < n_cells:
                if row[j]:
                    k = j
                    while k < n_cells and row[k]:
                        k += 1
                    rects.append((x0 + j * cell, y0 + i * cell, (k - j) * cell, cell))
                    j = k
                else:
                    j += 1
    squares = [(c * s, r * s, s, s) for r in range(spec.rows) for c in range(spec.cols) if (c, r) not in occupied]
    if len(occupied) + len(squares) != spec.cols * spec.rows or len(occupied) != len(board.getIds()):
        raise SpecError(f"OpenCV's board for {spec} does not put one marker in each white square")
    return squares + rects


# ---- the sheet ----------------------------------------------------------------------------------------
def _wrap(text: str, size_mm: float, width_mm: float) -> list[str]:
    chars = max(20, int(width_mm / (size_mm * CHAR_WIDTH_EM)))
    return textwrap.wrap(text, chars)


def _annotation_lines(spec: CharucoSpec, blank: BlankArea | None, option: str) -> tuple[str, list[str]]:
    u = spec.units
    mm = MM_PER_UNIT[u]
    w, h = spec.size

    def length(v):  # in the board's unit, with millimetres alongside when the unit is not mm
        return f"{_num(v)} {u}" if u == LengthUnit.MM else f"{_num(v)} {u} ({_num(v * mm, 5)} mm)"

    spec_line = f"Board spec for the station: {option} {spec_argument(spec)} --units {u}"
    details = (f"{spec.cols} x {spec.rows} squares of {length(spec.square_length)}, "
               f"{spec.dictionary} ArUco markers of {length(spec.marker_length)}; "
               f"squares area {_num(w)} x {_num(h)} {u}")
    if blank is not None:
        details += (f"; blank area {_num(blank.width)} x {_num(h)} {u}, {_num(blank.gap)} {u} right of the "
                    "squares")
    details += ". Cut along the crop marks."
    check = (f"Print at 100% / actual size (no fit-to-page, no scaling). The black bar is exactly 10 cm "
             f"long: check it with a ruler, and measure a square with calipers. If a square is not "
             f"{length(spec.square_length)}, give the station the measured size (and the marker scaled "
             f"by the same factor).")
    return spec_line, [details, check]


def _annotation_height(spec_line: str, lines: list[str], text_width_mm: float, has_blank: bool) -> float:
    h = CROP_GAP_MM + CROP_LEN_MM + 2.0  # below the crop marks
    if has_blank:
        h += TEXT_FONT_MM * LINE_SPACING
    h += SCALE_BAR_HEIGHT_MM + TEXT_FONT_MM * LINE_SPACING + 1.5  # bar and its labels
    h += SPEC_FONT_MM * LINE_SPACING * len(_wrap(spec_line, SPEC_FONT_MM, text_width_mm))
    for line in lines:
        h += TEXT_FONT_MM * LINE_SPACING * len(_wrap(line, TEXT_FONT_MM, text_width_mm))
    return h


#: the largest page drawn: a bigger board is a length in the wrong unit, and its PNG would not fit in memory
MAX_SHEET_MM = 2000.0


def layout_sheet(spec: CharucoSpec, blank: BlankArea | None = None, paper: str = "auto",
                 option: str = "--board") -> Sheet:
    """The sheet of `spec` (with its blank area, if any) at true scale on `paper` (a4..a0, or auto: the
    smallest ISO sheet it fits, in either orientation; a page of its own size beyond A0). `option` is the
    station option the spec is written for (--board, or --mirror-board for the mirror step's board)."""
    if paper not in PAPER_CHOICES:
        raise SpecError(f"unknown paper '{paper}' (one of {', '.join(PAPER_CHOICES)})")
    mm = MM_PER_UNIT[spec.units]
    layout = BoardLayout(spec, blank.width if blank else 0.0, blank.gap if blank else 0.0)
    ox0, oy0, ox1, oy1 = (v * mm for v in layout.outline)
    crop = CROP_GAP_MM + CROP_LEN_MM
    board_w, board_h = ox1 - ox0 + 2 * crop, oy1 - oy0 + crop  # crop marks above, left and right
    spec_line, lines = _annotation_lines(spec, blank, option)

    def board_left(page_w):  # the outline's left edge on the page: the board is centred
        return round((page_w - board_w) / 2 + crop, 1)

    def notes_left(page_w):  # the scale bar and the notes: at the board's left, the bar's line 150 mm wide
        return max(PAGE_MARGIN_MM, min(board_left(page_w), round(page_w / 2 - 75.0, 1)))

    def need(page_w):  # (width, height) the content needs on a page of this width
        text_w = page_w - PAGE_MARGIN_MM - notes_left(page_w)
        return (max(board_w, 150.0) + 2 * PAGE_MARGIN_MM,
                board_h + _annotation_height(spec_line, lines, text_w, blank is not None) + 2 * PAGE_MARGIN_MM + 0.5)

    candidates = []  # (name, width, height) of the sheets it fits, smallest first
    landscape = board_w >= board_h
    for name, (short, long) in PAPERS.items():
        for w, h in (((long, short), (short, long)) if landscape else ((short, long), (long, short))):
            nw, nh = need(w)
            if nw <= w and nh <= h:
                candidates.append((name, w, h))
                break
    if paper == "auto":
        if candidates:
            name, page_w, page_h = candidates[0]
        else:
            name = "custom"
            page_w = float(np.ceil(need(board_w + 2 * PAGE_MARGIN_MM)[0]))
            page_h = float(np.ceil(need(page_w)[1]))
            if max(page_w, page_h) > MAX_SHEET_MM:
                raise SpecError(f"{option} {spec_argument(spec)} ({spec.units}) needs a page of {page_w:.0f} x "
                                f"{page_h:.0f} mm, larger than any printer's ({MAX_SHEET_MM:g} mm at most): check the "
                                "square length and --units")
    else:
        hit = [c for c in candidates if c[0] == paper]
        if not hit:
            smallest = candidates[0][0].upper() if candidates else "none up to A0 (use --paper auto)"
            nw, nh = need(PAPERS[paper][1])
            raise SpecError(f"the board with its margins and notes needs about {nw:.0f} x {nh:.0f} mm; it does not "
                            f"fit {paper.upper()} ({_num(PAPERS[paper][0])} x {_num(PAPERS[paper][1])} mm); "
                            f"the smallest sheet it fits: {smallest}")
        name, page_w, page_h = hit[0]

    # content block centred on the page: board (with its crop marks), then the notes below it
    nw, nh = need(page_w)
    left, notes_x = board_left(page_w), notes_left(page_w)
    top = round((page_h - (nh - 2 * PAGE_MARGIN_MM)) / 2 + crop, 1)
    gx, gy = left - ox0, top - oy0  # page position of the board frame's origin
    items = []

    black = [(gx + x * mm, gy + y * mm, w * mm, h * mm) for x, y, w, h in board_rects(spec)]
    items.append(Fill(tuple(black), 0.0))

    # crop marks at the outline's corners, outside it
    o = (left, top, left + (ox1 - ox0), top + (oy1 - oy0))
    marks = []
    t = CROP_WIDTH_MM
    for cx in (o[0], o[2]):
        for cy in (o[1], o[3]):
            sx = -1 if cx == o[0] else 1
            sy = -1 if cy == o[1] else 1
            hx = cx + sx * CROP_GAP_MM if sx > 0 else cx - CROP_GAP_MM - CROP_LEN_MM
            marks.append((hx, cy - t / 2, CROP_LEN_MM, t))
            vy = cy + sy * CROP_GAP_MM if sy > 0 else cy - CROP_GAP_MM - CROP_LEN_MM
            marks.append((cx - t / 2, vy, t, CROP_LEN_MM))
    items.append(Fill(tuple(marks), 0.45))

    # notes below the board
    y = o[3] + crop + 2.0
    if blank is not None:
        bx0, _, bx1, _ = layout.blank_rect
        y += TEXT_FONT_MM
        items.append(Text(gx + (bx0 + bx1) / 2 * mm, y, TEXT_FONT_MM,
                          "<--  blank area: the projected circle pattern lands here  -->", anchor="middle"))
        y += TEXT_FONT_MM * (LINE_SPACING - 1)
    bar_x = notes_x
    items.append(Fill(((bar_x, y, SCALE_BAR_MM, SCALE_BAR_HEIGHT_MM),), 0.0))
    notches = tuple((bar_x + k * 10.0 - NOTCH_WIDTH_MM / 2, y, NOTCH_WIDTH_MM, SCALE_BAR_HEIGHT_MM / 2)
                    for k in range(1, 10))
    items.append(Fill(notches, 1.0))
    y += SCALE_BAR_HEIGHT_MM + TEXT_FONT_MM + 0.5
    for k, label in ((0, "0"), (5, "5"), (10, "10 cm")):
        items.append(Text(bar_x + k * 10.0, y, TEXT_FONT_MM, label, anchor="start" if k == 0 else "middle"))
    items.append(Text(bar_x + SCALE_BAR_MM + 3.0, y - SCALE_BAR_HEIGHT_MM + 0.3, TEXT_FONT_MM,
                      "<-- 100 mm at true scale"))
    y += TEXT_FONT_MM * (LINE_SPACING - 1) + 1.0
    text_w = page_w - PAGE_MARGIN_MM - notes_x
    for line in _wrap(spec_line, SPEC_FONT_MM, text_w):
        y += SPEC_FONT_MM * LINE_SPACING
        items.append(Text(notes_x, y, SPEC_FONT_MM, line, bold=True))
    for para in lines:
        for line in _wrap(para, TEXT_FONT_MM, text_w):
            y += TEXT_FONT_MM * LINE_SPACING
            items.append(Text(notes_x, y, TEXT_FONT_MM, line))
    if y > page_h - PAGE_MARGIN_MM + 1e-6:
        raise SpecError(f"internal layout error: the notes end at {y:.1f} mm on a {page_h:g} mm page")

    title = f"ChArUco board {spec_argument(spec)} {spec.units}" + (
        f", blank area {_num(blank.width)}:{_num(blank.gap)} {spec.units}" if blank else "")
    return Sheet(name, float(page_w), float(page_h), tuple(items), title, (gx, gy), mm)
