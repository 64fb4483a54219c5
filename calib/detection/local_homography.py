"""Projector coordinates of chosen camera points from a decoded structured-light map (Moreno & Taubin
2012): around each point, a homography from camera to projector pixels fitted over the decoded pixels
within a window, evaluated at the point.

A plane (the board) maps camera pixels to projector pixels by a homography, up to both lenses'
distortion, which varies little over a window of some 20 camera pixels. The fit (per point):
  1. the valid decoded pixels in the (2 r + 1)^2 window, coordinates centred on the point and scaled by
     r (so that the point is the origin and H's translation (h13, h23) is the answer);
  2. linear least squares on q (h31 u + h32 v + 1) = (h11 u + h12 v + h13, ...), then Gauss-Newton steps
     on the geometric (projector-pixel) error;
  3. pixels whose residual exceeds REJECT_SIGMAS x the robust sigma (from the median residual) are rejected
     (reflections, wrong codes that passed the neighbour check) and the fit repeated, up to 3 times;
  4. the uncertainty: sigma^2 (J^T J)^-1 of the last fit, sigma^2 the residuals' variance (2 n - 8
     degrees of freedom); the point's 2 x 2 covariance is the (h13, h23) block.
A point whose window holds fewer than `min_pixels` valid pixels, or whose pixels do not span both
directions around it (all on one side: the homography would extrapolate), gets NaN and a reason.

Entry point: `fit_local_homographies(decoded, points_cam_px) -> LocalProjectorPoints`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.detection.structured_light import DecodedMap

#: default half window (camera pixels): a 13 x 13 px window holds ~150 decoded pixels on a white board
#: area; smaller windows fit closer to the print, which spreads the points wider over the board
HALF_WINDOW_PX = 6
MIN_PIXELS = 40
REJECT_SIGMAS = 4.0
#: the points' pixels must extend at least this share of the half window on each side of it, on both axes
MIN_SPREAD = 0.3


@dataclass(frozen=True, eq=False)
class LocalProjectorPoints:
    """Per requested camera point (N): its projector pixel (NaN where none), the fit's 2 x 2 covariance
    (projector px^2), the pixels used and rejected, the fit's residual RMS, and why a point failed ("" if
    it did not)."""

    cam_px: np.ndarray
    proj_px: np.ndarray
    cov_px2: np.ndarray
    n_pixels: np.ndarray
    n_rejected: np.ndarray
    rms_px: np.ndarray
    reasons: tuple

    @property
    def ok(self) -> np.ndarray:
        return np.isfinite(self.proj_px).all(axis=1)

    @property
    def sigma_px(self) -> np.ndarray:
        """1-sigma of each point's projector position (the root of the covariance's larger eigenvalue)."""
        out = np.full(len(self.proj_px), np.nan)
        ok = self.ok
        if np.any(ok):
            out[ok] = np.sqrt(np.linalg.eigvalsh(self.cov_px2[ok])[:, -1])
        return out


def _ro(a):
    a = np.asarray(a)
    a.setflags(write=False)
    return a


def fit_local_homographies(decoded: DecodedMap, points_cam_px, half_window_px: int = HALF_WINDOW_PX,
                           min_pixels: int = MIN_PIXELS) -> LocalProjectorPoints:
    """The projector pixels of camera points `points_cam_px` (N, 2), each from a homography fitted over
    the valid decoded pixels of the (2 half_window_px + 1)^2 window around it (module docstring)."""
    pts = np.asarray(points_cam_px, float).reshape(-1, 2)
    n = len(pts)
    r = int(half_window_px)
    H, W = decoded.shape
    proj = np.full((n, 2), np.nan)
    cov = np.full((n, 2, 2), np.nan)
    used = np.zeros(n, int)
    rejected = np.zeros(n, int)
    rms = np.full(n, np.nan)
    reasons = [""] * n
    valid = decoded.valid
    for i, (cx, cy) in enumerate(pts):
        if not (np.isfinite(cx) and np.isfinite(cy)):
            reasons[i] = "not a finite point"
            continue
        x0, x1 = max(int(np.floor(cx)) - r, 0), min(int(np.ceil(cx)) + r + 1, W)
        y0, y1 = max(int(np.floor(cy)) - r, 0), min(int(np.ceil(cy)) + r + 1, H)
        if x0 >= x1 or y0 >= y1:
            reasons[i] = "outside the image"
            continue
        ys, xs = np.nonzero(valid[y0:y1, x0:x1])
        if len(ys) < min_pixels:
            reasons[i] = f"{len(ys)} decoded pixels around it (need {min_pixels})"
            continue
        u = (xs + x0 - cx) / r
        v = (ys + y0 - cy) / r
        if min(u.max(), -u.min(), v.max(), -v.min()) < MIN_SPREAD:
            reasons[i] = "decoded pixels on one side of it only"
            continue
        q = np.column_stack([decoded.proj_x[ys + y0, xs + x0], decoded.proj_y[ys + y0, xs + x0]]).astype(float)
        keep = np.ones(len(u), bool)
        fit = None
        for _round in range(4):
            fit = _fit(u[keep], v[keep], q[keep])
            res = np.hypot(*(_apply(fit[0], u, v) - q).T)
            s = np.median(res[keep]) / 1.1774  # the median of a 2D Gaussian's |residual| is 1.1774 sigma
            new = res <= max(REJECT_SIGMAS * s, 1e-6)
            if np.array_equal(new, keep) or new.sum() < min_pixels:
                break
            keep = new
        h, JtJ_inv, rss = fit
        dof = 2 * int(keep.sum()) - 8
        if dof <= 0:
            reasons[i] = "too few pixels after rejecting outliers"
            continue
        s2 = rss / dof
        proj[i] = h[[2, 5]]
        cov[i] = s2 * JtJ_inv[np.ix_([2, 5], [2, 5])]
        used[i] = int(keep.sum())
        rejected[i] = int((~keep).sum())
        rms[i] = np.sqrt(rss / keep.sum())
    return LocalProjectorPoints(_ro(pts.copy()), _ro(proj), _ro(cov), _ro(used), _ro(rejected), _ro(rms), tuple(reasons))


def _apply(h: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    w = h[6] * u + h[7] * v + 1.0
    return np.column_stack([(h[0] * u + h[1] * v + h[2]) / w, (h[3] * u + h[4] * v + h[5]) / w])


def _jacobian(h: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(2 n, 8) derivative of the mapped points (x rows then y rows interleaved per pixel) by h."""
    w = h[6] * u + h[7] * v + 1.0
    px = (h[0] * u + h[1] * v + h[2]) / w
    py = (h[3] * u + h[4] * v + h[5]) / w
    n = len(u)
    J = np.zeros((n, 2, 8))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2] = u / w, v / w, 1.0 / w
    J[:, 1, 3], J[:, 1, 4], J[:, 1, 5] = u / w, v / w, 1.0 / w
    J[:, 0, 6], J[:, 0, 7] = -px * u / w, -px * v / w
    J[:, 1, 6], J[:, 1, 7] = -py * u / w, -py * v / w
    return J.reshape(2 * n, 8)


