"""Rigid transforms and the mirror reflection, as 4x4 numpy matrices.

`T_a_b` maps points from frame b into frame a: p_a = T_a_b @ p_b (homogeneous), T_a_c = T_a_b @ T_b_c.
"""

from __future__ import annotations

import cv2
import numpy as np

#: The horizontal image flip as a transform of camera coordinates: x -> -x (docs/GEOMETRY.md "F").
FLIP_X = np.diag([-1.0, 1.0, 1.0, 1.0])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float).reshape(3, 3)
    T[:3, 3] = np.asarray(t, float).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (or improper orthogonal) transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    X = np.asarray(X, float).reshape(-1, 3)
    return X @ T[:3, :3].T + T[:3, 3]


def T_from_rvec_tvec(rvec, tvec) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))
    return make_T(R, np.asarray(tvec, float).reshape(3))


def rvec_tvec_from_T(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))
    return rvec.reshape(3), T[:3, 3].copy()


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, in degrees (robust near 0 and 180)."""
    R = np.asarray(R, float)[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def reflection_T(normal, d: float) -> np.ndarray:
    """S for the plane n.x + d = 0 (n unit): S = [[I - 2 n n^T, -2 d n], [0, 1]]. S @ S = I, det S = -1."""
    n = np.asarray(normal, float).reshape(3)
    n = n / np.linalg.norm(n)
    S = np.eye(4)
    S[:3, :3] -= 2.0 * np.outer(n, n)
    S[:3, 3] = -2.0 * d * n
    return S


def rotation_about(axis, angle_deg: float) -> np.ndarray:
    """3x3 rotation about `axis` by `angle_deg` (right-hand rule)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    R, _ = cv2.Rodrigues(a.reshape(3, 1) * np.radians(angle_deg))
    return R


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """T_world_dev of a device at `eye` looking at `target` in OpenCV axes (+z forward, +y down).

    `up` is the world direction that should appear up in the device's image (default -y, OpenCV's up)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), eye)


def rays_to_board_plane(T_board_dev: np.ndarray, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays from a device (directions in its frame) meet a board's plane z = 0, in board coordinates;
    `T_board_dev` maps the device's frame into the board's. Returns (points (N, 3), t (N,)), each point
    = origin + t x ray: t <= 0 (or not finite) where the ray meets the plane behind the device, or never."""
    dirs = np.asarray(rays, float) @ np.asarray(T_board_dev, float)[:3, :3].T
    o = np.asarray(T_board_dev, float)[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / dirs[:, 2]
        return o + t[:, None] * dirs, t


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that, with the unit vector n, make a right-handed orthonormal frame (e1, e2, n):
    the local parametrisation of a direction near n (a mirror's normal, its tilts along e1 and e2).
    Built from the world axis least aligned with n, so it is well conditioned for every n."""
    n = np.asarray(n, float)
    ref = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


# ---- rotations: the one local parametrisation -----------------------------------------------------
# Every least-squares problem of the project (the joint adjustment, the recalibration) parametrises a
# rotation near a reference R0 by a Gibbs vector g: R = R(g) R0, g = axis tan(angle / 2), the
# unnormalised quaternion (1, g). R(g) is rational in g, so it goes through complex-step
# differentiation, and it is the identity at g = 0, where the rotation vector is 2 g. A solver works at
# g = 0 around its current estimate and re-centres R0 after each step (the update on the tangent space).
def R_from_gibbs(g: np.ndarray) -> np.ndarray:
    """Rotation(s) of Gibbs vector(s): (..., 3) -> (..., 3, 3); complex input gives complex output."""
    x, y, z = g[..., 0], g[..., 1], g[..., 2]
    s = 1.0 + x * x + y * y + z * z
    R = np.empty(g.shape[:-1] + (3, 3), dtype=np.result_type(g, float))
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


def gibbs_from_R(R: np.ndarray) -> np.ndarray:
    """The Gibbs vector of a rotation matrix (the inverse of R_from_gibbs; infinite at 180 degrees)."""
    R = np.asarray(R, float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w / (1.0 + np.trace(R))


def update_R(g: np.ndarray, R0: np.ndarray) -> np.ndarray:
    """The rotation g (a Gibbs vector in the axes of the frame R0 maps into) applied after R0: R(g) R0.
    Broadcasts over leading axes: (V, 3) vectors and (V, 3, 3) references give (V, 3, 3)."""
    return R_from_gibbs(g) @ R0


def update_T(T0: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The pose near T0 of the correction p = (g, dt): rotation update_R(g, R0), translation t0 + dt."""
    p = np.asarray(p, float)
    return make_T(update_R(p[:3], np.asarray(T0, float)[:3, :3]), np.asarray(T0, float)[:3, 3] + p[3:6])


def rotvec_from_gibbs(g: np.ndarray) -> np.ndarray:
    """The rotation vector (axis x angle, OpenCV's rvec) of a Gibbs vector: 2 atan(|g|) g / |g|."""
    g = np.asarray(g, float)
    s = float(np.linalg.norm(g))
    return 2.0 * g if s < 1e-8 else (2.0 * np.arctan(s) / s) * g


def rotvec_gibbs_jacobian(g: np.ndarray) -> np.ndarray:
    """d rotvec / d g at g (3x3): how a covariance of g becomes one of the rotation vector, C_r = J C_g J^T.
    2 I at g = 0, where the solvers report."""
    g = np.asarray(g, float)
    s = float(np.linalg.norm(g))
    if s < 1e-4:  # series of f(s) = 2 atan(s) / s and f'(s) / s (whose closed form cancels at small s)
        f, df_s = 2.0 - 2.0 * s * s / 3.0, -4.0 / 3.0 + 8.0 * s * s / 5.0
    else:
        f = 2.0 * np.arctan(s) / s
        df_s = 2.0 * (s / (1.0 + s * s) - np.arctan(s)) / s**3
    return f * np.eye(3) + df_s * np.outer(g, g)


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation matrix closest to R in the Frobenius norm (R's polar factor): removes the rounding
    a product of many updates accumulates."""
    U, _, Vt = np.linalg.svd(np.asarray(R, float))
    return U @ Vt


def rotvec_covariance(C_g: np.ndarray, g: np.ndarray | None = None) -> np.ndarray:
    """The covariance of a rotation vector from C_g, the covariance of the Gibbs vector g (default 0, the
    solvers' estimate): J C_g J^T with J = rotvec_gibbs_jacobian(g). Angles are reported in this form."""
    J = rotvec_gibbs_jacobian(np.zeros(3) if g is None else g)
    return J @ np.asarray(C_g, float) @ J.T
