"""Joint maximum-likelihood refinement of a whole mirror-based projector-camera session.

One least-squares adjustment over everything the images constrain (docs/JOINT.md):

* camera K (fx, fy, cx, cy) and distortion, projector K and distortion,
* the mirror plane n . x + d = 0 (normal as 2 tangent parameters around the current normal, plus d),
* every board pose in the REAL camera frame (T_cam_board; a board lying on the mirror has 3 DOF),
* T_cam_proj.

Observations, all in camera pixels (where the noise is), with the exact models of docs/GEOMETRY.md:

* ChArUco corners through the mirror: u = project_cam(S T_cam_board X);
* projected pattern points through the mirror: projector pixel q -> undistorted ray -> T_cam_proj ->
  board plane -> S -> camera; for circles optionally the centre of the imaged conic (bias-free);
* mirror-calibration images: real corners project_cam(T X), virtual corners project_cam(S T X);
  real-mirror boards are parametrised on the plane offset by the board thickness;
* direct rigs: S = I.

Residuals are weighted by the noise sigma of their observation class (board corners, pattern points,
mirror real / virtual corners), estimated from the residuals. Derivatives are exact: the camera
intrinsics analytically, the rest by complex step grouped by the block structure (one evaluation per
global parameter plus six for all board poses together). The solver is Levenberg-Marquardt with the
board poses eliminated by the Schur complement (solver="scipy": scipy's least_squares, trf, sparse
Jacobian, x_scale='jac'): a robust pass (soft-L1), outlier rejection, then the plain squared loss on
the inliers (the maximum-likelihood estimate under Gaussian pixel noise), distortion model selection
(calib.joint.model_select) and the covariance (calib.joint.uncertainty). The solver itself (normal equations, LM)
is calib.joint.solver; non-finite numbers or a failed linear algebra there become a CalibrationError
(code "non_finite" / "solve_failed"), which calibrate_joint reports as an UntrustedCalibration.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from calib.errors import CalibrationError, UntrustedCalibration
from calib.joint import model_select, uncertainty
from calib.joint.solver import DIST_MODELS, MODEL_NAMES, _RowSums, solve
from calib.models.camera import CameraModel
from calib.models.observations import STEP_REAL_MIRROR, VIEW_DIRECT, SessionObservations
from calib.models.result import CalibrationResult, MirrorPlane
from calib.models.vocab import DistortionModel
from calib.paper.board_pose import solve_pnp
from calib.paper.method import calibrate_paper
from calib.quality.projection_uncertainty import projection_uncertainty
from calib.quality.trust import TrustReason, check_calibration
from calib.transforms import FLIP_X, make_T, tangent_basis

PATTERN_MODELS = ("auto", "point", "conic")

_KIND_BOARD, _KIND_REAL, _KIND_VIRTUAL, _KIND_PATTERN = 0, 1, 2, 3
_KIND_NAMES = {0: "board", 1: "mirror-real", 2: "mirror-virtual", 3: "pattern"}


@dataclass(frozen=True)
class JointOptions:
    """Options of refine_joint (all have sensible defaults).

    camera_model / projector_model: "auto" (selected per device, calib.joint.model_select) or one of
    DIST_MODELS. pattern_model: "conic" models a projected circle's observation as the centre of its
    imaged conic (what a centroid detector measures), "point" as the image of its centre; "auto" =
    conic for circle patterns, point for chessboards. loss / noise_px: robust loss of the first pass
    and its scale (None: estimated from the initial residuals). outlier_sigma: points whose residual
    exceeds this many robust sigmas of their class (and min_outlier_px) are rejected, then the problem
    is solved with the squared loss. selection: criterion of the model selection ("bic" or "lrt").
    solver: "lm" (Levenberg-Marquardt, Schur complement) or "scipy" (least_squares). fix_camera: hold
    the initial camera fixed (set when a camera is given). weighting: "class" (per observation class
    noise sigma) or "none". centroid_correction: with the conic model, the 32-point area-centroid
    correction for the lenses' curvature across a blob. tol: a solve stops when a step lowers the
    cost by less than this fraction (1e-7 of a whitened cost ~N moves the parameters by a few
    hundredths of a sigma, and the Gauss-Newton step after it by far less: results agree with
    tol=1e-9 to 1e-7 sigma, one Jacobian fewer per solve). coverage: after the BIC / LRT choice, step a
    device's model down when the coefficients it drops are not constrained where the image is used
    (calib.joint.model_select: the mean squared projection error over the image, bias + variance). shrinkage:
    with coverage, a kept k3 is pulled toward 0 by a zero-mean Gaussian prior whose width is set from the
    data (calib.joint.model_select.shrinkage_prior), instead of kept or dropped whole."""

    camera_model: str = "auto"
    projector_model: str = "auto"
    pattern_model: str = "auto"
    loss: str = "soft_l1"
    noise_px: float | None = None
    outlier_sigma: float = 5.0
    min_outlier_px: float = 0.25
    outlier_rounds: int = 3
    max_nfev: int = 60
    tol: float = 1e-7
    uncertainty: bool = True
    selection: str = "bic"
    centroid_correction: bool = True
    solver: str = "lm"
    fix_camera: bool = False
    weighting: str = "class"
    coverage: bool = True
    shrinkage: bool = False


# ==================================================================================================
# complex-safe building blocks
# ==================================================================================================
def gibbs_R(v: np.ndarray) -> np.ndarray:
    """Rotation(s) of the unnormalised quaternion (1, v): (..., 3) -> (..., 3, 3). Analytic everywhere,
    identity at v = 0, and for small v the rotation vector is 2 v."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    s = 1.0 + x * x + y * y + z * z
    R = np.empty(v.shape[:-1] + (3, 3), dtype=v.dtype)
    R[..., 0, 0] = 1 + x * x - y * y - z * z
    R[..., 0, 1] = 2 * (x * y - z)
    R[..., 0, 2] = 2 * (x * z + y)
    R[..., 1, 0] = 2 * (x * y + z)
    R[..., 1, 1] = 1 - x * x + y * y - z * z
    R[..., 1, 2] = 2 * (y * z - x)
    R[..., 2, 0] = 2 * (x * z - y)
    R[..., 2, 1] = 2 * (y * z + x)
    R[..., 2, 2] = 1 - x * x - y * y + z * z
    return R / s[..., None, None]


def distort(x, y, d):
    """OpenCV's distortion of normalised coordinates; d = 8 coefficients (scalars, maybe complex)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    r2 = x * x + y * y
    rad = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def distort_jac(x, y, d):
    """d(xd, yd)/d(x, y) as four arrays (a11, a12, a21, a22)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * r2 * k3)
    dden = k4 + r2 * (2 * k5 + 3 * r2 * k6)
    rad = num / den
    drad = (dnum * den - num * dden) / (den * den)
    a11 = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
    a12 = 2 * x * y * drad + 2 * p1 * x + 2 * p2 * y
    a22 = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
    return a11, a12, a12, a22


