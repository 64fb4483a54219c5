"""Projection uncertainty over the image: how far a ray's pixel moves at 1 sigma, at each place.

In the spirit of mrcal's projection uncertainty (at infinite range). A device's intrinsics theta =
(fx, fy, cx, cy, distortion coefficients) carry a covariance Cov (the joint adjustment's, board poses
marginalised: calib.joint.uncertainty). Take a pixel q of the image and the ray r(q) through it under the
estimated model, and project it back with perturbed intrinsics: q(theta) = K(theta) distort(r, theta).
To first order a perturbation moves the pixels of the whole grid by J dtheta (J_q = dq/dtheta).

Part of that motion is what a small rotation of the device would also produce (a shift of cx, cy is
nearly a rotation of the world in front of the device): in the joint problem the whole world (boards,
mirror, the other device) can follow such a rotation, so it says nothing about where the device puts a
ray relative to the scene. As mrcal compares the ray against the scene (the boards' reference frame,
not the device's own), that part is removed here: the motion field is projected, over the grid, onto
the complement of the fields of the three rotations (a least-squares fit of the best compensating
rotation). The value reported at q is the 1-sigma along the worst direction of what remains,
sqrt(largest eigenvalue of P J Cov J^T P at q), on a coarse grid of cell centres.

What it covers and what it does not: the intrinsics and distortion of the device (their correlations
with everything else in the adjustment are in the marginal covariance). The pose of the projector
(T_cam_proj) is not folded in: its own 1-sigma is reported in result.uncertainty. Only noise is
covered: systematic detection errors are not (docs/JOINT.md).

Entry point: `projection_uncertainty(result)` -> the dict stored as calibration.json's
"projection_uncertainty" (None when the result carries no covariance, e.g. the paper method).
`pixel_jacobian` is shared with the coverage-aware model selection (calib.joint.model_select).
"""

from __future__ import annotations

import numpy as np

from calib.models.camera import CameraModel

METHOD = ("rotation-compensated first-order propagation: sigma(q) = sqrt(max eig(C_q)), C = P J Cov J^T P over "
          "the grid, J the derivative of the pixel of the ray through q with respect to fx, fy, cx, cy and the free "
          "distortion coefficients, Cov their marginal covariance from the joint adjustment, P the projection "
          "removing what a rotation of the device would absorb (least squares over the grid)")
SCHEMA = "procam-projection-uncertainty-1"
GRID = (16, 10)
#: a place of the image whose 1-sigma exceeds this is "large": the calibration summary names it.
LARGE_SIGMA_PX = 0.5

_PARAMS = ("fx", "fy", "cx", "cy")


def grid_pixels(width: int, height: int, grid=GRID) -> tuple[np.ndarray, np.ndarray]:
    """Centres (x, y) of a grid of nx x ny equal cells over a width x height image (pixel centres at
    integers: the image spans -0.5 .. width - 0.5)."""
    nx, ny = int(grid[0]), int(grid[1])
    xs = (np.arange(nx) + 0.5) * width / nx - 0.5
    ys = (np.arange(ny) + 0.5) * height / ny - 0.5
    return xs, ys


def pixel_jacobian(K4, dist8, xy: np.ndarray) -> np.ndarray:
    """(N, 2, 12) derivative of the pixel of normalised undistorted points xy (N, 2) with respect to
    (fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6), OpenCV's model (zero skew)."""
    fx, fy = float(K4[0]), float(K4[1])
    d = np.zeros(8)
    d8 = np.asarray(dist8, float).reshape(-1)
    d[:d8.size] = d8
    k1, k2, p1, p2, k3, k4, k5, k6 = d
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    num = 1 + k1 * r2 + k2 * r4 + k3 * r6
    den = 1 + k4 * r2 + k5 * r4 + k6 * r6
    rad = num / den
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    J = np.zeros((len(x), 2, 12))
    J[:, 0, 0] = xd
    J[:, 1, 1] = yd
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    drad = {4: r2 / den, 5: r4 / den, 8: r6 / den,
            9: -num * r2 / den**2, 10: -num * r4 / den**2, 11: -num * r6 / den**2}
    for col, dr in drad.items():
        J[:, 0, col] = fx * x * dr
        J[:, 1, col] = fy * y * dr
    J[:, 0, 6], J[:, 1, 6] = fx * 2 * x * y, fy * (r2 + 2 * y * y)  # p1
    J[:, 0, 7], J[:, 1, 7] = fx * (r2 + 2 * x * x), fy * 2 * x * y  # p2
    return J


