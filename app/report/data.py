"""What the report shows, gathered from a saved session: the calibration (calibration.json), the
verification (verification.json, optional), the detections (detections.json, via calib.detection.detect) and the
per-point residuals recomputed from them.

calibration.json keeps per-view RMS values and every point's residual *norm*, but not the residual
vectors nor where in the image each point was. So the residuals are recomputed: the cached detections
are re-read and projected with the calibrated model through the joint adjustment's own model
(calib.joint.method.build_problem: the same corner, mirror and conic pattern-point models), with the board
poses of `diagnostics.board_poses` when the result holds them (joint method), else posed by PnP with the
calibrated model. Points the adjustment rejected as outliers (`diagnostics.rejected`) and views it left
out are kept apart: they are drawn, but not counted in the statistics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from calib.errors import ProcamError, SessionError
from calib.formats import session_files
from calib.formats.session import SessionStore
from calib.models.result import CalibrationResult
from calib.models.vocab import DistortionModel
from calib.transforms import invert_T

CALIBRATION_FILE = session_files.CALIBRATION
VERIFICATION_FILE = session_files.VERIFICATION

#: observation kinds of the camera residuals (calib.joint.method's names), in the order the report lists them
KINDS = ("board", "pattern", "mirror-real", "mirror-virtual")


class ReportError(ProcamError):
    """The report cannot be written (no calibration, unreadable files...)."""


@dataclass(frozen=True, eq=False)
class Residuals:
    """Recomputed residuals. Camera side, one row per observed point (camera pixels): `cam_uv` where it
    was detected, `cam_res` predicted - detected, `cam_kind` (index into KINDS), `cam_view` (index into
    `views`), `cam_point` (corner id or pattern index), `cam_rejected`. Projector side, one row per
    pattern point: `proj_q` the projector pixel it was drawn at, `proj_res` the camera residual carried
    into the projector (predicted and detected camera pixel both cast onto the board and projected into
    the projector, predicted - detected; projector pixels), `proj_view`, `proj_rejected`."""

    views: tuple  # capture ids
    steps: tuple  # step of each view
    cam_uv: np.ndarray
    cam_res: np.ndarray
    cam_kind: np.ndarray
    cam_view: np.ndarray
    cam_point: np.ndarray
    cam_rejected: np.ndarray
    proj_q: np.ndarray
    proj_res: np.ndarray
    proj_view: np.ndarray
    proj_rejected: np.ndarray
    board_poses: dict  # capture id -> T_cam_board (real camera frame)
    poses_source: str  # "calibration.json" or "PnP ..." (posed with the calibrated model)

    def view_rms(self) -> dict:
        """capture id -> RMS (camera px) of its inlier points."""
        out = {}
        e2 = np.einsum("ij,ij->i", self.cam_res, self.cam_res)
        for v, cid in enumerate(self.views):
            sel = (self.cam_view == v) & ~self.cam_rejected
            if sel.any():
                out[cid] = float(np.sqrt(e2[sel].mean()))
        return out

    def rms(self) -> float | None:
        ok = ~self.cam_rejected
        if not ok.any():
            return None
        return float(np.sqrt(np.mean(np.einsum("ij,ij->i", self.cam_res[ok], self.cam_res[ok]))))


# ---- the optional parts of calibration.json, checked (the file is untrusted) ------------------------------
def _num(x) -> float | None:
    """A finite number, else None."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    return float(x) if np.isfinite(x) else None


def _nums(x, n: int | None = None) -> list:
    if not isinstance(x, list) or (n is not None and len(x) != n):
        return [None] * (n or 0)
    return [_num(v) for v in x]


def _dict(x) -> dict:
    return x if isinstance(x, dict) else {}


def _list(x) -> list:
    return x if isinstance(x, list) else []


def clean_uncertainty(u) -> dict | None:
    """calibration.json's `uncertainty` (docs/JOINT.md) with every value the report prints either a
    finite number or None; None when there is none."""
    if not isinstance(u, dict):
        return None
    out = {"variance_factor": _num(u.get("variance_factor")), "dof": _num(u.get("dof"))}
    for dev in ("camera", "projector"):
        du = _dict(u.get(dev))
        out[dev] = {k: _num(du.get(k)) for k in ("fx", "fy", "cx", "cy")}
        out[dev]["dist"] = _nums(du.get("dist"))
        out[dev]["fixed"] = du.get("fixed") is True
    tu = _dict(u.get("T_cam_proj"))
    out["T_cam_proj"] = {"t": _nums(tu.get("t"), 3), "t_total": _num(tu.get("t_total")),
                         "rot_deg": _nums(tu.get("rot_deg"), 3), "rot_total_deg": _num(tu.get("rot_total_deg"))}
    mu = _dict(u.get("mirror"))
    out["mirror"] = {"normal_deg": _num(mu.get("normal_deg")), "d": _num(mu.get("d"))}
    return out


