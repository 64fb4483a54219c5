"""`procam session`: a whole guided session without the browser, start to finish.

With `--auto` on the simulated rig the station asks the simulated operator for every board pose,
auto-captures, calibrates and verifies: the README's run command. On a real rig a person moves the
board, reading the instructions printed in the terminal, and auto-capture takes the frames.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from app.commands._rig_options import add_rig_options
from calib.formats import session_files
from calib.models.vocab import MirrorMethod, RenderQuality, RigKind, choices

NAME = "session"
HELP = "run a guided capture-and-calibrate session headless (--rig sim --auto: fully simulated)"
DESCRIPTION = (
    "Runs the station's session (rig check, mirror capture, projector capture at every pattern position, "
    "calibration, verification) without the browser panel, printing progress and a final summary. "
    "DIR ends holding the captures, session.json, calibration.json, verification.json and, on the "
    "simulated rig, ground_truth.json. A killed session continues with --resume DIR."
)


def add_arguments(p) -> None:
    p.add_argument("--auto", action="store_true",
                   help="the station leads the whole session itself (on the simulated rig the simulated "
                        "operator moves the board)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--out", metavar="DIR", help="new session folder")
    g.add_argument("--resume", metavar="DIR", help="continue the session in DIR where it stopped")
    add_rig_options(p)
    p.add_argument("--mirror-method", choices=choices(MirrorMethod), default=None,
                   help="mirror calibration method (default: the scenario's, else real-virtual)")


def plan_from_args(args, base=None):
    from app.station.machine import Plan

    plan = base or Plan()
    kw = plan.to_dict()
    if getattr(args, "poses_per_position", None) is not None:
        kw["poses_per_position"] = args.poses_per_position
    if getattr(args, "stop_on_confidence", None):
        kw["stop_on_confidence"] = True
    if getattr(args, "next_best", None):
        if not kw["stop_on_confidence"]:
            from calib.errors import OptionError

            raise OptionError("--next-best chooses each pose from the calibration of the captures so far, which "
                              "only --stop-on-confidence computes: give both")
        kw["next_best"] = True
    if getattr(args, "ask_pose", None):
        from calib.errors import OptionError

        if not kw["stop_on_confidence"]:
            raise OptionError("--ask-pose chooses each pose from the calibration of the captures so far, which "
                              "only --stop-on-confidence computes: give both")
        if kw["next_best"]:
            raise OptionError("--ask-pose and --next-best both choose where the board goes next: give one "
                              "(--ask-pose chooses the whole pose, --next-best the position only)")
        kw["ask_pose"] = True
    if getattr(args, "mirror_frames", None) is not None:
        kw["mirror_frames"] = args.mirror_frames
    if getattr(args, "placements", None) is not None:
        kw["structured_placements"] = args.placements
    if getattr(args, "mirror_captures", None) is not None:
        kw["real_virtual_captures"] = kw["real_mirror_captures"] = args.mirror_captures
        kw["min_real_virtual"] = min(kw["min_real_virtual"], args.mirror_captures)
        kw["min_real_mirror"] = min(kw["min_real_mirror"], args.mirror_captures)
    return Plan(**kw)


def rig_options(args, kind: str) -> dict:
    """Device options for drivers.factory.open_rig from the command line: the rig's entry of
    drivers.factory.RIGS maps them, after the checks that need the station (the simulated rig's
    latency and faults, a pre-calibration's file)."""
    from argparse import Namespace

    from drivers.factory import RIGS, is_simulated

    entry = RIGS[kind]
    resolved = Namespace(**vars(args))
    if is_simulated(kind):
        from app.commands._rig_options import sim_hardware_options

        resolved.sim_hardware = sim_hardware_options(args)
    if getattr(args, "camera_intrinsics", None) and "intrinsics" in (entry.known_options or ()):
        from app.station.machine import load_intrinsics

        resolved.camera_intrinsics_model = load_intrinsics(args.camera_intrinsics)
    return entry.from_args(resolved)


def refuse_recalibration_folder(folder: Path) -> None:
    """A stopped recalibration is continued by its own flow (it checks PREVIOUS again), never as a plain
    session: `procam session --resume` and `procam station --resume` refuse it, naming the right command."""
    from app.station.setup import read_state
    from calib.errors import SessionError

    if (folder / session_files.MANIFEST).is_file() and (read_state(folder) or {}).get("recalibration"):
        raise SessionError(f"{folder} is a recalibration: continue it with `procam recalibrate PREVIOUS --out {folder} "
                           f"--resume` or `procam station --recalibrate PREVIOUS --resume {folder}`")


def open_session(args, log=print):
    """(rig, store, machine, request) for --out (new) or --resume (existing) from the arguments."""
    from app.station.setup import (
        DEFAULT_SCENARIO, RigRequest, check_same_rig, create_session, make_machine, open_requested_rig,
        resume_request,
    )
    from calib.errors import OptionError, SessionError
    from calib.formats.session import SessionStore
    from drivers.factory import default_rig_kind
    from calib.models.boards import CharucoSpec
    from calib.models.observations import VIEW_DIRECT, VIEW_MIRROR

    if args.resume:
        if getattr(args, "blank_area", None) is not None:
            raise OptionError("--blank-area is recorded when a session is created: a resumed session keeps its own "
                              "(session.json's projector_blank_area)")
        folder = Path(args.resume)
        refuse_recalibration_folder(folder)
        store = SessionStore.open(folder, lock=True)  # one process per session folder: refused while in use
        req = resume_request(folder, kind=args.rig, scenario=args.scenario, seed=args.seed, quality=args.quality)
        rig = open_requested_rig(req, **rig_options(args, req.kind))
        check_same_rig(store, rig)
        plan = None
        if args.projector_pattern is not None:
            raise SessionError("--projector-pattern is chosen when a session starts: a resumed session keeps its own")
        if args.poses_per_position is not None or args.mirror_captures is not None or args.placements is not None:
            from app.station.machine import Plan

            plan = plan_from_args(args, Plan.from_dict((store.manifest.state or {}).get("plan")))
        method = args.method or (store.manifest.state or {}).get("method")
        machine = make_machine(store, rig, plan, resume=True, workers=args.workers, method=method)
        c = machine.counts()
        log(f"resuming {folder}: {len(store.manifest.captures)} captures on disk "
            f"(mirror {c['mirror']}, projector {c['projector']}), step '{machine.state}'")
    else:
        from app.commands._outputs import check_output_folder

        folder = check_output_folder(args.out)  # never inside another session (its images/, ...)
        kind = args.rig or default_rig_kind()
        req = RigRequest(kind, args.scenario or DEFAULT_SCENARIO, args.seed or 0, args.quality or RenderQuality.LIVE)
        from drivers.factory import is_simulated

        if not is_simulated(kind) and not args.board:
            raise SessionError("a real rig needs the board spec: --board COLSxROWS:DICT:SQUARE[:MARKER]")
        blank = getattr(args, "blank_area", None)
        if blank is not None and is_simulated(kind):
            raise OptionError("--blank-area is for a real rig's board: the simulated rig's board is its scenario's")
        rig_kw = rig_options(args, kind)
        kw = {}
        if not is_simulated(kind):
            from app.board_sheet import BlankArea

            board = CharucoSpec.parse(args.board, args.units)
            area = None if blank is None else BlankArea.parse(blank, board.units)
            kw = dict(board=board, mirror_board=CharucoSpec.parse(args.mirror_board, args.units)
                      if args.mirror_board else None, view=VIEW_DIRECT if args.direct else VIEW_MIRROR,
                      blank_area=None if area is None else (area.width, area.gap))
        rig = open_requested_rig(req, **rig_kw)
        from app.commands._rig_options import structured_placements

        structured_placements(args)  # --placements only with --projector-pattern structured
        plan = plan_from_args(args)
        store = create_session(folder, rig, req, plan, projector_pattern=args.projector_pattern, **kw)
        machine = make_machine(store, rig, plan, workers=args.workers, method=args.method)
        if args.method:
            machine.extra_state["method"] = args.method  # a resumed session calibrates the same way
            machine.persist()
        what = f"{kind} rig" if not is_simulated(kind) else f"simulated rig '{req.scenario}' (seed {req.seed})" + (
            "" if kind == RigKind.SIM else ", camera through the OpenCV driver on a live stream" if kind == RigKind.SIM_UVC
            else ", camera through the RealSense driver")
        log(f"new session in {folder} on the {what}")
    if args.camera_intrinsics:
        machine.skip_camera(args.camera_intrinsics)
    if getattr(args, "board_thickness", None) is not None:
        machine.set_board_thickness(args.board_thickness)
    return rig, store, machine, req


def _projector_limit(machine, c) -> str:
    """The summary's words on the projector step's count when it stops on confidence (Plan.stop_on_confidence)."""
    if not machine.plan.stop_on_confidence:
        return ""
    conf = getattr(machine, "projector_confidence", None)
    why = "stopped when confident" if conf is not None and conf.all_met else "not confident"
    return f"of at most {c['projector_total']} ({why}) "


def _mirror_limit(machine, c) -> str:
    """The summary's words on the mirror step's count when it stops on confidence."""
    if not machine.plan.stop_on_confidence or getattr(machine, "direct", False) or not c["mirror_total"]:
        return ""
    conf = getattr(machine, "mirror_confidence", None)
    why = "stopped when confident" if conf is not None and conf.all_met else "not confident"
    return f" of at most {c['mirror_total']} ({why})"


def placement_split(machine) -> str:
    """The placements of each capture step (a structured placement is one however many frames it took)."""
    from calib.formats.session_captures import placements
    from calib.models.observations import STEP_PROJECTOR

    mirror = placements(machine.mirror_captures())
    proj = machine.captures_of(STEP_PROJECTOR)
    asked = sum(1 for c in proj if "asked_T_cam_board" in (c.meta or {}))
    return f"mirror {mirror}, projector {placements(proj)}" + (f", {asked} of them at the pose asked for" if asked else "")


def summary(machine, folder, elapsed_s: float) -> str:
    from app.station.setup import load_ground_truth

    lines = []
    c = machine.counts()
    lines.append(f"session {folder}: {STATE(machine)} after {elapsed_s:.1f} s")
    where = ("structured light" if machine.structured else
             f"at {c['positions_done']}/{c['positions']} pattern positions")
    lines.append(f"  captures: mirror {c['mirror']}{_mirror_limit(machine, c)} ({machine.mirror_method or 'none'}), "
                 f"projector {c['projector']} "
                 + _projector_limit(machine, c) + where)
    lines.append(f"  placements: {c['placements']} (the board's positions: {placement_split(machine)})")
    mconf = getattr(machine, "mirror_confidence", None)
    if _mirror_limit(machine, c) and mconf is not None and not mconf.all_met:
        # what the technician can do about it: the outlook says whether more mirror placements would
        # lower the normal or whether the camera holds it (more projector placements, a calibrated camera)
        lines.append("  mirror step not confident: " + "; ".join(mconf.lines()))
    res = machine.result
    if res is not None:
        from app.commands.calibrate import format_rms  # every RMS value with its unit

        lines.append(f"  calibration ({res.method}): {format_rms(res)}")
        t = res.T_cam_proj[:3, 3]
        lines.append(f"  projector position in the camera frame: [{t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}] {res.units}")
        if res.mirror is not None:
            n = res.mirror.normal
            lines.append(f"  mirror: normal [{n[0]:.4f}, {n[1]:.4f}, {n[2]:.4f}], d {res.mirror.d:.2f} {res.units}")
        gt = load_ground_truth(folder)
        if gt is not None:
            try:
                from calib.quality.metrics import compare

                mt = compare(res, gt)
                lines.append(f"  vs ground truth: distance {mt.distance:.2f} {mt.units}, angle {mt.angle_deg:.3f} deg, "
                             f"CamK {mt.cam_k_px:.2f} px, ProjK {mt.proj_k_px:.2f} px"
                             + (f", mirror {mt.mirror_angle_deg:.3f} deg / {mt.mirror_offset:.2f} {mt.units}"
                                if mt.mirror_angle_deg is not None else ""))
            except (ImportError, ValueError) as e:
                lines.append(f"  (no comparison with the ground truth: {e})")
    if machine.report is not None:
        r = machine.report
        verdict = "PASSED" if getattr(r, "passed", False) else "FAILED"
        lines.append(f"  verification {verdict} (threshold {getattr(r, 'threshold_px', float('nan')):.2f} projector px):")
        if hasattr(r, "summary"):
            lines.extend("    " + ln for ln in r.summary().splitlines())
    files = [p.name for p in sorted(Path(folder).iterdir()) if p.is_file() and not p.name.startswith(".")]
    lines.append(f"  files: {', '.join(files)}")
    return "\n".join(lines)


def rig_check_hint(kind: str, view: str) -> str | None:
    """What the person at a RealSense rig does during the rig check (said before it starts): the check
    measures the exposure and the projector's latency on the board the projector lights."""
    from drivers.factory import is_simulated
    from calib.models.observations import VIEW_MIRROR

    if kind == RigKind.SIM:
        return None
    where = "in the mirror, where the camera sees it" if view == VIEW_MIRROR else "where the camera sees it"
    who = " (the simulated operator does it here)" if is_simulated(kind) else ""
    return (f"Rig check{who}: hold the board {where}, lit by the projector, and keep it still until the check "
            "ends (about 20 s): the camera's exposure and the projector's latency are measured on it.")


def STATE(machine) -> str:
    from app.station.machine import STATE_TITLES

    return STATE_TITLES[machine.state].lower()


def run(args) -> int:
    from app.station.machine import CHECK_RIG, DONE
    from app.station.station import Station, StationOptions
    from calib.errors import SessionError

    t0 = time.monotonic()

    def log(text):  # the station's lines quote capture ids and detection reasons read from files
        from app.cli import terminal_safe

        print(terminal_safe(f"[{time.monotonic() - t0:6.1f} s] {text}"), flush=True)

    from app.station.setup import resume_request
    from drivers.factory import default_rig_kind

    kind = resume_request(args.resume, kind=args.rig).kind if args.resume else (args.rig or default_rig_kind())
    from drivers.factory import is_simulated

    if is_simulated(kind) and not args.auto:
        raise SessionError("the simulated rig has nobody to move the board: add --auto, or operate it from "
                           "the browser with `procam station --rig sim`")
    rig, store, machine, req = open_session(args, log)
    opts = StationOptions(auto=True, mirror_method=args.mirror_method, follow_operator=True)
    if not is_simulated(req.kind):  # a person needs time, and a pose too close to another is never kept
        opts.max_frames_per_target = 10**9
        opts.stuck_frames = 10**9
    station = Station(rig, machine, opts, log=log)
    shown = {}

    def progress(done, total, label=""):
        import re

        stage = "detecting captures" if re.fullmatch(r"(p|mrv|mrm)\d+", str(label)) else f"calibration: {label}"
        if shown.get(stage) is None or done == total or time.monotonic() - shown[stage] > 5:
            shown[stage] = time.monotonic()
            log(f"{stage} {done}/{total}")

    station.on_progress = progress
    machine.on_event = lambda text: None if text.startswith(("captured", "placement refused")) else log(text)  # the station logs these
    last_hint = ""

    check_hint = rig_check_hint(req.kind, machine.manifest.rig.view)

    def work():
        nonlocal last_hint
        if check_hint:
            print(check_hint, flush=True)
            if not is_simulated(req.kind) and sys.stdin.isatty():
                input("Press Enter when the board is in place: ")
        if machine.state != CHECK_RIG:  # resumed: the rig is checked again, the session stays where it is
            bad = [c for c in station.check_rig() if not c.ok]
            if bad:
                raise SessionError("the rig check failed: " + "; ".join(f"{c.name}: {c.detail}" for c in bad))
        while machine.state != DONE:
            station.tick()
            if not is_simulated(req.kind):
                hint = station.instruction()
                if hint != last_hint:
                    print(hint, flush=True)
                    last_hint = hint

    from app.station.setup import run_on_rig

    try:
        run_on_rig(rig, work)
    finally:
        close = getattr(rig, "close", None)
        if callable(close):
            close()
    print(summary(machine, store.folder, time.monotonic() - t0), flush=True)
    if machine.report is not None and not getattr(machine.report, "passed", True):
        return 1
    from app.commands._quality import EXIT_LOW_QUALITY, report_low_quality

    if machine.result is not None and report_low_quality(machine.result, file=sys.stdout):
        return EXIT_LOW_QUALITY
    return 0
