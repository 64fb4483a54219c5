"""Board poses from ChArUco corners, for direct views and views through the mirror.

A board seen through the mirror is imaged exactly like a rigid view of the MIRRORED board
(GEOMETRY.md): u = project(K, S T X) = project(K, (S T F_b)(F_b X)) with F_b = diag(-1, 1, 1), and
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

from calib.boards import CharucoSpec
from calib.camera import CameraModel
from calib.observations import BoardObservation
from calib.transforms import T_from_rvec_tvec, rvec_tvec_from_T, transform_points

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
    T, res = _pnp(camera, X, uv)
    inl = np.ones(len(X), bool)
    if reject_outliers:
        for _ in range(len(X) // 4):
            r = np.where(inl, res, -1.0)
            if r.max() <= outlier_limit(res[inl]) or inl.sum() <= MIN_CORNERS:
                break
            inl[int(np.argmax(r))] = False
            T, _ = _pnp(camera, X[inl], uv[inl])
            res = _residuals(camera, T, X, uv)
    return BoardPose(T, bool(obs.mirrored), res, None if inl.all() else inl)


def _pnp(camera: CameraModel, X: np.ndarray, uv: np.ndarray):
    K, dist = np.array(camera.K), np.array(camera.dist)
    X = np.ascontiguousarray(X, float)
    uv = np.ascontiguousarray(uv, float)
    n, rvecs, tvecs, errs = cv2.solvePnPGeneric(X, uv, K, dist, flags=cv2.SOLVEPNP_IPPE)
    best = None
    for rvec, tvec in zip(rvecs, tvecs):
        rvec, tvec = cv2.solvePnPRefineLM(X, uv, K, dist, rvec.copy(), tvec.copy(), criteria=_LM_CRITERIA)
        T = T_from_rvec_tvec(rvec, tvec)
        res = _residuals(camera, T, X, uv)
        if best is None or np.sum(res**2) < np.sum(best[1] ** 2):
            best = (T, res)
    return best


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


def calibrate_zhang(object_points: list, image_points: list, size: tuple[int, int], flags: int = 0,
                    max_restarts: int = 4):
    """cv2.calibrateCameraExtended, restarted from its own answer (CALIB_USE_INTRINSIC_GUESS) while the
    RMS keeps dropping: OpenCV's LM sometimes stops far from the minimum when the principal point is
    far from the image centre (a projector's is), and a restart finishes the job.

    Returns (rms, K, dist, rvecs, tvecs, std_intrinsics, per_view_errors). Raises cv2.error."""
    objp = [np.ascontiguousarray(o, np.float32).reshape(-1, 3) for o in object_points]
    imgp = [np.ascontiguousarray(i, np.float32).reshape(-1, 2) for i in image_points]
    out = cv2.calibrateCameraExtended(objp, imgp, size, None, None, flags=flags, criteria=_ZHANG_CRITERIA)
    for _ in range(max_restarts):
        rms, K, dist = out[0], out[1], out[2]
        nxt = cv2.calibrateCameraExtended(objp, imgp, size, K.copy(), dist.copy(),
                                          flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS, criteria=_ZHANG_CRITERIA)
        if not nxt[0] < rms * (1 - 1e-6):
            if nxt[0] <= rms:
                out = nxt
            break
        out = nxt
    rms, K, dist, rvecs, tvecs, std_i, _std_e, pve = out
    return float(rms), K, np.asarray(dist, float).reshape(-1), rvecs, tvecs, np.asarray(std_i, float).reshape(-1), \
        np.asarray(pve, float).reshape(-1)


_ZHANG_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


def point_residuals(K, dist, rvecs, tvecs, object_points, image_points) -> list[np.ndarray]:
    """Per-point reprojection error norms (pixels) of a calibration, one array per view."""
    out = []
    for r, t, X, u in zip(rvecs, tvecs, object_points, image_points):
        pred = cv2.projectPoints(np.asarray(X, np.float64).reshape(-1, 3), r, t, np.asarray(K, float),
                                 np.asarray(dist, float))[0].reshape(-1, 2)
        out.append(np.linalg.norm(pred - np.asarray(u, float).reshape(-1, 2), axis=1))
    return out
