"""`procam recalibrate PREVIOUS`: check an installed rig against its calibration, re-measure only what
moved, compare with before (docs/RECALIBRATION.md)."""

from __future__ import annotations

import time
from pathlib import Path

from app.commands._rig_options import add_sim_bump_option, add_sim_latency_option

NAME = "recalibrate"
HELP = "on-site recalibration: check what moved since PREVIOUS, re-measure only that, compare"
DESCRIPTION = (
    "PREVIOUS is a session folder holding calibration.json, or a calibration.json. A few captures check "
    "the camera intrinsics, the mirror and the projector pose against it (thresholds from its own "
    "1-sigma); what moved is re-estimated with the rest held, capturing until its 1-sigma reaches the "
    "previous calibration's. DIR becomes a session folder with previous/calibration.json (the archive), "
    "calibration.json, recalibration.json (verdicts, changes with their uncertainty, the previous file's "
    "sha256) and, on the simulated rig, ground_truth.json. Exit status 1 when the check is incomplete or "
    "the targets were not reached."
)


def add_arguments(p) -> None:
    p.add_argument("previous", metavar="PREVIOUS", help="session folder holding calibration.json, or a calibration.json")
    p.add_argument("--out", metavar="DIR", required=True, help="new session folder")
    p.add_argument("--rig", choices=("sim", "sim-realsense", "realsense"), default=None,
                   help="rig to use (default: realsense when one is connected, else sim)")
    p.add_argument("--auto", action="store_true", help="on the simulated rig the simulated operator moves the board")
    p.add_argument("--scenario", default=None, help="simulated rig scenario (default nonoverlap-136)")
    p.add_argument("--seed", type=int, default=None, help="simulated rig seed (default 0)")
    p.add_argument("--quality", default=None, help="simulated rendering quality (default live)")
    add_sim_latency_option(p)
    add_sim_bump_option(p)
    p.add_argument("--max-captures", type=int, default=None, metavar="N",
                   help="give up (exit 1) when the re-estimate needs more than N captures in all (default 24)")
    p.add_argument("--workers", type=int, default=2, help="detection threads (default 2)")


def run(args) -> int:
    from app.commands.session import rig_options
    from app.recalibration import (
        DEFAULT_MAX_CAPTURES, RecalibrationMachine, RecalibrationStation, find_previous,
    )
    from app.station.machine import Plan
    from app.station.setup import DEFAULT_SCENARIO, RigRequest, create_session, default_rig_kind, open_rig, run_on_rig
    from app.station.station import StationOptions
    from calib.errors import SessionError
    from drivers.factory import is_simulated

    t0 = time.monotonic()

    def log(text):
        print(f"[{time.monotonic() - t0:6.1f} s] {text}", flush=True)

    find_previous(args.previous)  # a clear error before any device is opened
    folder = Path(args.out)
    if folder.exists() and any(folder.iterdir()):
        raise SessionError(f"{folder} is not empty: a recalibration needs a new session folder")
    kind = args.rig or default_rig_kind()
    if not is_simulated(kind):
        raise SessionError("the headless recalibration runs on the simulated rig for now (--rig sim); on the "
                           "real rig it needs the board specs and a person's prompts, not written yet")
    if not args.auto:
        raise SessionError("the simulated rig has nobody to move the board: add --auto")
    max_caps = args.max_captures or DEFAULT_MAX_CAPTURES
    if max_caps < 4:
        raise SessionError(f"--max-captures must be at least 4 (the check's captures), got {max_caps}")
    req = RigRequest(kind, args.scenario or DEFAULT_SCENARIO, args.seed or 0, args.quality or "live")
    rig = open_rig(req, **rig_options(args, kind))
    outcome = None
    try:
        plan = Plan(min_real_virtual=1, min_projector_captures=1)
        store = create_session(folder, rig, req, plan)
        machine = RecalibrationMachine(store, plan)
        machine._persist()
        station = RecalibrationStation(rig, machine, StationOptions(auto=True, follow_operator=True), log=log)
        machine.on_event = lambda text: None if text.startswith("captured") else log(text)

        def work():
            nonlocal outcome
            from app.recalibration import run_recalibration

            from app.recalibration import rig_verify_fn

            outcome = run_recalibration(args.previous, station, machine, log=log, max_captures=max_caps,
                                        workers=args.workers, verify=rig_verify_fn(rig, folder))

        run_on_rig(rig, work)
    finally:
        close = getattr(rig, "close", None)
        if callable(close):
            close()
    print(summary(outcome.record, folder, time.monotonic() - t0), flush=True)
    if not outcome.ok:
        return 1
    import sys

    from app.commands._quality import EXIT_LOW_QUALITY, report_low_quality
    from calib.trust import check_calibration

    res = outcome.result  # the quality gate of the calibration written (computed where the file has none)
    if not isinstance((res.diagnostics or {}).get("trust"), dict):
        res = res.with_(diagnostics=dict(res.diagnostics or {}, trust=check_calibration(res).to_dict()))
    return EXIT_LOW_QUALITY if report_low_quality(res, file=sys.stdout) else 0


def summary(rec: dict, folder, elapsed_s: float) -> str:
    from app.recalibration import comparison_lines
    from app.station.setup import load_ground_truth

    lines = [f"recalibration {folder}: {rec['message']} ({'ok' if rec['ok'] else 'FAILED'}) after {elapsed_s:.1f} s"]
    lines += [f"  check {p}: {c['status']}" for p, c in rec["check"]["parts"].items()]
    lines += [f"  {line}" for line in comparison_lines(rec)]
    gt = load_ground_truth(folder)
    cal = Path(folder) / "calibration.json"
    if gt is not None and cal.exists():
        from calib.metrics import compare
        from calib.result import CalibrationResult

        mt = compare(CalibrationResult.load_json(cal), gt)
        lines.append(f"  vs ground truth: distance {mt.distance:.3f} {mt.units}, angle {mt.angle_deg:.4f} deg, CamK "
                     f"{mt.cam_k_px:.2f} px" + (f", mirror {mt.mirror_angle_deg:.4f} deg" if mt.mirror_angle_deg
                                                 is not None else ""))
    return "\n".join(lines)
