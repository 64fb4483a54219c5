"""`procam recalibrate PREVIOUS`: check an installed rig against its calibration, re-measure only what
moved, compare with before (docs/RECALIBRATION.md)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from app.commands import _types
from app.commands._rig_options import (
    add_board_options, add_device_options, add_rig_choice, add_sim_rig_options, add_workers_option,
)
from calib.formats import session_files
from calib.models.vocab import RenderQuality

NAME = "recalibrate"
HELP = "on-site recalibration: check what moved since PREVIOUS, re-measure only that, compare"
DESCRIPTION = (
    "PREVIOUS is a session folder holding calibration.json, or a calibration.json. A few captures check "
    "the camera intrinsics, the mirror and the projector pose against it (thresholds from its own "
    "1-sigma); what moved is re-estimated with the rest held, capturing until its 1-sigma reaches the "
    "previous calibration's. DIR becomes a session folder with previous/calibration.json (the archive), "
    "calibration.json, recalibration.json (verdicts, changes with their uncertainty, the previous file's "
    "sha256) and, on the simulated rig, ground_truth.json. The boards are PREVIOUS's (its session.json; "
    "--board for a calibration.json alone). Without --auto the technician is told each capture's step and "
    "presses Enter. Exit status 1 when the check is incomplete or the targets were not reached; 4 when the "
    "input closed part-way (130 after Ctrl-C): the folder continues with --resume."
)


def add_arguments(p) -> None:
    p.add_argument("previous", metavar="PREVIOUS", help="session folder holding calibration.json, or a calibration.json")
    p.add_argument("--out", metavar="DIR", required=True, help="new session folder (with --resume: the stopped one)")
    p.add_argument("--resume", action="store_true",
                   help="continue the recalibration in DIR where it stopped (Ctrl-C, closed input, crash): its "
                        "captures are kept; PREVIOUS must be the calibration it started from")
    add_rig_choice(p, previous=True)
    p.add_argument("--auto", action="store_true",
                   help="simulated rig: the simulated operator moves the board with no prompts (without it the "
                        "command tells the technician each step and waits for Enter)")
    p.add_argument("--max-captures", type=_types.int_range(4, 1000), default=None, metavar="N",
                   help="give up (exit 1) when the re-estimate needs more than N captures in all (default 24)")
    add_workers_option(p)
    add_sim_rig_options(p, previous=True)
    add_device_options(p)
    add_board_options(p, previous=True)


#: exit status of a recalibration stopped part-way by a closed input (Ctrl-C: 130); the folder is resumable
EXIT_STOPPED = 4


def run(args) -> int:
    t0 = time.monotonic()

    def log(text):  # the station's lines quote capture ids and detection reasons read from files
        from app.cli import terminal_safe

        print(terminal_safe(f"[{time.monotonic() - t0:6.1f} s] {text}"), flush=True)

    folder = Path(args.out)
    outcome = run_live(args, log)
    if isinstance(outcome, int):  # stopped part-way: resumable
        return outcome
    print(summary(outcome.record, folder, time.monotonic() - t0), flush=True)
    if not outcome.ok:
        return 1
    import sys

    from app.commands._quality import EXIT_LOW_QUALITY, report_low_quality
    from calib.quality.trust import check_calibration

    res = outcome.result  # the quality gate of the calibration written (computed where the file has none)
    if not isinstance((res.diagnostics or {}).get("trust"), dict):
        res = res.with_(diagnostics=dict(res.diagnostics or {}, trust=check_calibration(res).to_dict()))
    return EXIT_LOW_QUALITY if report_low_quality(res, file=sys.stdout) else 0


def run_live(args, log):
    """Open (or resume) the recalibration's session and run its flow on the rig: the Outcome, or the
    exit status of a recalibration stopped part-way (the command's message says how to resume)."""
    from app.recalibration import RecalibrationStopped, run_recalibration

    from app.recalibration import rig_verify_fn

    ready = prepare(args, log)
    rig = ready.open_rig()
    try:
        store, machine, station = open_recalibration(args, ready, rig, log)
        prompt = None if (args.auto and ready.simulated) else terminal_prompt

        def work():
            return run_recalibration(ready.src, station, machine, log=log, max_captures=ready.max_captures,
                                     workers=args.workers, verify=rig_verify_fn(rig, store.folder), prompt=prompt,
                                     resume=args.resume)

        from app.station.setup import run_on_rig as on_rig

        try:
            return on_rig(rig, work)
        except (RecalibrationStopped, KeyboardInterrupt) as e:
            stopped = isinstance(e, RecalibrationStopped)
            if stopped:  # the last capture's background detection, so detections.json is complete
                station.wait_for_detections(5.0)
            n = len(store.manifest.captures)
            print(f"recalibration stopped{': ' + str(e) if stopped else ' (Ctrl-C)'}; {n} captures kept in "
                  f"{store.folder}. Continue it with: procam recalibrate {args.previous} --out {store.folder} "
                  "--resume", flush=True)
            return EXIT_STOPPED if stopped else 130
    finally:
        close = getattr(rig, "close", None)
        if callable(close):
            close()


def terminal_prompt(text: str) -> None:
    """The technician's prompt on the terminal: what to do, then wait for Enter. A closed input stops the
    recalibration (RecalibrationStopped; the folder is resumable); Ctrl-C stops it too."""
    import sys

    from app.recalibration import RecalibrationStopped

    print(f"\n>>> {text}\n    Press Enter when the board is in place (Ctrl-C stops; --resume continues).", flush=True)
    if sys.stdin is None or not sys.stdin.readline():
        raise RecalibrationStopped("the input closed while waiting for the board")


@dataclass(frozen=True)
class Prepared:
    """What `prepare` checked before any device is opened, and how to open the rig."""

    kind: str  # the rig kind (RigKind's value)
    src: Path  # PREVIOUS's calibration.json
    previous: object  # its CalibrationResult
    specs: object  # PREVIOUS's boards (app.recalibration.previous_board_specs), None on resume
    req: object  # the RigRequest
    simulated: bool
    max_captures: int
    rig_options: dict  # drivers.factory.open_rig's device options

    def open_rig(self):
        from app.station.setup import open_requested_rig

        return open_requested_rig(self.req, **self.rig_options)


def prepare(args, log) -> Prepared:
    """Everything checked before a device is opened: PREVIOUS, the folder (new, or the stopped
    recalibration to resume, with the same PREVIOUS), the boards of PREVIOUS and the rig to open."""
    from app.commands.session import rig_options
    from app.recalibration import DEFAULT_MAX_CAPTURES, check_resumed_previous, load_previous, previous_board_specs
    from app.station.setup import DEFAULT_SCENARIO, RigRequest, resume_request
    from calib.errors import SessionError
    from drivers.factory import default_rig_kind, is_simulated

    src, previous = load_previous(args.previous)  # a clear error before any device is opened
    folder = Path(args.out)
    if args.resume:
        from app.recalibration import RECALIBRATION_FILE

        if not (folder / session_files.MANIFEST).is_file():
            raise SessionError(f"{folder} holds no session to resume (no session.json): start the recalibration "
                               "without --resume")
        if (folder / RECALIBRATION_FILE).exists():
            raise SessionError(f"the recalibration in {folder} is finished ({RECALIBRATION_FILE}): nothing to resume")
        check_resumed_previous(src, folder)
        req = resume_request(folder, kind=args.rig, scenario=args.scenario, seed=args.seed, quality=args.quality)
        kind = req.kind
        if is_simulated(kind) and args.sim_bump is None:  # the same simulated world as before the stop
            from calib.formats.session import SessionStore

            args.sim_bump = (SessionStore.open(folder).manifest.rig.camera_settings or {}).get("bump")
    elif folder.exists() and any(folder.iterdir()):
        raise SessionError(f"{folder} is not empty: a recalibration needs a new session folder (or --resume to "
                           "continue a stopped one)")
    else:
        from app.commands._outputs import check_output_folder

        check_output_folder(folder, "--out", inputs=[args.previous])  # never inside a session, PREVIOUS's or another's
        kind = args.rig or default_rig_kind()
    simulated = is_simulated(kind)
    max_caps = args.max_captures or DEFAULT_MAX_CAPTURES  # at least 4 (the check's captures): --max-captures' type
    specs = None
    if not args.resume:
        specs = previous_board_specs(args.previous, previous, args.board, args.mirror_board, args.units, simulated)
        if specs is not None:
            log(f"boards of PREVIOUS: {specs.describe()}")
        rr = (specs.rig_request if specs is not None else None) or {}
        from_prev = simulated and is_simulated(rr.get("kind"))
        req = RigRequest(kind, args.scenario or (rr.get("scenario") if from_prev else None) or DEFAULT_SCENARIO,
                         args.seed if args.seed is not None else (rr.get("seed") if from_prev else None) or 0,
                         args.quality or RenderQuality.LIVE)
    return Prepared(kind, src, previous, specs, req, simulated, max_caps, rig_options(args, kind))


def open_recalibration(args, ready: Prepared, rig, log):
    """(store, machine, station) of the recalibration on the opened rig: a new session folder with
    PREVIOUS's boards, or the stopped one (its captures kept), after checking the rig is PREVIOUS's."""
    from app.recalibration import (
        RECALIBRATION_PLAN, RecalibrationMachine, RecalibrationStation, check_rig_matches, is_structured_pattern,
    )
    from calib.models.vocab import PatternKind
    from app.station.setup import check_same_rig, create_session
    from app.station.station import StationOptions
    from calib.formats.session import SessionStore

    req = ready.req
    check_rig_matches(ready.previous, ready.specs, rig, req.scenario)
    plan = RECALIBRATION_PLAN
    folder = Path(args.out)
    if args.resume:
        store = SessionStore.open(folder, lock=True)  # one process per session folder: refused while in use
        check_same_rig(store, rig)
        machine = RecalibrationMachine.from_store(store, plan)
        c = machine.counts()
        log(f"resuming the recalibration in {folder}: {len(store.manifest.captures)} captures on disk (mirror "
            f"{c['mirror']}, projector {c['projector']}), step '{machine.state}'")
    else:
        kw = {} if ready.simulated or ready.specs is None else ready.specs.manifest_kw()
        # the projector step PREVIOUS was measured with: the structured-light sequence, or the circle grid
        step = PatternKind.STRUCTURED.value if ready.specs is not None and is_structured_pattern(ready.specs.pattern) \
            else None
        store = create_session(folder, rig, req, plan, projector_pattern=step, **kw)
        machine = RecalibrationMachine(store, plan)
    machine.persist()
    opts = StationOptions(auto=True, follow_operator=True)
    if not ready.simulated:  # a person needs time, and a pose too close to another is never kept
        opts.max_frames_per_target = 10**9
        opts.stuck_frames = 10**9
    station = RecalibrationStation(rig, machine, opts, log=log)
    machine.on_event = lambda text: None if text.startswith("captured") else log(text)
    return store, machine, station


def summary(rec: dict, folder, elapsed_s: float) -> str:
    from app.recalibration import comparison_lines
    from app.station.setup import load_ground_truth

    lines = [f"recalibration {folder}: {rec['message']} ({'ok' if rec['ok'] else 'FAILED'}) after {elapsed_s:.1f} s"]
    lines += [f"  check {p}: {c['status']}" for p, c in rec["check"]["parts"].items()]
    lines += [f"  {line}" for line in comparison_lines(rec)]
    gt = load_ground_truth(folder)
    cal = Path(folder) / session_files.CALIBRATION
    if gt is not None and cal.exists():
        from calib.models.result import CalibrationResult
        from calib.quality.metrics import compare

        mt = compare(CalibrationResult.load_json(cal), gt)
        lines.append(f"  vs ground truth: distance {mt.distance:.3f} {mt.units}, angle {mt.angle_deg:.4f} deg, CamK "
                     f"{mt.cam_k_px:.2f} px" + (f", mirror {mt.mirror_angle_deg:.4f} deg" if mt.mirror_angle_deg
                                                 is not None else ""))
    return "\n".join(lines)
