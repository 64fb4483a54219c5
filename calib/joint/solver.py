"""The least-squares machinery of the joint adjustment (calib.joint.method), shared with the distortion-model
selection (calib.joint.model_select) and the covariance (calib.joint.uncertainty): the distortion-model table, the
weighted normal equations in block form (board poses eliminated by the Schur complement), robust
losses by reweighting, and Levenberg-Marquardt.

Everything here works on any `prob` object with JointProblem's interface (x0, residuals,
jacobian_blocks, poses, pose_ndof, pose_start, pose_sum, row_pose, n_global, n_params, set_state,
rebase); it imports nothing from calib.joint.method, so the dependency is one-way: solver <- model_select,
uncertainty <- method <- calib.pipeline.
"""

from __future__ import annotations

import numpy as np

from calib.errors import CalibrationError
from calib.models.vocab import DistortionModel

#: Distortion models: name -> indices of the free coefficients in OpenCV's 8-vector
#: [k1, k2, p1, p2, k3, k4, k5, k6]. Nested, simplest first.
DIST_MODELS = {
    DistortionModel.NONE: (),
    DistortionModel.K1: (0,),
    DistortionModel.K1K2: (0, 1),
    DistortionModel.FOURCOEF: (0, 1, 2, 3),
    DistortionModel.FIVECOEF: (0, 1, 2, 3, 4),
    DistortionModel.RATIONAL: (0, 1, 2, 3, 4, 5, 6, 7),
}
MODEL_NAMES = tuple(DIST_MODELS)
#: the candidates of the BIC / LRT selection (calib.joint.model_select); "4coef" (k1, k2, p1, p2: OpenCV's
#: CALIB_FIX_K3) is reached only by the coverage criterion, which steps down from a model with k3
SELECTION_MODELS = (DistortionModel.NONE, DistortionModel.K1, DistortionModel.K1K2, DistortionModel.FIVECOEF,
                    DistortionModel.RATIONAL)


def _loss_cost_weights(r: np.ndarray, loss: str, f: float) -> tuple[float, np.ndarray]:
    """Robust cost of the residuals (per point: the 2D residual norm) and the IRLS weight per residual."""
    e2 = r[0::2] ** 2 + r[1::2] ** 2
    if loss == "linear":
        return float(e2.sum()), np.ones_like(r)
    z = e2 / (f * f)
    if loss == "soft_l1":
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0)
        w = 1.0 / np.sqrt(1.0 + z)
    elif loss == "huber":
        rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0)
        w = np.where(z <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    elif loss == "cauchy":
        rho = np.log1p(z)
        w = 1.0 / (1.0 + z)
    else:
        raise CalibrationError(f"unknown loss '{loss}' (linear, soft_l1, huber, cauchy)")
    return float(f * f * rho.sum()), np.repeat(w, 2)


class _RowSums:
    """`P @ M` for the (V, N) 0/1 matrix P that sums the rows of M belonging to each pose: rows come in
    runs of one pose (view by view, corners then pattern points), so np.add.reduceat over the runs,
    then one scatter-add of the few run sums, does it without copying M (and without scipy.sparse)."""

    def __init__(self, row_pose: np.ndarray, n_poses: int):
        row_pose = np.asarray(row_pose, int)
        self.starts = np.flatnonzero(np.r_[True, row_pose[1:] != row_pose[:-1]]) if len(row_pose) else \
            np.zeros(0, int)
        self.run_pose = row_pose[self.starts]
        self.n_poses = n_poses

    def __matmul__(self, M: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n_poses,) + M.shape[1:], np.result_type(M, float))
        if len(self.starts):
            np.add.at(out, self.run_pose, np.add.reduceat(M, self.starts, axis=0))
        return out


