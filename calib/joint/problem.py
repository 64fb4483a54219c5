"""The joint adjustment's least-squares problem (JointProblem): the parameter layout relative to a
reference state, the model of every observation (docs/GEOMETRY.md), the whitened residuals and their
exact Jacobian in block form.

Parameters: camera fx, fy, cx, cy and its free distortion coefficients (unless held), the projector's,
T_cam_proj (a Gibbs vector about the reference rotation, calib.transforms, and the translation), the
mirror (two tilts along calib.transforms.tangent_basis of the reference normal, and d), then per view
its board pose: six (Gibbs vector, translation) or, for a board lying on the mirror, three (its angle
and position in the mirror plane). A solve moves the reference to its solution (rebase), so the
rotations are always evaluated near g = 0.

Derivatives are exact: the camera intrinsics analytically, everything else by complex step, grouped
by the block structure (one complex evaluation per global parameter, of only the residuals it can
affect, and six for all board poses together)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.joint import conic, lens
from calib.joint.points import (
    CLASS_OF_KIND,
    KIND_BOARD,
    KIND_REAL,
    KIND_VIRTUAL,
    PATTERN_CLASS,
    CornerSet,
    PatternSet,
)
from calib.joint.solver import DIST_MODELS, _RowSums
from calib.models.camera import CameraModel
from calib.models.observations import VIEW_DIRECT, SessionObservations
from calib.models.vocab import DistortionModel
from calib.transforms import make_T, nearest_rotation, tangent_basis, update_R

#: the step of the complex-step derivatives: far below rounding, and no subtraction to cancel
_H = 1e-30


@dataclass(frozen=True)
class View:
    """One view of the problem: its capture, its step ("projector", "mirror-real-virtual",
    "mirror-real-mirror") and whether its board lies on the mirror (a 3-DOF pose)."""

    capture_id: str
    role: str
    on_mirror: bool


@dataclass
class ReferenceState:
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

    def copy(self) -> ReferenceState:
        return ReferenceState(self.cam_K.copy(), self.cam_d.copy(), self.proj_K.copy(), self.proj_d.copy(),
                              self.R_cp.copy(), self.t_cp.copy(), None if self.n is None else self.n.copy(),
                              self.d, self.R.copy(), self.t.copy(), self.plane.copy(), self.cam_model,
                              self.proj_model)


def plane_axes(ref: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The in-plane axes (e1, e2) of a board lying on the mirror of normal n: e1 the fixed reference `ref`
    projected onto the plane, e1 x e2 = -n = the board's z (into the board, away from the camera).
    Complex-safe (no conjugation)."""
    e1 = ref - (ref @ n) * n
    e1 = e1 / np.sqrt(e1 @ e1)
    return e1, np.cross(-n, e1)


def plane_params(T: np.ndarray, ref: np.ndarray, n: np.ndarray, d: float, thickness: float) -> np.ndarray:
    """(theta, a, b) of a board lying on the mirror (n, d) with pose T = T_cam_board: the angle of its x
    axis from e1 and its origin along (e1, e2) from the plane offset by the board's thickness."""
    e1, e2 = plane_axes(ref, n)
    X0 = (thickness - d) * n
    xa = T[:3, 0]
    return np.array([np.arctan2(xa @ e2, xa @ e1), (T[:3, 3] - X0) @ e1, (T[:3, 3] - X0) @ e2])


def _reflect(X, n, d):
    s2 = 2.0 * (X[:, 0] * n[0] + X[:, 1] * n[1] + X[:, 2] * n[2] + d)
    return np.stack([X[:, 0] - s2 * n[0], X[:, 1] - s2 * n[1], X[:, 2] - s2 * n[2]], axis=-1)