def _dist8(dist) -> np.ndarray:
    d = np.zeros(8)
    dist = np.asarray(dist, float).reshape(-1)
    d[: dist.size] = dist
    return d


def _dist_out(d8: np.ndarray, model: str) -> np.ndarray:
    return np.array(d8[:8] if model == DistortionModel.RATIONAL else d8[:5], float)


# ==================================================================================================
# the problem: observations (fixed) + parametrisation
# ==================================================================================================
@dataclass
class _Pose:
    capture_id: str
    role: str  # "projector", "mirror-real-virtual", "mirror-real-mirror"
    on_mirror: bool  # 3-DOF pose lying on the mirror plane


@dataclass
class _State:
    """Reference values the parameter vector is relative to (rotations, mirror normal)."""

    cam_K: np.ndarray  # fx, fy, cx, cy
    cam_d: np.ndarray  # 8
    proj_K: np.ndarray
    proj_d: np.ndarray
    R_cp: np.ndarray
    t_cp: np.ndarray
    n: np.ndarray | None
    d: float
    R: np.ndarray  # (V, 3, 3)
    t: np.ndarray  # (V, 3)
    plane: np.ndarray  # (V, 3): theta, a, b of poses on the mirror
    cam_model: str = DistortionModel.FIVECOEF
    proj_model: str = DistortionModel.FIVECOEF

    def copy(self) -> "_State":
        return _State(self.cam_K.copy(), self.cam_d.copy(), self.proj_K.copy(), self.proj_d.copy(),
                      self.R_cp.copy(), self.t_cp.copy(), None if self.n is None else self.n.copy(), self.d,
                      self.R.copy(), self.t.copy(), self.plane.copy(), self.cam_model, self.proj_model)


