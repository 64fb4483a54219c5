"""The joint adjustment's CalibrationResult (make_result): the fitted devices, T_cam_proj and mirror,
the residuals per observation kind and per view, and the diagnostics of how the result was reached."""

from __future__ import annotations

import numpy as np

from calib.joint.lens import dist_out
from calib.joint.points import KIND_BOARD, KIND_NAMES, KIND_REAL, KIND_VIRTUAL
from calib.joint.problem import JointProblem
from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult, MirrorPlane
from calib.transforms import make_T, nearest_rotation
from calib.models.vocab import CalibrationMethod


def _rms(a: np.ndarray) -> float | None:
    return float(np.sqrt(a.mean())) if a.size else None


def per_view_residuals(prob: JointProblem, x: np.ndarray) -> list[dict]:
    """Per view: point count, rms and max residual (px), per observation kind, and every point's
    residual norm (px; board corners first, by corner id, then pattern points, by index)."""
    r = prob.raw_residuals(x)
    corners = prob.corners
    nc = len(corners)
    e2 = r[0::2] ** 2 + r[1::2] ** 2
    out = []
    for v, ps in enumerate(prob.poses):
        mc = corners.pose == v
        mp = prob.pattern.pose == v
        ec, ep = e2[:nc][mc], e2[nc:][mp]
        allv = np.concatenate([ec, ep])
        rec = {"capture_id": ps.capture_id, "step": ps.role, "n_points": int(allv.size),
               "rms_px": _rms(allv), "max_px": float(np.sqrt(allv.max())) if allv.size else None,
               "point_residuals_px": np.round(np.sqrt(allv), 4).tolist()}
        if ps.role == "projector":
            rec["rms_board_px"] = _rms(ec)
            rec["rms_pattern_px"] = _rms(ep)
        else:
            kinds = corners.kind[mc]
            for kind, name in ((KIND_REAL, "rms_real_px"), (KIND_VIRTUAL, "rms_virtual_px")):
                sel = ec[kinds == kind]
                if sel.size:
                    rec[name] = _rms(sel)
        out.append(rec)
    return out


def _worst_points(prob: JointProblem, e2: np.ndarray, count: int = 10) -> list[dict]:
    nc = len(prob.corners)
    out = []
    for j in np.argsort(-e2)[:count]:
        pts, i = (prob.corners, j) if j < nc else (prob.pattern, j - nc)
        out.append({"capture_id": prob.captures[pts.cid[i]],
                    "kind": KIND_NAMES[pts.kind[i]] if j < nc else "pattern",
                    "point": int(pts.pid[i]), "residual_px": round(float(np.sqrt(e2[j])), 4)})
    return out


def _device(size, K4, d8, model: str) -> CameraModel:
    return CameraModel(size[0], size[1], [[K4[0], 0, K4[2]], [0, K4[1], K4[3]], [0, 0, 1]],
                       dist_out(np.array(d8, float), model))


def make_result(obs, init: CalibrationResult, prob: JointProblem, x: np.ndarray, rejected: list, left_out: list,
                selection: dict, unc: dict | None, solves: list, timing: dict) -> CalibrationResult:
    """The result of the adjustment at its solution x (prob rebased there)."""
    m = prob.unpack(x)
    s = prob.state
    cam = init.camera if prob.fix_camera else _device(obs.camera_size, m["cam_K"], m["cam_d"], s.cam_model)
    proj = _device(obs.projector_size, m["proj_K"], m["proj_d"], s.proj_model)
    T = make_T(nearest_rotation(m["R_cp"]), np.array(m["t_cp"], float))
    mirror = MirrorPlane(np.array(m["n"], float), float(m["d"])) if prob.mirrored else None
    r = prob.raw_residuals(x)
    rw = prob.residuals(x)
    nc = len(prob.corners)
    e2 = r[0::2] ** 2 + r[1::2] ** 2
    kinds = prob.corners.kind
    rms_d = {"joint": _rms(e2), "board": _rms(e2[:nc][kinds == KIND_BOARD]), "pattern": _rms(e2[nc:]),
             "mirror_real": _rms(e2[:nc][kinds == KIND_REAL]),
             "mirror_virtual": _rms(e2[:nc][kinds == KIND_VIRTUAL])}
    rms_d = {k: v for k, v in rms_d.items() if v is not None}
    per_view = per_view_residuals(prob, x)
    worst = sorted((pv for pv in per_view if pv["rms_px"] is not None), key=lambda pv: -pv["rms_px"])[:5]
    diag = {
        "stage": "joint",
        "pattern_model": prob.pattern_model,
        "camera_model": s.cam_model,
        "projector_model": s.proj_model,
        "n_points": {"corners": int(nc), "pattern": len(prob.pattern), "views": len(prob.poses)},
        "n_residuals": int(r.size),
        "n_params": int(prob.n_params),
        "sigma_px": float(np.sqrt((r @ r) / max(r.size - prob.n_params, 1))),
        "class_sigma_px": dict(prob.class_sigma),
        "variance_factor": float((rw @ rw) / max(rw.size - prob.n_params, 1)),
        "worst_points": _worst_points(prob, e2),
        "rejected": rejected,
        "n_rejected": len([x_ for x_ in rejected if x_["kind"] != "view"]),
        "views_left_out": left_out,
        "worst_views": [{"capture_id": w["capture_id"], "step": w["step"], "rms_px": round(w["rms_px"], 4)}
                        for w in worst],
        "model_selection": selection,
        "solves": solves,
        "init_rms": dict(init.rms) if isinstance(init.rms, dict) else {},
        "init_method": init.method,
        "timing_s": timing,
        "board_poses": {ps.capture_id: make_T(s.R[v], s.t[v]).tolist() for v, ps in enumerate(prob.poses)},
    }
    skipped = tuple(init.skipped) + tuple(left_out)
    return CalibrationResult(cam, proj, T, mirror, obs.units, method=CalibrationMethod.JOINT, rms=rms_d, per_view=tuple(per_view),
                             skipped=skipped, uncertainty=unc, diagnostics=diag)
