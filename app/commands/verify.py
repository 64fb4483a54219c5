"""`procam verify SESSION --rig sim|sim-realsense|sim-uvc|realsense|uvc`: the automatic epipolar check of SESSION/calibration.json.

Exit codes (scripts rely on them): 0 the calibration passes, 1 it fails the check (or too few pixels
could be measured), 2 the check could not run (missing files, devices, bad arguments).

A camera with exposure control (RealSense, the simulated camera) is set as the session recorded it
(session.json rig.camera_settings: manual exposure and gain, emitter off) and the projector's latency is
the one the session measured (rig.camera_settings.projector.latency_ms), unless --settle is given. The
frames are linearised with the camera's response (tone curve) the session recorded; without one, the
camera's own (simulated) or, on a RealSense, one measured now as the station's rig check does
(camera_response); verification.json records which ("response", null when none).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from app.commands import _types
from calib.formats import session_files
from calib.models.vocab import RenderQuality, Step, choices
from drivers.factory import is_simulated

NAME = "verify"
HELP = "measure a session's calibration on the rig: epipolar curves drawn by the projector vs picked camera pixels"
DESCRIPTION = (
    "Runs the automatic epipolar check (docs/VERIFICATION.md) with SESSION/calibration.json: for a grid of camera "
    "pixels over the board, the projector draws each pixel's epipolar curve, the camera finds the drawn curve, "
    "and the distance from the pixel to it is measured. Prints the mean and worst distance and the verdict, "
    "writes SESSION/verification.json, and exits with 0 (pass), 1 (fail) or 2 (could not run). On --rig sim "
    "the simulated rig of the session's scenario is used (the session must come from `procam simulate` or a "
    "simulated station session, or give --scenario). The session's recorded exposure, gain and emitter setting "
    "(on a camera with exposure control) and its measured projector latency are applied first; the frames are "
    "linearised with the camera's recorded response (tone curve), measured now on a RealSense when the session "
    "recorded none."
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
    from app.verification import DEFAULT_GRID, DEFAULT_THRESHOLD_PX, VERIFY_RIGS

    p.add_argument("session", metavar="SESSION", help="session folder (with session.json and calibration.json)")
    p.add_argument("--rig", choices=VERIFY_RIGS, required=True,
                   help="the rig to measure on (sim-realsense: the simulated rig through the RealSense driver; "
                        "sim-uvc: through the OpenCV driver on a live stream; uvc: any camera OpenCV opens)")
    p.add_argument("--threshold", type=_positive, default=DEFAULT_THRESHOLD_PX, metavar="PX",
                   help=f"verdict threshold on the mean distance, projector pixels (default {DEFAULT_THRESHOLD_PX:g}; "
                        "the worst pixel may reach twice it)")
    p.add_argument("--grid", type=_grid, default=DEFAULT_GRID, metavar="CxR",
                   help=f"pixels to check, columns x rows over the lit board (default {DEFAULT_GRID[0]}x{DEFAULT_GRID[1]})")
    p.add_argument("--calibration", metavar="FILE", default=None,
                   help="calibration to verify (default SESSION/calibration.json)")
    p.add_argument("--out", metavar="FILE", default=None, help="report file (default SESSION/verification.json)")
    p.add_argument("--average", type=_types.int_range(1, 100), default=1, metavar="N",
                   help="camera frames averaged per image (default 1)")
    sim = p.add_argument_group("--rig sim, sim-realsense, sim-uvc")
    sim.add_argument("--scenario", default=None, help="scenario (default: the one the session was simulated with)")
    sim.add_argument("--seed", type=_types.seed, default=None, help="scenario seed (default: the session's)")
    sim.add_argument("--quality", choices=choices(RenderQuality), default=RenderQuality.LIVE,
                     help="render quality of the simulated camera (default live: 1 sample per pixel)")
    from app.commands._rig_options import add_sim_faults_option, add_sim_latency_option

    add_sim_latency_option(sim)
    add_sim_faults_option(sim)
    hw = p.add_argument_group("--rig realsense, uvc")
    hw.add_argument("--serial", default=None, help="RealSense serial number (default: the first camera)")
    hw.add_argument("--camera", type=_types.camera_source, default=0, metavar="INDEX|URL",
                    help="--rig uvc: the camera, an index or a stream URL (default 0)")
    hw.add_argument("--camera-fps", type=_types.float_range(1.0, 1000.0), default=None, metavar="FPS",
                    help="--rig uvc: the camera's frame rate (default: what the backend reports)")
    hw.add_argument("--screen", type=_types.screen, default=None, metavar="N",
                    help="projector screen from `procam devices` (default: the non-primary one of two screens)")
    hw.add_argument("--settle", type=_types.seconds, default=None, metavar="S",
                    help="projector latency in seconds (every rig): how long after presentation an image counts as visible "
                         "(default: the latency the session's rig check measured, session.json "
                         f"rig.camera_settings.projector.latency_ms; {DEFAULT_SETTLE_S:g} when none was recorded)")
    hw.add_argument("--delay", type=_types.seconds, default=3.0, metavar="S",
                    help="seconds between the instruction to hold the board and the measurement (default 3)")


DEFAULT_SETTLE_S = 0.1


def recorded_latency_s(manifest) -> float | None:
    """The projector latency the session measured (seconds), or None."""
    from drivers.settle import recorded_latency_s as from_settings

    return from_settings(manifest.rig.camera_settings)


def apply_recorded(rig, manifest, settle_s: float | None = None) -> list[str]:
    """Make the rig time and expose frames as the session did: the camera's exposure, gain and emitter
    and the projector's latency (`settle_s` overrides the recorded one). Uses the station's own
    procedure (drivers.settle.apply_timing: it also searches an exposure / measures the latency the
    session did not record). Returns the lines to print."""
    return _apply_recorded(rig, manifest, settle_s)[1]


def _apply_recorded(rig, manifest, settle_s: float | None = None) -> tuple[dict, list[str]]:
    """apply_recorded, also returning the settings applied (drivers.settle.apply_timing's)."""
    from drivers.settle import apply_timing, recorded_exposure

    rec = dict(manifest.rig.camera_settings or {})
    if settle_s is not None:
        rec["projector"] = {**(rec.get("projector") if isinstance(rec.get("projector"), dict) else {}),
                            "latency_ms": float(settle_s) * 1000.0}
    got = apply_timing(rig.camera, rig.projector, rec)
    lines = []
    if "exposure_us" in got:
        recorded = recorded_exposure(rec)
        line = f"camera: manual exposure {got['exposure_us']:g} us, gain {got['gain']:g}"
        if recorded is not None:
            line += " as the session recorded"
            same = (abs(got["exposure_us"] - recorded[0]) <= 1e-6 * max(1.0, got["exposure_us"])
                    and got["gain"] == recorded[1])
            if not same:
                line += (f" (recorded {recorded[0]:g} us, gain {recorded[1]:g}: the camera's range or step "
                         "differs)")
        else:
            line += " (the session recorded none: searched now)"
        lines.append(line + "; emitter off")
    elif got.get("manual_exposure") == "ignored by the camera":
        lines.append("warning: camera: ignores manual exposure, so its own auto exposure stays on (the measurement "
                     "may flicker)")
    elif got:
        lines.append("camera: the session recorded no manual exposure, so auto exposure is on (the measurement "
                     "may flicker); emitter off")
    else:
        lines.append("camera: no exposure control, left as it is")
    proj = got.get("projector")
    if isinstance(proj, dict) and proj.get("latency_ms") is not None:
        rec_proj = rec.get("projector") if isinstance(rec.get("projector"), dict) else {}
        how = "--settle" if settle_s is not None else \
            ("as the session assumed: not measurable under the camera's auto exposure" if rec_proj.get("assumed")
             else "as the session measured") if recorded_latency_s(manifest) is not None else "measured now"
        lines.append(f"projector latency: {float(proj['latency_ms']):.0f} ms ({how})")
    return got, lines


def camera_response(rig, manifest, applied: dict):
    """The camera's response (tone curve) the check linearises the frames with: (CameraResponse or
    None, what verification.json records of it or None, the line to print). The session's recorded one
    (rig.camera_settings["response"]); else the camera's own (the simulated camera knows it); else, on a
    camera with exposure control (a RealSense), measured now as the station's rig check does
    (drivers.exposure.measure_response while the projector's white lights the board), the exposure and
    gain `applied` (apply_recorded's) restored after. A failed measurement is a warning and the check
    goes on with the camera's levels uncorrected."""
    from calib.detection.response import parse_response, recorded_response
    from calib.errors import ProcamError
    from drivers.base import ExposureControl
    from drivers.exposure import apply_exposure, measure_response
    from drivers.projector_images import white

    rec = recorded_response(manifest.rig.camera_settings)
    if rec is not None:
        return rec, {**rec.to_dict(), "from": "session"}, \
            f"camera response: tone curve {rec.model}, gamma {rec.gamma:g} as the session recorded"
    cam, proj = rig.camera, rig.projector
    own = getattr(cam, "response", None)
    if callable(own):
        r = parse_response(own())
        if r is not None:
            return r, {**r.to_dict(), "from": "camera"}, \
                f"camera response: tone curve {r.model}, gamma {r.gamma:g} (the camera's own; the session recorded none)"
    if not isinstance(cam, ExposureControl) or "exposure_us" not in applied:
        return None, None, "camera response: unknown (the session recorded none): the camera's levels are used as they are"
    try:
        proj.wait_presented(proj.show(white(tuple(proj.size))))
        fit = measure_response(cam, float(getattr(proj, "refresh_hz", 60.0) or 60.0))
    except ProcamError as e:  # DeviceError included
        return None, None, f"warning: camera response not measured ({e}): the check uses the camera's levels uncorrected"
    finally:
        apply_exposure(cam, applied["exposure_us"], applied["gain"])  # no later frame at the bracket's gain
    r = parse_response(fit.camera_settings()["response"])
    if r is None:
        return None, None, f"warning: the measured camera response (gamma {fit.gamma:g}) is implausible: not used"
    return r, {**fit.camera_settings()["response"], "from": "measured"}, \
        (f"camera response: tone curve bt709, gamma {fit.gamma:g} measured now (fit rms {fit.rms:.4f}); exposure "
         f"{applied['exposure_us']:g} us, gain {applied['gain']:g} restored")


def _sim_options(manifest, args) -> dict:
    """open_sim_rig options matching the session's simulated scenario (or the arguments)."""
    from calib.errors import SessionError
    from drivers.sim.render import RenderSettings

    settings = dict(manifest.rig.camera_settings or {})
    state = dict(manifest.state or {})
    request = state.get("rig_request") if isinstance(state.get("rig_request"), dict) else {}
    scenario = args.scenario or settings.get("scenario") or state.get("scenario") or request.get("scenario")
    seed = args.seed if args.seed is not None else settings.get("seed", state.get("seed", request.get("seed", 0)))
    if not scenario:
        raise SessionError("this session was not recorded on the simulated rig, so its scenario is unknown; "
                           "give --scenario NAME (see `procam simulate --list`) or use --rig realsense")
    if settings.get("driver") not in (None, "sim"):  # a RealSense driver's settings are not the renderer's
        settings = {}
    render = {k: v for k, v in settings.items()
              if k in RenderSettings.__dataclass_fields__ and k != "supersample" and not isinstance(v, (dict, list))}
    from app.commands._rig_options import sim_hardware_options

    return {"scenario": scenario, "seed": int(seed), "quality": args.quality, **render, **sim_hardware_options(args)}


def run(args) -> int:
    from app.verification import verify
    from calib.errors import SessionError
    from calib.formats.session import SessionStore
    from calib.models.result import CalibrationResult

    folder = Path(args.session)
    store = SessionStore.open(folder)
    man = store.manifest
    cal_path = Path(args.calibration) if args.calibration else folder / session_files.CALIBRATION
    if not cal_path.exists():
        raise SessionError(f"{cal_path} does not exist: run `procam calibrate {folder}` first")
    result = CalibrationResult.load_json(cal_path)
    if tuple(result.camera.size) != tuple(man.rig.camera_size) or \
            tuple(result.projector.size) != tuple(man.rig.projector_size):
        raise SessionError(f"{cal_path} is for a {result.camera.width}x{result.camera.height} camera and a "
                           f"{result.projector.width}x{result.projector.height} projector, the session's rig differs")
    if args.average < 1:
        raise SessionError("--average must be >= 1")
    out = Path(args.out) if args.out else folder / session_files.VERIFICATION
    # never a session's file (app/commands/_outputs.py)
    if out.resolve() != (folder / session_files.VERIFICATION).resolve():
        from app.commands._outputs import check_output_file

        check_output_file(out, "--out", inputs=[cal_path])
    info = {"path": str(cal_path), "method": result.method, "units": result.units}

    def progress(done, total, label):
        if done < total:
            print(f"  [{done + 1}/{total}] {label}", file=sys.stderr, flush=True)

    def check(rig, settle_frames):
        rig.camera.start()
        try:
            instruction = rig.operator.request_pose(Step.VERIFICATION, None, 0)
            print(instruction, file=sys.stderr, flush=True)
            if not is_simulated(args.rig) and args.delay > 0:
                time.sleep(args.delay)
            # exposure, emitter and projector latency as the session recorded them
            applied, lines = _apply_recorded(rig, man, args.settle)
            # the camera's tone curve: recorded, the camera's own, or measured now (after the exposure)
            response, record, line = camera_response(rig, man, applied)
            for line in lines + [line]:
                print(line, file=sys.stderr, flush=True)
            # the operator has been asked already: pass None so verify does not ask again
            # the session's board, found in the white frame, adds the predicted curves to the report
            report = verify(rig.camera, rig.projector, None, result, grid=args.grid, threshold_px=args.threshold,
                            progress=progress, board=man.projector_board, settle_frames=settle_frames,
                            average=args.average, calibration_info=info, response=response)
            return replace(report, response=record)
        finally:
            rig.camera.stop()

    if args.settle is not None and not args.settle >= 0:
        raise SessionError(f"--settle must be >= 0 seconds, got {args.settle:g}")
    if is_simulated(args.rig):
        from drivers.factory import open_rig

        rig = open_rig(args.rig, **_sim_options(man, args))
        try:
            report = check(rig, settle_frames=1)
        finally:
            rig.close()
    else:
        from drivers.factory import open_rig
        from drivers.projector_window import run_projector_loop

        settle = args.settle if args.settle is not None else recorded_latency_s(man)
        settle = DEFAULT_SETTLE_S if settle is None else settle  # until apply_recorded sets the recorded one
        from drivers.factory import RIGS

        # the camera's own options as its rig reads them from a command line (verify names the screen --screen)
        camera = RIGS[args.rig].from_args(argparse.Namespace(camera=args.camera, camera_fps=args.camera_fps or None,
                                                    serial=args.serial))
        rig = open_rig(args.rig, projector_screen=args.screen, settle_s=settle,
                       projector_size=tuple(man.rig.projector_size), **camera)
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
