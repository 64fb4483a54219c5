"""`procam export SESSION|calibration.json --format NAME[,NAME]|all --out DIR`: a calibration in the
files other software loads (calib.export; docs/FORMATS.md, "Exports")."""

from __future__ import annotations

import sys
from pathlib import Path

from calib.formats import session_files

NAME = "export"
HELP = "write a calibration for other software: opencv, ros, mrcal, opengl, unity, threejs"
DESCRIPTION = (
    "Writes a trusted calibration (SESSION/calibration.json or a calibration.json given) in the formats asked "
    "for: opencv (FileStorage YAML), ros (camera_info YAML per device), mrcal (.cameramodel per device), "
    "opengl (projection and view matrices), unity and threejs (virtual cameras with lens shift and pose in "
    "the engine's axes). A distortion a format cannot represent is left out with a warning giving its "
    "residual in px (also stated in the file). docs/FORMATS.md describes each file and how to load it."
)


def add_arguments(p) -> None:
    from calib.export.registry import EXPORTERS

    p.add_argument("source", metavar="SESSION|calibration.json",
                   help="a calibrated session folder (its calibration.json) or a calibration.json")
    p.add_argument("--format", required=True, metavar="NAME[,NAME]|all",
                   help="; ".join(f"{n}: {e.summary}" for n, e in EXPORTERS.items()) + "; all: every one")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="folder to write into (created if needed); files are named after the calibration "
                        "file (calibration-projector.ros.yaml, calibration-opengl.json, ...)")
    p.add_argument("--near", type=float, default=0.1, help="opengl, unity, threejs: near clipping plane, metres "
                                                           "(default %(default)s)")
    p.add_argument("--far", type=float, default=100.0, help="opengl, unity, threejs: far clipping plane, metres "
                                                            "(default %(default)s)")


def calibration_file(source) -> Path:
    """SOURCE itself, or SOURCE/calibration.json for a folder; a SessionError when there is none."""
    from calib.errors import SessionError

    p = Path(source)
    if p.is_dir():
        if not (p / session_files.CALIBRATION).is_file():
            raise SessionError(f"no calibration.json in {p}: calibrate it first (procam calibrate {p}) or give "
                               f"the calibration file")
        return p / session_files.CALIBRATION
    if not p.is_file():
        raise SessionError(f"{p} does not exist: give a calibrated session folder or a calibration.json")
    return p


def load_trusted(path: Path):
    """The calibration in `path`; an ExportError when the trust check rejects it."""
    from calib.errors import ExportError
    from calib.export.registry import trust_reasons
    from calib.models.result import CalibrationResult

    result = CalibrationResult.load_json(path)
    reasons = trust_reasons(result)
    if reasons:
        raise ExportError(f"{path}: the trust check rejects this calibration ({'; '.join(reasons)}); nothing was "
                          f"written: calibrate again (docs/CALIBRATION.md, \"Trust check\")")
    return result


def run(args) -> int:
    from calib.errors import SessionError
    from calib.export.common import ExportOptions
    from calib.export.registry import output_paths, parse_formats, write_exports

    from app.commands._outputs import check_output_file, write_error

    names = parse_formats(args.format)
    options = ExportOptions(args.near, args.far)
    path = calibration_file(args.source)
    result = load_trusted(path)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise SessionError(f"--out {out} is a file; give a folder to write the exports into")
    paths = output_paths(names, out, path.stem)
    for p in paths:
        check_output_file(p, "--out", inputs=[path])
    try:
        out.mkdir(parents=True, exist_ok=True)
        warnings = write_exports(result, names, out, path.stem, options)
    except OSError as e:
        raise write_error(e.filename or out, e) from None
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    print("\n".join(f"wrote {p}" for p in paths))
    return 0