class JointProblem:
    """Observations gathered once into flat arrays, the parameter layout, residuals and Jacobian."""

    def __init__(self, obs: SessionObservations, state: _State, pattern_model: str, thickness: float,
                 poses: list[_Pose], corners: dict, pattern: dict, radius_px: float, fix_camera: bool = False):
        self.obs = obs
        self.fix_camera = fix_camera
        self.mirrored = obs.view != VIEW_DIRECT
        self.poses = poses
        self.thickness = thickness
        self.pattern_model = pattern_model
        self.radius_px = radius_px
        self.c = corners  # pose, X (N,3), uv (N,2), mirror (N,), kind, cid, pid
        self.p = pattern  # pose, q (M,2), uv (M,2), mirror (M,), cid, pid
        self.on_mirror = np.array([ps.on_mirror for ps in poses], bool)
        # a fixed in-plane reference for boards lying on the mirror (their 3 parameters are relative to it)
        self.plane_ref = tangent_basis(state.n)[0] if self.mirrored else None
        self.set_state(state)
        self.centroid_corr = np.zeros((len(self.p["q"]), 2))
        self._xu_cache = None
        self._proj_cache = None
        self.class_sigma = {}

    # ---- layout ---------------------------------------------------------------------------------
    def set_state(self, state: _State) -> None:
        self.state = state
        self._any_c_mirror = bool(np.any(self.c["mirror"]))
        self.cam_free = DIST_MODELS[state.cam_model]
        self.proj_free = DIST_MODELS[state.proj_model]
        names = [] if self.fix_camera else (["cam.fx", "cam.fy", "cam.cx", "cam.cy"]
                                            + [f"cam.dist{i}" for i in self.cam_free])
        self.n_cam = len(names)
        names += ["proj.fx", "proj.fy", "proj.cx", "proj.cy"] + [f"proj.dist{i}" for i in self.proj_free]
        names += ["T_cam_proj.rot_x", "T_cam_proj.rot_y", "T_cam_proj.rot_z",
                  "T_cam_proj.t_x", "T_cam_proj.t_y", "T_cam_proj.t_z"]
        if self.mirrored:
            names += ["mirror.tilt_1", "mirror.tilt_2", "mirror.d"]
            self.e1, self.e2 = tangent_basis(state.n)
        self.global_names = names
        self.n_global = len(names)
        ndof = np.where(self.on_mirror, 3, 6)
        self.pose_ndof = ndof
        self.pose_start = self.n_global + np.concatenate([[0], np.cumsum(ndof)[:-1]]).astype(int)
        self.n_params = self.n_global + int(ndof.sum())
        self._build_sparsity()

    def x0(self) -> np.ndarray:
        s = self.state
        x = [] if self.fix_camera else [s.cam_K, s.cam_d[list(self.cam_free)]]
        x += [s.proj_K, s.proj_d[list(self.proj_free)], np.zeros(3), s.t_cp]
        if self.mirrored:
            x.append([0.0, 0.0, s.d])
        for v in range(len(self.poses)):
            x.append(s.plane[v] if self.on_mirror[v] else np.concatenate([np.zeros(3), s.t[v]]))
        return np.concatenate([np.asarray(a, float).reshape(-1) for a in x])

    def unpack(self, x: np.ndarray) -> dict:
        """Parameter vector -> model quantities (complex when x is complex)."""
        s = self.state
        i = 0
        out = {}
        if self.fix_camera:
            cK, cd = s.cam_K, s.cam_d
        else:
            cK = x[i:i + 4]
            i += 4
            cd = np.zeros(8, dtype=x.dtype)
            cd[list(self.cam_free)] = x[i:i + len(self.cam_free)]
            i += len(self.cam_free)
        pK = x[i:i + 4]
        i += 4
        pd = np.zeros(8, dtype=x.dtype)
        pd[list(self.proj_free)] = x[i:i + len(self.proj_free)]
        i += len(self.proj_free)
        out["cam_K"], out["cam_d"], out["proj_K"], out["proj_d"] = cK, cd, pK, pd
        out["R_cp"] = gibbs_R(x[i:i + 3]) @ s.R_cp
        out["t_cp"] = x[i + 3:i + 6]
        i += 6
        V = len(self.poses)
        R = np.empty((V, 3, 3), dtype=x.dtype)
        t = np.empty((V, 3), dtype=x.dtype)
        if self.mirrored:
            a, b, d = x[i], x[i + 1], x[i + 2]
            i += 3
            n = s.n + a * self.e1 + b * self.e2
            n = n / np.sqrt(n @ n)
            out["n"], out["d"] = n, d
        free = ~self.on_mirror
        if free.any():
            idx = self.pose_start[free][:, None] + np.arange(6)
            P = x[idx]
            R[free] = gibbs_R(P[:, :3]) @ s.R[free]
            t[free] = P[:, 3:]
        if self.on_mirror.any():
            n, d = out["n"], out["d"]
            ref = self.plane_ref
            e1 = ref - (ref @ n) * n
            e1 = e1 / np.sqrt(e1 @ e1)
            e2 = np.cross(-n, e1)  # e1 x e2 = -n = board z (into the board, away from the camera)
            idx = self.pose_start[self.on_mirror][:, None] + np.arange(3)
            P = x[idx]
            c, sn = np.cos(P[:, 0]), np.sin(P[:, 0])
            xa = c[:, None] * e1 + sn[:, None] * e2
            ya = -sn[:, None] * e1 + c[:, None] * e2
            R[self.on_mirror] = np.stack([xa, ya, np.broadcast_to(-n, xa.shape)], axis=-1)
            t[self.on_mirror] = (self.thickness - d) * n + P[:, 1:2] * e1 + P[:, 2:3] * e2
        out["R"], out["t"] = R, t
        return out

    # ---- model ----------------------------------------------------------------------------------
    @staticmethod
    def _project(K, d, X):
        x = X[:, 0] / X[:, 2]
        y = X[:, 1] / X[:, 2]
        xd, yd = distort(x, y, d)
        return np.stack([K[0] * xd + K[2], K[1] * yd + K[3]], axis=-1)

    @staticmethod
    def _reflect(X, n, d):
        s2 = 2.0 * (X[:, 0] * n[0] + X[:, 1] * n[1] + X[:, 2] * n[2] + d)
        return np.stack([X[:, 0] - s2 * n[0], X[:, 1] - s2 * n[1], X[:, 2] - s2 * n[2]], axis=-1)

    def reset_warm_start(self) -> None:
        """Forget the last undistorted projector points: the next solve starts its Newton iterations afresh."""
        self._xu_cache = None

    def subset(self, keep_c: np.ndarray, keep_p: np.ndarray, drop_pose: np.ndarray) -> None:
        """Keep the corner and pattern observations of the masks and drop the poses of `drop_pose`
        (with their state); the caches that hold per-observation values start again."""
        state = self.state
        if drop_pose.any():
            keep_pose = ~drop_pose
            remap = -np.ones(len(self.poses), int)
            remap[keep_pose] = np.arange(int(keep_pose.sum()))
            self.poses = [p for p, k in zip(self.poses, keep_pose) if k]
            self.on_mirror = self.on_mirror[keep_pose]
            state.R, state.t, state.plane = state.R[keep_pose], state.t[keep_pose], state.plane[keep_pose]
        else:
            remap = np.arange(len(self.poses))
        self.c = {k: v[keep_c] for k, v in self.c.items()}
        self.p = {k: v[keep_p] for k, v in self.p.items()}
        self.c["pose"] = remap[self.c["pose"]]
        self.p["pose"] = remap[self.p["pose"]]
        self.centroid_corr = self.centroid_corr[keep_p]
        self.reset_warm_start()
        self._proj_cache = None
        self.set_state(state)

    def _undistort_proj(self, pK, pd):
        """Undistorted normalised projector coordinates of every pattern point (Newton, warm start)."""
        q = self.p["q"]
        K = pK.real
        dr = pd.real
        mx = (q[:, 0] - K[2]) / K[0]
        my = (q[:, 1] - K[3]) / K[1]
        x, y = (mx.copy(), my.copy()) if self._xu_cache is None else self._xu_cache
        for _ in range(30):
            fx_, fy_ = distort(x, y, dr)
            fx_, fy_ = fx_ - mx, fy_ - my
            if max(np.abs(fx_).max(initial=0), np.abs(fy_).max(initial=0)) < 1e-15:
                break
            a11, a12, a21, a22 = distort_jac(x, y, dr)
            det = a11 * a22 - a12 * a21
            x = x - (a22 * fx_ - a12 * fy_) / det
            y = y - (-a21 * fx_ + a11 * fy_) / det
        self._xu_cache = (x, y)
        if (np.iscomplexobj(pK) and np.any(pK.imag)) or (np.iscomplexobj(pd) and np.any(pd.imag)):
            # one Newton step in complex arithmetic carries the implicit derivative
            mxc = (q[:, 0] - pK[2]) / pK[0]
            myc = (q[:, 1] - pK[3]) / pK[1]
            fx_, fy_ = distort(x, y, pd)
            fx_, fy_ = fx_ - mxc, fy_ - myc
            a11, a12, a21, a22 = distort_jac(x, y, pd)
            det = a11 * a22 - a12 * a21
            x = x - (a22 * fx_ - a12 * fy_) / det
            y = y - (-a21 * fx_ + a11 * fy_) / det
        return x, y

    def corner_points(self, m: dict) -> np.ndarray:
        """(N, 3) ChArUco corners in the (virtual, when seen through the mirror) camera frame."""
        c = self.c
        pose = c["pose"]
        if len(pose) == 0:
            return np.zeros((0, 3))
        R, t = m["R"], m["t"]
        # board points have z = 0: only the first two columns of R matter
        X = R[pose, :, 0] * c["X"][:, 0:1] + R[pose, :, 1] * c["X"][:, 1:2] + t[pose]
        if self.mirrored and self._any_c_mirror:
            mm = c["mirror"]
            X[mm] = self._reflect(X[mm], m["n"], m["d"])
        return X

    def _projector_side(self, pK, pd, need_A: bool):
        """(xu, yu, A): undistorted normalised projector coordinates of the pattern points and the local
        linear map A = d(xu, yu)/dq (2x2 per point). Cached for real projector parameters, so that the
        complex evaluations of the Jacobian that do not perturb the projector reuse them."""
        complex_ = (np.iscomplexobj(pK) and np.any(pK.imag)) or (np.iscomplexobj(pd) and np.any(pd.imag))
        key = (tuple(np.real(pK)), tuple(np.real(pd)), need_A)
        if not complex_ and self._proj_cache is not None and self._proj_cache[0] == key:
            return self._proj_cache[1]
        xu, yu = self._undistort_proj(pK, pd)
        A = None
        if need_A:
            a11, a12, a21, a22 = distort_jac(xu, yu, pd)
            det = a11 * a22 - a12 * a21
            # J_D^-1 diag(1/fx, 1/fy): projector pixels -> undistorted normalised coordinates
            A = (a22 / det / pK[0], -a12 / det / pK[1], -a21 / det / pK[0], a11 / det / pK[1])
        out = (xu, yu, A)
        if not complex_:
            self._proj_cache = (key, (np.real(xu), np.real(yu),
                                      None if A is None else tuple(np.real(a) for a in A)))
        return out

    def pattern_points(self, m: dict, model: str | None = None) -> np.ndarray:
        """(M, 3) homogeneous (virtual) camera coordinates of what the camera sees of each projected
        pattern point: the point itself ("point") or the centre of the imaged conic ("conic").

        Conic: the circle of radius rho around q maps to the undistorted projector plane as the ellipse
        {x_u + rho A u}, then by the board-plane homography H into the camera; with P = H[:, :2] rho A
        and c = H (x_u, 1) the dual conic's centre is (P P_z - c c_z) (calib.joint.conic)."""
        p = self.p
        if len(p["q"]) == 0:
            return np.zeros((0, 3))
        model = model or self.pattern_model
        xu, yu, A = self._projector_side(m["proj_K"], m["proj_d"], model == "conic")
        H = self._homographies(m)[p["pose"]]
        c = H[:, :, 0] * xu[:, None] + H[:, :, 1] * yu[:, None] + H[:, :, 2]
        if model != "conic":
            return c
        a11, a12, a21, a22 = A
        rho = self.radius_px
        P0 = rho * (H[:, :, 0] * a11[:, None] + H[:, :, 1] * a21[:, None])
        P1 = rho * (H[:, :, 0] * a12[:, None] + H[:, :, 1] * a22[:, None])
        return P0 * P0[:, 2:3] + P1 * P1[:, 2:3] - c * c[:, 2:3]

    def predict(self, x: np.ndarray, pattern_model: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(corner pixels (N, 2), pattern pixels (M, 2)) predicted by parameters x."""
        m = self.unpack(x)
        uv_c = self._project(m["cam_K"], m["cam_d"], self.corner_points(m))
        uv_p = self._project(m["cam_K"], m["cam_d"], self.pattern_points(m, pattern_model))
        if (pattern_model or self.pattern_model) == "conic":
            uv_p = uv_p + self.centroid_corr
        return uv_c, uv_p

    def _homographies(self, m) -> np.ndarray:
        """Per pose: the map from projector normalised coordinates to (virtual) camera coordinates
        induced by the board plane: H = R_s R_cp - (R_s t_cp + t_s) n_p^T / d_p."""
        R, t = m["R"], m["t"]
        nu = R[:, :, 2]  # board normal in the camera frame
        R_cp, t_cp = m["R_cp"], m["t_cp"]
        n_p = nu @ R_cp  # (V, 3) = R_cp^T nu
        dt = t_cp[None, :] - t
        d_p = nu[:, 0] * dt[:, 0] + nu[:, 1] * dt[:, 1] + nu[:, 2] * dt[:, 2]
        if self.mirrored:
            n, d = m["n"], m["d"]
            Rs = np.eye(3) - 2.0 * np.outer(n, n)
            ts = -2.0 * d * n
        else:
            Rs = np.eye(3, dtype=R_cp.dtype)
            ts = np.zeros(3, dtype=R_cp.dtype)
        A = Rs @ R_cp
        b = Rs @ t_cp + ts
        return A[None] - b[None, :, None] * (n_p / d_p[:, None])[:, None, :]

    def raw_residuals(self, x: np.ndarray) -> np.ndarray:
        """Residuals in pixels, [u0, v0, u1, v1, ...] over corners then pattern points."""
        uv_c, uv_p = self.predict(x)
        return np.concatenate([(uv_c - self.c["uv"]).reshape(-1), (uv_p - self.p["uv"]).reshape(-1)])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals: pixels divided by the noise sigma of each observation's class."""
        return self.raw_residuals(x) / self.row_scale

    # ---- observation classes and their noise ----------------------------------------------------
    def class_masks(self) -> dict:
        """Point masks (over corners + pattern points) of the observation classes."""
        nc, npat = len(self.c["pose"]), len(self.p["pose"])
        out = {}
        for kind, name in ((_KIND_BOARD, "board"), (_KIND_REAL, "mirror_real"), (_KIND_VIRTUAL, "mirror_virtual")):
            m = np.zeros(nc + npat, bool)
            m[:nc] = self.c["kind"] == kind
            if m.any():
                out[name] = m
        if npat:
            m = np.zeros(nc + npat, bool)
            m[nc:] = True
            out["pattern"] = m
        return out

    def set_class_sigmas(self, sig_px: dict) -> None:
        """Weight every observation by 1 / sigma of its class (pixels)."""
        self.class_sigma = dict(sig_px)
        scale = np.ones(len(self.c["pose"]) + len(self.p["pose"]))
        for name, m in self.class_masks().items():
            scale[m] = sig_px.get(name, 1.0)
        nc = len(self.c["pose"])
        self.c["s"], self.p["s"] = scale[:nc], scale[nc:]
        self.row_scale = np.repeat(scale, 2)

    # ---- Jacobian (complex step, grouped by block structure) ------------------------------------
    def _build_sparsity(self) -> None:
        self.row_scale = np.repeat(np.concatenate([self.c["s"], self.p["s"]]), 2)
        rows_pose = np.concatenate([self.c["pose"], self.p["pose"]])
        rows_pose = np.repeat(rows_pose, 2)  # two residuals per point
        self.row_pose = rows_pose
        N = len(rows_pose)
        G = self.n_global
        r_g = np.repeat(np.arange(N), G)
        c_g = np.tile(np.arange(G), N)
        r_p, c_p = [], []
        for k in range(6):
            ok = self.pose_ndof[rows_pose] > k
            r_p.append(np.nonzero(ok)[0])
            c_p.append(self.pose_start[rows_pose[ok]] + k)
        self._jrows = np.concatenate([r_g] + r_p)
        self._jcols = np.concatenate([c_g] + c_p)
        self._jmask = [ok for ok in (self.pose_ndof[rows_pose] > k for k in range(6))]
        self._jmask_full = np.stack(self._jmask, axis=1)
        self.pose_sum = _RowSums(rows_pose, len(self.poses))
        self.row_pose = rows_pose
        self.n_res = N
        # global parameters a residual does not depend on are structural zeros
        dep = np.ones((N, G), bool)
        is_pattern = np.zeros(N, bool)
        is_pattern[2 * len(self.c["pose"]):] = True
        ncf = self.n_cam
        npf = 4 + len(self.proj_free)
        dep[~is_pattern, ncf:ncf + npf + 6] = False  # corners: no projector, no T_cam_proj
        if self.mirrored:
            through = np.repeat(np.concatenate([self.c["mirror"], self.p["mirror"]]), 2)
            on_m = self.on_mirror[rows_pose]
            dep[~through & ~on_m, G - 3:] = False
        self._gdep = dep
        nc2 = 2 * len(self.c["pose"])
        self._gdep_c = dep[:nc2].any(axis=0)
        self._gdep_p = dep[nc2:].any(axis=0)
        keep = np.concatenate([dep.reshape(-1)] + [np.ones(len(r), bool) for r in r_p])
        self._jkeep = keep

    def _camera_columns(self, X: np.ndarray, cd: np.ndarray, cK: np.ndarray) -> np.ndarray:
        """Analytic d(u, v)/d(camera fx, fy, cx, cy, free distortion) of points X: (2N, n_cam)."""
        x = X[:, 0] / X[:, 2]
        y = X[:, 1] / X[:, 2]
        k1, k2, p1, p2, k3, k4, k5, k6 = cd
        r2 = x * x + y * y
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        xd, yd = distort(x, y, cd)
        n = len(x)
        cols = [np.column_stack([xd, np.zeros(n)]), np.column_stack([np.zeros(n), yd]),
                np.column_stack([np.ones(n), np.zeros(n)]), np.column_stack([np.zeros(n), np.ones(n)])]
        for i in self.cam_free:
            if i in (0, 1, 4):
                pw = {0: r2, 1: r2 * r2, 4: r2 * r2 * r2}[i]
                f = pw / den
                dx, dy = x * f, y * f
            elif i in (5, 6, 7):
                pw = {5: r2, 6: r2 * r2, 7: r2 * r2 * r2}[i]
                f = -num * pw / (den * den)
                dx, dy = x * f, y * f
            elif i == 2:
                dx, dy = 2 * x * y, r2 + 2 * y * y
            else:
                dx, dy = r2 + 2 * x * x, 2 * x * y
            cols.append(np.column_stack([cK[0] * dx, cK[1] * dy]))
        return np.stack([c.reshape(-1) for c in cols], axis=1)

    def _complex_parts(self, xc: np.ndarray, corners: bool, pattern: bool) -> np.ndarray:
        m = self.unpack(xc)
        nc2 = 2 * len(self.c["pose"])
        out = np.zeros(self.n_res)
        if corners and nc2:
            out[:nc2] = self._project(m["cam_K"], m["cam_d"], self.corner_points(m)).imag.reshape(-1)
        if pattern and self.n_res > nc2:
            out[nc2:] = self._project(m["cam_K"], m["cam_d"], self.pattern_points(m)).imag.reshape(-1)
        return out

    def jacobian_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact Jacobian in block form: (Jg (N, G) for the global parameters, Jl (N, 6) for the pose
        of each residual's own view, zero beyond that pose's DOF). Camera intrinsics analytically,
        everything else by complex-step differentiation: one complex evaluation per global parameter
        (only of the residuals it can affect) and six for all board poses at once."""
        h = 1e-30
        N, G = self.n_res, self.n_global
        Jg = np.zeros((N, G))
        m = self.unpack(x)
        X = np.concatenate([self.corner_points(m), self.pattern_points(m)])
        ncam = self.n_cam
        if ncam:
            Jg[:, :ncam] = self._camera_columns(X, m["cam_d"], m["cam_K"])
        xc = x.astype(complex)
        for j in range(ncam, G):
            xc.imag[:] = 0.0
            xc.imag[j] = h
            Jg[:, j] = self._complex_parts(xc, self._gdep_c[j], self._gdep_p[j]) / h
        Jl = np.zeros((N, 6))
        for k in range(6):
            has = self.pose_ndof > k
            if not has.any():
                continue
            xc.imag[:] = 0.0
            xc.imag[self.pose_start[has] + k] = h
            Jl[:, k] = self._complex_parts(xc, True, True) / h
        Jl[~self._jmask_full] = 0.0
        Jg /= self.row_scale[:, None]
        Jl /= self.row_scale[:, None]
        return Jg, Jl

    def to_sparse(self, Jg: np.ndarray, Jl: np.ndarray):
        """The Jacobian blocks as one scipy.sparse (N, P) CSR matrix."""
        import scipy.sparse as sp

        vals = [Jg.reshape(-1)] + [Jl[self._jmask[k], k] for k in range(6)]
        data = np.concatenate(vals)[self._jkeep]
        return sp.csr_matrix((data, (self._jrows[self._jkeep], self._jcols[self._jkeep])),
                             shape=(self.n_res, self.n_params))

    def jacobian(self, x: np.ndarray):
        """The Jacobian as a sparse (N, P) matrix (see jacobian_blocks)."""
        return self.to_sparse(*self.jacobian_blocks(x))

    # ---- state update ---------------------------------------------------------------------------
    def rebase(self, x: np.ndarray) -> _State:
        """A new reference state at x (rotations re-centred, so that x0() of it is x re-expressed)."""
        m = self.unpack(x)
        s = self.state.copy()
        s.cam_K, s.cam_d = np.array(m["cam_K"], float), np.array(m["cam_d"], float)
        s.proj_K, s.proj_d = np.array(m["proj_K"], float), np.array(m["proj_d"], float)
        s.R_cp, s.t_cp = _orthonormalise(m["R_cp"]), np.array(m["t_cp"], float)
        if self.mirrored:
            s.n, s.d = np.array(m["n"], float), float(m["d"])
        s.R = np.array([_orthonormalise(r) for r in m["R"]])
        s.t = np.array(m["t"], float)
        for v in np.nonzero(self.on_mirror)[0]:
            s.plane[v] = x[self.pose_start[v]:self.pose_start[v] + 3]
        return s


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.asarray(R, float))
    return U @ Vt


# ==================================================================================================
# initialisation: board poses from PnP under the initial calibration
# ==================================================================================================
def _pnp(cam: CameraModel, X: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """T_cam_board, or None (calib.paper.board_pose.solve_pnp: the better of IPPE's two solutions)."""
    found = solve_pnp(cam, X, uv)
    return None if found is None else found[0]


def _pose_through_mirror(cam: CameraModel, S: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """T_cam_board of a board seen through the mirror: PnP in the flipped image, T = S F T_V'."""
    T_v = _pnp(cam.flipped(), X, cam.flip_points(uv))
    return None if T_v is None else S @ FLIP_X @ T_v


def _camera_K4(cam: CameraModel) -> np.ndarray:
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy])


def build_problem(obs: SessionObservations, init: CalibrationResult, options: JointOptions,
                  cam_model: str, proj_model: str) -> tuple[JointProblem, list]:
    """Gather the observations, initialise every board pose, and return the problem and the list of
    views left out (with reasons)."""
    mirrored = obs.view != VIEW_DIRECT
    if mirrored and init.mirror is None:
        raise CalibrationError("the joint refinement of a mirrored rig needs an initial mirror plane; "
                               "calibrate the mirror first (paper method) or pass one in the initial result")
    S = init.mirror.reflection() if mirrored else np.eye(4)
    cam = init.camera
    poses: list[_Pose] = []
    Rs, ts, planes = [], [], []
    C = {k: [] for k in ("pose", "X", "uv", "mirror", "kind", "cid", "pid")}
    P = {k: [] for k in ("pose", "q", "uv", "mirror", "cid", "pid")}
    left_out = []
    n = init.mirror.normal if mirrored else None
    d = init.mirror.d if mirrored else 0.0
    thickness = float(obs.board_thickness)
    e1 = tangent_basis(n)[0] if mirrored else None

    def add_corners(v, bo, X_all, kind, through, cid):
        C["pose"].append(np.full(len(bo.ids), v))
        C["X"].append(X_all[bo.ids])
        C["uv"].append(np.asarray(bo.corners_px, float))
        C["mirror"].append(np.full(len(bo.ids), through))
        C["kind"].append(np.full(len(bo.ids), kind))
        C["cid"].append(np.full(len(bo.ids), cid))
        C["pid"].append(np.asarray(bo.ids, int))

    captures = []
    Xp = obs.projector_board.corner_points()
    for pv in obs.projector_views:
        bo = pv.board
        if bo is None or len(bo.ids) < 6:
            left_out.append({"capture_id": pv.capture_id, "reason": "fewer than 6 ChArUco corners"})
            continue
        X = Xp[bo.ids]
        T = _pose_through_mirror(cam, S, X, bo.corners_px) if mirrored else _pnp(cam, X, bo.corners_px)
        if T is None:
            left_out.append({"capture_id": pv.capture_id, "reason": "board pose (PnP) failed"})
            continue
        v = len(poses)
        poses.append(_Pose(pv.capture_id, "projector", False))
        captures.append(pv.capture_id)
        Rs.append(T[:3, :3])
        ts.append(T[:3, 3])
        planes.append(np.zeros(3))
        add_corners(v, bo, Xp, _KIND_BOARD, mirrored, len(captures) - 1)
        if len(pv.pattern_proj_px):
            k = len(pv.pattern_proj_px)
            P["pose"].append(np.full(k, v))
            P["q"].append(np.asarray(pv.pattern_proj_px, float))
            P["uv"].append(np.asarray(pv.pattern_cam_px, float))
            P["mirror"].append(np.full(k, mirrored))
            P["cid"].append(np.full(k, len(captures) - 1))
            P["pid"].append(np.arange(k))
    if mirrored:
        if obs.mirror_board is None or not obs.mirror_views:
            raise CalibrationError("a mirrored session needs mirror-calibration images (real-virtual or "
                                   "real-mirror) to locate the mirror")
        Xm = obs.mirror_board.corner_points()
        for mv in obs.mirror_views:
            on_mirror = mv.method == STEP_REAL_MIRROR
            T = None
            if mv.real is not None and len(mv.real.ids) >= 6:
                T = _pnp(cam, Xm[mv.real.ids], mv.real.corners_px)
            elif mv.virtual is not None and len(mv.virtual.ids) >= 6 and not on_mirror:
                T = _pose_through_mirror(cam, S, Xm[mv.virtual.ids], mv.virtual.corners_px)
            if T is None:
                left_out.append({"capture_id": mv.capture_id, "reason": "too few corners or PnP failed"})
                continue
            v = len(poses)
            poses.append(_Pose(mv.capture_id, mv.method, on_mirror))
            captures.append(mv.capture_id)
            Rs.append(T[:3, :3])
            ts.append(T[:3, 3])
            if on_mirror:
                e1p = e1 - (e1 @ n) * n
                e1p /= np.linalg.norm(e1p)
                e2p = np.cross(-n, e1p)
                xa = T[:3, 0]
                X0 = (thickness - d) * n
                planes.append(np.array([np.arctan2(xa @ e2p, xa @ e1p), (T[:3, 3] - X0) @ e1p,
                                        (T[:3, 3] - X0) @ e2p]))
            else:
                planes.append(np.zeros(3))
            if mv.real is not None and len(mv.real.ids):
                add_corners(v, mv.real, Xm, _KIND_REAL, False, len(captures) - 1)
            if mv.virtual is not None and len(mv.virtual.ids) and not on_mirror:
                add_corners(v, mv.virtual, Xm, _KIND_VIRTUAL, True, len(captures) - 1)
    if not any(ps.role == "projector" for ps in poses):
        raise CalibrationError("no usable projector-calibration view: every board detection failed or had "
                               "fewer than 6 corners")

    def cat(lst, shape, dtype=float):
        return np.concatenate(lst).astype(dtype) if lst else np.zeros(shape, dtype)

    corners = {"pose": cat(C["pose"], (0,), int), "X": cat(C["X"], (0, 3)), "uv": cat(C["uv"], (0, 2)),
               "mirror": cat(C["mirror"], (0,), bool), "kind": cat(C["kind"], (0,), int),
               "cid": cat(C["cid"], (0,), int), "pid": cat(C["pid"], (0,), int)}
    pattern = {"pose": cat(P["pose"], (0,), int), "q": cat(P["q"], (0, 2)), "uv": cat(P["uv"], (0, 2)),
               "mirror": cat(P["mirror"], (0,), bool), "cid": cat(P["cid"], (0,), int),
               "pid": cat(P["pid"], (0,), int)}
    corners["s"] = np.ones(len(corners["pose"]))
    pattern["s"] = np.ones(len(pattern["pose"]))
    state = _State(_camera_K4(cam), _dist8(cam.dist), _camera_K4(init.projector), _dist8(init.projector.dist),
                   np.array(init.T_cam_proj[:3, :3]), np.array(init.T_cam_proj[:3, 3]),
                   None if n is None else np.array(n), float(d), np.array(Rs), np.array(ts), np.array(planes),
                   cam_model, proj_model)
    for key, free in (("cam_d", DIST_MODELS[cam_model]), ("proj_d", DIST_MODELS[proj_model])):
        dd = getattr(state, key)
        mask = np.ones(8, bool)
        mask[list(free)] = False
        dd[mask] = 0.0
    pm = options.pattern_model
    if pm == "auto":
        pm = "conic" if obs.pattern.kind == "circles" else "point"
    if pm not in ("point", "conic"):
        raise CalibrationError(f"unknown pattern model '{options.pattern_model}' (one of {', '.join(PATTERN_MODELS)})")
    prob = JointProblem(obs, state, pm, thickness, poses, corners, pattern, float(obs.pattern.radius_px),
                        fix_camera=options.fix_camera)
    prob.captures = captures
    return prob, left_out


# ==================================================================================================
# solving
# ==================================================================================================
def _robust_sigma(r: np.ndarray) -> float:
    if r.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _update_centroid_correction(prob: JointProblem, x: np.ndarray, n_boundary: int = 32) -> None:
    """Difference between the area centroid of the imaged circle (32 boundary points through the full
    model, distortion included) and the conic-centre model, evaluated at x and held fixed: makes the
    conic model exact to second order in the distortion's variation across a blob."""
    if prob.pattern_model != "conic" or len(prob.p["q"]) == 0:
        return
    from calib.joint.conic import circle_boundary, polygon_centroid

    m = prob.unpack(x)
    q = prob.p["q"]
    B = circle_boundary(q, prob.radius_px, n_boundary).reshape(-1, 2)
    cam = CameraModel(1, 1, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], m["proj_d"].real)
    K = m["proj_K"].real
    xy = cam.undistort_normalized(np.column_stack([(B[:, 0] - K[2]) / K[0], (B[:, 1] - K[3]) / K[1]]))
    H = np.repeat(prob._homographies(m)[prob.p["pose"]], n_boundary, axis=0)
    Xh = np.einsum("nij,nj->ni", H, np.column_stack([xy, np.ones(len(xy))]))
    uv = prob._project(m["cam_K"], m["cam_d"], Xh).reshape(len(q), n_boundary, 2)
    conic = prob._project(m["cam_K"], m["cam_d"], prob.pattern_points(m, "conic"))
    prob.centroid_corr = polygon_centroid(uv) - conic


