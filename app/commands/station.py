"""`procam station`: the guided station, operated from a browser (viser panel).

The panel leads the operator through the session (rig check, mirror capture, projector capture,
calibration, verification) and shows the live camera image, coverage, pose diversity, the 3D rig and
the results. It binds to 127.0.0.1 unless told otherwise; served on a network (--host 0.0.0.0) it
prints an access code (and an address carrying it), and a browser without the code sees only a page
asking for it. Security rules: app/station/access.py and docs/STATION.md.
"""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

from app.commands import _types
from app.commands._rig_options import add_rig_options
from calib.models.vocab import MirrorMethod, RigKind, choices

NAME = "station"
HELP = "the guided capture-and-calibrate station, operated from a browser panel"
DESCRIPTION = (
    "Starts the station and its browser panel (viser). With no RealSense connected the simulated rig is "
    "used, and its simulated operator moves the board when asked, so a whole session can be run from "
    "the browser. Every capture is written to the session folder before the panel acknowledges it; "
    "--resume DIR continues a session where it stopped."
)


def add_arguments(p) -> None:
    p.add_argument("--port", type=_types.port, default=8080,
                   help="panel port, 1-65535, or 0 for any free one (default 8080)")
    p.add_argument("--host", type=_types.host, default="127.0.0.1",
                   help="address to serve the panel on (default 127.0.0.1; 0.0.0.0 serves the network, and "
                        "every browser then needs the printed access code to see the panel)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--session", metavar="DIR", help="new session folder (default: ./session-YYYYmmdd-HHMMSS)")
    g.add_argument("--resume", metavar="DIR", help="continue the session in DIR where it stopped")
    p.add_argument("--auto", action="store_true",
                   help="simulated rig: the simulated operator moves the board by itself and the station runs "
                        "the whole session (watch it in the browser)")
    add_rig_options(p)
    p.add_argument("--recalibrate", metavar="PREVIOUS", default=None,
                   help="recalibration mode: check the rig against PREVIOUS (a session folder holding "
                        "calibration.json, or a calibration.json; its boards are used), re-measure what moved, "
                        "compare; the panel shows its checklist and prompts the operator; with --resume DIR a "
                        "stopped recalibration continues (docs/RECALIBRATION.md)")
    p.add_argument("--mirror-method", choices=choices(MirrorMethod), default=None,
                   help="with --auto: the mirror method the station chooses (default: the scenario's)")


def rig_note(req, defaulted: bool) -> str:
    from drivers.factory import is_simulated

    if is_simulated(req.kind):
        note = f"**Simulated rig** `{req.scenario}` (seed {req.seed})"
        if defaulted:
            note += ": no RealSense camera is connected, so the station uses the simulated rig"
        return note + ". Its simulated operator moves the board when you press *Move board*."
    return f"**{req.kind} rig**: a person moves the board, following the instructions below."


def check_serving(args) -> None:
    """Before any folder or device: the panel's address can be served on (a host that is not this
    machine's would hang viser) and a new session folder is not inside another session."""
    from app.commands._outputs import check_output_folder
    from app.station._origin import check_bind

    check_bind(args.host, args.port)
    if not args.resume:
        check_output_folder(args.session, "--session")


def run(args) -> int:
    from app.commands.session import open_session
    from app.station.panel import StationPanel, needs_access_code, new_access_code
    from app.station.setup import resume_request
    from drivers.factory import default_rig_kind
    from app.station.station import Station, StationOptions

    defaulted = False
    if not args.resume and not args.session:
        args.session = time.strftime("session-%Y%m%d-%H%M%S")
    check_serving(args)
    if args.resume:
        kind = resume_request(args.resume, kind=args.rig).kind
    else:
        kind = args.rig
        if kind is None:
            kind = default_rig_kind()
            defaulted = kind == RigKind.SIM
        args.rig = kind
    args.out = args.session
    if args.recalibrate:
        if args.projector_pattern is not None or args.placements is not None:
            from calib.errors import SpecError

            raise SpecError("--projector-pattern and --placements start a new session's projector step; a "
                            "recalibration re-measures with PREVIOUS's own (the circle grid or the structured-light "
                            "sequence, as its session.json says)")
        if args.stop_on_confidence or args.next_best or args.ask_pose or args.mirror_frames is not None:
            from calib.errors import SpecError

            raise SpecError("--stop-on-confidence, --next-best, --ask-pose and --mirror-frames plan a new session's "
                            "capture steps; a recalibration asks for the captures its rig check and re-estimate need")
        return run_recalibration_mode(args, kind, defaulted)
    rig, store, machine, req = open_session(args, print)
    from drivers.factory import is_simulated

    sim = is_simulated(req.kind)  # sim, sim-realsense: a simulated operator moves the board
    opts = StationOptions(auto=bool(args.auto and sim), follow_operator=(not sim) or bool(args.auto),
                          mirror_method=args.mirror_method)
    if not sim:
        opts.max_frames_per_target = 10**9
        opts.stuck_frames = 10**9
    station = Station(rig, machine, opts, log=lambda text: None)
    code = new_access_code() if needs_access_code(args.host) else None
    panel = StationPanel(station, args.host, args.port, code, rig_note(req, defaulted))

    return serve(args, rig, store, station, panel, code, lambda: _start(machine, station))


