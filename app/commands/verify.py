"""`procam verify SESSION --rig sim|realsense`: the automatic epipolar check of SESSION/calibration.json.

Exit codes (scripts rely on them): 0 the calibration passes, 1 it fails the check (or too few pixels
could be measured), 2 the check could not run (missing files, devices, bad arguments).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

NAME = "verify"
HELP = "measure a session's calibration on the rig: epipolar curves drawn by the projector vs picked camera pixels"
DESCRIPTION = (
    "Runs the automatic epipolar check (docs/VERIFICATION.md) with SESSION/calibration.json: for a grid of camera "
    "pixels over the board, the projector draws each pixel's epipolar curve, the camera finds the drawn curve, "
    "and the distance from the pixel to it is measured. Prints the mean and worst distance and the verdict, "
    "writes SESSION/verification.json, and exits with 0 (pass), 1 (fail) or 2 (could not run). On --rig sim "
    "the simulated rig of the session's scenario is used (the session must come from `procam simulate` or a "
    "simulated station session, or give --scenario)."
)


def _grid(text: str) -> tuple[int, int]:
    try:
        c, r = text.lower().split("x")
        g = (int(c), int(r))
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must be COLSxROWS, e.g. 4x3, got '{text}'") from None
    if g[0] < 1 or g[1] < 1 or g[0] * g[1] > 400:
        raise argparse.ArgumentTypeError(f"grid must be between 1x1 and 400 pixels in all, got '{text}'")
    return g


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got '{text}'") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got '{text}'")
    return v


def add_arguments(p) -> None:
    from app.verification import DEFAULT_GRID, DEFAULT_THRESHOLD_PX

    p.add_argument("session", metavar="SESSION", help="session folder (with session.json and calibration.json)")
    p.add_argument("--rig", choices=("sim", "realsense"), required=True, help="the rig to measure on")
    p.add_argument("--threshold", type=_positive, default=DEFAULT_THRESHOLD_PX, metavar="PX",
                   help=f"verdict threshold on the mean distance, projector pixels (default {DEFAULT_THRESHOLD_PX:g}; "
                        "the worst pixel may reach twice it)")
    p.add_argument("--grid", type=_grid, default=DEFAULT_GRID, metavar="CxR",
                   help=f"pixels to check, columns x rows over the lit board (default {DEFAULT_GRID[0]}x{DEFAULT_GRID[1]})")
    p.add_argument("--calibration", metavar="FILE", default=None,
                   help="calibration to verify (default SESSION/calibration.json)")
    p.add_argument("--out", metavar="FILE", default=None, help="report file (default SESSION/verification.json)")
    p.add_argument("--average", type=int, default=1, metavar="N", help="camera frames averaged per image (default 1)")
    sim = p.add_argument_group("--rig sim")
    sim.add_argument("--scenario", default=None, help="scenario (default: the one the session was simulated with)")
    sim.add_argument("--seed", type=int, default=None, help="scenario seed (default: the session's)")
    sim.add_argument("--quality", choices=("live", "session"), default="live",
                     help="render quality of the simulated camera (default live: 1 sample per pixel)")
    hw = p.add_argument_group("--rig realsense")
    hw.add_argument("--serial", default=None, help="RealSense serial number (default: the first camera)")
    hw.add_argument("--screen", type=int, default=None, metavar="N", help="projector screen (default: the last)")
    hw.add_argument("--settle", type=float, default=0.1, metavar="S",
                    help="projector settle time in seconds (see `procam devices --settle`; default 0.1)")
    hw.add_argument("--delay", type=float, default=3.0, metavar="S",
                    help="seconds between the instruction to hold the board and the measurement (default 3)")


def _sim_options(manifest, args) -> dict:
    """open_sim_rig options matching the session's simulated scenario (or the arguments)."""
    from calib.errors import SessionError
    from drivers.sim.render import RenderSettings

    settings = dict(manifest.rig.camera_settings or {})
    state = dict(manifest.state or {})
    scenario = args.scenario or settings.get("scenario") or state.get("scenario")
    seed = args.seed if args.seed is not None else settings.get("seed", state.get("seed", 0))
    if not scenario:
        raise SessionError("this session was not recorded on the simulated rig, so its scenario is unknown; "
                           "give --scenario NAME (see `procam simulate --list`) or use --rig realsense")
    render = {k: v for k, v in settings.items()
              if k in RenderSettings.__dataclass_fields__ and k != "supersample" and not isinstance(v, (dict, list))}
    return {"scenario": scenario, "seed": int(seed), "quality": args.quality, **render}


def run(args) -> int:
    from app.verification import verify
    from calib.errors import SessionError
    from calib.result import CalibrationResult
    from calib.session import SessionStore

    folder = Path(args.session)
    store = SessionStore.open(folder)
    man = store.manifest
    cal_path = Path(args.calibration) if args.calibration else folder / "calibration.json"
    if not cal_path.exists():
        raise SessionError(f"{cal_path} does not exist: run `procam calibrate {folder}` first")
    result = CalibrationResult.load_json(cal_path)
    if tuple(result.camera.size) != tuple(man.rig.camera_size) or \
            tuple(result.projector.size) != tuple(man.rig.projector_size):
        raise SessionError(f"{cal_path} is for a {result.camera.width}x{result.camera.height} camera and a "
                           f"{result.projector.width}x{result.projector.height} projector, the session's rig differs")
    if args.average < 1:
        raise SessionError("--average must be >= 1")
    out = Path(args.out) if args.out else folder / "verification.json"
    if out.resolve() != (folder / "verification.json").resolve():  # never a session's file (app/commands/_outputs.py)
        from app.commands._outputs import check_output_file

        check_output_file(out, "--out", inputs=[cal_path])
    info = {"path": str(cal_path), "method": result.method, "units": result.units}

    def progress(done, total, label):
        if done < total:
            print(f"  [{done + 1}/{total}] {label}", file=sys.stderr, flush=True)

    def check(rig, settle_frames):
        rig.camera.start()
        try:
            instruction = rig.operator.request_pose("verification", None, 0)
            print(instruction, file=sys.stderr, flush=True)
            if args.rig == "realsense" and args.delay > 0:
                time.sleep(args.delay)
            # the operator has been asked already: pass None so verify does not ask again
            # the session's board, found in the white frame, adds the predicted curves to the report
            return verify(rig.camera, rig.projector, None, result, grid=args.grid, threshold_px=args.threshold,
                          progress=progress, board=man.projector_board, settle_frames=settle_frames,
                          average=args.average, calibration_info=info)
        finally:
            rig.camera.stop()

    if args.rig == "sim":
        from drivers.factory import open_rig

        rig = open_rig("sim", **_sim_options(man, args))
        report = check(rig, settle_frames=1)
    else:
        from drivers.factory import open_rig
        from drivers.projector_window import run_projector_loop

        rig = open_rig("realsense", serial=args.serial, projector_screen=args.screen, settle_s=args.settle,
                       projector_size=tuple(man.rig.projector_size))
        try:
            report = run_projector_loop(rig.projector, lambda: check(rig, settle_frames=2))
        finally:
            rig.close()
    report.save_json(out)
    for c in report.checks:
        print(f"  {c.label()}")
    print(report.summary())
    print(f"wrote {out}", file=sys.stderr)
    return 0 if report.passed else 1
