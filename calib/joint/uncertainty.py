"""Covariance of the joint adjustment and the 1-sigma values reported in calibration.json.

Cov = sigma^2 (J^T J)^-1 at the maximum-likelihood solution, sigma^2 = RSS / (N - P) from the
residuals. The board poses are nuisance parameters: they are marginalised with the Schur complement
of their (block-diagonal) part of J^T J, so only a small (global x global) system is inverted.
Key layout of `result.uncertainty`: docs/JOINT.md.
"""

from __future__ import annotations

import numpy as np

from calib.joint.solver import normal_blocks, prior_terms


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


def marginal_covariance(prob, x: np.ndarray):
    """(Cov of the global parameters, variance factor, dof) at x, the board poses marginalised:
    Cov = s^2 (A - B D^-1 B^T)^-1 with J^T J = [[A, B^T], [B, D]] (D block-diagonal per pose) and
    s^2 = r.r / (N - P) of the (whitened) residuals."""
    Jg, Jl = prob.jacobian_blocks(x)
    r = prob.residuals(x)
    A, B, D, _, _ = normal_blocks(prob, Jg, Jl, np.ones_like(r), r)
    E = np.einsum("vij,vjg->vig", np.linalg.inv(D), B)
    schur = A - np.einsum("vkg,vkh->gh", B, E)
    pi, pl = prior_terms(prob)  # a zero-mean prior (k3 shrinkage) adds its precision
    schur[pi, pi] += pl
    dof = max(r.size - prob.n_params, 1)
    s2 = float(np.einsum("i,i->", r, r)) / dof
    return s2 * _sym_inv(schur), s2, dof


def joint_uncertainty(prob, x: np.ndarray) -> dict:
    """1-sigma values of the joint adjustment (prob rebased at its solution x)."""
    cov, sigma2, dof = marginal_covariance(prob, x)
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
        "camera": device("cam", 8 if s.cam_model == "rational" else 5),
        "projector": device("proj", 8 if s.proj_model == "rational" else 5),
    }
    ri = [idx[f"T_cam_proj.rot_{a}"] for a in "xyz"]
    ti = [idx[f"T_cam_proj.t_{a}"] for a in "xyz"]
    # Gibbs vector v at 0: rotation vector = 2 v (left perturbation, camera-frame axes)
    cov_rot = 4.0 * cov[np.ix_(ri, ri)]
    cov_t = cov[np.ix_(ti, ti)]
    out["T_cam_proj"] = {
        "t": np.sqrt(np.diag(cov_t)).tolist(),
        "t_total": float(np.sqrt(np.trace(cov_t))),
        "rot_deg": np.degrees(np.sqrt(np.diag(cov_rot))).tolist(),
        "rot_total_deg": float(np.degrees(np.sqrt(np.trace(cov_rot)))),
    }
    if prob.mirrored:
        mi = [idx["mirror.tilt_1"], idx["mirror.tilt_2"]]
        cov_n = cov[np.ix_(mi, mi)]
        out["mirror"] = {"normal_deg": float(np.degrees(np.sqrt(np.trace(cov_n)))),
                         "d": float(sd[idx["mirror.d"]])}
    else:
        out["mirror"] = None
    out["covariance"] = {"names": list(names), "matrix": cov.tolist(),
                         "note": "global parameters; rotations as Gibbs vectors (rotation vector / 2) about "
                                 "the solution, mirror tilts in radians along two tangent axes"}
    return out
