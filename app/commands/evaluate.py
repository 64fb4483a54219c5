"""`procam evaluate RESULT GROUND_TRUTH`: the paper's metrics of a calibration against ground truth."""

from __future__ import annotations

import json

from calib.formats import session_files

NAME = "evaluate"
HELP = "compare a calibration.json with ground truth (the paper's metrics)"
DESCRIPTION = (
    "Prints the metrics of Vanherck et al. (Sect. 5.2): CamK/ProjK (Frobenius norm of the K difference, px), "
    "CamD/ProjD (norm of the distortion difference), Distance and Angle of the camera-projector pose, the "
    "mirror's normal angle and offset difference, and the RMS values the result carries. GROUND_TRUTH is a "
    "file in the calibration.json schema (e.g. written by `procam simulate`)."
)


def add_arguments(p) -> None:
    p.add_argument("result", metavar="RESULT", help="calibration.json to evaluate")
    p.add_argument("ground_truth", metavar="GROUND_TRUTH", help="ground truth in the calibration.json schema")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON")


#: the method name of a ground truth (calib.synthetic, the simulator's ground_truth.json)
GROUND_TRUTH_METHOD = "ground-truth"


def _check_file(path: str, what: str, example: str) -> None:
    from pathlib import Path

    from calib.errors import SessionError

    p = Path(path)
    if p.is_dir():
        hint = p / example
        more = f": give {hint}" if hint.is_file() else f" (give a file such as {hint})"
        raise SessionError(f"{what} {path} is a folder, not a file{more}")
    if not p.exists():
        raise SessionError(f"{what} {path} does not exist")


def run(args) -> int:
    from calib.errors import FormatError, SessionError
    from calib.models.result import CalibrationResult
    from calib.quality.metrics import compare

    _check_file(args.result, "RESULT", session_files.CALIBRATION)
    _check_file(args.ground_truth, "GROUND_TRUTH", session_files.GROUND_TRUTH)
    result = CalibrationResult.load_json(args.result)
    truth = CalibrationResult.load_json(args.ground_truth)
    if result.method == GROUND_TRUTH_METHOD and truth.method != GROUND_TRUTH_METHOD:
        raise SessionError(f"the arguments are swapped: {args.result} is a ground truth and {args.ground_truth} a "
                           f"{truth.method} calibration; run procam evaluate {args.ground_truth} {args.result}")
    if result.units != truth.units:
        raise FormatError(args.ground_truth, "units",
                          f"is '{truth.units}' but the result is in '{result.units}'; compare like with like")
    m = compare(result, truth)
    if args.json:
        print(json.dumps(m.to_dict(), indent=2))
    else:
        print(f"{args.result} vs {args.ground_truth} (method {result.method}, units {result.units})")
        if truth.method != GROUND_TRUTH_METHOD:
            print(f"note: GROUND_TRUTH {args.ground_truth} is a '{truth.method}' result, not a ground truth: "
                  f"the numbers are differences between two calibrations")
        print(m.format_table())
    return 0
