"""`procam calibrate SESSION`: detect, calibrate, print a summary, write calibration.json + .yaml."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

NAME = "calibrate"
HELP = "calibrate a saved capture session (camera, mirror, projector) and write calibration.json"
DESCRIPTION = (
    "Runs detection and the calibration pipeline on a session folder, prints a summary (intrinsics, "
    "camera-projector pose, mirror plane, RMS per stage, skipped images and why) and writes "
    "calibration.json plus an OpenCV FileStorage export (calibration.yaml) beside it."
)


def add_arguments(p) -> None:
    p.add_argument("session", metavar="SESSION", help="session folder (with session.json)")
    p.add_argument("--method", default="joint",
                   help="calibration method: joint (default: the paper's pipeline, then one joint maximum-likelihood "
                        "refinement, docs/JOINT.md) or paper (the method of Vanherck et al.)")
    models = ("auto", "none", "k1", "k1k2", "5coef", "rational")
    p.add_argument("--camera-model", choices=models, default=None,
                   help="joint method: camera distortion model (default auto: selected by significance tests)")
    p.add_argument("--projector-model", choices=models, default=None,
                   help="joint method: projector distortion model (default auto)")
    p.add_argument("--camera-intrinsics", metavar="FILE", default=None,
                   help="pre-calibrated camera: a calibration.json or an OpenCV YAML with camera_matrix and "
                        "distortion_coefficients; skips the camera stage")
    p.add_argument("--out", metavar="FILE", default=None,
                   help="result file (default SESSION/calibration.json); the YAML export goes beside it")
    p.add_argument("--workers", type=int, default=2, help="detection threads (default 2)")
    p.add_argument("--redetect", action="store_true",
                   help="detect every image again instead of reusing the session's detections.json (results "
                        "of earlier runs, kept per image and detector version)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--accept-untrusted", action="store_true",
                   help="experts: write the result even when the trust check rejects it (absurd parameters, "
                        "huge residuals or uncertainty; docs/CALIBRATION.md); the reasons are printed and "
                        "recorded in the file under diagnostics.trust")


class _Bars:
    """tqdm bars on stderr, one per phase, fed by progress(done, total, label) callbacks."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bars = {}

    def callback(self, phase: str):
        def cb(done, total, label=""):
            if not self.enabled:
                return
            from tqdm import tqdm

            bar = self.bars.get(phase)
            if bar is None:
                bar = self.bars[phase] = tqdm(total=total, desc=phase, file=sys.stderr, unit="step" if phase != "detect" else "img",
                                              leave=True, dynamic_ncols=True)
            if bar.total != total:
                bar.total = total
            bar.n = done
            bar.set_postfix_str(str(label), refresh=False)
            bar.refresh()
        return cb

    def close(self):
        for bar in self.bars.values():
            bar.close()


def run(args) -> int:
    from calib.errors import CalibrationError, SessionError, UntrustedCalibration
    from calib.pipeline import calibrate_session

    session = Path(args.session)
    if not session.is_dir():
        raise SessionError(f"session folder {session} does not exist")
    if args.workers < 1:
        raise SessionError("--workers must be at least 1")
    bars = _Bars(not args.no_progress)
    try:
        opts = {k: v for k, v in (("camera_model", args.camera_model), ("projector_model", args.projector_model))
                if v is not None}
        if opts and args.method != "joint":
            raise SessionError("--camera-model / --projector-model apply to --method joint only")
        result = calibrate_session(session, args.method, args.camera_intrinsics, args.workers,
                                   progress=bars.callback("calibrate"), detect_progress=bars.callback("detect"),
                                   method_options=opts or None, detect_cache="refresh" if args.redetect else "use",
                                   trust="accept" if args.accept_untrusted else "check")
    except UntrustedCalibration as e:
        out = Path(args.out) if args.out else session / "calibration.json"
        _report_rejected(e, out)
        raise CalibrationError(f"the calibration is not trustworthy ({len(e.report.reasons)} reason(s) above); "
                               f"{out.name} was not written", code="untrusted") from None
    finally:
        bars.close()
    out = Path(args.out) if args.out else session / "calibration.json"
    trust = result.diagnostics.get("trust", {}) if isinstance(result.diagnostics, dict) else {}
    if trust.get("reasons"):
        print("WARNING: the trust check rejects this calibration; written anyway (--accept-untrusted):",
              file=sys.stderr)
        for r in trust["reasons"]:
            print(f"  [{r['code']}] {r['message']}", file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    result.save_json(out)
    yaml_path = out.with_suffix(".yaml")
    result.save_opencv_yaml(yaml_path)
    print(format_summary(result))
    print(f"\nwrote {out}\nwrote {yaml_path}")
    return 0


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


def format_summary(result) -> str:
    """A readable multi-line summary of a CalibrationResult."""
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
    rms = result.rms or {}
    parts = []
    for key, unit in (("camera", "px"), ("mirror_plane", u), ("projector", "px"), ("stereo", "px")):
        v = rms.get(key)
        if v is not None:
            parts.append(f"{key} {v:.3f} {unit}")
    for key, v in rms.items():
        if key not in ("camera", "mirror_plane", "projector", "stereo") and isinstance(v, (int, float)):
            parts.append(f"{key} {v:.3f}")
    lines.append("RMS: " + ", ".join(parts))
    lines += _fmt_uncertainty(result.uncertainty, u)
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
    return "\n".join(lines)