def _fit(u: np.ndarray, v: np.ndarray, q: np.ndarray):
    """(h (8,), (J^T J)^-1 at h, residual sum of squares) of the homography (u, v) -> q."""
    n = len(u)
    A = np.zeros((2 * n, 8))
    A[0::2, 0], A[0::2, 1], A[0::2, 2] = u, v, 1.0
    A[0::2, 6], A[0::2, 7] = -q[:, 0] * u, -q[:, 0] * v
    A[1::2, 3], A[1::2, 4], A[1::2, 5] = u, v, 1.0
    A[1::2, 6], A[1::2, 7] = -q[:, 1] * u, -q[:, 1] * v
    b = q.reshape(-1)
    h = np.linalg.lstsq(A, b, rcond=None)[0]
    for _ in range(3):  # Gauss-Newton on the projector-pixel error (the linear fit weights by w)
        J = _jacobian(h, u, v)
        e = b - _apply(h, u, v).reshape(-1)
        step = np.linalg.lstsq(J, e, rcond=None)[0]
        h = h + step
        if np.abs(step).max() < 1e-10:
            break
    J = _jacobian(h, u, v)
    e = b - _apply(h, u, v).reshape(-1)
    JtJ_inv = np.linalg.pinv(J.T @ J)
    return h, JtJ_inv, float(e @ e)
