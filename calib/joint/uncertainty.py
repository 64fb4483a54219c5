"""Covariance of the joint adjustment and the 1-sigma values reported in calibration.json.

Cov = sigma^2 (J^T J)^-1 at the maximum-likelihood solution, sigma^2 = RSS / (N - P) from the
residuals. The board poses are nuisance parameters: they are marginalised with the Schur complement
of their (block-diagonal) part of J^T J, so only a small (global x global) system is inverted.
Key layout of `result.uncertainty`: docs/JOINT.md.
"""

from __future__ import annotations

import numpy as np

from calib.joint.solver import normal_blocks, prior_terms
from calib.transforms import rotvec_covariance
from calib.models.vocab import DistortionModel, Step


def _sym_inv(A: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi-)definite matrix, Jacobi-scaled for conditioning."""
    s = np.sqrt(np.clip(np.diag(A), 1e-300, None))
    As = A / s[:, None] / s[None, :]
    try:
        inv = np.linalg.solve(As, np.eye(len(As)))
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(As, hermitian=True)
    inv = (inv + inv.T) / 2
    return inv / s[:, None] / s[None, :]


#: how many more placements of each step the mirror outlook predicts for (result.uncertainty["mirror"]
#: ["normal_deg_with_more_mirror"][k - 1] is the normal's 1-sigma with k more mirror placements)
MIRROR_OUTLOOK_MAX = 16


def _normal_deg(cov: np.ndarray, mi: list[int]) -> float:
    """The mirror normal's angular 1-sigma (deg, both tilts together) in a covariance."""
    return float(np.degrees(np.sqrt(max(float(np.trace(cov[np.ix_(mi, mi)])), 0.0))))


def _schur_terms(prob, x: np.ndarray, unit_noise: bool = False):
    """(Jg, w, B, D, Schur complement, residuals) of the (whitened, or with `unit_noise` un-whitened)
    normal equations at x, the board poses eliminated."""
    Jg, Jl = prob.jacobian_blocks(x)
    r = prob.residuals(x)
    w = np.ones_like(r)
    if unit_noise:
        scale = getattr(prob, "row_scale", None)
        if scale is None or len(scale) != len(r):
            raise ValueError("the residuals have no class sigma per row")
        w = np.asarray(scale, float) ** 2
    A, B, D, _, _ = normal_blocks(prob, Jg, Jl, w, r)
    E = np.einsum("vij,vjg->vig", np.linalg.inv(D), B)
    schur = A - np.einsum("vkg,vkh->gh", B, E)
    pi, pl = prior_terms(prob)  # a zero-mean prior (k3 shrinkage) adds its precision
    schur[pi, pi] += pl
    return Jg, w, B, D, schur, r


def _variance_factor(prob, r: np.ndarray, unit_noise: bool, variance_factor: float | None):
    dof = max(r.size - prob.n_params, 1)
    if unit_noise:
        return 1.0, dof
    if variance_factor is not None:
        return float(variance_factor), dof
    return float(np.einsum("i,i->", r, r)) / dof, dof


def marginal_covariance(prob, x: np.ndarray, unit_noise: bool = False, variance_factor: float | None = None):
    """(Cov of the global parameters, variance factor, dof) at x, the board poses marginalised:
    Cov = s^2 (A - B D^-1 B^T)^-1 with J^T J = [[A, B^T], [B, D]] (D block-diagonal per pose) and
    s^2 = r.r / (N - P) of the (whitened) residuals.

    `unit_noise`: instead, the covariance the same observations would give with 1 px of noise on every
    one of them (each row un-whitened by its class sigma, s^2 = 1): the session's geometry alone, for
    the quality gate, which must not judge a session by which of its classes happen to be the cleaner."""
    *_, schur, r = _schur_terms(prob, x, unit_noise)
    s2, dof = _variance_factor(prob, r, unit_noise, variance_factor)
    return s2 * _sym_inv(schur), s2, dof