def refine_joint(obs: SessionObservations, init: CalibrationResult, options: JointOptions = JointOptions(),
                 progress=None) -> CalibrationResult:
    """Joint maximum-likelihood refinement of every parameter of the session from `init` (usually the
    paper's sequential result). See the module docstring and docs/JOINT.md."""
    t_start = time.perf_counter()
    timing = {}
    if isinstance(init.diagnostics, dict) and isinstance(init.diagnostics.get("timing_s"), dict):
        for k, v in init.diagnostics["timing_s"].items():
            timing[f"{init.method}.{k}"] = v
    for name, val in (("camera_model", options.camera_model), ("projector_model", options.projector_model)):
        if val != "auto" and val not in DIST_MODELS:
            raise CalibrationError(f"unknown {name} '{val}' (one of auto, {', '.join(MODEL_NAMES)})")

    stages = ("joint.setup", "joint.robust", "joint.outliers_and_ml", "joint.model_selection", "joint.uncertainty")

    def tick(stage, t0):
        timing[stage] = round(time.perf_counter() - t0, 4)
        if progress is not None:
            progress(stages.index(stage) + 1, len(stages), stage)

    t0 = time.perf_counter()
    cam0 = options.camera_model if options.camera_model != "auto" else DistortionModel.FIVECOEF
    if options.fix_camera:  # keep the given camera exactly (all its coefficients)
        cam0 = DistortionModel.RATIONAL if init.camera.dist.size == 8 else DistortionModel.FIVECOEF
    proj0 = options.projector_model if options.projector_model != "auto" else DistortionModel.FIVECOEF
    prob, left_out = build_problem(obs, init, options, cam0, proj0)
    tick("joint.setup", t0)

    # ---- pass 1: robust loss ------------------------------------------------------------------
    t0 = time.perf_counter()
    x = prob.x0()
    r0 = prob.residuals(x)
    sigma0 = options.noise_px if options.noise_px else max(_robust_sigma(r0), 0.05)
    prob.reset_warm_start()
    x, info1 = solve(prob, options.loss, sigma0, options.max_nfev, max(options.tol, 1e-4), options.solver)
    if prob.pattern_model == "conic" and options.centroid_correction:
        _update_centroid_correction(prob, x)
    tick("joint.robust", t0)

    # ---- noise per observation class, outlier rejection, maximum-likelihood solve -------------------
    t0 = time.perf_counter()
    rejected = []
    solves = [info1]
    prob.set_class_sigmas(_class_sigmas(prob, prob.raw_residuals(x), options, robust=True))
    for _round in range(max(options.outlier_rounds, 0) + 1):
        new = _reject(prob, x, options.outlier_sigma, options.min_outlier_px, rejected) \
            if _round < options.outlier_rounds else 0
        if _round > 0 and not new:
            break
        x, info = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        solves.append(info)
    # the final weights: per-class RMS of the inlier residuals at the ML solution
    before = dict(prob.class_sigma)
    prob.set_class_sigmas(_class_sigmas(prob, prob.raw_residuals(x), options, robust=False))
    # a class whose every residual was rejected as an outlier has no sigma any more: the weights changed
    changed = any(k not in prob.class_sigma or abs(prob.class_sigma[k] / before[k] - 1) > 0.05 for k in before)
    if prob.pattern_model == "conic" and options.centroid_correction:
        old = prob.centroid_corr.copy()
        _update_centroid_correction(prob, x)
        changed |= bool(old.size and np.abs(prob.centroid_corr - old).max() > 1e-4)
    if changed:
        x, info = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        solves.append(info)
    tick("joint.outliers_and_ml", t0)

    # ---- distortion model selection -------------------------------------------------------------
    t0 = time.perf_counter()
    selection = _guarded("the distortion model selection", model_select.select_models, prob, options)
    x = prob.x0()
    tick("joint.model_selection", t0)

    # ---- uncertainty ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    unc = None
    if options.uncertainty:
        unc = _guarded("the covariance", uncertainty.joint_uncertainty, prob, x)
    tick("joint.uncertainty", t0)

    result = _make_result(obs, init, prob, x, rejected, left_out, selection, unc, solves, timing)
    if unc is not None:  # the 1-sigma pixel motion over each device's image (calib.quality.projection_uncertainty)
        result = result.with_(projection_uncertainty=projection_uncertainty(result))
    timing["joint.total"] = round(time.perf_counter() - t_start, 4)
    return result


