"""On-site recalibration: check what moved, re-measure only that, compare with before.

Pure computation (docs/RECALIBRATION.md). One entry function per stage:

  check_rig(previous, obs)            -> CheckReport: per part (camera intrinsics, mirror, projector
                                         pose) whether the new observations say it moved
  reestimate(previous, obs, parts)    -> Reestimate: the moved parts re-fitted (intrinsics under a prior)
  compare_calibrations(prev, new)     -> dict: the change of each part with its uncertainty

The model is the previous calibration with small corrections of three parameter blocks:
  camera    4: fx, fy, cx, cy (px; distortion held: a refocus changes the focal length)
  mirror    3: two tilts of the normal (rad, about tangent axes of the previous normal) and d (units)
  projector 6: rotation vector (rad, camera axes, R = exp([w]) R_prev) and translation (units, camera
               frame) of T_cam_proj
and one free board pose per capture (a nuisance parameter). The re-estimate adds, by default, the
intrinsics of both devices (fx, fy, cx, cy and the distortion coefficients the previous calibration
estimated) under a Gaussian prior from the previous calibration's covariance (IntrinsicsPrior;
reestimate's `intrinsics` "prior" | "held", docs/RECALIBRATION.md for the numbers). Residuals are
whitened by the previous calibration's per-class noise sigma (uncertainty.class_sigma_px) and minimised
with scipy.optimize.least_squares; the covariance of a fitted block is s^2 (J^T J)^-1 (s^2 the variance
factor), marginal over the board poses.

The rule of the check, per part p with correction delta_p fitted from the new captures (C_new its
covariance) and C_prev the previous calibration's covariance of the same parameters:

    m2 = delta_p^T (F^2 (C_prev + C_new))^-1 delta_p,   moved when m2 > chi2.ppf(1 - ALPHA, dim p)

ALPHA = 1e-3, F = SYSTEMATIC_FACTOR = 2: docs/JOINT.md measures true errors of 1-2x the reported sigma
on rendered sessions (detection biases no residual sees), so a change must exceed twice the combined
sigma, at 99.9 % confidence, to be called a move. A change well inside the previous 1-sigma is
"unchanged" by construction.

Parts are tested in order, each with what was decided before held: the camera from every board view
(the mirror free, so that a moved mirror cannot pass for a change of focal length), then the mirror
from real-virtual captures (a board seen directly and in the mirror), then the projector from the
projected pattern. The pattern alone cannot tell a moved mirror from a moved projector (it only sees
the projector's mirror image), which is why the mirror is tested first on its own captures.
"""

from __future__ import annotations

import hashlib
import os
import math
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from calib.errors import CalibrationError
from calib.formats.fileio import RESULT_MAX_BYTES, open_regular
from calib.models.camera import CameraModel
from calib.models.observations import BoardObservation, SessionObservations
from calib.models.result import CalibrationResult, MirrorPlane
from calib.paper.board_pose import solve_board_pose
from calib.transforms import make_T, rays_to_board_plane, rotation_angle_deg, transform_points

PARTS = ("camera", "mirror", "projector")
BLOCK_SIZE = {"camera": 4, "mirror": 3, "projector": 6}
ALPHA = 1e-3
SYSTEMATIC_FACTOR = 2.0
#: xtol and ftol of the least squares: at 1e-12 every fit ran to max_nfev (200 evaluations of a finite-
#: difference Jacobian); 1e-8 stops after 4-10 with changes below 1/100 of the 1-sigma (docs/RECALIBRATION.md)
TOL = 1e-8
DEFAULT_CLASS_SIGMA_PX = 0.3
#: 1-sigma targets of a re-estimate where the previous calibration reports none (see targets_from)
DEFAULT_TARGETS = {"projector_t": 0.5, "projector_rot_deg": 0.05, "mirror_normal_deg": 0.05, "mirror_d": 0.5,
                   "camera_f_px": 1.0}
_F = np.diag([-1.0, 1.0, 1.0, 1.0])  # board frame x -> -x (a mirrored view's board frame)


# ---- the model --------------------------------------------------------------------------------------
def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u1 = np.cross(n, a)
    u1 /= np.linalg.norm(u1)
    return u1, np.cross(n, u1)


def _rotvec_R(w) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))
    return R


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
            u1, u2 = _tangent_basis(mirror.normal)
            n = mirror.normal + d[0] * u1 + d[1] * u2
            mirror = MirrorPlane(n / np.linalg.norm(n), mirror.d + d[2])
        T = prev.T_cam_proj
        if "projector" in blocks:
            d = blocks["projector"]
            T = make_T(_rotvec_R(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])
        return prev.with_(camera=cam, projector=proj, mirror=mirror, T_cam_proj=T)


def _S(res: CalibrationResult) -> np.ndarray:
    return np.eye(4) if res.mirror is None else res.mirror.reflection()


def _pose_T(p: np.ndarray) -> np.ndarray:
    return make_T(_rotvec_R(p[:3]), p[3:])