def normal_blocks(prob, Jg: np.ndarray, Jl: np.ndarray, w: np.ndarray, r: np.ndarray):
    """Blocks of the weighted normal equations J^T W J = [[A, B], [B^T, D]] (D block-diagonal, one
    6x6 block per pose, padded with identity beyond the pose's DOF) and the gradient J^T W r."""
    V = len(prob.poses)
    G = prob.n_global
    wJg = Jg * w[:, None]
    # einsum, not BLAS: threaded GEMM stalls on a busy machine, and these products are small
    A = np.einsum("ni,nj->ij", Jg, wJg)
    wJl = Jl * w[:, None]
    P = prob.pose_sum  # (V, N) sparse: sums rows per pose
    D = np.asarray(P @ (Jl[:, :, None] * wJl[:, None, :]).reshape(-1, 36)).reshape(V, 6, 6)
    B = np.asarray(P @ (wJl[:, :, None] * Jg[:, None, :]).reshape(-1, 6 * G)).reshape(V, 6, G)
    wr = w * r
    g_g = np.einsum("ni,n->i", Jg, wr)
    g_p = np.asarray(P @ (Jl * wr[:, None]))
    pad = np.arange(6)[None, :] >= prob.pose_ndof[:, None]  # unused DOF of 3-DOF poses
    D[:, np.arange(6), np.arange(6)] += pad
    return A, B, D, g_g, g_p


def _schur_solve(A, B, D, g_g, g_p, lam_g, lam_p):
    """Solve [[A + lam_g, B^T], [B, D + lam_p]] [dg; dp] = -[g_g; g_p] with B (V, 6, G)."""
    Dd = D + lam_p
    Dinv = np.linalg.inv(Dd)  # (V, 6, 6), batched
    E = np.einsum("vij,vjg->vig", Dinv, B)  # D^-1 B
    S = (A + lam_g) - np.einsum("vkg,vkh->gh", B, E)
    rhs = -(g_g - np.einsum("vkg,vk->g", E, g_p))
    s_ = np.sqrt(np.clip(np.diag(S), 1e-300, None))
    dg = np.linalg.solve(S / s_[:, None] / s_[None, :], rhs / s_) / s_
    dp = -np.einsum("vij,vj->vi", Dinv, g_p + np.einsum("vkg,g->vk", B, dg))
    return dg, dp


def require_finite(what: str, *arrays) -> None:
    """Raise a CalibrationError (code "non_finite") when any of `arrays` holds NaN or infinity: a solve
    that meets them cannot go on, and numpy would fail later with a message nobody can act on."""
    for a in arrays:
        a = np.asarray(a)
        if a.size and not np.all(np.isfinite(a)):
            bad = int(a.size - np.count_nonzero(np.isfinite(a)))
            raise CalibrationError(
                f"the joint adjustment failed: {what} has {bad} non-finite value(s) (NaN or infinite); the "
                "session's data are probably degenerate (the same image in every capture, wrong pattern points, "
                "boards seen from one pose only): check the captures, or try --method paper to see the "
                "sequential estimate", code="non_finite")


def prior_terms(prob) -> tuple[np.ndarray, np.ndarray]:
    """(indices, precisions) of the zero-mean Gaussian priors on global parameters that `prob.prior`
    ({global parameter name: precision in whitened-residual units}, set by calib.joint.model_select's k3
    shrinkage; absent or empty: none) puts on the current parametrisation. A prior adds
    precision * x^2 to the cost: its normal equations gain the precision on the diagonal."""
    prior = getattr(prob, "prior", None) or {}
    idx = {n: i for i, n in enumerate(prob.global_names)}
    names = [n for n in prior if n in idx]
    return np.array([idx[n] for n in names], int), np.array([float(prior[n]) for n in names])