class JointProblem:
    """Observations gathered once into frozen point sets, the parameter layout, residuals and Jacobian."""

    def __init__(self, obs: SessionObservations, state: ReferenceState, pattern_model: str, thickness: float,
                 poses: list[View], corners: CornerSet, pattern: PatternSet, radius_px: float,
                 captures: list[str], fix_camera: bool = False):
        self.obs = obs
        self.fix_camera = fix_camera
        self.mirrored = obs.view != VIEW_DIRECT
        self.poses = list(poses)
        self.captures = list(captures)
        self.thickness = thickness
        self.pattern_model = pattern_model
        self.radius_px = radius_px
        self.corners = corners
        self.pattern = pattern
        self.on_mirror = np.array([ps.on_mirror for ps in poses], bool)
        # a fixed in-plane reference for boards lying on the mirror (their 3 parameters are relative to it)
        self.plane_ref = tangent_basis(state.n)[0] if self.mirrored else None
        #: noise sigma (px) of every point, corners then pattern points: its class's sigma times the
        #: point's relative noise (PatternSet.rel; set_class_sigmas)
        self.point_sigma = self.relative_noise()
        self.set_state(state)
        self.centroid_corr = np.zeros((len(pattern), 2))
        self._xu_cache = None
        self._proj_cache = None
        self.class_sigma = {}
        self.prior = {}

    # ---- layout ---------------------------------------------------------------------------------
    def set_state(self, state: ReferenceState) -> None:
        self.state = state
        self._any_c_mirror = bool(np.any(self.corners.mirror))
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
        out["R_cp"] = update_R(x[i:i + 3], s.R_cp)
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
            R[free] = update_R(P[:, :3], s.R[free])
            t[free] = P[:, 3:]
        if self.on_mirror.any():
            n, d = out["n"], out["d"]
            e1, e2 = plane_axes(self.plane_ref, n)
            idx = self.pose_start[self.on_mirror][:, None] + np.arange(3)
            P = x[idx]
            c, sn = np.cos(P[:, 0]), np.sin(P[:, 0])
            xa = c[:, None] * e1 + sn[:, None] * e2
            ya = -sn[:, None] * e1 + c[:, None] * e2
            R[self.on_mirror] = np.stack([xa, ya, np.broadcast_to(-n, xa.shape)], axis=-1)
            t[self.on_mirror] = (self.thickness - d) * n + P[:, 1:2] * e1 + P[:, 2:3] * e2
        out["R"], out["t"] = R, t
        return out

    # ---- the views' board poses -----------------------------------------------------------------
    def plane_params(self, T: np.ndarray) -> np.ndarray:
        """(theta, a, b) of a board lying on the reference mirror with pose T = T_cam_board."""
        return plane_params(T, self.plane_ref, self.state.n, self.state.d, self.thickness)

    def board_poses(self, x: np.ndarray) -> dict:
        """T_cam_board (4x4) of every view at x, by capture id."""
        m = self.unpack(x)
        return {ps.capture_id: make_T(np.real(m["R"][v]), np.real(m["t"][v])) for v, ps in enumerate(self.poses)}

    def set_board_poses(self, T_cam_board: dict) -> None:
        """Start every view from the given T_cam_board (by capture id; one for every view): ValueError
        when one is not a finite 4x4 matrix (TypeError when it is not numbers)."""
        state = self.state.copy()
        for v, ps in enumerate(self.poses):
            T = np.asarray(T_cam_board[ps.capture_id], float).reshape(4, 4)
            if not np.isfinite(T).all():
                raise ValueError(f"the board pose of {ps.capture_id} is not finite")
            state.R[v], state.t[v] = T[:3, :3], T[:3, 3]
            if ps.on_mirror:
                state.plane[v] = self.plane_params(T)
        self.set_state(state)

    # ---- model ----------------------------------------------------------------------------------
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
        nc = len(self.corners)
        self.point_sigma = np.concatenate([self.point_sigma[:nc][keep_c], self.point_sigma[nc:][keep_p]])
        self.corners = self.corners.subset(keep_c).renumbered(remap)
        self.pattern = self.pattern.subset(keep_p).renumbered(remap)
        self.centroid_corr = self.centroid_corr[keep_p]
        self.reset_warm_start()
        self._proj_cache = None
        self.set_state(state)

    def corner_points(self, m: dict) -> np.ndarray:
        """(N, 3) ChArUco corners in the (virtual, when seen through the mirror) camera frame."""
        c = self.corners
        pose = c.pose
        if len(pose) == 0:
            return np.zeros((0, 3))
        R, t = m["R"], m["t"]
        # board points have z = 0: only the first two columns of R matter
        X = R[pose, :, 0] * c.X[:, 0:1] + R[pose, :, 1] * c.X[:, 1:2] + t[pose]
        if self.mirrored and self._any_c_mirror:
            mm = c.mirror
            X[mm] = _reflect(X[mm], m["n"], m["d"])
        return X

    def _projector_side(self, pK, pd, need_A: bool):
        """(xu, yu, A): undistorted normalised projector coordinates of the pattern points and the local
        linear map A = d(xu, yu)/dq (2x2 per point). Cached for real projector parameters, so that the
        complex evaluations of the Jacobian that do not perturb the projector reuse them."""
        complex_ = lens.is_perturbed(pK, pd)
        key = (tuple(np.real(pK)), tuple(np.real(pd)), need_A)
        if not complex_ and self._proj_cache is not None and self._proj_cache[0] == key:
            return self._proj_cache[1]
        xu, yu, self._xu_cache = lens.undistort(self.pattern.q, pK, pd, self._xu_cache)
        A = None
        if need_A:
            a11, a12, a21, a22 = lens.distort_jac(xu, yu, pd)
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
        p = self.pattern
        if len(p) == 0:
            return np.zeros((0, 3))
        model = model or self.pattern_model
        xu, yu, A = self._projector_side(m["proj_K"], m["proj_d"], model == "conic")
        H = self._homographies(m)[p.pose]
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
        uv_c = lens.project(m["cam_K"], m["cam_d"], self.corner_points(m))
        uv_p = lens.project(m["cam_K"], m["cam_d"], self.pattern_points(m, pattern_model))
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

    def update_centroid_correction(self, x: np.ndarray, n_boundary: int = 32) -> None:
        """Difference between the area centroid of the imaged circle (32 boundary points through the full
        model, distortion included) and the conic-centre model, evaluated at x and held fixed: makes the
        conic model exact to second order in the distortion's variation across a blob."""
        if self.pattern_model != "conic" or len(self.pattern) == 0:
            return
        m = self.unpack(x)
        q = self.pattern.q
        B = conic.circle_boundary(q, self.radius_px, n_boundary).reshape(-1, 2)
        cam = CameraModel(1, 1, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], m["proj_d"].real)
        K = m["proj_K"].real
        xy = cam.undistort_normalized(np.column_stack([(B[:, 0] - K[2]) / K[0], (B[:, 1] - K[3]) / K[1]]))
        H = np.repeat(self._homographies(m)[self.pattern.pose], n_boundary, axis=0)
        Xh = np.einsum("nij,nj->ni", H, np.column_stack([xy, np.ones(len(xy))]))
        uv = lens.project(m["cam_K"], m["cam_d"], Xh).reshape(len(q), n_boundary, 2)
        centre = lens.project(m["cam_K"], m["cam_d"], self.pattern_points(m, "conic"))
        self.centroid_corr = conic.polygon_centroid(uv) - centre

    def raw_residuals(self, x: np.ndarray) -> np.ndarray:
        """Residuals in pixels, [u0, v0, u1, v1, ...] over corners then pattern points."""
        uv_c, uv_p = self.predict(x)
        return np.concatenate([(uv_c - self.corners.uv).reshape(-1), (uv_p - self.pattern.uv).reshape(-1)])

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals: pixels divided by the noise sigma of each observation's class."""
        return self.raw_residuals(x) / self.row_scale

    # ---- observation classes and their noise ----------------------------------------------------
    def class_masks(self) -> dict:
        """Point masks (over corners + pattern points) of the observation classes."""
        nc, npat = len(self.corners), len(self.pattern)
        out = {}
        for kind in (KIND_BOARD, KIND_REAL, KIND_VIRTUAL):
            m = np.zeros(nc + npat, bool)
            m[:nc] = self.corners.kind == kind
            if m.any():
                out[CLASS_OF_KIND[kind]] = m
        if npat:
            m = np.zeros(nc + npat, bool)
            m[nc:] = True
            out[PATTERN_CLASS] = m
        return out

    def relative_noise(self) -> np.ndarray:
        """Every point's noise relative to its class's sigma: 1 for corners, PatternSet.rel for pattern points."""
        return np.concatenate([np.ones(len(self.corners)), self.pattern.rel])

    def set_class_sigmas(self, sig_px: dict) -> None:
        """Weight every observation by 1 / (sigma of its class (pixels) x its relative noise)."""
        self.class_sigma = dict(sig_px)
        scale = np.ones(len(self.corners) + len(self.pattern))
        for name, m in self.class_masks().items():
            scale[m] = sig_px.get(name, 1.0)
        scale = scale * self.relative_noise()
        self.point_sigma = scale
        self.row_scale = np.repeat(scale, 2)

    # ---- Jacobian (complex step, grouped by block structure) ------------------------------------
    def _build_sparsity(self) -> None:
        self.row_scale = np.repeat(self.point_sigma, 2)
        rows_pose = np.concatenate([self.corners.pose, self.pattern.pose])
        rows_pose = np.repeat(rows_pose, 2)  # two residuals per point
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
        nc2 = 2 * len(self.corners)
        is_pattern = np.zeros(N, bool)
        is_pattern[nc2:] = True
        ncf = self.n_cam
        npf = 4 + len(self.proj_free)
        dep[~is_pattern, ncf:ncf + npf + 6] = False  # corners: no projector, no T_cam_proj
        if self.mirrored:
            through = np.repeat(np.concatenate([self.corners.mirror, self.pattern.mirror]), 2)
            on_m = self.on_mirror[rows_pose]
            dep[~through & ~on_m, G - 3:] = False
        self._gdep_c = dep[:nc2].any(axis=0)
        self._gdep_p = dep[nc2:].any(axis=0)
        keep = np.concatenate([dep.reshape(-1)] + [np.ones(len(r), bool) for r in r_p])
        self._jkeep = keep

    def _complex_parts(self, xc: np.ndarray, corners: bool, pattern: bool) -> np.ndarray:
        m = self.unpack(xc)
        nc2 = 2 * len(self.corners)
        out = np.zeros(self.n_res)
        if corners and nc2:
            out[:nc2] = lens.project(m["cam_K"], m["cam_d"], self.corner_points(m)).imag.reshape(-1)
        if pattern and self.n_res > nc2:
            out[nc2:] = lens.project(m["cam_K"], m["cam_d"], self.pattern_points(m)).imag.reshape(-1)
        return out

    def jacobian_blocks(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact Jacobian in block form: (Jg (N, G) for the global parameters, Jl (N, 6) for the pose
        of each residual's own view, zero beyond that pose's DOF)."""
        N, G = self.n_res, self.n_global
        Jg = np.zeros((N, G))
        m = self.unpack(x)
        X = np.concatenate([self.corner_points(m), self.pattern_points(m)])
        ncam = self.n_cam
        if ncam:
            Jg[:, :ncam] = lens.intrinsics_columns(X, m["cam_K"], m["cam_d"], self.cam_free)
        xc = x.astype(complex)
        for j in range(ncam, G):
            xc.imag[:] = 0.0
            xc.imag[j] = _H
            Jg[:, j] = self._complex_parts(xc, self._gdep_c[j], self._gdep_p[j]) / _H
        Jl = np.zeros((N, 6))
        for k in range(6):
            has = self.pose_ndof > k
            if not has.any():
                continue
            xc.imag[:] = 0.0
            xc.imag[self.pose_start[has] + k] = _H
            Jl[:, k] = self._complex_parts(xc, True, True) / _H
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
    def rebase(self, x: np.ndarray) -> ReferenceState:
        """A new reference state at x (rotations re-centred, so that x0() of it is x re-expressed)."""
        m = self.unpack(x)
        s = self.state.copy()
        s.cam_K, s.cam_d = np.array(m["cam_K"], float), np.array(m["cam_d"], float)
        s.proj_K, s.proj_d = np.array(m["proj_K"], float), np.array(m["proj_d"], float)
        s.R_cp, s.t_cp = nearest_rotation(m["R_cp"]), np.array(m["t_cp"], float)
        if self.mirrored:
            s.n, s.d = np.array(m["n"], float), float(m["d"])
        s.R = np.array([nearest_rotation(r) for r in m["R"]])
        s.t = np.array(m["t"], float)
        for v in np.nonzero(self.on_mirror)[0]:
            s.plane[v] = x[self.pose_start[v]:self.pose_start[v] + 3]
        return s