def _pose_p(T: np.ndarray) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.asarray(T[:3, :3], float))
    return np.concatenate([r.reshape(3), T[:3, 3]])


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
    return _S(cal) @ T_view @ _F


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
    """The global parameters of `model` under the names of calib.joint.method's covariance (the projector's
    rotation and the mirror's tilts in this module's own parametrisation: _updated_uncertainty converts)."""
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
    poses0 = []
    for v in views:
        try:
            poses0.append(_pose_p(_initial_pose(previous, v)))
        except Exception as e:  # a pose that cannot be solved is a capture that cannot be used
            raise CalibrationError(f"capture {v.capture_id}: no board pose ({e})") from None
    ng = model.n_global
    n_prior = 0 if prior is None else prior.n
    # the prior's parameters are solved for in whitened coordinates z = W (x - x_prev) (the prior's residual
    # itself): the intrinsics' correlations (k1, k2, k3; f and the distortion) then do not slow the solver
    g0 = np.zeros(ng)
    if prior is not None:
        g0[ng - n_prior:] = prior.W @ prior.offset
    x0 = np.concatenate([g0] + poses0)

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
        r = [_residuals(cal, v, _pose_T(rest[6 * i:6 * i + 6]), sig, mirror_view[i]) for i, v in enumerate(views)]
        if prior is not None:
            r.append(z)
        return np.concatenate(r)

    n_res = len(fun(x0))
    sparsity = np.zeros((n_res, len(x0)), bool)
    row = 0
    blocks0, _, _ = decode(x0)
    cal0 = model.apply(blocks0)
    for i, v in enumerate(views):
        k = len(_residuals(cal0, v, _pose_T(x0[ng + 6 * i:ng + 6 * i + 6]), sig, mirror_view[i]))
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
    k = BLOCK_SIZE[part]
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    cv = u.get("covariance") if isinstance(u.get("covariance"), dict) else {}
    names, M = cv.get("names"), cv.get("matrix")
    idx = {n: i for i, n in enumerate(names)} if isinstance(names, list) else {}
    try:
        M = np.array(M, float) if M is not None else None
    except (TypeError, ValueError):
        M = None
    C = np.zeros((k, k))
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
        C = M[np.ix_(ii, ii)].copy()
        C[:3, :] *= 2.0  # Gibbs vector -> rotation vector
        C[:, :3] *= 2.0
        return C
    t = u.get("T_cam_proj") or {}
    rot = [math.radians(float(v)) for v in (t.get("rot_deg") or [0, 0, 0])]
    tt = [float(v) for v in (t.get("t") or [0, 0, 0])]
    return np.diag([v**2 for v in rot + tt])


# ---- the intrinsics prior ---------------------------------------------------------------------------
#: eigenvalues of the prior's correlation matrix below PRIOR_EIG_FLOOR x the largest are raised to it:
#: along directions the previous session could not separate (e.g. k3 against k1, k2) the prior becomes
#: weaker, never stronger, and its Cholesky factor exists
PRIOR_EIG_FLOOR = 1e-9
INTRINSICS_MODES = ("held", "prior")
_DEVICE_BLOCK = {"cam": "cam_intr", "proj": "proj_intr"}


@dataclass(frozen=True, eq=False)
class IntrinsicsPrior:
    """A Gaussian prior on device intrinsics (fx, fy, cx, cy and the distortion coefficients the
    previous calibration estimated): the previous values as its mean, the previous covariance of those
    parameters (the marginal: the matching rows and columns of the stored covariance) as its
    covariance. Its residuals are W (x - x_prev), W = L^-1 D^-1 where D^-1 C D^-1 = L L^T (Cholesky of
    the correlation matrix, eigenvalues floored at PRIOR_EIG_FLOOR): |r|^2 = (x - x_prev)^T C^-1 (x - x_prev)."""

    blocks: tuple[str, ...]  # "cam_intr" and/or "proj_intr"
    params: dict  # block -> tuple of names ("cam.fx", ..., "cam.dist1", ...)
    offset: np.ndarray  # the model's start minus the prior's mean, in the order of the blocks' names
    W: np.ndarray  # (n, n) whitening matrix
    floored: int  # eigenvalues raised to the floor

    @property
    def n(self) -> int:
        return len(self.offset)

    def block_size(self, block: str) -> int:
        return len(self.params[block])

    def names_of(self, block: str) -> tuple[str, ...]:
        return self.params[block]

    def residual(self, blocks: dict) -> np.ndarray:
        return self.W @ (self.offset + np.concatenate([blocks[b] for b in self.blocks]))

    @cached_property
    def W_inv(self) -> np.ndarray:
        return np.linalg.inv(self.W)

    def unwhiten(self, z: np.ndarray) -> np.ndarray:
        """The corrections (all blocks, in order) whose residual is z."""
        return self.W_inv @ z - self.offset

    def device(self, dev: CameraModel, block: str, blocks: dict) -> CameraModel:
        """`dev` with the correction of `block` applied (unchanged when the block is not there)."""
        if block not in blocks:
            return dev
        return _with_intrinsics(dev, self.params[block], _intrinsics(dev, self.params[block]) + blocks[block])


def _dist_index(name: str) -> int | None:
    tail = name.rsplit(".", 1)[-1]
    return int(tail[4:]) if tail.startswith("dist") and tail[4:].isdigit() else None


def _intrinsics(dev: CameraModel, names) -> np.ndarray:
    K = np.asarray(dev.K, float)
    d8 = np.zeros(8)
    d8[:dev.dist.size] = dev.dist
    val = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    return np.array([val[n.rsplit(".", 1)[-1]] if _dist_index(n) is None else d8[_dist_index(n)] for n in names])