def _guarded(what: str, fn, *args):
    """fn(*args), with numpy's linear-algebra failures (which only degenerate data cause: an SVD that
    does not converge, a singular system) turned into a CalibrationError that says so."""
    try:
        return fn(*args)
    except np.linalg.LinAlgError as e:
        raise CalibrationError(f"the joint adjustment failed in {what} ({e}); the session's data are probably "
                               "degenerate (the same image in every capture, wrong pattern points, boards seen "
                               "from one pose only): check the captures", code="solve_failed") from None


def calibrate_joint(obs: SessionObservations, camera: CameraModel | None = None, progress=None,
                    options: JointOptions | None = None, **option_overrides) -> CalibrationResult:
    """The "joint" method of calib.pipeline.METHODS: the paper's sequential pipeline as the starting
    point, then refine_joint. A given `camera` is held fixed (as the paper method keeps it), unless
    fix_camera=False is passed. Keyword arguments override fields of JointOptions (camera_model=...)."""
    opts = options or JointOptions()
    if camera is not None and "fix_camera" not in option_overrides:
        option_overrides["fix_camera"] = True
    if option_overrides:
        unknown = set(option_overrides) - set(JointOptions.__dataclass_fields__)
        if unknown:
            raise CalibrationError(f"unknown joint option(s): {', '.join(sorted(unknown))}")
        opts = replace(opts, **option_overrides)
    init = calibrate_paper(obs, camera, progress)
    try:
        return refine_joint(obs, init, opts, progress)
    except CalibrationError as e:
        if e.code not in ("non_finite", "solve_failed"):
            raise
        # the refinement met NaN / inf or a singular system: report it with what is wrong with its starting
        # point, and keep that starting point (the paper method's result) for diagnosis
        start = check_calibration(init)
        report = replace(start, reasons=(TrustReason(e.code, str(e)),) + start.reasons)
        rejected = init.with_(diagnostics=dict(init.diagnostics, joint_error=str(e), trust=report.to_dict()))
        raise UntrustedCalibration(report, rejected) from None


