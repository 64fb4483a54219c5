"""`procam board`: a printable board at true scale (PDF, SVG or PNG), or every file of assets/.

`procam board --board 8x6:DICT_5X5_50:44.3 --out board.pdf` draws the board the station's
`--board` option describes (the same CharucoSpec and OpenCV board the detector uses: app/board_sheet.py),
with a 10 cm scale bar, the spec to give the station, and crop marks. `--blank-area WIDTH[:GAP]` adds the
projector board's blank area, where the projected circle grid lands.

`procam board --assets DIR` writes the default boards and the projector patterns (assets/ in the
repository, byte for byte: tests/test_assets.py regenerates and compares).
"""

from __future__ import annotations

import sys
from pathlib import Path

from app.commands import _types
from calib.models.vocab import LengthUnit

#: squares outside this range (mm) are most likely a length given in the wrong unit
PLAUSIBLE_SQUARE_MM = (10.0, 500.0)


def size_warning(spec) -> str | None:
    """A warning naming the unit when a board's squares are implausibly small or large (a square of 4.43
    read as mm when cm was meant), else None."""
    from calib.models.boards import MM_PER_UNIT

    mm = spec.square_length * MM_PER_UNIT.get(spec.units, 1.0)
    lo, hi = PLAUSIBLE_SQUARE_MM
    if lo <= mm <= hi:
        return None
    w, h = spec.size
    alt = [u for u in LengthUnit if u != spec.units
           and lo <= spec.square_length * MM_PER_UNIT[u] <= hi]
    hint = f"; if the lengths are in {alt[0]}, add --units {alt[0]}" if alt else ""
    return (f"squares of {spec.square_length:g} {spec.units} make a board of {w:g} x {h:g} {spec.units}, "
            f"{'smaller' if mm < lo else 'larger'} than any calibration board ({lo:g}-{hi:g} mm squares){hint}")


NAME = "board"
HELP = "a printable board at true scale (PDF, SVG, PNG), or regenerate assets/"
DESCRIPTION = (
    "Draws the ChArUco board that --board describes (the station's spec) at true scale, with a 10 cm scale "
    "bar to check the printer did not rescale, the spec to give the station, and crop marks. Print at "
    "100% / actual size. --assets DIR writes the default boards and the 13 pattern images instead."
)

FORMATS = (".pdf", ".svg", ".png")
DEFAULT_DPI = 300.0
PATTERN_SIZES = ((1280, 720), (1920, 1080))  # the default projector resolutions


def add_arguments(p) -> None:
    p.add_argument("--board", metavar="SPEC", help="COLSxROWS:DICT:SQUARE[:MARKER], as given to the station, "
                   "e.g. 8x6:DICT_5X5_50:44.3 (squares of 44.3 mm; marker defaults to half the square)")
    p.add_argument("--units", default=LengthUnit.MM, help="unit of the board lengths: mm (default), cm, m, in")
    p.add_argument("--blank-area", metavar="WIDTH[:GAP]",
                   help="projector board: a blank area WIDTH wide, GAP (default 20 mm) right of the squares, "
                        "as tall as them (board units)")
    p.add_argument("--out", metavar="FILE", help="FILE.pdf, FILE.svg or FILE.png to write")
    p.add_argument("--dpi", type=_types.float_range(10.0, 2400.0), default=None,
                   help=f"PNG resolution (default {DEFAULT_DPI:g})")
    p.add_argument("--paper", default="auto", help="a4, a3, a2, a1, a0, or auto (default: the smallest "
                   "ISO sheet the board fits at true scale)")
    p.add_argument("--assets", metavar="DIR", help="write the default boards and the projector patterns "
                   "(the repository's assets/) into DIR")


def _blank_for(spec, text):
    from app.board_sheet import BlankArea

    return None if text is None else BlankArea.parse(text, spec.units)


def board_file(spec, blank, fmt: str, paper: str = "auto", dpi: float = DEFAULT_DPI,
               option: str = "--board") -> tuple[bytes, object]:
    """(file bytes, Sheet) of `spec` with `blank` (a BlankArea or None) as '.pdf', '.svg' or '.png'."""
    from app.board_sheet import layout_sheet
    from app.sheet_writers import sheet_pdf, sheet_png, sheet_svg

    sheet = layout_sheet(spec, blank, paper, option)
    if fmt == ".pdf":
        return sheet_pdf(sheet), sheet
    if fmt == ".svg":
        return sheet_svg(sheet).encode("utf-8"), sheet
    return sheet_png(sheet, dpi), sheet


