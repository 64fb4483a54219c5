"""Board poses from ChArUco corners, for direct views and views through the mirror.

A board seen through the mirror is imaged exactly like a rigid view of the MIRRORED board
(docs/GEOMETRY.md): u = project(K, S T X) = project(K, (S T F_b)(F_b X)) with F_b = diag(-1, 1, 1), and
S T F_b is a proper rigid transform. So a mirrored observation is solved like a direct one with object
points (-x, y, 0) and the original pixel coordinates; the pose found is that of the *virtual* board,
`T_cam_vboard = S @ T_cam_board @ F_b`, in the frame of the mirrored board. With a known mirror the
physical pose is `T_cam_board = S @ T_cam_vboard @ F_b`.

Used by every calibration stage (camera, mirror, projector).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import CalibrationError
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import BoardObservation
from calib.transforms import FLIP_X, T_from_rvec_tvec, rvec_tvec_from_T, transform_points

#: F_b: the board-frame mirror x -> -x (as a 4x4 transform). Numerically the same matrix as FLIP_X.
MIRROR_BOARD = np.diag([-1.0, 1.0, 1.0, 1.0])

#: Fewer corners than this and a view is not used (a planar pose needs 4; 6 keeps it well posed).
MIN_CORNERS = 6

_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def view_object_points(spec: CharucoSpec, obs: BoardObservation) -> np.ndarray:
    """(N, 3) object points of the observed corners in the frame of the board *as seen*: the board
    frame for a direct view, the mirrored board frame (x -> -x) for a view through the mirror."""
    X = spec.corner_points()[np.asarray(obs.ids, int)]
    if obs.mirrored:
        X[:, 0] = -X[:, 0]
    return X


def usable_reason(spec: CharucoSpec, obs: BoardObservation | None, min_corners: int = MIN_CORNERS) -> str | None:
    """None when the observation can give a pose, else why not (a sentence a user can act on)."""
    if obs is None:
        return "no board observation"
    n = len(obs.ids)
    if n < min_corners:
        return f"only {n} ChArUco corners found (need at least {min_corners}); show more of the board"
    if np.any(obs.ids < 0) or np.any(obs.ids >= spec.n_corners):
        return f"corner ids outside 0..{spec.n_corners - 1}: the board spec does not match the printed board"
    if len(np.unique(obs.ids)) != n:
        return "duplicate corner ids in one view"
    if not np.all(np.isfinite(obs.corners_px)):
        return "non-finite corner coordinates"
    X = spec.corner_points()[obs.ids, :2]
    ev = np.linalg.eigvalsh(np.cov((X - X.mean(axis=0)).T))
    if ev[0] < (0.25 * spec.square_length) ** 2:
        return "the detected corners are (nearly) collinear; show more rows of the board"
    return None


@dataclass(frozen=True, eq=False)
class BoardPose:
    """Pose of the board as seen (virtual board for a mirrored view) and its reprojection residuals."""

    T_cam_view: np.ndarray
    mirrored: bool
    residuals_px: np.ndarray  # (N,) reprojection error per corner (all corners, outliers included)
    inliers: np.ndarray | None = None  # (N,) bool: corners the pose was fitted to (None: all)

    @property
    def rms_px(self) -> float:
        r = self.residuals_px if self.inliers is None else self.residuals_px[self.inliers]
        return float(np.sqrt(np.mean(r**2)))

    @property
    def n_outliers(self) -> int:
        return 0 if self.inliers is None else int((~self.inliers).sum())

    def physical(self, S: np.ndarray | None) -> np.ndarray:
        """T_cam_board of the physical board (needs the mirror reflection S for a mirrored view)."""
        if not self.mirrored:
            return self.T_cam_view
        if S is None:
            raise ValueError("a mirrored view needs the mirror to give the physical board pose")
        return S @ self.T_cam_view @ MIRROR_BOARD

    def seen_points(self, X_board: np.ndarray) -> np.ndarray:
        """Camera-frame points where the camera *sees* board points X_board (the virtual points for a
        mirrored view: S X for the physical X)."""
        X = np.array(X_board, float).reshape(-1, 3)
        if self.mirrored:
            X[:, 0] = -X[:, 0]
        return transform_points(self.T_cam_view, X)


#: A corner (or pattern point) is an outlier when its residual exceeds
#: max(OUTLIER_FACTOR x the median residual, OUTLIER_MIN_PX); removed worst first.
OUTLIER_FACTOR = 6.0
OUTLIER_MIN_PX = 2.0


def outlier_limit(residuals: np.ndarray) -> float:
    return max(OUTLIER_FACTOR * float(np.median(residuals)), OUTLIER_MIN_PX)


def solve_board_pose(camera: CameraModel, spec: CharucoSpec, obs: BoardObservation,
                     reject_outliers: bool = True) -> BoardPose:
    """PnP of one board observation: IPPE (both planar solutions, the better one), then LM. With
    `reject_outliers`, corners far off the fitted pose (outlier_limit) are dropped one at a time, worst
    first (at most a quarter of them), and the pose refitted."""
    X = view_object_points(spec, obs)
    uv = np.ascontiguousarray(obs.corners_px, float)
    found = solve_pnp(camera, X, uv)
    if found is None:
        raise CalibrationError(f"no board pose fits these {len(X)} ChArUco corners (too few, or all on one line): "
                               "retake the capture with more of the board in view")
    T, res = found
    inl = np.ones(len(X), bool)
    if reject_outliers:
        for _ in range(len(X) // 4):
            r = np.where(inl, res, -1.0)
            if r.max() <= outlier_limit(res[inl]) or inl.sum() <= MIN_CORNERS:
                break
            inl[int(np.argmax(r))] = False
            T = solve_pnp(camera, X[inl], uv[inl])[0]  # >= 3/4 of the corners: a pose exists
            res = _residuals(camera, T, X, uv)
    return BoardPose(T, bool(obs.mirrored), res, None if inl.all() else inl)


def solve_pnp(camera: CameraModel, X: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(T_cam_board, per-point residuals in px) of a planar target from (N, 3) points on z = 0 and their
    (N, 2) pixels: both IPPE solutions (a plane seen at a small tilt is ambiguous) refined by LM, the one
    with the smaller residuals kept. None with fewer than 4 points or when OpenCV finds no pose."""
    if len(X) < 4:
        return None
    K = np.array(camera.K)
    dist = camera.dist5() if camera.dist.size <= 5 else np.array(camera.dist)
    X = np.ascontiguousarray(X, np.float64)
    uv = np.ascontiguousarray(uv, np.float64).reshape(-1, 2)
    try:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
        best = None
        for rvec, tvec in zip(rvecs, tvecs):
            rvec, tvec = cv2.solvePnPRefineLM(X, uv, K, dist, rvec.copy(), tvec.copy(), criteria=_LM_CRITERIA)
            T = T_from_rvec_tvec(rvec, tvec)
            res = _residuals(camera, T, X, uv)
            if best is None or np.sum(res**2) < np.sum(best[1] ** 2):
                best = (T, res)
    except cv2.error:
        return None
    return best