def _mean_view_information(prob, Jg, w, B, D, views) -> np.ndarray | None:
    """The mean information one of `views` brings to the global parameters, its board pose eliminated:
    I_v = A_v - B_v^T D_v^-1 B_v (the poses are eliminated per pose, so the views' shares add up)."""
    if not views:
        return None
    row_pose = np.asarray(prob.row_pose)
    info = np.zeros((Jg.shape[1], Jg.shape[1]))
    for v in views:
        rows = np.flatnonzero(row_pose == v)
        Jv = Jg[rows]
        info += Jv.T @ (Jv * w[rows, None]) - B[v].T @ np.linalg.solve(D[v], B[v])
    return info / len(views)


def _mirror_outlook(prob, Jg, w, B, D, schur, s2: float, cov: np.ndarray) -> dict:
    """What more placements could still do for the mirror normal, and what limits it.

    `normal_deg_with_more_mirror[k - 1]` (`_projector`): the normal's 1-sigma with k more mirror
    (projector) placements, each bringing the mean information of this session's views of that step (so
    as well spread as those); empty when the session has none. `normal_deg_given_camera`: its 1-sigma were
    the camera's intrinsics and distortion known, the part the mirror views themselves leave; the rest
    comes from the camera. Boards seen directly and in the mirror constrain the camera too; boards lying
    on the mirror, all in one plane, hardly do, so further ones lower the normal's 1-sigma slowly."""
    idx = {n: i for i, n in enumerate(prob.global_names)}
    mi = [idx["mirror.tilt_1"], idx["mirror.tilt_2"]]
    ci = [i for n, i in idx.items() if n.startswith("cam.")]
    if ci:
        cmc = cov[np.ix_(mi, ci)]
        given = cov[np.ix_(mi, mi)] - cmc @ np.linalg.solve(cov[np.ix_(ci, ci)], cmc.T)
        given_deg = _normal_deg(given, [0, 1])
    else:
        given_deg = _normal_deg(cov, mi)
    out = {"normal_deg_given_camera": given_deg}
    for key, is_step in (("mirror", lambda st: st.is_mirror), ("projector", lambda st: st == Step.PROJECTOR)):
        info = _mean_view_information(prob, Jg, w, B, D,
                                      [v for v, ps in enumerate(prob.poses) if is_step(Step(ps.role))])
        out[f"normal_deg_with_more_{key}"] = [] if info is None else [
            _normal_deg(s2 * _sym_inv(schur + k * info), mi) for k in range(1, MIRROR_OUTLOOK_MAX + 1)]
    return out


def _guarded_outlook(*args) -> dict:
    """The mirror outlook, or none: it only informs, so a degenerate system (a singular block) must not
    fail a calibration whose covariance itself was computed; non-finite predictions are left out."""
    try:
        out = _mirror_outlook(*args)
    except np.linalg.LinAlgError:
        return {}
    if not np.isfinite(out["normal_deg_given_camera"]):
        return {}
    for key in ("normal_deg_with_more_mirror", "normal_deg_with_more_projector"):
        if not all(np.isfinite(out[key])):
            out[key] = []
    return out


def _summary(prob, cov: np.ndarray, unit_to_mm: float = 1.0) -> dict:
    """The gate's 1-sigma values of a covariance: projector position (total), orientation (total, deg),
    the largest of fx, fy, cx, cy per device (None when held fixed), the mirror normal (deg)."""
    idx = {n: i for i, n in enumerate(prob.global_names)}
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    ri = [idx[f"T_cam_proj.rot_{a}"] for a in "xyz"]
    ti = [idx[f"T_cam_proj.t_{a}"] for a in "xyz"]
    out = {"t_total": float(np.sqrt(np.trace(cov[np.ix_(ti, ti)]))),
           "rot_total_deg": float(np.degrees(np.sqrt(np.trace(rotvec_covariance(cov[np.ix_(ri, ri)])))))}
    for dev, prefix in (("camera", "cam"), ("projector", "proj")):
        keys = [f"{prefix}.{k}" for k in ("fx", "fy", "cx", "cy")]
        out[f"{dev}_intrinsics_px"] = float(max(sd[idx[k]] for k in keys)) if all(k in idx for k in keys) else None
    if prob.mirrored:
        mi = [idx["mirror.tilt_1"], idx["mirror.tilt_2"]]
        out["mirror_normal_deg"] = _normal_deg(cov, mi)
    else:
        out["mirror_normal_deg"] = None
    return out