def _class_sigmas(prob: JointProblem, r_px: np.ndarray, options: JointOptions, robust: bool) -> dict:
    """Noise sigma (px, per coordinate) of each observation class: robust (MAD) or RMS of the residuals.
    weighting="none" pools all classes; classes with fewer than 20 points take the pooled value."""
    floor = 1e-3
    pooled = _robust_sigma(r_px) if robust else float(np.sqrt(np.mean(r_px ** 2))) if r_px.size else 1.0
    pooled = max(pooled, floor)
    out = {}
    for name, m in prob.class_masks().items():
        rr = np.stack([r_px[0::2][m], r_px[1::2][m]], axis=1).reshape(-1)
        if options.weighting == "none" or m.sum() < 20:
            out[name] = pooled
        else:
            v = _robust_sigma(rr) if robust else float(np.sqrt(np.mean(rr ** 2)))
            out[name] = max(v, floor)
    return out


def _reject(prob: JointProblem, x: np.ndarray, k: float, min_px: float, rejected: list) -> int:
    """Drop points whose whitened residual norm exceeds k robust sigmas and whose pixel residual exceeds
    min_px (and views left with fewer than 6 corners); append a record per dropped point to `rejected`.
    Returns the number of points dropped."""
    nc = len(prob.c["pose"])
    rw = prob.residuals(x)
    rp = rw * prob.row_scale
    sig = max(_robust_sigma(rw), 1e-12)
    ew = np.hypot(rw[0::2], rw[1::2]) / sig
    e = np.hypot(rp[0::2], rp[1::2])
    bad = (ew > k) & (e > min_px)
    if not bad.any():
        return 0
    keep_c = ~bad[:nc]
    keep_p = ~bad[nc:]
    # a pose needs at least 6 corners to stay determined; otherwise drop the whole view
    counts = np.bincount(prob.c["pose"][keep_c], minlength=len(prob.poses))
    weak = np.where(prob.on_mirror, counts < 3, counts < 6)
    scale = np.concatenate([prob.c["s"], prob.p["s"]]) * sig
    for kind, keep, arr in (("corner", keep_c, prob.c), ("pattern", keep_p, prob.p)):
        off = 0 if kind == "corner" else nc
        for i in np.nonzero(~keep)[0]:
            j = off + i
            rejected.append({
                "capture_id": prob.captures[arr["cid"][i]],
                "kind": _KIND_NAMES[arr["kind"][i]] if kind == "corner" else "pattern",
                "point": int(arr["pid"][i]), "residual_px": round(float(e[j]), 4),
                "reason": f"residual {e[j]:.3g} px = {ew[j]:.1f} robust sigma ({scale[j]:.3g} px) of its class "
                          f"> {k:g} sigma"})
    if weak.any():
        for v in np.nonzero(weak)[0]:
            rejected.append({"capture_id": prob.poses[v].capture_id, "kind": "view", "point": -1,
                             "residual_px": None,
                             "reason": f"view dropped: only {int(counts[v])} ChArUco corners left after rejection"})
        keep_c &= ~weak[prob.c["pose"]]
        keep_p &= ~weak[prob.p["pose"]]
    prob.subset(keep_c, keep_p, weak)
    return int(bad.sum())