def _with_intrinsics(dev: CameraModel, names, values) -> CameraModel:
    K = np.array(dev.K, float)
    top = max([_dist_index(n) for n in names if _dist_index(n) is not None], default=-1)
    d = np.zeros(8 if max(top, dev.dist.size - 1) >= 5 else 5)
    d[:dev.dist.size] = dev.dist
    pos = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
    for n, v in zip(names, values):
        i = _dist_index(n)
        if i is None:
            K[pos[n.rsplit(".", 1)[-1]]] = v
        else:
            d[i] = v
    return dev.with_params(K=K, dist=d)


def _stored_covariance(previous: CalibrationResult) -> tuple[list, np.ndarray] | None:
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    cv = u.get("covariance") if isinstance(u.get("covariance"), dict) else {}
    names = cv.get("names")
    try:
        M = np.array(cv.get("matrix"), float)
    except (TypeError, ValueError):
        return None
    if not isinstance(names, list) or M.ndim != 2 or M.shape != (len(names), len(names)) or \
            not np.all(np.isfinite(M)):
        return None
    return names, (M + M.T) / 2


def intrinsics_prior(previous: CalibrationResult, current: CalibrationResult,
                     devices=("cam", "proj")) -> IntrinsicsPrior | None:
    """The prior on the intrinsics of `devices` ("cam", "proj") from `previous`'s stored covariance, for
    a model started at `current`; None when the previous calibration stored no covariance of them (held
    fixed, another method, or an unreadable file): then they can only be held."""
    stored = _stored_covariance(previous)
    if stored is None:
        return None
    names, M = stored
    idx = {n: i for i, n in enumerate(names)}
    params = {}
    for dev in devices:
        core = [f"{dev}.{k}" for k in ("fx", "fy", "cx", "cy")]
        if not all(n in idx for n in core):
            continue
        dist = sorted((n for n in names if n.startswith(f"{dev}.dist") and _dist_index(n) is not None),
                      key=_dist_index)
        params[_DEVICE_BLOCK[dev]] = tuple(core + dist)
    if not params:
        return None
    blocks = tuple(params)
    order = [n for b in blocks for n in params[b]]
    ii = [idx[n] for n in order]
    C = M[np.ix_(ii, ii)]
    sd = np.sqrt(np.diag(C))
    if not np.all(sd > 0):
        return None
    R = C / sd[:, None] / sd[None, :]
    lam, V = np.linalg.eigh((R + R.T) / 2)
    floor = PRIOR_EIG_FLOOR * float(lam[-1])
    floored = int(np.sum(lam < floor))
    L = np.linalg.cholesky((V * np.maximum(lam, floor)) @ V.T)
    from scipy.linalg import solve_triangular

    W = solve_triangular(L, np.diag(1.0 / sd), lower=True)
    devs = {"cam_intr": (current.camera, previous.camera), "proj_intr": (current.projector, previous.projector)}
    offset = np.concatenate([_intrinsics(devs[b][0], params[b]) - _intrinsics(devs[b][1], params[b]) for b in blocks])
    return IntrinsicsPrior(blocks, params, offset, W, floored)


# ---- stage 1: check ---------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PartCheck:
    part: str
    status: str  # "moved" | "unchanged" | "not checked"
    change: dict  # the fitted change in physical units (px, deg, units)
    sigma: dict  # its combined 1-sigma (previous and new), same keys
    mahalanobis2: float | None
    threshold: float | None
    captures: int
    reason: str

    @property
    def moved(self) -> bool:
        return self.status == "moved"

    def to_dict(self) -> dict:
        return {"part": self.part, "status": self.status, "change": self.change, "sigma": self.sigma,
                "mahalanobis2": self.mahalanobis2, "threshold": self.threshold, "captures": self.captures,
                "reason": self.reason}


@dataclass(frozen=True, eq=False)
class CheckReport:
    parts: dict  # part -> PartCheck
    current: CalibrationResult  # the previous calibration with the parts found moved provisionally re-fitted
    rule: str = ""

    @property
    def moved(self) -> tuple[str, ...]:
        return tuple(p for p in PARTS if p in self.parts and self.parts[p].moved)

    @property
    def verdict(self) -> str:
        if any(c.status == "not checked" for c in self.parts.values()):
            return "incomplete"
        return "unchanged" if not self.moved else "moved: " + ", ".join(self.moved)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "moved": list(self.moved), "rule": self.rule,
                "parts": {p: c.to_dict() for p, c in self.parts.items()}}


