"""`procam import-procamcalib RECORDING PATTERNS --board SPEC [--mirror DIR --mirror-board SPEC]
[--units cm] --out SESSION`: convert a recording of the reference implementation into a session."""

from __future__ import annotations

import sys

from app.commands import _types
from calib.models.vocab import LengthUnit, View, choices

NAME = "import-procamcalib"
HELP = "convert a recording made with EDM-Research/ProcamCalib into a session folder"
DESCRIPTION = (
    "Converts a ProcamCalib recording into a procam session (session.json + images). RECORDING: folder of "
    "numbered PNGs (0.png, 1.png, ...; name starting with 'S' = seen through the mirror). PATTERNS: folder "
    "<Name>_<cols>_<rows> of the projector images (01.png ... 13.png, white asymmetric circles on black); "
    "consecutive recording images share a pattern. --mirror: folder of mirror-calibration images (name "
    "starting with 'M' = real-virtual, 'F' = real-mirror). Then run `procam calibrate SESSION`."
)


def add_arguments(p) -> None:
    p.add_argument("recording", metavar="RECORDING", help="recording folder of numbered PNGs (S... = mirrored)")
    p.add_argument("patterns", metavar="PATTERNS", help="patterns folder named <Name>_<cols>_<rows>, e.g. Asym_4_9")
    p.add_argument("--board", required=True, metavar="SPEC",
                   help="board of the projector step: COLSxROWS:DICT:SQUARE[:MARKER], e.g. 8x6:DICT_5X5_50:4.43 with --units cm "
                        "(marker defaults to half the square)")
    p.add_argument("--mirror", metavar="DIR", help="mirror-calibration folder (M... real-virtual, F... real-mirror)")
    p.add_argument("--mirror-board", metavar="SPEC", help="board of the mirror step (default: --board)")
    p.add_argument("--board-thickness", type=_types.float_range(0.0, 1000.0), default=0.0, metavar="T",
                   help="real-mirror: printed face above the mirror surface, in --units (default %(default)s)")
    p.add_argument("--units", default=LengthUnit.MM, choices=choices(LengthUnit),
                   help="length unit of the square/marker lengths (default mm)")
    p.add_argument("--out", required=True, metavar="SESSION", help="session folder to create (new or empty)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress output (default: a bar on a terminal, a line at start and end otherwise)")


def run(args) -> int:
    from calib.errors import SpecError
    from calib.formats.procamcalib import import_procamcalib
    from calib.models.boards import CharucoSpec

    board = CharucoSpec.parse(args.board, units=args.units)
    mboard = CharucoSpec.parse(args.mirror_board, units=args.units) if args.mirror_board else None
    if mboard is not None and not args.mirror:
        raise SpecError("--mirror-board needs --mirror DIR (the mirror-calibration images)")
    if args.board_thickness < 0:
        raise SpecError("--board-thickness must be >= 0")
    from app.commands._outputs import check_output_folder
    from app.commands._progress import Progress, progress_mode

    check_output_folder(args.out, inputs=[args.recording, args.patterns, args.mirror])
    bars = Progress(progress_mode(args.no_progress))
    tick = bars.callback("import", unit="images")

    def progress(done, total, name):
        tick(done, total, name)

    try:
        store = import_procamcalib(args.recording, args.patterns, board, args.out, args.mirror, mboard,
                                   args.board_thickness, progress)
    finally:
        bars.close()
    m = store.manifest
    n_proj = len(m.captures_of("projector"))
    n_mirror = len(m.captures) - n_proj
    print(f"wrote {args.out}: {n_proj} projector images ({m.pattern.positions} patterns x "
          f"{n_proj // max(m.pattern.positions, 1)}), {n_mirror} mirror images "
          f"({m.mirror_method or 'none'}); camera {m.rig.camera_size[0]}x{m.rig.camera_size[1]}, projector "
          f"{m.rig.projector_size[0]}x{m.rig.projector_size[1]}, view {m.rig.view}; pattern {m.pattern.cols}x"
          f"{m.pattern.rows} circles, spacing {m.pattern.spacing_px:.1f} px, radius {m.pattern.radius_px:.1f} px")
    if m.rig.view == View.MIRROR and not m.mirror_method:
        print("note: the recording is mirrored (S...) but no --mirror images were given; calibration needs them",
              file=sys.stderr)
    return 0