# ==================================================================================================
# result
# ==================================================================================================
def per_view_residuals(prob: JointProblem, x: np.ndarray) -> list[dict]:
    """Per view: point count, rms and max residual (px), per observation kind, and every point's
    residual norm (px; board corners first, by corner id, then pattern points, by index)."""
    r = prob.raw_residuals(x)
    nc = len(prob.c["pose"])
    e2 = r[0::2] ** 2 + r[1::2] ** 2
    out = []
    for v, ps in enumerate(prob.poses):
        mc = prob.c["pose"] == v
        mp = prob.p["pose"] == v
        ec, ep = e2[:nc][mc], e2[nc:][mp]
        allv = np.concatenate([ec, ep])
        rec = {"capture_id": ps.capture_id, "step": ps.role, "n_points": int(allv.size),
               "rms_px": float(np.sqrt(allv.mean())) if allv.size else None,
               "max_px": float(np.sqrt(allv.max())) if allv.size else None,
               "point_residuals_px": np.round(np.sqrt(allv), 4).tolist()}
        if ps.role == "projector":
            rec["rms_board_px"] = float(np.sqrt(ec.mean())) if ec.size else None
            rec["rms_pattern_px"] = float(np.sqrt(ep.mean())) if ep.size else None
        else:
            kinds = prob.c["kind"][mc]
            for kind, name in ((_KIND_REAL, "rms_real_px"), (_KIND_VIRTUAL, "rms_virtual_px")):
                sel = ec[kinds == kind]
                if sel.size:
                    rec[name] = float(np.sqrt(sel.mean()))
        out.append(rec)
    return out