def clean_diagnostics(diag) -> dict:
    """The parts of `diagnostics` the report shows: distortion model names, RMS units, worst views."""
    diag = _dict(diag)
    worst = []
    for w in diag.get("worst_views") or []:
        if isinstance(w, dict) and isinstance(w.get("capture_id"), str):
            worst.append({"capture_id": w["capture_id"], "step": str(w.get("step", "")), "rms_px": _num(w.get("rms_px"))})
    return {"camera_model": diag.get("camera_model") if isinstance(diag.get("camera_model"), str) else None,
            "projector_model": diag.get("projector_model") if isinstance(diag.get("projector_model"), str) else None,
            "rms_units": {k: str(v) for k, v in _dict(diag.get("rms_units")).items()},
            "worst_views": worst}


def clean_per_view(per_view) -> list[dict]:
    return [{"capture_id": pv["capture_id"], "rms_px": _num(pv.get("rms_px"))}
            for pv in per_view if isinstance(pv, dict) and isinstance(pv.get("capture_id"), str)]


@dataclass(frozen=True, eq=False)
class ReportData:
    session_dir: Path
    store: SessionStore
    result: CalibrationResult
    calibration: dict  # calibration.json as read (the numbers the report prints)
    verification: object | None  # app.verification.VerificationReport
    verification_problem: str | None  # why verification.json could not be used, when it exists
    residuals: Residuals | None
    residuals_problem: str | None  # why the residuals could not be recomputed
    uncertainty: dict | None = None  # clean_uncertainty
    diagnostics: dict = field(default_factory=dict)  # clean_diagnostics
    per_view: list = field(default_factory=list)  # clean_per_view
    calibration_stem: str = "calibration"  # the calibration file's name without .json: the exports' prefix


def gather(session_dir, calibration_path=None) -> ReportData:
    """Read everything the report needs; the calibration from `calibration_path` (default
    SESSION/calibration.json). ReportError / SessionError / FormatError with a one-line reason when the
    session or its calibration cannot be read."""
    session_dir = Path(session_dir)
    if not session_dir.is_dir():
        raise SessionError(f"session folder {session_dir} does not exist")
    store = SessionStore.open(session_dir)
    cal_path = Path(calibration_path) if calibration_path is not None else session_dir / CALIBRATION_FILE
    if not cal_path.is_file():
        if calibration_path is not None:
            raise ReportError(f"{cal_path} does not exist or is not a file")
        raise ReportError(f"{session_dir} has no {CALIBRATION_FILE}: calibrate it first (procam calibrate {session_dir})")
    result = CalibrationResult.load_json(cal_path)
    calibration = result.to_dict()  # the file as its one reader checked it (not read a second time)
    cam_size, proj_size = store.manifest.rig.camera_size, store.manifest.rig.projector_size
    if tuple(result.camera.size) != tuple(cam_size) or tuple(result.projector.size) != tuple(proj_size):
        raise ReportError(f"{cal_path} is for a {result.camera.width}x{result.camera.height} camera and a "
                          f"{result.projector.width}x{result.projector.height} projector, the session's are "
                          f"{cam_size[0]}x{cam_size[1]} and {proj_size[0]}x{proj_size[1]}: not this session's calibration")
    verification, vproblem = _read_verification(session_dir / VERIFICATION_FILE, cal_path)
    residuals, rproblem = None, None
    try:
        residuals = recompute_residuals(store, result)
    except (ProcamError, ValueError, TypeError, IndexError, np.linalg.LinAlgError, cv2.error) as e:
        rproblem = str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__
    return ReportData(session_dir, store, result, calibration, verification, vproblem, residuals, rproblem,
                      clean_uncertainty(calibration.get("uncertainty")), clean_diagnostics(calibration.get("diagnostics")),
                      clean_per_view(calibration.get("per_view") or []), cal_path.stem)


def _read_verification(path: Path, cal_path: Path):
    """(app.verification.VerificationReport or None when absent, None or the reason it is unusable):
    unreadable, or the verification of another calibration (it records the SHA-256 of the file it
    verified; a report written before that was recorded is taken as it is)."""
    if not path.exists():
        return None, None
    from app.verification import VerificationReport, verification_is_stale

    if verification_is_stale(path, cal_path):
        return None, (f"{path.name} verified another calibration than {cal_path.name} (it was recalibrated since, "
                      "or it is another method's result): verify this one with procam verify")

    try:  # validated field by field
        return VerificationReport.from_json(path), None
    except (ProcamError, OSError, ValueError, TypeError) as e:
        return None, f"{path.name} cannot be read: {e}"


# ---- residuals ---------------------------------------------------------------------------------------
def _dist_model(dist) -> str:
    return DistortionModel.RATIONAL if np.asarray(dist).size == 8 else DistortionModel.FIVECOEF


