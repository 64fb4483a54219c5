"""The lens model of the joint adjustment in complex-safe arithmetic (complex-step derivatives go through
every function here): OpenCV's distortion of normalised coordinates, its 2x2 Jacobian, the projection of
camera-frame points to pixels, its analytic derivatives with respect to the intrinsics, and the undistortion
of projector pixels by Newton's method."""

from __future__ import annotations

import numpy as np

from calib.models.vocab import DistortionModel


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


def dist8(dist) -> np.ndarray:
    """Distortion coefficients padded to OpenCV's 8."""
    d = np.zeros(8)
    dist = np.asarray(dist, float).reshape(-1)
    d[: dist.size] = dist
    return d


def dist_out(d8: np.ndarray, model: str) -> np.ndarray:
    """The coefficients a result stores for `model`: 8 for the rational model, else 5."""
    return np.array(d8[:8] if model == DistortionModel.RATIONAL else d8[:5], float)


def project(K, d, X):
    """Pixels of (N, 3) camera-frame points under K = (fx, fy, cx, cy) and 8 distortion coefficients d."""
    x = X[:, 0] / X[:, 2]
    y = X[:, 1] / X[:, 2]
    xd, yd = distort(x, y, d)
    return np.stack([K[0] * xd + K[2], K[1] * yd + K[3]], axis=-1)


def intrinsics_columns(X: np.ndarray, K: np.ndarray, d: np.ndarray, free) -> np.ndarray:
    """Analytic d(u, v)/d(fx, fy, cx, cy, the `free` distortion coefficients) of points X: (2N, 4 + len(free)),
    rows [u0, v0, u1, v1, ...]."""
    x = X[:, 0] / X[:, 2]
    y = X[:, 1] / X[:, 2]
    k1, k2, _, _, k3, k4, k5, k6 = d
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    xd, yd = distort(x, y, d)
    n = len(x)
    cols = [np.column_stack([xd, np.zeros(n)]), np.column_stack([np.zeros(n), yd]),
            np.column_stack([np.ones(n), np.zeros(n)]), np.column_stack([np.zeros(n), np.ones(n)])]
    for i in free:
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
        cols.append(np.column_stack([K[0] * dx, K[1] * dy]))
    return np.stack([c.reshape(-1) for c in cols], axis=1)


def is_perturbed(*arrays) -> bool:
    """Whether any of the arrays carries a complex-step perturbation (a non-zero imaginary part)."""
    return any(np.iscomplexobj(a) and np.any(a.imag) for a in arrays)


def _newton_step(x, y, mx, my, d):
    fx_, fy_ = distort(x, y, d)
    fx_, fy_ = fx_ - mx, fy_ - my
    a11, a12, a21, a22 = distort_jac(x, y, d)
    det = a11 * a22 - a12 * a21
    return x - (a22 * fx_ - a12 * fy_) / det, y - (-a21 * fx_ + a11 * fy_) / det, fx_, fy_


def undistort(q: np.ndarray, K, d, start=None):
    """Undistorted normalised coordinates (x, y) of pixels q (M, 2): Newton's method in real arithmetic
    from `start` (a previous solution, or the distorted coordinates), then, when K or d carry a
    complex-step perturbation, one Newton step in complex arithmetic, which carries the implicit
    derivative. Returns (x, y, real solution to start from next time)."""
    Kr, dr = np.real(K), np.real(d)
    mx = (q[:, 0] - Kr[2]) / Kr[0]
    my = (q[:, 1] - Kr[3]) / Kr[1]
    x, y = (mx.copy(), my.copy()) if start is None else start
    for _ in range(30):
        xn, yn, fx_, fy_ = _newton_step(x, y, mx, my, dr)
        if max(np.abs(fx_).max(initial=0), np.abs(fy_).max(initial=0)) < 1e-15:
            break
        x, y = xn, yn
    real = (x, y)
    if is_perturbed(K, d):
        x, y, _, _ = _newton_step(x, y, (q[:, 0] - K[2]) / K[0], (q[:, 1] - K[3]) / K[1], d)
    return x, y, real
