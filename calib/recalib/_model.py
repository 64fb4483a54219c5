"""The recalibration's model and its least-squares fit: the previous calibration with small corrections
of the camera, mirror and projector blocks and a free board pose per capture (calib.recalib's docstring)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.errors import CalibrationError
from calib.models.observations import BoardObservation, SessionObservations
from calib.models.result import CalibrationResult, MirrorPlane
from calib.paper.board_pose import solve_board_pose
from calib.recalib.prior import IntrinsicsPrior
from calib.transforms import (
    FLIP_X,
    make_T,
    rays_to_board_plane,
    rotvec_gibbs_jacobian,
    tangent_basis,
    transform_points,
    update_R,
    update_T,
)

PARTS = ("camera", "mirror", "projector")
BLOCK_SIZE = {"camera": 4, "mirror": 3, "projector": 6}
#: xtol and ftol of the least squares: tighter tolerances only run the finite-difference Jacobian to
#: max_nfev for changes far below the 1-sigma (docs/RECALIBRATION.md)
TOL = 1e-8
DEFAULT_CLASS_SIGMA_PX = 0.3


# ---- the model --------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Model:
    """The previous calibration and which blocks are free; `prior` (optional) adds the intrinsics
    blocks "cam_intr" / "proj_intr" (see IntrinsicsPrior)."""

    previous: CalibrationResult
    free: tuple[str, ...]
    prior: "IntrinsicsPrior | None" = None

    def size(self, p: str) -> int:
        return BLOCK_SIZE[p] if p in BLOCK_SIZE else self.prior.block_size(p)

    @property
    def blocks(self) -> tuple[str, ...]:
        return self.free + (self.prior.blocks if self.prior is not None else ())

    def split(self, x: np.ndarray) -> tuple[dict, np.ndarray]:
        out, i = {}, 0
        for p in self.blocks:
            out[p] = x[i:i + self.size(p)]
            i += self.size(p)
        return out, x[i:]

    @property
    def n_global(self) -> int:
        return sum(self.size(p) for p in self.blocks)

    def apply(self, blocks: dict) -> CalibrationResult:
        prev = self.previous
        cam = prev.camera
        proj = prev.projector
        if self.prior is not None:
            cam = self.prior.device(cam, "cam_intr", blocks)
            proj = self.prior.device(proj, "proj_intr", blocks)
        if "camera" in blocks:
            K = np.array(cam.K, float)
            d = blocks["camera"]
            K[0, 0] += d[0]
            K[1, 1] += d[1]
            K[0, 2] += d[2]
            K[1, 2] += d[3]
            cam = cam.with_params(K=K)
        mirror = prev.mirror
        if "mirror" in blocks and mirror is not None:
            d = blocks["mirror"]
            u1, u2 = tangent_basis(mirror.normal)
            n = mirror.normal + d[0] * u1 + d[1] * u2
            mirror = MirrorPlane(n / np.linalg.norm(n), mirror.d + d[2])
        T = prev.T_cam_proj
        if "projector" in blocks:
            T = update_T(T, blocks["projector"])
        return prev.with_(camera=cam, projector=proj, mirror=mirror, T_cam_proj=T)


def _S(res: CalibrationResult) -> np.ndarray:
    return np.eye(4) if res.mirror is None else res.mirror.reflection()


def _pose_start(T0: np.ndarray) -> np.ndarray:
    """The parameters of a board pose at its start T0: (Gibbs vector about T0's rotation, translation)."""
    return np.concatenate([np.zeros(3), np.asarray(T0, float)[:3, 3]])


def _pose_T(T0: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The board pose of parameters p (see _pose_start) near its start T0."""
    return make_T(update_R(p[:3], np.asarray(T0, float)[:3, :3]), p[3:])


# ---- the evidence -----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _View:
    """One capture: its board observations (real and/or through the mirror) and pattern points."""

    capture_id: str
    spec: object
    real: BoardObservation | None = None
    virtual: BoardObservation | None = None
    pattern_cam_px: np.ndarray | None = None
    pattern_proj_px: np.ndarray | None = None


def _views(obs: SessionObservations, use: str) -> list[_View]:
    """use: 'boards' (every board observation), 'mirror' (real-virtual captures), 'pattern', or
    'mirror+pattern' (both: a joint re-estimate of the mirror and the projector)."""
    out = []
    if use in ("boards", "mirror", "mirror+pattern"):
        for mv in obs.mirror_views:
            if mv.real is None or mv.virtual is None:
                continue  # real-mirror captures: not used by the check (docs/RECALIBRATION.md)
            out.append(_View(mv.capture_id, obs.mirror_board, mv.real, mv.virtual))
    if use in ("boards", "pattern", "mirror+pattern"):
        for pv in obs.projector_views:
            b = pv.board
            real, virt = (None, b) if b.mirrored else (b, None)
            pat = use in ("pattern", "mirror+pattern") and len(pv.pattern_cam_px) > 0
            out.append(_View(pv.capture_id, obs.projector_board, real, virt,
                             pv.pattern_cam_px if pat else None, pv.pattern_proj_px if pat else None))
    return out


def _class_sigma(prev: CalibrationResult) -> dict:
    u = prev.uncertainty or {}
    cs = u.get("class_sigma_px") if isinstance(u, dict) else None
    cs = cs if isinstance(cs, dict) else {}

    def get(k):
        v = cs.get(k)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) and v > 0 else DEFAULT_CLASS_SIGMA_PX

    return {"board": get("board"), "pattern": get("pattern"), "mirror_real": get("mirror_real"),
            "mirror_virtual": get("mirror_virtual")}


def _initial_pose(cal: CalibrationResult, v: _View) -> np.ndarray:
    if v.real is not None:
        return solve_board_pose(cal.camera, v.spec, v.real).T_cam_view
    T_view = solve_board_pose(cal.camera, v.spec, v.virtual).T_cam_view
    return _S(cal) @ T_view @ FLIP_X


def _residuals(cal: CalibrationResult, v: _View, T: np.ndarray, sig: dict, mirror_view: bool) -> np.ndarray:
    cam, S = cal.camera, _S(cal)
    X = v.spec.corner_points()
    parts = []
    if v.real is not None:
        uv = cam.project(transform_points(T, X[v.real.ids]))
        parts.append(((uv - v.real.corners_px) / sig["mirror_real" if mirror_view else "board"]).ravel())
    if v.virtual is not None:
        uv = cam.project(transform_points(S @ T, X[v.virtual.ids]))
        parts.append(((uv - v.virtual.corners_px) / sig["mirror_virtual" if mirror_view else "board"]).ravel())
    if v.pattern_cam_px is not None:
        Xb, _ = rays_to_board_plane(np.linalg.inv(T) @ cal.T_cam_proj, cal.projector.rays(v.pattern_proj_px))
        uv = cam.project(transform_points(S @ T, Xb))
        parts.append(((uv - v.pattern_cam_px) / sig["pattern"]).ravel())
    r = np.concatenate(parts) if parts else np.zeros(0)
    return np.where(np.isfinite(r), r, 1e3)


@dataclass(frozen=True, eq=False)
class Fit:
    """A fit of the free blocks: the corrections, their covariance, the fitted calibration."""

    free: tuple[str, ...]
    delta: dict  # block -> correction vector (the free parts, and "cam_intr" / "proj_intr" under a prior)
    cov: dict  # block -> covariance (marginal over everything else)
    result: CalibrationResult
    variance_factor: float
    n_views: int
    rms_whitened: float  # RMS of the whitened data residuals (~1 when the noise model fits)
    names: tuple[str, ...] = ()  # the global parameters, named as in the joint's covariance (see _joint_names)
    cov_global: np.ndarray | None = None  # their covariance, board poses marginalised
    prior: "IntrinsicsPrior | None" = None
    #: under a prior: block -> covariance of the free parts with the intrinsics held exactly (the part of
    #: the 1-sigma that more captures lower; the rest is the previous intrinsics' uncertainty)
    cov_data: dict | None = None


def _joint_names(model: _Model) -> tuple[str, ...]:
    """The global parameters of `model` under the names of the joint adjustment's covariance, in the same
    parametrisation (the projector's rotation a Gibbs vector, calib.transforms; the mirror's tilts along
    the tangent basis of the normal the fit started from)."""
    names = []
    for p in model.blocks:
        if p == "camera":
            names += ["cam.fx", "cam.fy", "cam.cx", "cam.cy"]
        elif p == "mirror":
            names += ["mirror.tilt_1", "mirror.tilt_2", "mirror.d"]
        elif p == "projector":
            names += [f"T_cam_proj.rot_{a}" for a in "xyz"] + [f"T_cam_proj.t_{a}" for a in "xyz"]
        else:
            names += list(model.prior.names_of(p))
    return tuple(names)


def fit_blocks(previous: CalibrationResult, obs: SessionObservations, free: tuple[str, ...], use: str,
               prior: "IntrinsicsPrior | None" = None) -> Fit:
    """Least squares of the `free` blocks (others held at `previous`) and one board pose per capture,
    over the captures `use` selects ('boards' | 'mirror' | 'pattern' | 'mirror+pattern'). With `prior`
    the intrinsics it names are free too, pulled to their previous values by its Gaussian prior term."""
    from scipy.optimize import least_squares

    if "mirror" in free and previous.mirror is None:
        free = tuple(p for p in free if p != "mirror")
    views = _views(obs, use)
    if not views:
        raise CalibrationError(f"no captures to test {', '.join(free)} with ({use} captures needed)")
    model = _Model(previous, tuple(free), prior)
    sig = _class_sigma(previous)
    mirror_view = [v.real is not None and v.virtual is not None for v in views]
    starts = []
    for v in views:
        try:
            starts.append(_initial_pose(previous, v))
        except Exception as e:  # a pose that cannot be solved is a capture that cannot be used
            raise CalibrationError(f"capture {v.capture_id}: no board pose ({e})") from None
    ng = model.n_global
    n_prior = 0 if prior is None else prior.n
    # the prior's parameters are solved for in whitened coordinates z = W (x - x_prev) (the prior's residual
    # itself): the intrinsics' correlations (k1, k2, k3; f and the distortion) then do not slow the solver
    g0 = np.zeros(ng)
    if prior is not None:
        g0[ng - n_prior:] = prior.W @ prior.offset
    x0 = np.concatenate([g0] + [_pose_start(T0) for T0 in starts])

    def decode(x):
        blocks, rest = model.split(x)
        if prior is None:
            return blocks, rest, None
        z = x[ng - n_prior:ng]
        d = prior.unwhiten(z)
        i = 0
        for b in prior.blocks:
            blocks[b] = d[i:i + prior.block_size(b)]
            i += prior.block_size(b)
        return blocks, rest, z

    def fun(x):
        blocks, rest, z = decode(x)
        cal = model.apply(blocks)
        r = [_residuals(cal, v, _pose_T(starts[i], rest[6 * i:6 * i + 6]), sig, mirror_view[i])
             for i, v in enumerate(views)]
        if prior is not None:
            r.append(z)
        return np.concatenate(r)

    n_res = len(fun(x0))
    sparsity = np.zeros((n_res, len(x0)), bool)
    row = 0
    blocks0, _, _ = decode(x0)
    cal0 = model.apply(blocks0)
    for i, v in enumerate(views):
        k = len(_residuals(cal0, v, _pose_T(starts[i], x0[ng + 6 * i:ng + 6 * i + 6]), sig, mirror_view[i]))
        sparsity[row:row + k, :ng] = True
        sparsity[row:row + k, ng + 6 * i:ng + 6 * i + 6] = True
        row += k
    sparsity[row:, :ng] = True  # the prior's rows (the intrinsics columns; zeros elsewhere are harmless)
    sol = least_squares(fun, x0, jac_sparsity=sparsity, method="trf", x_scale="jac", xtol=TOL, ftol=TOL,
                        max_nfev=200)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    n_data = n_res - n_prior
    r, Jd, Jp = sol.fun[:n_data], J[:n_data], J[n_data:]
    # the variance factor from the data alone (the prior's parameters are determined by the prior, so they
    # do not use up data degrees of freedom); the prior enters the information with weight 1
    dof = max(n_data - (len(x0) - n_prior), 1)
    s2 = float(r @ r) / dof
    info = Jd.T @ Jd / s2 + Jp.T @ Jp
    try:
        cov_all = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov_all = np.linalg.pinv(info)
    if prior is not None:  # back from the whitened coordinates: d = W^-1 z - offset
        T = np.eye(len(x0))
        T[ng - n_prior:ng, ng - n_prior:ng] = prior.W_inv
        cov_all = T @ cov_all @ T.T
    blocks, _, _ = decode(sol.x)
    cov, i = {}, 0
    for p in model.blocks:
        k = model.size(p)
        cov[p] = cov_all[i:i + k, i:i + k]
        i += k
    cov_data = None
    if prior is not None:  # the free parts' covariance were the intrinsics known exactly: what captures lower
        keep = np.r_[0:ng - n_prior, ng:len(x0)]
        try:
            cov_fixed = np.linalg.inv(info[np.ix_(keep, keep)])
        except np.linalg.LinAlgError:
            cov_fixed = np.linalg.pinv(info[np.ix_(keep, keep)])
        cov_data, i = {}, 0
        for p in model.free:
            k = model.size(p)
            cov_data[p] = cov_fixed[i:i + k, i:i + k]
            i += k
    result = model.apply(blocks)
    rms = float(np.sqrt(np.mean(r**2)))
    return Fit(model.free, {p: np.asarray(blocks[p]) for p in model.blocks}, cov, result, s2, len(views), rms,
               _joint_names(model), cov_all[:ng, :ng], prior, cov_data)


# ---- the previous calibration's covariance of each block --------------------------------------------
def previous_covariance(previous: CalibrationResult, part: str) -> np.ndarray:
    """Covariance of `part`'s correction parameters from the previous calibration's uncertainty (the
    stored covariance where its parameter names are there, else its 1-sigma values; zeros for a part
    the previous calibration held fixed or did not report)."""
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    cv = u.get("covariance") if isinstance(u.get("covariance"), dict) else {}
    names, M = cv.get("names"), cv.get("matrix")
    idx = {n: i for i, n in enumerate(names)} if isinstance(names, list) else {}
    try:
        M = np.array(M, float) if M is not None else None
    except (TypeError, ValueError):
        M = None
    if part == "camera":
        keys = ["cam.fx", "cam.fy", "cam.cx", "cam.cy"]
        if M is not None and all(n in idx for n in keys):
            ii = [idx[n] for n in keys]
            return M[np.ix_(ii, ii)]
        c = u.get("camera") or {}
        return np.diag([float(c.get(n, 0.0) or 0.0) ** 2 for n in ("fx", "fy", "cx", "cy")])
    if part == "mirror":
        m = u.get("mirror") or {}
        s_n = math.radians(float(m.get("normal_deg", 0.0) or 0.0))
        s_d = float(m.get("d", 0.0) or 0.0)
        # the total angular sigma split evenly over the two tilts (isotropic in the mirror's plane)
        return np.diag([s_n**2 / 2, s_n**2 / 2, s_d**2])
    keys_r = [f"T_cam_proj.rot_{a}" for a in "xyz"]
    keys_t = [f"T_cam_proj.t_{a}" for a in "xyz"]
    if M is not None and all(n in idx for n in keys_r + keys_t):
        ii = [idx[n] for n in keys_r + keys_t]
        return M[np.ix_(ii, ii)].copy()
    t = u.get("T_cam_proj") or {}
    # the 1-sigma angles are of the rotation vector: the Gibbs vector's are the inverse map's at 0
    to_gibbs = np.linalg.inv(rotvec_gibbs_jacobian(np.zeros(3)))
    rot = to_gibbs @ [math.radians(float(v)) for v in (t.get("rot_deg") or [0, 0, 0])]
    tt = [float(v) for v in (t.get("t") or [0, 0, 0])]
    return np.diag([v**2 for v in [*rot, *tt]])