def recompute_residuals(store: SessionStore, result: CalibrationResult) -> Residuals:
    """Detections (from detections.json when it is current, else detected now) projected with `result`."""
    from calib.detection.detect import detect_session
    from calib.joint.method import JointOptions, build_problem
    from calib.joint.points import KIND_NAMES

    obs = detect_session(store, workers=2, cache="use")
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    left_out = {v.get("capture_id") for v in _list(diag.get("views_left_out")) if isinstance(v, dict)}
    rejected_views = {r.get("capture_id") for r in _list(diag.get("rejected"))
                      if isinstance(r, dict) and r.get("kind") == "view"}
    keep = lambda cid: cid not in left_out and cid not in rejected_views  # noqa: E731
    obs = replace(obs, projector_views=tuple(v for v in obs.projector_views if keep(v.capture_id)),
                  mirror_views=tuple(v for v in obs.mirror_views if keep(v.capture_id)))
    try:
        prob, _ = build_problem(obs, result, JointOptions(), _dist_model(result.camera.dist),
                                _dist_model(result.projector.dist))
    except ProcamError as e:
        raise ReportError(f"the residuals cannot be recomputed: {e}") from None
    # the board poses the calibration found, when it stored them
    stored = _dict(diag.get("board_poses"))
    source = "PnP"
    if stored and all(ps.capture_id in stored for ps in prob.poses):
        try:
            prob.set_board_poses(stored)
            source = session_files.CALIBRATION
        except (TypeError, ValueError):  # unreadable: the poses PnP found with the calibrated model stay
            source = "PnP (calibration.json's board poses are unreadable)"
    x = prob.x0()
    prob.update_centroid_correction(x)
    uv_c, uv_p = prob.predict(x)
    poses = prob.board_poses(x)
    corners, pattern = prob.corners, prob.pattern

    cam_kind_c = np.array([KINDS.index(KIND_NAMES[int(k)]) for k in corners.kind], int)
    views = tuple(ps.capture_id for ps in prob.poses)
    steps = tuple(ps.role for ps in prob.poses)
    # the point sets' cid indexes prob.captures, which lists the views in the order of prob.poses
    vid = {cid: views.index(cid) for cid in views}
    cview_c = np.array([vid[prob.captures[i]] for i in corners.cid], int)
    cview_p = np.array([vid[prob.captures[i]] for i in pattern.cid], int)
    rej = _rejected_keys(diag)
    rej_c = np.array([(views[v], KINDS[k], int(p)) in rej for v, k, p in zip(cview_c, cam_kind_c, corners.pid)], bool)
    rej_p = np.array([(views[v], "pattern", int(p)) in rej for v, p in zip(cview_p, pattern.pid)], bool)

    proj_res = _projector_residuals(result, poses, views, cview_p, pattern.uv, uv_p, prob.mirrored)
    res = Residuals(
        views=views, steps=steps,
        cam_uv=np.concatenate([corners.uv, pattern.uv]).reshape(-1, 2),
        cam_res=np.concatenate([uv_c - corners.uv, uv_p - pattern.uv]).reshape(-1, 2),
        cam_kind=np.concatenate([cam_kind_c, np.full(len(pattern.uv), KINDS.index("pattern"))]),
        cam_view=np.concatenate([cview_c, cview_p]),
        cam_point=np.concatenate([corners.pid, pattern.pid]).astype(int),
        cam_rejected=np.concatenate([rej_c, rej_p]),
        proj_q=np.asarray(pattern.q, float).reshape(-1, 2), proj_res=proj_res, proj_view=cview_p,
        proj_rejected=rej_p, board_poses=poses, poses_source=source)
    return res


def _rejected_keys(diag: dict) -> set:
    out = set()
    for r in _list(diag.get("rejected")):
        if isinstance(r, dict) and r.get("kind") in KINDS:
            try:
                out.add((r.get("capture_id"), r["kind"], int(r.get("point"))))
            except (TypeError, ValueError):
                continue
    return out


def _projector_residuals(result: CalibrationResult, poses: dict, views, view_idx, uv_obs, uv_pred,
                         mirrored: bool) -> np.ndarray:
    """Camera residuals of the pattern points in projector pixels: the detected and the predicted camera
    pixel are both cast onto the board (through the mirror) and projected into the projector."""
    out = np.full((len(uv_obs), 2), np.nan)
    if len(uv_obs) == 0:
        return out
    S = result.mirror.reflection() if (mirrored and result.mirror is not None) else np.eye(4)
    T_proj_cam = invert_T(result.T_cam_proj)
    for v in np.unique(view_idx):
        sel = view_idx == v
        T_seen = S @ poses[views[v]]  # the board as the camera sees it (virtual when through the mirror)
        n, p0 = T_seen[:3, 2], T_seen[:3, 3]

        def to_projector(uv):
            r = result.camera.rays(uv)
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = (n @ p0) / (r @ n)
            X = S[:3, :3] @ (r * lam[:, None]).T + S[:3, 3:4]  # back to the real board
            Xp = T_proj_cam[:3, :3] @ X + T_proj_cam[:3, 3:4]
            return result.projector.project(Xp.T)

        out[sel] = to_projector(np.asarray(uv_pred)[sel]) - to_projector(np.asarray(uv_obs)[sel])
    return out


__all__ = ["gather", "ReportData", "Residuals", "ReportError", "recompute_residuals", "KINDS"]