def _start(machine, station) -> None:
    from app.station.machine import CHECK_RIG

    if machine.state != CHECK_RIG:  # resumed: check the rig again (the panel shows the outcome)
        station.check_rig()
    station.start_loop()


def run_recalibration_mode(args, kind: str, defaulted: bool) -> int:
    """--recalibrate PREVIOUS: the flow of `procam recalibrate` (app/recalibration.py, opened by
    app/commands/recalibrate.py's prepare / open_recalibration: PREVIOUS's boards, the rig checked against
    it, --resume DIR of a stopped one) driven from the panel's recalibration checklist
    (app/station/panel_recal.py), which prompts the operator at each capture."""
    import argparse

    from app.commands.recalibrate import open_recalibration, prepare
    from app.recalibration import RECALIBRATION_FILE, rig_verify_fn
    from app.station.panel import StationPanel, needs_access_code, new_access_code
    from app.station.panel_recal import RecalibrationPanel

    rargs = argparse.Namespace(**vars(args))
    rargs.previous, rargs.out, rargs.resume = args.recalibrate, args.resume or args.session, bool(args.resume)
    rargs.max_captures = None
    ready = prepare(rargs, print)  # every check before a device is opened
    rig = ready.open_rig()
    try:
        store, machine, station = open_recalibration(rargs, ready, rig, lambda text: None)
    except BaseException:
        close = getattr(rig, "close", None)
        if callable(close):
            close()
        raise
    req = ready.req
    code = new_access_code() if needs_access_code(args.host) else None
    panel = StationPanel(station, args.host, args.port, code, rig_note(req, defaulted))
    RecalibrationPanel(panel, ready.src, verify=rig_verify_fn(rig, store.folder), workers=args.workers,
                       resume=rargs.resume)
    rc = serve(args, rig, store, station, panel, code, station.start_preview)  # the flow ticks the station
    if not (Path(store.folder) / RECALIBRATION_FILE).exists():
        print(f"procam station: the recalibration is not finished; continue it with --recalibrate {args.recalibrate} "
              f"--resume {store.folder}")
    return rc


def serve(args, rig, store, station, panel, code, start) -> int:
    """Run the panel until SIGTERM or Ctrl-C; `start()` first (the station's loop)."""
    from app.station.setup import run_on_rig

    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    try:
        signal.signal(signal.SIGTERM, on_signal)
    except ValueError:  # not the main thread (tests call run() in a thread)
        pass

    def work():
        start()
        panel.start()
        print(f"procam station: panel at {panel.url}  (session {Path(store.folder)})", flush=True)
        if code is not None:
            print(f"procam station: served on {args.host}; access code: {code}", flush=True)
            print("procam station: the panel's traffic is plain HTTP, not encrypted: anyone on the network can "
                  "read it (live images, results, the access code); serve it only on a network you trust",
                  flush=True)
            for url in panel.network_urls():
                print(f"procam station: on the network open {url}", flush=True)
        else:
            ws = panel.url.replace("http://", "ws://", 1)
            print(f"procam station: clients without a browser connect to {ws}/code/{panel.gate.secret} "
                  "(browsers need no code here)", flush=True)
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            station.stop_loop()
            panel.stop()

    try:
        run_on_rig(rig, work)
    except KeyboardInterrupt:
        pass
    finally:
        stop.set()
        close = getattr(rig, "close", None)
        if callable(close):
            close()
    print(f"procam station: stopped; the session is in {store.folder} (continue with --resume {store.folder})")
    return 0