def _lm(prob, loss: str, f_scale: float, max_iter: int, tol: float) -> tuple[np.ndarray, dict]:
    """Levenberg-Marquardt on the block normal equations (poses eliminated by the Schur complement,
    Marquardt's diagonal scaling, the equivalent of x_scale='jac'); robust losses by iteratively
    reweighted least squares."""
    x = prob.x0()
    r = prob.residuals(x)
    require_finite("the model's predicted pixels at the start of a solve", r)
    cost, w = _loss_cost_weights(r, loss, f_scale)
    pi, pl = prior_terms(prob)
    cost += float(pl @ x[pi] ** 2)
    lam = 1e-7
    nfev, njev, status = 1, 0, 0
    G = prob.n_global
    idx_p = prob.pose_start[:, None] + np.arange(6)[None, :]
    valid = np.arange(6)[None, :] < prob.pose_ndof[:, None]
    for _it in range(max_iter):
        Jg, Jl = prob.jacobian_blocks(x)
        njev += 1
        require_finite("the Jacobian", Jg, Jl)
        A, B, D, g_g, g_p = normal_blocks(prob, Jg, Jl, w, r)
        A[pi, pi] += pl
        g_g[pi] += pl * x[pi]
        dA = np.clip(np.diag(A).copy(), 1e-12, None)
        dD = np.clip(np.diagonal(D, axis1=1, axis2=2).copy(), 1e-12, None)
        accepted = False
        converged = False
        while lam < 1e10:
            lam_g = np.diag(lam * dA)
            lam_p = np.zeros_like(D)
            lam_p[:, np.arange(6), np.arange(6)] = lam * dD
            try:
                dg, dp = _schur_solve(A, B, D, g_g, g_p, lam_g, lam_p)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            step = np.zeros(prob.n_params)
            step[:G] = dg
            step[idx_p[valid]] = dp[valid]
            # predicted decrease of the (reweighted) quadratic model
            Jstep = np.einsum("ng,g->n", Jg, dg) + np.einsum("nk,nk->n", Jl, dp[prob.row_pose])
            pred = -2.0 * (w * r) @ Jstep - (w * Jstep) @ Jstep - 2.0 * (pl * x[pi]) @ dg[pi] - pl @ dg[pi] ** 2
            if pred <= 1e-12 * cost or cost < 1e-18 * r.size:
                converged = True
                break
            x_new = x + step
            r_new = prob.residuals(x_new)
            nfev += 1
            cost_new, w_new = _loss_cost_weights(r_new, loss, f_scale)
            cost_new += float(pl @ x_new[pi] ** 2)
            if np.isfinite(cost_new) and cost_new <= cost:
                accepted = True
                break
            lam = max(lam * 10.0, 1e-6)
        if converged or not accepted:
            status = 1 if converged else 2
            break
        decrease = cost - cost_new
        x, r, w = x_new, r_new, w_new
        cost_prev, cost = cost, cost_new
        lam = max(lam / 10.0, 1e-15)
        if decrease <= tol * cost_prev:
            status = 1
            break
    return x, {"nfev": nfev, "njev": njev, "status": status, "cost": cost, "loss": loss}


def solve(prob, loss: str = "linear", f_scale: float = 1.0, max_nfev: int = 60,
          tol: float = 1e-9, solver: str = "lm") -> tuple[np.ndarray, dict]:
    """One least-squares solve from prob.state; returns (x, info) and rebases prob on the solution.

    solver "lm": Levenberg-Marquardt on the normal equations of the sparse Jacobian (default: ~5-10
    iterations); "scipy": scipy.optimize.least_squares (trf, lsmr, x_scale='jac'), same model and
    Jacobian, typically 3-5x more iterations."""
    prob.reset_warm_start()
    if solver == "scipy":
        from scipy.optimize import least_squares  # only here: importing scipy.optimize takes ~0.8 s

        require_finite("the model's predicted pixels at the start of a solve", prob.residuals(prob.x0()))
        pi, pl = prior_terms(prob)
        import scipy.sparse as sp

        # the priors (if any) as extra residual rows sqrt(precision) x
        rows = sp.csr_matrix((np.sqrt(pl), (np.arange(pi.size), pi)), shape=(pi.size, prob.n_params))

        def fun(x):
            return np.concatenate([prob.residuals(x), np.sqrt(pl) * x[pi]]) if pi.size else prob.residuals(x)

        def jac(x):
            return sp.vstack([prob.jacobian(x), rows]).tocsr() if pi.size else prob.jacobian(x)
        res = least_squares(fun, prob.x0(), jac=jac, method="trf", loss=loss,
                            f_scale=f_scale, x_scale="jac", ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev,
                            tr_solver="lsmr", jac_sparsity=None)
        x = res.x
        info = {"nfev": int(res.nfev), "njev": int(res.njev or 0), "status": int(res.status),
                "cost": float(2 * res.cost), "loss": loss}
    elif solver == "lm":
        x, info = _lm(prob, loss, f_scale, max_nfev, tol)
    else:
        raise CalibrationError(f"unknown solver '{solver}' (lm or scipy)")
    require_finite("the solution", x)
    prob.set_state(prob.rebase(x))
    return prob.x0(), info