def _make_result(obs, init, prob: JointProblem, x, rejected, left_out, selection, unc, solves, timing):
    m = prob.unpack(x)
    s = prob.state
    if prob.fix_camera:
        cam = init.camera
    else:
        cam = CameraModel(obs.camera_size[0], obs.camera_size[1],
                          [[m["cam_K"][0], 0, m["cam_K"][2]], [0, m["cam_K"][1], m["cam_K"][3]], [0, 0, 1]],
                          _dist_out(np.array(m["cam_d"], float), s.cam_model))
    proj = CameraModel(obs.projector_size[0], obs.projector_size[1],
                       [[m["proj_K"][0], 0, m["proj_K"][2]], [0, m["proj_K"][1], m["proj_K"][3]], [0, 0, 1]],
                       _dist_out(np.array(m["proj_d"], float), s.proj_model))
    T = make_T(_orthonormalise(m["R_cp"]), np.array(m["t_cp"], float))
    mirror = MirrorPlane(np.array(m["n"], float), float(m["d"])) if prob.mirrored else None
    r = prob.raw_residuals(x)
    rw = prob.residuals(x)
    nc = len(prob.c["pose"])
    e2 = r[0::2] ** 2 + r[1::2] ** 2
    kinds = prob.c["kind"]
    order = np.argsort(-e2)[:10]
    worst_points = []
    for j in order:
        arr, i = (prob.c, j) if j < nc else (prob.p, j - nc)
        worst_points.append({"capture_id": prob.captures[arr["cid"][i]],
                             "kind": _KIND_NAMES[arr["kind"][i]] if j < nc else "pattern",
                             "point": int(arr["pid"][i]), "residual_px": round(float(np.sqrt(e2[j])), 4)})

    def rms(a):
        return float(np.sqrt(a.mean())) if a.size else None

    rms_d = {"joint": rms(e2), "board": rms(e2[:nc][kinds == _KIND_BOARD]), "pattern": rms(e2[nc:]),
             "mirror_real": rms(e2[:nc][kinds == _KIND_REAL]),
             "mirror_virtual": rms(e2[:nc][kinds == _KIND_VIRTUAL])}
    rms_d = {k: v for k, v in rms_d.items() if v is not None}
    per_view = per_view_residuals(prob, x)
    worst = sorted((pv for pv in per_view if pv["rms_px"] is not None), key=lambda pv: -pv["rms_px"])[:5]
    diag = {
        "stage": "joint",
        "pattern_model": prob.pattern_model,
        "camera_model": s.cam_model,
        "projector_model": s.proj_model,
        "n_points": {"corners": int(nc), "pattern": int(len(prob.p["q"])), "views": len(prob.poses)},
        "n_residuals": int(r.size),
        "n_params": int(prob.n_params),
        "sigma_px": float(np.sqrt((r @ r) / max(r.size - prob.n_params, 1))),
        "class_sigma_px": dict(prob.class_sigma),
        "variance_factor": float((rw @ rw) / max(rw.size - prob.n_params, 1)),
        "worst_points": worst_points,
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
    return CalibrationResult(cam, proj, T, mirror, obs.units, method="joint", rms=rms_d, per_view=tuple(per_view),
                             skipped=skipped, uncertainty=unc, diagnostics=diag)


__all__ = ["JointOptions", "refine_joint", "calibrate_joint", "DIST_MODELS", "MODEL_NAMES", "JointProblem",
           "build_problem", "solve", "gibbs_R", "distort", "distort_jac"]