def pose_from_points(camera: CameraModel, X: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """T_cam_board of a planar target from its points and pixels (solve_pnp), or None."""
    found = solve_pnp(camera, X, uv)
    return None if found is None else found[0]


def pose_through_mirror(camera: CameraModel, S: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """T_cam_board of a board seen through the mirror of reflection S, or None: the pose of the board in
    the flipped image (a direct view for the flipped camera), T_cam_board = S F T_V'_board."""
    T_v = pose_from_points(camera.flipped(), X, camera.flip_points(uv))
    return None if T_v is None else S @ FLIP_X @ T_v


def refine_pose(camera: CameraModel, X: np.ndarray, uv: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """LM refinement of a pose from (N, 3) object points and (N, 2) pixels."""
    rvec, tvec = rvec_tvec_from_T(T0)
    rvec, tvec = cv2.solvePnPRefineLM(np.ascontiguousarray(X, float), np.ascontiguousarray(uv, float),
                                      np.array(camera.K), np.array(camera.dist), rvec.reshape(3, 1),
                                      tvec.reshape(3, 1), criteria=_LM_CRITERIA)
    return T_from_rvec_tvec(rvec, tvec)


def _residuals(camera: CameraModel, T: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    pred = camera.project(transform_points(T, X))
    r = np.linalg.norm(pred - uv, axis=1)
    r[~np.isfinite(r)] = np.inf
    return r


def zhang_flags(fix_k3: bool = False, rational: bool = False, fix_tangential: bool = False) -> int:
    """cv2.calibrateCamera flags for the distortion model a stage asks for."""
    flags = 0
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    if fix_tangential:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    return flags


def zhang_closed_form(object_points: list, image_points: list) -> np.ndarray | None:
    """K (3x3, zero skew) from Zhang's closed form over the homographies of planar views (z = 0), with
    the principal point free; None when the views do not determine it (fewer than 3, or degenerate).

    OpenCV's own initialisation fixes the principal point at the image centre, which is far off for a
    projector (its lens is shifted: cy is often near the bottom edge), and its LM then needs hundreds
    of iterations or stops early; started from this K it converges in a few."""
    rows = []
    for X, u in zip(object_points, image_points):
        X = np.asarray(X, float).reshape(-1, 3)
        u = np.asarray(u, float).reshape(-1, 2)
        if len(X) < 4 or np.ptp(X[:, 2]) > 1e-9 * max(1.0, float(np.ptp(X[:, :2]))):
            return None
        H, _ = cv2.findHomography(X[:, :2], u, 0)
        if H is None:
            continue
        h = H.T  # h[i] = i-th column of H

        def v(i, j):
            a, b = h[i], h[j]
            return [a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[1] * b[1],
                    a[2] * b[0] + a[0] * b[2], a[2] * b[1] + a[1] * b[2], a[2] * b[2]]
        v12, v11, v22 = np.array(v(0, 1)), np.array(v(0, 0)), np.array(v(1, 1))
        for r in (v12, v11 - v22):
            rows.append(r / max(np.linalg.norm(r), 1e-300))
    if len(rows) < 6:
        return None
    V = np.array(rows)
    V = np.vstack([V, [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]])  # zero skew: B12 = 0
    b = np.linalg.svd(V)[2][-1]
    B11, B12, B22, B13, B23, B33 = b
    den = B11 * B22 - B12 ** 2
    if abs(B11) < 1e-300 or abs(den) < 1e-300:
        return None
    v0 = (B12 * B13 - B11 * B23) / den
    lam = B33 - (B13 ** 2 + v0 * (B12 * B13 - B11 * B23)) / B11
    if not (lam / B11 > 0 and lam * B11 / den > 0):
        return None
    fx = np.sqrt(lam / B11)
    fy = np.sqrt(lam * B11 / den)
    u0 = -B13 * fx ** 2 / lam
    K = np.array([[fx, 0.0, u0], [0.0, fy, v0], [0.0, 0.0, 1.0]])
    return K if np.all(np.isfinite(K)) else None


def calibrate_zhang(object_points: list, image_points: list, size: tuple[int, int], flags: int = 0,
                    max_restarts: int = 4):
    """cv2.calibrateCamera started from Zhang's closed form (zhang_closed_form; OpenCV's default start
    when that fails), then restarted from its own answer (CALIB_USE_INTRINSIC_GUESS) while the RMS
    keeps dropping: OpenCV's LM sometimes stops short of the minimum. No restart once a Gauss-Newton
    step from the answer would move every intrinsic by less than 1% of its sigma. The 1-sigma of the
    intrinsics and the per-view RMS are computed here (zhang_statistics) as calibrateCameraExtended
    defines them, at a fraction of its cost, from the same normal equations as that test.

    Returns (rms, K, dist, rvecs, tvecs, std_intrinsics, per_view_errors). Raises cv2.error."""
    objp = [np.ascontiguousarray(o, np.float32).reshape(-1, 3) for o in object_points]
    imgp = [np.ascontiguousarray(i, np.float32).reshape(-1, 2) for i in image_points]
    K0 = None if flags & cv2.CALIB_USE_INTRINSIC_GUESS else zhang_closed_form(objp, imgp)
    if K0 is not None and -size[0] < K0[0, 2] < size[0] * 2 and -size[1] < K0[1, 2] < size[1] * 2:
        out = _calibrate_from_guess(objp, imgp, size, K0, None, flags)
    else:
        out = cv2.calibrateCamera(objp, imgp, size, None, None, flags=flags, criteria=_ZHANG_CRITERIA)
    normal = None  # the normal equations at `out`, once computed
    for _ in range(max_restarts):
        rms, K, dist = out[0], out[1], out[2]
        normal = _zhang_normal(objp, imgp, *out[1:], flags)
        if _converged(normal, len(objp)):
            break
        nxt = _calibrate_from_guess(objp, imgp, size, K.copy(), dist.copy(), flags)
        improved = nxt[0] < rms * (1 - 1e-6)
        if nxt[0] <= rms:
            out, normal = nxt, None
        if not improved:
            break
    rms, K, dist, rvecs, tvecs = out
    dist = np.asarray(dist, float).reshape(-1)
    if normal is None:
        normal = _zhang_normal(objp, imgp, K, dist, rvecs, tvecs, flags)
    std_i, pve = _statistics(normal, len(objp))
    return float(rms), K, dist, rvecs, tvecs, std_i, pve


def _calibrate_from_guess(objp, imgp, size, K, dist, flags: int):
    """cv2.calibrateCamera started from the intrinsics K (and dist). OpenCV refuses a start whose
    principal point lies outside the image, and a projector's may (lens shift puts it near or beyond
    the bottom edge, or the top edge when ceiling-mounted); with a start given, the image size serves
    no other purpose. So the image points are shifted by whole pixels and the size enlarged until the
    start's principal point lies inside, and the answer's principal point is shifted back: the same
    problem, exactly (the distortion is centred on the principal point, which moves with the pixels)."""
    K = np.array(K, float)
    off = np.array([max(0.0, np.ceil(-K[0, 2]) + 1.0), max(0.0, np.ceil(-K[1, 2]) + 1.0)])
    W = max(int(size[0] + off[0]), int(np.floor(K[0, 2] + off[0])) + 2)
    H = max(int(size[1] + off[1]), int(np.floor(K[1, 2] + off[1])) + 2)
    if off.any():
        imgp = [(i + off).astype(np.float32) for i in imgp]
        K[:2, 2] += off
    out = cv2.calibrateCamera(objp, imgp, (W, H), K, dist, flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
                              criteria=_ZHANG_CRITERIA)
    if off.any():
        K_out = out[1].copy()
        K_out[:2, 2] -= off
        out = (out[0], K_out, *out[2:])
    return out


#: calibrateCamera's distortion coefficients in order, and the flag that holds each fixed (at 0 unless
#: a guess is given); the rational and thin-prism terms are free only with their model flag.
_DIST_FIXED_BY = (cv2.CALIB_FIX_K1, cv2.CALIB_FIX_K2, cv2.CALIB_ZERO_TANGENT_DIST, cv2.CALIB_ZERO_TANGENT_DIST,
                  cv2.CALIB_FIX_K3, cv2.CALIB_FIX_K4, cv2.CALIB_FIX_K5, cv2.CALIB_FIX_K6)


def _zhang_normal(objp, imgp, K, dist, rvecs, tvecs, flags: int):
    """Normal equations of Zhang's problem with the poses eliminated view by view (Schur complement):
    (U, b, rss, number of residuals, per-view RMS, mask of the free intrinsics among fx, fy, cx, cy and
    the distortion slots) with U the reduced J^T J and b the reduced J^T r over the free intrinsics."""
    dist = np.asarray(dist, float).reshape(-1)
    nd = dist.size
    free_d = np.zeros(nd, bool)
    for i in range(min(nd, 8)):
        free_d[i] = not (flags & _DIST_FIXED_BY[i])
        if i >= 5 and not flags & cv2.CALIB_RATIONAL_MODEL:
            free_d[i] = False
    free_d[8:] = False  # thin prism / tilted models are not used here
    free = np.concatenate([[not flags & cv2.CALIB_FIX_FOCAL_LENGTH] * 2,
                           [not flags & cv2.CALIB_FIX_PRINCIPAL_POINT] * 2, free_d])
    ni = int(free.sum())
    U = np.zeros((ni, ni))
    b = np.zeros(ni)
    rss, n_res, pve = 0.0, 0, []
    K = np.asarray(K, float)
    for X, u, r, t in zip(objp, imgp, rvecs, tvecs):
        proj, J = cv2.projectPoints(np.asarray(X, float).reshape(-1, 3), r, t, K, dist)
        res = proj.reshape(-1, 2) - np.asarray(u, float).reshape(-1, 2)
        rss += float(np.sum(res ** 2))
        n_res += res.size
        pve.append(float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))))
        B = J[:, :6]  # rvec, tvec
        A = J[:, 6:10 + nd][:, free]  # focal, principal point, distortion
        W = A.T @ B
        V = B.T @ B
        WVinv = np.linalg.solve(V, W.T).T
        rv = res.reshape(-1)
        U += A.T @ A - WVinv @ W.T
        b += A.T @ rv - WVinv @ (B.T @ rv)
    return U, b, rss, n_res, np.array(pve), free


def _covariance(normal, n_views: int) -> np.ndarray | None:
    """sigma^2 U^-1 over the free intrinsics (sigma^2 = RSS / degrees of freedom), or None when the
    views leave them undetermined."""
    U, b, rss, n_res, _pve, _free = normal
    dof = n_res - len(b) - 6 * n_views
    if dof <= 0 or not np.all(np.isfinite(U)):
        return None
    try:
        return np.linalg.inv(U) * (rss / dof)
    except np.linalg.LinAlgError:
        return None


def _converged(normal, n_views: int, tol_sigma: float = 0.01) -> bool:
    """Whether a Gauss-Newton step from the solution `normal` was computed at would move every free
    intrinsic by less than tol_sigma of its 1-sigma (then a restart cannot improve it)."""
    cov = _covariance(normal, n_views)
    if cov is None:
        return False
    U, b = normal[0], normal[1]
    step = -np.linalg.solve(U, b)
    return bool(np.all(np.abs(step) < tol_sigma * np.sqrt(np.clip(np.diag(cov), 1e-300, None))))


def _statistics(normal, n_views: int) -> tuple[np.ndarray, np.ndarray]:
    """(18 1-sigma values, per-view RMS) from the normal equations (see zhang_statistics)."""
    free, pve = normal[5], normal[4]
    std = np.zeros(18)
    cov = _covariance(normal, n_views)
    idx = np.flatnonzero(np.concatenate([free, np.zeros(18 - free.size, bool)]))
    std[idx] = np.nan if cov is None else np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return std, pve


def zhang_statistics(objp, imgp, K, dist, rvecs, tvecs, flags: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(1-sigma of fx, fy, cx, cy and the 14 distortion slots (18 values, 0 for fixed ones), per-view
    RMS in pixels) of a Zhang calibration, as calibrateCameraExtended reports them: sigma^2 = sum of
    squared residuals / (2 N - free parameters), covariance = sigma^2 (J^T J)^-1 over intrinsics and
    all poses; the poses are eliminated view by view (Schur complement), so the cost is linear in the
    number of views."""
    return _statistics(_zhang_normal(objp, imgp, K, dist, rvecs, tvecs, flags), len(objp))


_ZHANG_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def point_residuals(K, dist, rvecs, tvecs, object_points, image_points) -> list[np.ndarray]:
    """Per-point reprojection error norms (pixels) of a calibration, one array per view."""
    out = []
    for r, t, X, u in zip(rvecs, tvecs, object_points, image_points):
        pred = cv2.projectPoints(np.asarray(X, np.float64).reshape(-1, 3), r, t, np.asarray(K, float),
                                 np.asarray(dist, float))[0].reshape(-1, 2)
        out.append(np.linalg.norm(pred - np.asarray(u, float).reshape(-1, 2), axis=1))
    return out