def asset_files() -> dict[str, bytes]:
    """Every generated file of assets/ (relative path -> bytes), from the code's own defaults: the
    simulated rig's projector board with the blank area it renders, the same squares without it, the
    mirror board, and the default circle pattern at its 13 positions at each default projector size."""
    from app.board_sheet import BlankArea
    from app.sheet_writers import png_bytes
    from calib.models.pattern import PatternSpec
    from calib.synthetic import BoardLayout
    from drivers.projector_images import pattern_images
    from drivers.sim.scenarios import default_mirror_board, default_projector_board

    layout = BoardLayout(default_projector_board())
    blank = BlankArea(layout.blank_width, layout.gap)
    files = {
        "projector-board.pdf": board_file(layout.charuco, blank, ".pdf")[0],
        "projector-board-squares.pdf": board_file(layout.charuco, None, ".pdf")[0],
        "mirror-board.pdf": board_file(default_mirror_board(), None, ".pdf", option="--mirror-board")[0],
    }
    for w, h in PATTERN_SIZES:
        spec = PatternSpec.default_for(w, h)
        for k, img in enumerate(pattern_images(spec, (w, h))):
            files[f"patterns/{w}x{h}/position-{k + 1:02d}.png"] = png_bytes(img)
    return files


def _check_out(path: Path) -> None:
    from calib.errors import SpecError

    if path.is_dir():
        raise SpecError(f"--out {path} is a folder; give a file name such as {path / 'board.pdf'}")
    if path.suffix.lower() not in FORMATS:
        raise SpecError(f"--out {path}: the file name must end in {', '.join(FORMATS)} (it picks the format)")
    if not path.parent.is_dir():
        raise SpecError(f"--out {path}: folder {path.parent} does not exist")
    from app.commands._outputs import check_output_file  # never a session's file; a writable folder

    check_output_file(path)


def run(args) -> int:
    from calib.errors import SpecError
    from calib.formats.fileio import atomic_write_bytes
    from calib.models.boards import CharucoSpec

    if args.assets:
        if args.board or args.out or args.blank_area or args.dpi is not None:
            raise SpecError("--assets writes the default boards and patterns; give it alone (no --board, "
                            "--blank-area, --out, --dpi)")
        root = Path(args.assets)
        if root.exists() and not root.is_dir():
            raise SpecError(f"--assets {root} is a file, not a folder")
        from app.commands._outputs import check_output_folder

        check_output_folder(root, "--assets")
        files = asset_files()
        for rel, data in files.items():
            path = root / rel
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, data)
            except OSError as e:
                raise SpecError(f"cannot write {path}: {e.strerror or e}") from None
        print(f"wrote {len(files)} files into {root}")
        return 0

    if not args.board:
        raise SpecError("give the board: --board COLSxROWS:DICT:SQUARE[:MARKER] (e.g. 8x6:DICT_5X5_50:44.3), "
                        "or --assets DIR")
    if not args.out:
        raise SpecError("give the file to write: --out FILE.pdf (or .svg, .png)")
    out = Path(args.out)
    _check_out(out)
    fmt = out.suffix.lower()
    if args.dpi is not None and fmt != ".png":
        raise SpecError(f"--dpi applies to PNG output only; {fmt[1:].upper()} is vector (true size at any zoom)")
    try:
        spec = CharucoSpec.parse(args.board, args.units)
    except SpecError as e:  # the spec's own bounds: say which option holds it
        raise SpecError(f"--board {args.board} (--units {args.units}): {e}") from None
    blank = _blank_for(spec, args.blank_area)
    data, sheet = board_file(spec, blank, fmt, args.paper.lower(), DEFAULT_DPI if args.dpi is None else args.dpi)
    warning = size_warning(spec)  # after the layout: a board too large to draw is an error alone
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    try:
        atomic_write_bytes(out, data)
    except OSError as e:
        raise SpecError(f"cannot write {out}: {e.strerror or e}") from None
    print(f"wrote {out}: {sheet.title}, on {sheet.describe()}; print at 100% / actual size")
    return 0