def describe_change(part: str, delta: np.ndarray, cov: np.ndarray, units: str) -> tuple[dict, dict]:
    """(change, 1-sigma) of a block's correction in physical units."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    if part in ("camera", "cam_intr", "proj_intr"):  # fx, fy, cx, cy first (distortion not described)
        keys = ("fx_px", "fy_px", "cx_px", "cy_px")
        return ({k: float(v) for k, v in zip(keys, delta)}, {k: float(v) for k, v in zip(keys, sd)})
    if part == "mirror":
        return ({"normal_deg": math.degrees(float(np.linalg.norm(delta[:2]))), f"d_{units}": float(delta[2])},
                {"normal_deg": math.degrees(float(np.sqrt(cov[0, 0] + cov[1, 1]))), f"d_{units}": float(sd[2])})
    return ({"rot_deg": math.degrees(float(np.linalg.norm(delta[:3]))), f"t_{units}": float(np.linalg.norm(delta[3:])),
             f"t_xyz_{units}": [float(v) for v in delta[3:]]},
            {"rot_deg": math.degrees(float(np.sqrt(np.trace(cov[:3, :3])))),
             f"t_{units}": float(np.sqrt(np.trace(cov[3:, 3:])))})


def describe_movement(check: PartCheck, units: str) -> str:
    """A part's fitted change in physical units with its 1-sigma: what the check's statistic stands for
    ("" for a part not checked)."""
    c, s = check.change, check.sigma
    if not c:
        return ""
    if check.part == "camera":
        return (f"fx {c['fx_px']:+.2f} px, fy {c['fy_px']:+.2f} px (1-sigma {s['fx_px']:.2f}, "
                f"{s['fy_px']:.2f} px)")
    if check.part == "mirror":
        return (f"tilted {c['normal_deg']:.3f} deg, offset {c[f'd_{units}']:+.2f} {units} (1-sigma "
                f"{s['normal_deg']:.3f} deg, {s[f'd_{units}']:.2f} {units})")
    return (f"turned {c['rot_deg']:.3f} deg, shifted {c[f't_{units}']:.2f} {units} (1-sigma {s['rot_deg']:.3f} deg, "
            f"{s[f't_{units}']:.2f} {units})")


def _test(previous: CalibrationResult, fit: Fit, part: str, alpha: float, factor: float) -> PartCheck:
    from scipy.stats import chi2

    d, Cn = fit.delta[part], fit.cov[part]
    Cp = previous_covariance(previous, part)
    change, sigma = describe_change(part, d, Cp + Cn, previous.units)
    if part == "camera":  # tested on the focal lengths (what a refocus changes); cx, cy re-fitted with them
        d, Cn, Cp = d[:2], Cn[:2, :2], Cp[:2, :2]
    C = factor**2 * (Cp + Cn)
    try:
        m2 = float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        m2 = float(d @ np.linalg.pinv(C) @ d)
    thr = float(chi2.ppf(1.0 - alpha, len(d)))
    moved = m2 > thr
    reason = (f"change {m2:.1f} > {thr:.1f} (chi-square, {len(d)} dof, p < {alpha:g}) in units of {factor:g}x the "
              f"combined 1-sigma of the previous calibration and these {fit.n_views} captures" if moved else
              f"change {m2:.1f} <= {thr:.1f}: within {factor:g}x the combined 1-sigma")
    return PartCheck(part, "moved" if moved else "unchanged", change, sigma, m2, thr, fit.n_views, reason)


def check_rig(previous: CalibrationResult, obs: SessionObservations, alpha: float = ALPHA,
              factor: float = SYSTEMATIC_FACTOR) -> CheckReport:
    """Stage 1: for the camera intrinsics, the mirror and the projector pose, whether the new captures
    `obs` agree with `previous` (see the module docstring for the rule). A part without the captures
    its test needs is "not checked"."""
    parts = {}
    cur = previous
    rule = (f"moved when d^T (F^2 (C_prev + C_new))^-1 d > chi2.ppf(1 - {alpha:g}, dim), F = {factor:g}; "
            "parts tested in order camera, mirror, projector, each with the earlier verdicts held")
    # (part, blocks fitted, observations, result attribute, what to capture when it cannot be tested); the
    # camera from every board view with the mirror free (views through the mirror constrain it too)
    order = (("camera", ("camera", "mirror"), "boards", "camera", ""),
             ("mirror", ("mirror",), "mirror", "mirror", ": capture the board held between camera and mirror"),
             ("projector", ("projector",), "pattern", "T_cam_proj", ": capture the board with the pattern on it"))
    for part, blocks, data, attr, hint in order:
        if part == "mirror" and previous.mirror is None:
            continue
        try:
            fit = fit_blocks(cur, obs, blocks, data)
            parts[part] = _test(previous, fit, part, alpha, factor)
            if parts[part].moved:
                cur = cur.with_(**{attr: getattr(fit.result, attr)})
        except CalibrationError as e:
            parts[part] = PartCheck(part, "not checked", {}, {}, None, None, 0, f"{e}{hint}")
    return CheckReport(parts, cur, rule)


def merge_observations(a: SessionObservations, b: SessionObservations) -> SessionObservations:
    """The captures of `a` and `b` together (same rig and boards): the check's captures count for the
    re-estimate too."""
    from dataclasses import replace

    return replace(a, projector_views=tuple(a.projector_views) + tuple(b.projector_views),
                   mirror_views=tuple(a.mirror_views) + tuple(b.mirror_views),
                   skipped=tuple(a.skipped) + tuple(b.skipped))


# ---- stage 2: re-estimate ---------------------------------------------------------------------------
def targets_from(previous: CalibrationResult) -> dict:
    """The 1-sigma a re-estimated part must reach: the previous calibration's own 1-sigma of that part
    (a recalibration at least as certain as the calibration it replaces); DEFAULT_TARGETS where the
    previous calibration reports none (or held the part fixed)."""
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    out = dict(DEFAULT_TARGETS)

    def pos(v):
        return isinstance(v, (int, float)) and math.isfinite(v) and v > 0

    t = u.get("T_cam_proj") or {}
    if pos(t.get("t_total")):
        out["projector_t"] = float(t["t_total"])
    if pos(t.get("rot_total_deg")):
        out["projector_rot_deg"] = float(t["rot_total_deg"])
    m = u.get("mirror") or {}
    if pos(m.get("normal_deg")):
        out["mirror_normal_deg"] = float(m["normal_deg"])
    if pos(m.get("d")):
        out["mirror_d"] = float(m["d"])
    c = u.get("camera") or {}
    if pos(c.get("fx")) and pos(c.get("fy")):
        out["camera_f_px"] = max(float(c["fx"]), float(c["fy"]))
    return out


_USE = {"camera": "boards", "mirror": "mirror", "projector": "pattern"}


#: how a re-estimate treats the intrinsics of the parts it does not re-fit (docs/RECALIBRATION.md,
#: "Intrinsics: held or prior", for the numbers behind the default)
DEFAULT_INTRINSICS = "prior"
_SIGMA_KEY = {"cam_intr": "camera_intrinsics", "proj_intr": "projector_intrinsics"}


@dataclass(frozen=True, eq=False)
class Reestimate:
    result: CalibrationResult
    parts: tuple[str, ...]
    sigma: dict  # part -> 1-sigma of the re-estimated parameters (describe_change keys)
    targets: dict
    reached: bool
    missing: tuple[str, ...]  # targets not reached, as sentences
    intrinsics: str = "held"  # the mode used: "held" | "prior" (see reestimate)
    intrinsics_note: str = ""
    #: under the prior: targets whose 1-sigma stays above the target only because of the previous
    #: intrinsics' uncertainty (the captures' own share is below it: more captures cannot help), as sentences
    floor: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"parts": list(self.parts), "intrinsics": self.intrinsics, "intrinsics_note": self.intrinsics_note,
                "sigma": self.sigma, "targets": self.targets, "reached": self.reached, "missing": list(self.missing),
                "limited_by_previous_intrinsics": list(self.floor)}


def _missing(p: str, s: dict, targets: dict, u: str) -> list[str]:
    out = []
    if p == "camera" and max(s["fx_px"], s["fy_px"]) > targets["camera_f_px"]:
        out.append(f"camera focal length 1-sigma {max(s['fx_px'], s['fy_px']):.2f} px > "
                   f"{targets['camera_f_px']:.2f} px")
    if p == "mirror":
        if s["normal_deg"] > targets["mirror_normal_deg"]:
            out.append(f"mirror normal 1-sigma {s['normal_deg']:.3f} deg > {targets['mirror_normal_deg']:.3f} deg")
        if s[f"d_{u}"] > targets["mirror_d"]:
            out.append(f"mirror offset 1-sigma {s[f'd_{u}']:.3f} {u} > {targets['mirror_d']:.3f} {u}")
    if p == "projector":
        if s["rot_deg"] > targets["projector_rot_deg"]:
            out.append(f"projector rotation 1-sigma {s['rot_deg']:.3f} deg > {targets['projector_rot_deg']:.3f} deg")
        if s[f"t_{u}"] > targets["projector_t"]:
            out.append(f"projector position 1-sigma {s[f't_{u}']:.3f} {u} > {targets['projector_t']:.3f} {u}")
    return out


def reestimate(previous: CalibrationResult, obs: SessionObservations, parts, targets: dict | None = None,
               method: str = "recalibration", intrinsics: str = DEFAULT_INTRINSICS,
               prior_from: CalibrationResult | None = None) -> Reestimate:
    """Stage 2: re-fit only `parts` from the captures `obs`, with the 1-sigma of each and whether it
    reached `targets` (default: targets_from(previous)). `previous` is where the model starts (the
    check's `current`); `prior_from` the calibration whose values and covariance make the prior
    (default `previous`).

    intrinsics "held": the parts one after the other (camera, mirror, projector), each from the
    captures that see it, everything else held at `previous`. "prior": the camera first when it moved
    (re-fitted freely, as held), then the mirror and the projector together from their captures, with
    the intrinsics of both devices free under the Gaussian prior of the previous covariance (the
    camera's only when it did not move): their previous uncertainty propagates into the 1-sigma of the
    re-estimated parts. "prior" falls back to "held" (said in `intrinsics_note`) when the previous
    calibration stored no covariance."""
    if intrinsics not in INTRINSICS_MODES:
        raise CalibrationError(f"unknown intrinsics mode '{intrinsics}' ({' or '.join(INTRINSICS_MODES)})")
    prior_from = prior_from or previous
    targets = {**targets_from(prior_from), **(targets or {})}
    cur, sigma, missing, fits, floor = previous, {}, [], [], []
    u = previous.units
    note = ""
    todo = [p for p in PARTS if p in parts]
    rest = [p for p in todo if p != "camera"]
    prior = None
    if intrinsics == "prior":
        devices = ("proj",) if "camera" in todo else ("cam", "proj")
        if "projector" not in rest:
            devices = tuple(d for d in devices if d != "proj")  # the mirror's captures do not see the projector
        prior = intrinsics_prior(prior_from, previous, devices) if rest and devices else None
        if not rest or not devices:
            intrinsics, note = "held", "nothing to constrain by a prior (the camera re-fitted freely)"
        elif prior is None:
            intrinsics, note = "held", "the previous calibration stored no covariance of the intrinsics: held"
        else:
            note = (f"{', '.join(prior.blocks)} free under the previous covariance as a prior "
                    f"({prior.n} parameters, {prior.floored} eigenvalue(s) floored)")
    groups = [(p,) for p in todo] if prior is None else ([("camera",)] if "camera" in todo else []) + [tuple(rest)]
    for group in groups:
        use = "mirror+pattern" if len(group) > 1 else _USE[group[0]]
        with_prior = prior if group != ("camera",) else None
        if with_prior is not None:  # the prior's offset from where this fit starts
            with_prior = intrinsics_prior(prior_from, cur, tuple(b.split("_")[0] for b in prior.blocks))
        fit = fit_blocks(cur, obs, group, use, prior=with_prior)
        fits.append(fit)
        cur = fit.result
        for p in fit.delta:
            _, s = describe_change(p, fit.delta[p], fit.cov[p], u)
            sigma[_SIGMA_KEY.get(p, p)] = s
            if p not in PARTS:
                continue
            over = _missing(p, s, targets, u)
            if over and fit.cov_data is not None and p in fit.cov_data:
                # the captures' own share: where it meets the target, the rest is the previous intrinsics'
                # uncertainty (the prior), which no further capture of this part lowers
                _, s_data = describe_change(p, fit.delta[p], fit.cov_data[p], u)
                still = _missing(p, s_data, targets, u)
                floor += [f"{m} (from the captures alone: within the target; the rest is the previous "
                          "intrinsics' uncertainty)" for m in over if _same_quantity(m, still) is None]
                over = [m for m in over if _same_quantity(m, still) is not None]
            missing += over
    diag = dict(previous.diagnostics) if isinstance(previous.diagnostics, dict) else {}
    diag["recalibration"] = {"reestimated": todo, "intrinsics": intrinsics, "sigma": sigma}
    result = cur.with_(method=method, diagnostics=diag)
    result = _with_updated_uncertainty(result, prior_from, fits, intrinsics)
    return Reestimate(result, tuple(todo), sigma, targets, not missing, tuple(missing), intrinsics, note,
                      tuple(floor))


def _same_quantity(sentence: str, others: list[str]) -> str | None:
    """The sentence of `others` about the same quantity as `sentence` (both from _missing: the text before
    "1-sigma" names it), or None."""
    name = sentence.split(" 1-sigma")[0]
    return next((o for o in others if o.split(" 1-sigma")[0] == name), None)


# ---- the recalibrated result's uncertainty ----------------------------------------------------------
def _to_joint(fit: Fit, result: CalibrationResult) -> np.ndarray:
    """The Jacobian A of the joint's parametrisation with respect to this module's, at `result`
    (cov_joint = A cov A^T): rotation vector -> Gibbs vector (1/2); the mirror's tilts from this
    module's tangent basis to calib.joint.method's at the new normal."""
    from calib.joint.method import _tangent_basis as joint_basis

    A = np.eye(len(fit.names))
    names = list(fit.names)
    for a in "xyz":
        if f"T_cam_proj.rot_{a}" in names:
            i = names.index(f"T_cam_proj.rot_{a}")
            A[i, i] = 0.5
    if "mirror.tilt_1" in names and result.mirror is not None:
        i = names.index("mirror.tilt_1")
        u1, u2 = _tangent_basis(fit.result.mirror.normal)  # at the fitted normal (the fit's start is < 1 deg away)
        e1, e2 = joint_basis(result.mirror.normal)
        A[i:i + 2, i:i + 2] = [[e1 @ u1, e1 @ u2], [e2 @ u1, e2 @ u2]]
    return A


def _with_updated_uncertainty(result: CalibrationResult, previous: CalibrationResult, fits: list,
                              intrinsics: str) -> CalibrationResult:
    """`result` with an `uncertainty` that says what it is: the previous calibration's covariance with the
    rows and columns of every re-fitted parameter replaced by the re-estimate's (their correlation with
    the parameters not re-fitted set to 0: the fits held those), the 1-sigma summaries recomputed from
    it, the projection-uncertainty grids and the trust/quality report recomputed too. Without a stored
    covariance only the summaries of the re-estimated parts are replaced."""
    u = dict(previous.uncertainty) if isinstance(previous.uncertainty, dict) else None
    if u is None:
        return result
    u["unit_noise"] = None  # the previous session's geometry, not this one's: the gate scales by the RMS
    stored = _stored_covariance(previous)
    if stored is not None:
        names, M = stored
        M = M.copy()
        idx = {n: i for i, n in enumerate(names)}
        for fit in fits:
            keep = [k for k, n in enumerate(fit.names) if n in idx]
            A = _to_joint(fit, result)
            C = (A @ fit.cov_global @ A.T)[np.ix_(keep, keep)]
            ii = [idx[fit.names[k]] for k in keep]
            M[ii, :] = 0.0
            M[:, ii] = 0.0
            M[np.ix_(ii, ii)] = C
        sd = np.sqrt(np.clip(np.diag(M), 0, None))

        def dev(prefix, old):
            if not isinstance(old, dict) or old.get("fixed") or f"{prefix}.fx" not in idx:
                return old
            new = dict(old)
            for k in ("fx", "fy", "cx", "cy"):
                new[k] = float(sd[idx[f"{prefix}.{k}"]])
            dist = list(old.get("dist") or [])
            for n in names:
                i = _dist_index(n) if n.startswith(f"{prefix}.dist") else None
                if i is not None and i < len(dist):
                    dist[i] = float(sd[idx[n]])
            new["dist"] = dist
            return new

        u["camera"] = dev("cam", u.get("camera"))
        u["projector"] = dev("proj", u.get("projector"))
        ri = [idx.get(f"T_cam_proj.rot_{a}") for a in "xyz"]
        ti = [idx.get(f"T_cam_proj.t_{a}") for a in "xyz"]
        if None not in ri + ti:
            cr, ct = 4.0 * M[np.ix_(ri, ri)], M[np.ix_(ti, ti)]
            u["T_cam_proj"] = {"t": np.sqrt(np.diag(ct)).tolist(), "t_total": float(np.sqrt(np.trace(ct))),
                               "rot_deg": np.degrees(np.sqrt(np.diag(cr))).tolist(),
                               "rot_total_deg": float(np.degrees(np.sqrt(np.trace(cr))))}
        mi = [idx.get("mirror.tilt_1"), idx.get("mirror.tilt_2"), idx.get("mirror.d")]
        if None not in mi and isinstance(u.get("mirror"), dict):
            u["mirror"] = {"normal_deg": float(np.degrees(np.sqrt(M[mi[0], mi[0]] + M[mi[1], mi[1]]))),
                           "d": float(sd[mi[2]])}
        u["covariance"] = dict(u["covariance"], matrix=M.tolist())
    else:
        for fit in fits:
            for p in fit.free:
                _, s = describe_change(p, fit.delta[p], fit.cov[p], previous.units)
                if p == "projector":
                    u["T_cam_proj"] = {"t_total": s[f"t_{previous.units}"], "rot_total_deg": s["rot_deg"]}
                elif p == "mirror":
                    u["mirror"] = {"normal_deg": s["normal_deg"], "d": s[f"d_{previous.units}"]}
    u["recalibration"] = {"intrinsics": intrinsics, "reestimated": sorted({p for f in fits for p in f.free}),
                          "note": "the re-fitted parameters' covariance from the recalibration's captures"
                                  + (" and the intrinsics prior" if intrinsics == "prior" else
                                     " with everything else held exact") + "; the rest the previous calibration's"}
    from calib.quality.projection_uncertainty import projection_uncertainty
    from calib.quality.trust import check_calibration

    out = result.with_(uncertainty=u)
    if previous.projection_uncertainty is not None:
        out = out.with_(projection_uncertainty=projection_uncertainty(out))
    diag = dict(out.diagnostics) if isinstance(out.diagnostics, dict) else {}
    diag["trust"] = check_calibration(out).to_dict()
    return out.with_(diagnostics=diag)


# ---- the recalibration's own residuals ------------------------------------------------------------
#: diagnostics of the previous calibration that describe its own captures (names this session lacks)
_PREVIOUS_CAPTURE_KEYS = ("worst_points", "board_poses", "rejected", "n_rejected", "views_left_out", "n_points",
                          "n_residuals", "sigma_px")


def own_residuals(cal: CalibrationResult, obs: SessionObservations) -> dict:
    """`cal`'s reprojection residuals (px) on this session's captures, each board pose fitted with the
    calibration held: "rms" per kind ("board", "pattern", "mirror_real", "mirror_virtual", "joint"),
    "per_view" (capture_id, step, n_points, rms_px, as a calibration's), "worst_views", and "dof" and
    "variance_factor" of the whitened residuals (6 pose parameters per view)."""
    from scipy.optimize import least_squares

    unit = dict.fromkeys(("board", "pattern", "mirror_real", "mirror_virtual"), 1.0)
    sig = _class_sigma(cal)
    per_view, e2 = [], {k: [] for k in unit}
    n_res, rw2 = 0, 0.0
    for v in _views(obs, "mirror+pattern"):
        mirror_view = v.real is not None and v.virtual is not None
        try:
            sol = least_squares(lambda p: _residuals(cal, v, _pose_T(p), sig, mirror_view),
                                _pose_p(_initial_pose(cal, v)))
        except Exception:  # no board pose: the capture has no residual to show (as the fits leave it out)
            per_view.append({"capture_id": v.capture_id, "step": "mirror" if mirror_view else "projector",
                             "n_points": 0, "rms_px": None})
            continue
        r = _residuals(cal, v, _pose_T(sol.x), unit, mirror_view)
        n_res, rw2 = n_res + r.size, rw2 + float(sol.fun @ sol.fun)
        pts = r[0::2] ** 2 + r[1::2] ** 2
        kinds = [("mirror_real" if mirror_view else "board", v.real), ("mirror_virtual" if mirror_view else "board",
                                                                         v.virtual)]
        i = 0
        for kind, ob in kinds:
            if ob is not None:
                e2[kind].append(pts[i:i + len(ob.ids)])
                i += len(ob.ids)
        e2["pattern"].append(pts[i:])
        per_view.append({"capture_id": v.capture_id, "step": "mirror" if mirror_view else "projector",
                         "n_points": int(pts.size), "rms_px": float(np.sqrt(pts.mean())) if pts.size else None})
    every = [a for k in e2 for a in e2[k]]
    rms = {k: float(np.sqrt(np.concatenate(a).mean())) for k, a in (("joint", every), *e2.items())
           if a and np.concatenate(a).size}
    dof = max(n_res - 6 * sum(1 for p in per_view if p["n_points"]), 1)
    worst = sorted((p for p in per_view if p["rms_px"] is not None), key=lambda p: -p["rms_px"])[:5]
    return {"rms": rms, "per_view": per_view, "worst_views": worst, "dof": dof, "variance_factor": rw2 / dof}


def with_own_residuals(result: CalibrationResult, obs: SessionObservations, reestimated: bool) -> CalibrationResult:
    """`result` with this session's residuals in place of the previous calibration's (RMS, per-view,
    worst views; the previous session's per-capture diagnostics dropped). Re-estimated, its uncertainty
    came from these captures: their degrees of freedom and variance factor too."""
    own = own_residuals(result, obs)
    diag = {k: v for k, v in (result.diagnostics or {}).items() if k not in _PREVIOUS_CAPTURE_KEYS}
    diag["worst_views"] = own["worst_views"]
    u = result.uncertainty
    if reestimated and isinstance(u, dict):
        u = dict(u, dof=own["dof"], variance_factor=own["variance_factor"])
    return result.with_(rms=own["rms"], per_view=tuple(own["per_view"]), diagnostics=diag, uncertainty=u)


# ---- stage 3: compare -------------------------------------------------------------------------------
def projection_difference(a: CameraModel, b: CameraModel, grid: tuple[int, int] = (16, 10)) -> dict:
    """How far the same ray lands between two intrinsic models: pixels on a grid over the image,
    unprojected with `a` and projected with `b` (mean, max, and the grid of distances in px)."""
    w, h = a.size
    xs = np.linspace(0.05 * w, 0.95 * w, grid[0])
    ys = np.linspace(0.05 * h, 0.95 * h, grid[1])
    uv = np.array([[x, y] for y in ys for x in xs])
    uv2 = b.project(a.rays(uv))
    dist = np.linalg.norm(uv2 - uv, axis=1)
    return {"mean_px": float(dist.mean()), "max_px": float(dist.max()), "grid": [int(grid[0]), int(grid[1])],
            "px": dist.reshape(grid[1], grid[0]).round(4).tolist()}


def compare_calibrations(previous: CalibrationResult, new: CalibrationResult, sigma: dict | None = None) -> dict:
    """Stage 3: the change of each part from `previous` to `new` (mm/units, deg, px) with its 1-sigma
    (previous and re-estimate combined, where known), and the projection difference of the intrinsics."""
    u = previous.units
    sigma = sigma or {}
    out = {"units": u}
    T0, T1 = previous.T_cam_proj, new.T_cam_proj
    sp = describe_change("projector", np.zeros(6), previous_covariance(previous, "projector"), u)[1]
    sn = sigma.get("projector", {})
    out["projector"] = {
        f"position_change_{u}": float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])),
        "rotation_change_deg": rotation_angle_deg(T1[:3, :3] @ T0[:3, :3].T),
        f"position_sigma_{u}": math.hypot(sp[f"t_{u}"], sn.get(f"t_{u}", 0.0)),
        "rotation_sigma_deg": math.hypot(sp["rot_deg"], sn.get("rot_deg", 0.0)),
    }
    if previous.mirror is not None and new.mirror is not None:
        sp = describe_change("mirror", np.zeros(3), previous_covariance(previous, "mirror"), u)[1]
        sn = sigma.get("mirror", {})
        cosang = float(np.clip(previous.mirror.normal @ new.mirror.normal, -1, 1))
        out["mirror"] = {"normal_change_deg": math.degrees(math.acos(cosang)),
                         f"d_change_{u}": float(new.mirror.d - previous.mirror.d),
                         "normal_sigma_deg": math.hypot(sp["normal_deg"], sn.get("normal_deg", 0.0)),
                         f"d_sigma_{u}": math.hypot(sp[f"d_{u}"], sn.get(f"d_{u}", 0.0))}
    else:
        out["mirror"] = None
    sp = describe_change("camera", np.zeros(4), previous_covariance(previous, "camera"), u)[1]
    sn = sigma.get("camera", {})
    dK = np.array(new.camera.K) - np.array(previous.camera.K)
    out["camera"] = {
        "fx_change_px": float(dK[0, 0]), "fy_change_px": float(dK[1, 1]),
        "cx_change_px": float(dK[0, 2]), "cy_change_px": float(dK[1, 2]),
        "sigma_px": {k: math.hypot(sp[k], sn.get(k, 0.0)) for k in ("fx_px", "fy_px", "cx_px", "cy_px")},
        "projection_difference": projection_difference(previous.camera, new.camera),
    }
    out["projector_intrinsics"] = {"projection_difference": projection_difference(previous.projector, new.projector)}
    return out


# ---- the record -------------------------------------------------------------------------------------
def sha256_file(path) -> str:
    """SHA-256 of a regular file, never hashed through a link (calib.formats.fileio.open_regular)."""
    h = hashlib.sha256()
    with os.fdopen(open_regular(path, RESULT_MAX_BYTES, "calibration file"), "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class RecalibrationRecord:
    """recalibration.json: where the previous calibration came from, the check, the re-estimate, the
    comparison, the captures used."""

    previous_path: str
    previous_sha256: str
    archived_as: str
    check: CheckReport
    reestimate: Reestimate | None
    comparison: dict | None
    captures: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"schema": "procam-recalibration-1",
                "previous": {"path": self.previous_path, "sha256": self.previous_sha256, "archived_as": self.archived_as},
                "verdict": self.check.verdict, "check": self.check.to_dict(),
                # how the intrinsics were treated by the re-estimate (None: nothing was re-estimated)
                "intrinsics": None if self.reestimate is None else self.reestimate.intrinsics,
                "reestimate": None if self.reestimate is None else self.reestimate.to_dict(),
                "comparison": self.comparison, "captures": self.captures}