def _param_columns(names, prefix: str) -> tuple[list[int], list[int]]:
    """(rows of the covariance, columns of pixel_jacobian) of the device's free intrinsics."""
    idx = {n: i for i, n in enumerate(names)}
    rows, cols = [], []
    for j, p in enumerate(_PARAMS):
        if f"{prefix}.{p}" in idx:
            rows.append(idx[f"{prefix}.{p}"])
            cols.append(j)
    for i in range(8):
        if f"{prefix}.dist{i}" in idx:
            rows.append(idx[f"{prefix}.dist{i}"])
            cols.append(4 + i)
    return rows, cols


def rotation_jacobian(model: CameraModel, uv: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(N, 2, 3) derivative of the pixels of the rays through uv (N, 2) with respect to a small rotation
    w of the ray (r -> r + w x r), by central differences of model.project."""
    r = model.rays(uv)
    out = np.zeros((len(r), 2, 3))
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        out[:, :, k] = (model.project(r + np.cross(w, r)) - model.project(r - np.cross(w, r))) / (2 * h)
    return out


def motion_fields(model: CameraModel, cols: list[int], uv: np.ndarray) -> np.ndarray:
    """(N, 2, len(cols)): pixel motion at uv per intrinsic parameter (pixel_jacobian columns `cols`),
    with the part a rotation of the device would absorb removed (least squares over all of uv)."""
    xy = model.undistort_normalized(uv)
    K = model.K
    J = pixel_jacobian((K[0, 0], K[1, 1], K[0, 2], K[1, 2]), model.dist, xy)[:, :, cols]
    R = rotation_jacobian(model, uv).reshape(-1, 3)
    Jf = J.reshape(-1, len(cols))
    ok = np.all(np.isfinite(R), axis=1) & np.all(np.isfinite(Jf), axis=1)
    coef = np.linalg.lstsq(R[ok], Jf[ok], rcond=None)[0]
    return (Jf - R @ coef).reshape(J.shape)


def sigma_at(model: CameraModel, cov: np.ndarray, cols: list[int], uv: np.ndarray) -> np.ndarray:
    """Worst-direction 1-sigma (px) at pixels uv (N, 2) of `model` (rotation-compensated over uv), Cov
    (len(cols) square) over the pixel_jacobian columns `cols`."""
    J = motion_fields(model, cols, uv)
    C = np.einsum("nik,kl,njl->nij", J, cov, J)
    a, b, c = C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]
    lam = 0.5 * (a + c) + np.sqrt(np.maximum(0.25 * (a - c) ** 2 + b * b, 0.0))
    return np.sqrt(np.maximum(lam, 0.0))


def device_grid(model: CameraModel, cov_full: np.ndarray, names, prefix: str, grid=GRID) -> dict:
    """The grid of one device ("cam" / "proj" prefix in the covariance's names)."""
    rows, cols = _param_columns(names, prefix)
    xs, ys = grid_pixels(model.width, model.height, grid)
    out = {"width": model.width, "height": model.height, "grid": [len(xs), len(ys)],
           "x_px": xs.tolist(), "y_px": ys.tolist()}
    if not rows:  # held fixed: this session says nothing about it
        out.update({"fixed": True, "sigma_px": None, "median_px": None, "max_px": None, "large_fraction": None})
        return out
    cov = np.asarray(cov_full, float)[np.ix_(rows, rows)]
    X, Y = np.meshgrid(xs, ys)
    s = sigma_at(model, cov, cols, np.column_stack([X.ravel(), Y.ravel()])).reshape(len(ys), len(xs))
    s = np.where(np.isfinite(s), s, np.inf)
    out.update({"fixed": False, "params": [names[r] for r in rows], "sigma_px": s.tolist(),
                "median_px": float(np.median(s)), "max_px": float(s.max()),
                "large_fraction": float(np.mean(s > LARGE_SIGMA_PX))})
    return out


def projection_uncertainty(result, grid=GRID) -> dict | None:
    """calibration.json's "projection_uncertainty" of a result: {"schema", "method", "large_sigma_px",
    "camera": grid, "projector": grid}, each grid {"width", "height", "grid": [nx, ny], "x_px", "y_px"
    (cell centres), "sigma_px" (ny rows of nx, worst-direction 1-sigma), "median_px", "max_px",
    "large_fraction", "fixed", "params"}. None when the result has no parameter covariance."""
    unc = result.uncertainty if isinstance(result.uncertainty, dict) else None
    covd = unc.get("covariance") if unc else None
    if not isinstance(covd, dict) or "names" not in covd or "matrix" not in covd:
        return None
    names = list(covd["names"])
    cov = np.asarray(covd["matrix"], float)
    return {"schema": SCHEMA, "method": METHOD, "large_sigma_px": LARGE_SIGMA_PX,
            "camera": device_grid(result.camera, cov, names, "cam", grid),
            "projector": device_grid(result.projector, cov, names, "proj", grid)}


def _parts(big: np.ndarray) -> dict:
    ny, nx = big.shape
    tx, ty = max(nx // 4, 1), max(ny // 4, 1)
    parts = {"top-left corner": big[:ty, :tx], "top-right corner": big[:ty, -tx:],
             "bottom-left corner": big[-ty:, :tx], "bottom-right corner": big[-ty:, -tx:],
             "top edge": big[:ty, tx:-tx], "bottom edge": big[-ty:, tx:-tx],
             "left edge": big[ty:-ty, :tx], "right edge": big[ty:-ty, -tx:], "centre": big[ty:-ty, tx:-tx]}
    return parts


def large_regions(dev: dict, threshold_px: float = LARGE_SIGMA_PX) -> list[str]:
    """Where a device grid's sigma exceeds the threshold, in words: the image corners and edges that do
    (e.g. ["top-left corner", "right edge"]), or ["centre"]."""
    s = dev.get("sigma_px")
    if s is None:
        return []
    big = np.asarray(s, float) > threshold_px
    if not big.any():
        return []
    return [name for name, m in _parts(big).items() if m.size and m.any()]


def where_max(dev: dict) -> str | None:
    """The part of the image (corner, edge or centre) where a device grid's sigma is largest."""
    s = dev.get("sigma_px")
    if s is None:
        return None
    s = np.asarray(s, float)
    at = np.zeros(s.shape, bool)
    at[np.unravel_index(int(np.argmax(s)), s.shape)] = True
    return next((name for name, m in _parts(at).items() if m.size and m.any()), None)


def summary_line(pu: dict | None, device: str) -> str | None:
    """One line for the calibration summary, None when there is nothing to say."""
    if not pu or device not in pu:
        return None
    dev = pu[device]
    if dev.get("fixed") or dev.get("sigma_px") is None:
        return f"{device} projection uncertainty: held fixed (given intrinsics)"
    line = (f"{device} projection uncertainty (1 sigma over the image): median {dev['median_px']:.3f} px, "
            f"max {dev['max_px']:.3f} px ({where_max(dev)})")
    where = large_regions(dev)
    if where:
        line += (f"; LARGE (> {LARGE_SIGMA_PX:g} px) over {100 * dev['large_fraction']:.0f}% of the image: "
                 f"{', '.join(where)} -- few or no observations there; take views that reach those places")
    return line
