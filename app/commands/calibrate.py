"""`procam calibrate SESSION`: detect, calibrate, print a summary, write calibration.json + .yaml."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from app.commands import _types
from calib.formats import session_files
from calib.models.vocab import CalibrationMethod, DistortionModel, choices

NAME = "calibrate"
HELP = "calibrate a saved capture session (camera, mirror, projector) and write calibration.json"
DESCRIPTION = (
    "Runs detection and the calibration pipeline on a session folder, prints a summary (intrinsics, "
    "camera-projector pose, mirror plane, RMS per stage, skipped images and why) and writes "
    "calibration.json plus the default exports beside it (an OpenCV FileStorage YAML, calibration.yaml; "
    "others with `procam export`)."
)


MODELS = ("auto", *choices(DistortionModel))
DEFAULT_METHOD = CalibrationMethod.JOINT
RESULT_NAME = session_files.CALIBRATION
VERIFICATION_NAME = session_files.VERIFICATION
SAME_TOL = 1e-9  # a re-run giving the same result to this keeps the file and its verification


def add_arguments(p) -> None:
    p.add_argument("session", metavar="SESSION", help="session folder (with session.json)")
    p.add_argument("--method", default=DEFAULT_METHOD,
                   help=f"calibration method: joint (default: the paper's pipeline, then one joint maximum-likelihood "
                        f"refinement, docs/JOINT.md) or paper (the method of Vanherck et al.). When SESSION/"
                        f"{RESULT_NAME} holds another method's result, it is kept and this one is written to "
                        f"SESSION/calibration-METHOD.json")
    p.add_argument("--camera-model", choices=MODELS, default=None,
                   help="joint method: camera distortion model (default auto: selected by significance tests)")
    p.add_argument("--projector-model", choices=MODELS, default=None,
                   help="joint method: projector distortion model (default auto)")
    p.add_argument("--camera-intrinsics", metavar="FILE", type=_types.regular_file, default=None,
                   help="pre-calibrated camera: a calibration.json or an OpenCV YAML with camera_matrix and "
                        "distortion_coefficients; skips the camera stage")
    p.add_argument("--out", metavar="FILE.json", default=None,
                   help=f"result file, *.json (default SESSION/{RESULT_NAME}); the YAML export goes beside it with "
                        f"the same name and .yaml. Session files (session.json, detections.json, images...) are "
                        f"refused")
    p.add_argument("--workers", type=_types.workers, default=2, help="detection threads (default %(default)s)")
    p.add_argument("--redetect", action="store_true",
                   help="detect every image again instead of reusing the session's detections.json (results "
                        "of earlier runs, kept per image and detector version)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress output (default: bars on a terminal, a line per stage otherwise)")
    p.add_argument("--accept-untrusted", action="store_true",
                   help="experts: write the result even when the trust check rejects it (absurd parameters, "
                        "huge residuals or uncertainty; docs/CALIBRATION.md); the reasons are printed and "
                        "recorded in the file under diagnostics.trust")


def check_session_arg(path) -> Path:
    """SESSION must be a folder; a session.json (or any file) given instead is said to be a file."""
    from calib.errors import SessionError

    session = Path(path)
    if session.is_file():
        if session.name == session_files.MANIFEST:
            raise SessionError(f"{session} is the session's manifest file; give its folder: "
                               f"procam calibrate {session.parent}")
        raise SessionError(f"{session} is a file, not a session folder (a folder holding session.json and images/)")
    if not session.exists():
        raise SessionError(f"session folder {session} does not exist")
    return session


def _method_of(path: Path) -> str | None:
    """The method recorded in a calibration.json, or None when there is none or it is not JSON; an
    UnsafeFileError when it is a link, a pipe or a device (calib.formats.fileio.read_regular)."""
    from calib.errors import FormatError
    from calib.formats.fileio import RESULT_MAX_BYTES, read_json

    try:
        m = read_json(path, RESULT_MAX_BYTES, "calibration file").get("method")
    except (FileNotFoundError, FormatError, AttributeError):
        return None
    return m if isinstance(m, str) else None


def default_output(session: Path, method: str) -> tuple[Path, str | None]:
    """Where a result goes without --out, and a note when that is not SESSION/calibration.json: a result
    of another method already there is kept (it may be the verified one), this one is named by method."""
    main = session / RESULT_NAME
    other = _method_of(main)
    if other is None or other == method:
        return main, None
    alt = session / f"calibration-{method}.json"
    return alt, (f"note: {main} holds the {other} calibration and was kept; this {method} calibration is "
                 f"{alt.name} (--out {main} would replace the other)")


def validate(args):
    """Every check that needs no detection: the session, the options, the intrinsics file, the outputs.
    Returns (session, camera model or None, JSON path, the default exports' paths, note or None)."""
    from calib.errors import SessionError
    from calib.formats.session import SessionStore
    from calib.pipeline import METHODS, load_camera_intrinsics

    from calib.export.registry import DEFAULTS, output_paths

    from app.commands._outputs import check_output_file, result_paths

    session = check_session_arg(args.session)
    if args.workers < 1:
        raise SessionError("--workers must be at least 1")
    if args.method not in METHODS:
        raise SessionError(f"unknown calibration method '{args.method}' (available: {', '.join(sorted(METHODS))})")
    if (args.camera_model or args.projector_model) and args.method != CalibrationMethod.JOINT:
        raise SessionError("--camera-model / --projector-model apply to --method joint only")
    store = SessionStore.open(session)
    camera = None
    if args.camera_intrinsics is not None:
        if not Path(args.camera_intrinsics).is_file():
            what = "is a folder, not a file" if Path(args.camera_intrinsics).is_dir() else "does not exist"
            raise SessionError(f"--camera-intrinsics {args.camera_intrinsics} {what} (give a calibration.json or "
                               f"an OpenCV YAML with camera_matrix and distortion_coefficients)")
        size = tuple(store.manifest.rig.camera_size)
        camera = load_camera_intrinsics(args.camera_intrinsics, size)
        if tuple(camera.size) != size:
            raise SessionError(f"--camera-intrinsics {args.camera_intrinsics} is for {camera.width}x{camera.height} "
                               f"images but the session's are {size[0]}x{size[1]}; give intrinsics calibrated at the "
                               f"session's resolution")
    note = None
    if args.out:
        json_path, _ = result_paths(args.out)
    else:
        json_path, note = default_output(session, args.method)
    exports = output_paths(DEFAULTS, json_path.parent, json_path.stem)
    for p in (json_path, *exports):
        check_output_file(p, "--out" if args.out else "the result file", inputs=[args.camera_intrinsics])
    return session, camera, json_path, exports, note


def run(args) -> int:
    from calib.errors import CalibrationError, UntrustedCalibration
    from calib.pipeline import calibrate_session

    from calib.formats.fileio import remove_stale_temporaries

    from app.commands._progress import Progress, progress_mode

    session, camera, out, exports, note = validate(args)
    for path in (out, *exports):  # what a calibrate killed while writing its result left behind
        remove_stale_temporaries(path.parent, (path.name,))
    bars = Progress(progress_mode(args.no_progress))
    try:
        opts = {k: v for k, v in (("camera_model", args.camera_model), ("projector_model", args.projector_model))
                if v is not None}
        result = calibrate_session(session, args.method, camera, args.workers,
                                   progress=bars.callback("calibrate", stages=True),
                                   detect_progress=bars.callback("detect", unit="images"),
                                   method_options=opts or None, detect_cache="refresh" if args.redetect else "use",
                                   trust="accept" if args.accept_untrusted else "check")
    except UntrustedCalibration as e:
        _report_rejected(e, out)
        raise CalibrationError(f"the calibration is not trustworthy ({len(e.report.reasons)} reason(s) above); "
                               f"{out.name} was not written", code="untrusted") from None
    finally:
        bars.close()
    trust = result.diagnostics.get("trust", {}) if isinstance(result.diagnostics, dict) else {}
    if trust.get("reasons"):
        print("WARNING: the trust check rejects this calibration; written anyway (--accept-untrusted):",
              file=sys.stderr)
        for r in trust["reasons"]:
            print(f"  [{r['code']}] {r['message']}", file=sys.stderr)
    kept = verified_and_unchanged(session, out, result)
    write_result(result, out, keep_json=kept)
    print(format_summary(result))
    print(f"placements: {session_placements(session)}")
    print(f"\nkept {out}: the result is the one it holds (to {SAME_TOL:g}), so {VERIFICATION_NAME} still verifies it"
          if kept else f"\nwrote {out}")
    print("\n".join(f"wrote {p}" for p in exports))
    if note:
        print(note)
    stale = stale_verification_note(session, out)
    if stale:
        print(stale)
    from app.commands._quality import EXIT_LOW_QUALITY, report_low_quality

    return EXIT_LOW_QUALITY if report_low_quality(result) else 0


def session_placements(session) -> int:
    """How many positions the operator put the board in for the session's captures."""
    from calib.formats.session import SessionStore
    from calib.formats.session_captures import placements

    return placements(SessionStore.open(session).manifest.captures)


def write_result(result, out: Path, keep_json: bool = False) -> None:
    """calibration.json at `out` (unless `keep_json`: it already holds this result) and the default exports
    beside it (calib.export.registry.DEFAULTS)."""
    from calib.export.registry import DEFAULTS, write_exports

    from app.commands._outputs import write_error

    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        if not keep_json:
            result.save_json(out)
        for warning in write_exports(result, DEFAULTS, out.parent, out.stem):
            print(f"warning: {warning}", file=sys.stderr)
    except OSError as e:
        raise write_error(e.filename or out, e) from None


def stale_verification_note(session: Path, written: Path) -> str | None:
    """A note when `written` replaced SESSION/calibration.json and SESSION/verification.json verified
    something else (it records the SHA-256 of the calibration it checked)."""
    main = session / RESULT_NAME
    report = session / VERIFICATION_NAME
    if not report.exists() or written.resolve() != main.resolve():
        return None
    from app.verification import verification_is_stale, verify_command

    if verification_is_stale(report, main) is False:
        return None
    return (f"note: {report} verified the calibration this one replaced, so it is stale: run "
            f"`{verify_command(session)}` again")


def verified_and_unchanged(session: Path, out: Path, result) -> bool:
    """True when `out` is SESSION/calibration.json, verified by a verification.json that is not stale, and
    `result` is the calibration it holds to SAME_TOL: then the file is kept, and so is its verification
    (re-running the same calibration says nothing new about the rig)."""
    from calib.errors import ProcamError
    from calib.models.result import CalibrationResult

    from app.verification import verification_is_stale

    main = session / RESULT_NAME
    if not main.is_file() or out.resolve() != main.resolve():
        return False
    if verification_is_stale(session / VERIFICATION_NAME, main) is not False:
        return False
    try:
        old = CalibrationResult.load_json(main)
    except (ProcamError, OSError, ValueError):
        return False
    return same_calibration(old, result)


def same_calibration(a, b, tol: float = None) -> bool:
    """Both results' parameters (intrinsics, distortion, pose, mirror, units) agree to `tol` (relative,
    and absolute near zero)."""
    tol = SAME_TOL if tol is None else tol

    def close(x, y):
        x, y = np.asarray(x, float), np.asarray(y, float)
        return x.shape == y.shape and bool(np.allclose(x, y, rtol=tol, atol=tol))

    if a.units != b.units or (a.mirror is None) != (b.mirror is None):
        return False
    pairs = [(a.camera.K, b.camera.K), (a.camera.dist, b.camera.dist), (a.projector.K, b.projector.K),
             (a.projector.dist, b.projector.dist), (a.T_cam_proj, b.T_cam_proj)]
    if a.mirror is not None:
        pairs += [(a.mirror.normal, b.mirror.normal), ([a.mirror.d], [b.mirror.d])]
    return all(close(x, y) for x, y in pairs)


def _report_rejected(e, out: Path) -> None:
    """An untrusted calibration: its reasons on stderr, and the rejected result beside where the result
    would have gone, as NAME.rejected.json (for diagnosis; calibration.json and .yaml are not written)."""
    rejected = out.with_name(out.stem + ".rejected.json")
    print("the trust check rejects this calibration:", file=sys.stderr)
    for r in e.report.reasons:
        print(f"  [{r.code}] {r.message}", file=sys.stderr)
    if e.result is not None:
        try:
            rejected.parent.mkdir(parents=True, exist_ok=True)
            e.result.save_json(rejected)
            print(f"the rejected result is in {rejected} (for diagnosis only; not a calibration)", file=sys.stderr)
        except OSError as err:
            print(f"could not write {rejected}: {err.strerror}", file=sys.stderr)


def _fmt_model(name: str, cam) -> list[str]:
    K = cam.K
    d = ", ".join(f"{x:+.5f}" for x in cam.dist)
    return [f"{name} ({cam.width}x{cam.height}): fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f} px",
            f"{' ' * len(name)}  distortion [k1 k2 p1 p2 k3...] = [{d}]"]


def _fmt_uncertainty(unc, units: str) -> list[str]:
    """1-sigma lines from result.uncertainty (docs/JOINT.md key layout); none when absent."""
    if not isinstance(unc, dict):
        return []
    lines = ["1-sigma:"]
    for name in ("camera", "projector"):
        dev = unc.get(name) or {}
        if dev.get("fixed"):
            lines.append(f"  {name}: fixed (given)")
        elif all(k in dev for k in ("fx", "fy", "cx", "cy")):
            lines.append(f"  {name}: fx {dev['fx']:.2f}  fy {dev['fy']:.2f}  cx {dev['cx']:.2f}  cy {dev['cy']:.2f} px")
    T = unc.get("T_cam_proj") or {}
    if "t_total" in T and "rot_total_deg" in T:
        lines.append(f"  T_cam_proj: position {T['t_total']:.3f} {units}, rotation {T['rot_total_deg']:.4f} deg")
    m = unc.get("mirror")
    if isinstance(m, dict) and "normal_deg" in m and "d" in m:
        lines.append(f"  mirror: normal {m['normal_deg']:.4f} deg, d {m['d']:.3f} {units}")
    return lines if len(lines) > 1 else []


def _fmt_projection_uncertainty(pu) -> list[str]:
    """Projection-uncertainty lines (calib.quality.projection_uncertainty): median and max per device, and where
    it is large; none when the result has no grids."""
    from calib.quality.projection_uncertainty import summary_line

    out = [summary_line(pu, dev) for dev in ("camera", "projector")] if isinstance(pu, dict) else []
    return [line for line in out if line]


#: units of the RMS values of the paper's stages (the joint method's are all camera pixels)
RMS_UNITS = {"camera": "px", "projector": "projector px", "stereo": "px"}


def format_rms(result) -> str:
    """The RMS line, every value with its unit: pixels (of which image, when not the camera's) or the
    length unit for the mirror plane's fit."""
    rms = result.rms or {}
    given = result.diagnostics.get("rms_units", {}) if isinstance(result.diagnostics, dict) else {}
    parts = []
    for key, v in rms.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        if key == "mirror_plane":
            unit = result.units
        elif key in RMS_UNITS:
            unit = RMS_UNITS[key]
        else:
            unit = given.get(key) or "px"
        parts.append(f"{key} {v:.3f} {unit}")
    tail = " (px: camera pixels unless marked)" if parts else ""
    return "RMS: " + (", ".join(parts) if parts else "none") + tail


def format_summary(result) -> str:
    """A readable multi-line summary of a CalibrationResult, safe to print: the skipped images' reasons come
    from files (a detection cache, calibration.json) and their control characters are shown escaped."""
    from app.cli import terminal_safe
    from calib.transforms import invert_T, rotation_angle_deg

    u = result.units
    lines = [f"method: {result.method}    units: {u}"]
    lines += _fmt_model("camera   ", result.camera)
    lines += _fmt_model("projector", result.projector)
    T = np.asarray(result.T_cam_proj)
    t = T[:3, 3]
    pos = invert_T(T)[:3, 3]
    fwd = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    axis_angle = float(np.degrees(np.arccos(np.clip(fwd[2], -1, 1))))
    lines.append(f"T_cam_proj: projector at ({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) {u} in the camera frame "
                 f"(|t| = {np.linalg.norm(t):.2f} {u}); rotation {rotation_angle_deg(T[:3, :3]):.2f} deg; "
                 f"optical axes {axis_angle:.1f} deg apart")
    lines.append(f"            camera at ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}) {u} in the projector frame")
    if result.mirror is not None:
        n = result.mirror.normal
        m = result.diagnostics.get("mirror", {}) if isinstance(result.diagnostics, dict) else {}
        extra = ""
        if m:
            extra = f"; {m.get('method', '?')}, {m.get('n_inliers', '?')} inliers, {m.get('n_outliers', '?')} outliers"
        lines.append(f"mirror: normal ({n[0]:+.4f}, {n[1]:+.4f}, {n[2]:+.4f}), d = {result.mirror.d:.2f} {u}{extra}")
    else:
        lines.append("mirror: none (direct view)")
    lines.append(format_rms(result))
    lines += _fmt_uncertainty(result.uncertainty, u)
    lines += _fmt_projection_uncertainty(result.projection_uncertainty)
    timing = result.diagnostics.get("timing_s", {}) if isinstance(result.diagnostics, dict) else {}
    if timing:
        lines.append("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in timing.items()))
    if result.skipped:
        lines.append(f"skipped ({len(result.skipped)}):")
        for s in result.skipped:
            if isinstance(s, dict):
                where = s.get("image") or s.get("capture_id", "?")
                view = f" [{s['view']}]" if s.get("view") and s.get("view") != s.get("capture_id") else ""
                lines.append(f"  {where}{view} ({s.get('stage', '?')}): {s.get('reason', '')}")
            else:
                lines.append(f"  {s}")
    else:
        lines.append("skipped: none")
    return terminal_safe("\n".join(lines))