def joint_uncertainty(prob, x: np.ndarray, variance_factor: float | None = None) -> dict:
    """1-sigma values of the joint adjustment (prob rebased at its solution x); `variance_factor` as
    marginal_covariance's."""
    Jg, w, B, D, schur, r = _schur_terms(prob, x)
    sigma2, dof = _variance_factor(prob, r, False, variance_factor)
    cov = sigma2 * _sym_inv(schur)
    names = prob.global_names
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    idx = {n: i for i, n in enumerate(names)}
    s = prob.state

    def device(prefix: str, model_len: int) -> dict:
        if f"{prefix}.fx" not in idx:  # held fixed (given by the user): no uncertainty from this session
            return {"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0, "dist": [0.0] * model_len, "fixed": True}
        dist = np.zeros(model_len)
        for i in range(model_len):
            key = f"{prefix}.dist{i}"
            if key in idx:
                dist[i] = sd[idx[key]]
        return {"fx": float(sd[idx[f"{prefix}.fx"]]), "fy": float(sd[idx[f"{prefix}.fy"]]),
                "cx": float(sd[idx[f"{prefix}.cx"]]), "cy": float(sd[idx[f"{prefix}.cy"]]),
                "dist": dist.tolist()}

    out = {
        "schema": "procam-uncertainty-1",
        "units": prob.obs.units,
        "variance_factor": float(sigma2),
        "class_sigma_px": dict(prob.class_sigma),
        "dof": int(dof),
        "camera": device("cam", 8 if s.cam_model == DistortionModel.RATIONAL else 5),
        "projector": device("proj", 8 if s.proj_model == DistortionModel.RATIONAL else 5),
    }
    ri = [idx[f"T_cam_proj.rot_{a}"] for a in "xyz"]
    ti = [idx[f"T_cam_proj.t_{a}"] for a in "xyz"]
    # the Gibbs vector about the solution (left perturbation, camera-frame axes) as a rotation vector
    cov_rot = rotvec_covariance(cov[np.ix_(ri, ri)])
    cov_t = cov[np.ix_(ti, ti)]
    out["T_cam_proj"] = {
        "t": np.sqrt(np.diag(cov_t)).tolist(),
        "t_total": float(np.sqrt(np.trace(cov_t))),
        "rot_deg": np.degrees(np.sqrt(np.diag(cov_rot))).tolist(),
        "rot_total_deg": float(np.degrees(np.sqrt(np.trace(cov_rot)))),
    }
    if prob.mirrored:
        mi = [idx["mirror.tilt_1"], idx["mirror.tilt_2"]]
        out["mirror"] = {"normal_deg": _normal_deg(cov, mi),
                         "d": float(sd[idx["mirror.d"]]),
                         **_guarded_outlook(prob, Jg, w, B, D, schur, sigma2, cov)}
    else:
        out["mirror"] = None
    try:  # the same observations with 1 px of noise on every one: what the quality gate judges
        unit = _summary(prob, marginal_covariance(prob, x, unit_noise=True)[0])
        out["unit_noise"] = {**unit, "note": "1-sigma values if every observation had 1 px of noise (the "
                                              "session's geometry alone); t_total in the result's units"}
    except (ValueError, np.linalg.LinAlgError):
        out["unit_noise"] = None
    out["covariance"] = {"names": list(names), "matrix": cov.tolist(),
                         "note": "global parameters; rotations as Gibbs vectors (rotation vector / 2) about "
                                 "the solution, mirror tilts in radians along two tangent axes"}
    return out
