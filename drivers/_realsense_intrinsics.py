"""librealsense's factory intrinsics as an OpenCV-style CameraModel (behind drivers/realsense.py).

`convert_intrinsics` turns an `rs.intrinsics` record into a calib.models.camera.CameraModel, exactly
where the formulas agree and by a fit checked over the whole image where they do not; docs/DRIVERS.md
says how each librealsense distortion model is handled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from calib.models.camera import CameraModel
from drivers.errors import DeviceError


class IntrinsicsConversionError(DeviceError):
    """librealsense's intrinsics cannot be expressed as an OpenCV camera model closely enough."""


_MODEL_NAMES = {0: "none", 1: "modified_brown_conrady", 2: "inverse_brown_conrady", 3: "ftheta",
                4: "brown_conrady", 5: "kannala_brandt4"}


def distortion_model_name(model) -> str:
    """librealsense's distortion model as a plain name ('brown_conrady', ...): accepts an
    rs.distortion value, its integer or its name."""
    if isinstance(model, str):
        name = model.split(".")[-1].lower()
    else:
        try:
            name = _MODEL_NAMES[int(model)]
        except (KeyError, TypeError, ValueError):
            name = str(model).split(".")[-1].lower()
    if name not in _MODEL_NAMES.values():
        raise IntrinsicsConversionError(f"unknown librealsense distortion model {model!r}")
    return name


def rs_distort_normalized(model, coeffs, xy: np.ndarray) -> np.ndarray:
    """librealsense's projection (rs2_project_point_to_pixel in rsutil.h) from normalized undistorted
    coordinates (x/z, y/z) to normalized distorted ones, in float64. (N, 2) -> (N, 2).

    - none: identity.
    - brown_conrady: OpenCV's model, coeffs [k1, k2, p1, p2, k3].
    - modified_brown_conrady and inverse_brown_conrady (librealsense projects both the same way):
      the radial factor first, then the tangential terms evaluated at the radially distorted point
      (with the undistorted r^2).
    - ftheta: r_d = atan(2 r tan(w / 2)) / w with w = coeffs[0].
    - kannala_brandt4: theta = atan(r), r_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
      coeffs [k1, k2, k3, k4, -].
    """
    name = distortion_model_name(model)
    c = np.zeros(5)
    cc = np.asarray(coeffs, float).reshape(-1)[:5]
    c[: cc.size] = cc
    xy = np.asarray(xy, float).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    if name == "none":
        return xy.copy()
    if name in ("brown_conrady", "modified_brown_conrady", "inverse_brown_conrady"):
        f = 1 + c[0] * r2 + c[1] * r2 * r2 + c[4] * r2 * r2 * r2
        if name == "brown_conrady":
            xt, yt = x, y
        else:
            xt, yt = x * f, y * f
        xd = x * f + 2 * c[2] * xt * yt + c[3] * (r2 + 2 * xt * xt)
        yd = y * f + 2 * c[3] * xt * yt + c[2] * (r2 + 2 * yt * yt)
        return np.column_stack([xd, yd])
    r = np.maximum(np.sqrt(r2), np.finfo(np.float32).eps)
    if name == "ftheta":
        if c[0] == 0:
            raise IntrinsicsConversionError("ftheta distortion with a zero field-of-view coefficient")
        rd = np.arctan(2 * r * np.tan(c[0] / 2)) / c[0]
    else:  # kannala_brandt4
        t = np.arctan(r)
        t2 = t * t
        rd = t * (1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3]))))
    s = rd / r
    return np.column_stack([x * s, y * s])


def _invert(fn: Callable[[np.ndarray], np.ndarray], target: np.ndarray, iterations: int = 60):
    """Solve fn(xy) = target by Newton steps with a numerical Jacobian; (xy, converged mask)."""
    xy = target.copy()
    h = 1e-7
    for _ in range(iterations):
        f = fn(xy) - target
        if np.all(np.abs(f) < 1e-13):
            break
        jx = (fn(xy + [h, 0]) - fn(xy - [h, 0])) / (2 * h)
        jy = (fn(xy + [0, h]) - fn(xy - [0, h])) / (2 * h)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (jy[:, 1] * f[:, 0] - jy[:, 0] * f[:, 1]) / det
            dy = (-jx[:, 1] * f[:, 0] + jx[:, 0] * f[:, 1]) / det
        step = np.column_stack([dx, dy])
        step[~np.isfinite(step)] = 0.0
        xy = xy - np.clip(step, -0.5, 0.5)
    ok = np.all(np.abs(fn(xy) - target) < 1e-9, axis=1) & np.isfinite(xy).all(axis=1)
    return xy, ok


@dataclass(frozen=True, eq=False)
class IntrinsicsConversion:
    """A librealsense intrinsics record turned into a CameraModel, and how exactly.

    method: 'exact' (the same formula) or 'fit-5' / 'fit-8' (OpenCV coefficients least-squares fitted
    to librealsense's projection over the whole image); max_error_px: the largest pixel difference
    between CameraModel.project and librealsense's projection over a dense grid covering the image."""

    model: CameraModel
    source_model: str
    source_coeffs: tuple
    method: str
    max_error_px: float

    def to_dict(self) -> dict:
        return {"camera": self.model.to_dict(), "source_model": self.source_model,
                "source_coeffs": list(self.source_coeffs), "method": self.method,
                "max_error_px": self.max_error_px}


def _image_grid(width: int, height: int, nx: int, ny: int) -> np.ndarray:
    u = np.linspace(-0.5, width - 0.5, nx)
    v = np.linspace(-0.5, height - 0.5, ny)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def _fit_brown5(xy: np.ndarray, xyd: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Linear least squares for OpenCV's [k1, k2, p1, p2, k3] mapping xy -> xyd (pixel-weighted)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    ax = np.column_stack([x * r2, x * r2 * r2, 2 * x * y, r2 + 2 * x * x, x * r2 ** 3]) * fx
    ay = np.column_stack([y * r2, y * r2 * r2, r2 + 2 * y * y, 2 * x * y, y * r2 ** 3]) * fy
    A = np.vstack([ax, ay])
    b = np.concatenate([(xyd[:, 0] - x) * fx, (xyd[:, 1] - y) * fy])
    return np.linalg.lstsq(A, b, rcond=None)[0]


def convert_intrinsics(intr, tolerance_px: float = 0.05) -> IntrinsicsConversion:
    """Turn an `rs.intrinsics` (or any object with width, height, fx, fy, ppx, ppy, model, coeffs)
    into a CameraModel (OpenCV order [k1, k2, p1, p2, k3, k4, k5, k6]).

    Both libraries put pixel (0, 0) at the centre of the top-left pixel, so K is [[fx, 0, ppx],
    [0, fy, ppy], [0, 0, 1]] in every case. The distortion:
    - none -> no coefficients (exact).
    - brown_conrady -> coeffs as they are, [k1, k2, p1, p2, k3] (exact: the same formula).
    - modified_brown_conrady / inverse_brown_conrady -> librealsense projects both with the same
      "modified" formula (tangential terms at the radially distorted point). Exact (coeffs as they
      are) when p1 = p2 = 0; otherwise OpenCV's 5 coefficients are fitted to librealsense's projection
      over the whole image (then 8 rational ones if 5 are not within `tolerance_px`).
    - ftheta, kannala_brandt4 (fisheye models) -> the same fit; when no OpenCV model reproduces
      librealsense's projection within `tolerance_px` everywhere in the image, raise
      IntrinsicsConversionError (calibrate the camera instead).
    """
    name = distortion_model_name(intr.model)
    coeffs = tuple(float(c) for c in list(intr.coeffs)[:5])
    c = np.zeros(5)
    c[: len(coeffs)] = coeffs
    W, H = int(intr.width), int(intr.height)
    fx, fy, cx, cy = float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy)
    if W <= 0 or H <= 0 or fx <= 0 or fy <= 0:
        raise IntrinsicsConversionError(f"librealsense intrinsics are not usable: {W}x{H}, fx={fx}, fy={fy}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    if name == "none":
        return IntrinsicsConversion(CameraModel(W, H, K, []), name, coeffs, "exact", 0.0)
    if name == "brown_conrady" or (name in ("modified_brown_conrady", "inverse_brown_conrady")
                                   and c[2] == 0.0 and c[3] == 0.0):
        return IntrinsicsConversion(CameraModel(W, H, K, c), name, coeffs, "exact", 0.0)

    def fwd(xy):
        return rs_distort_normalized(name, c, xy)

    def to_norm(uv):
        return np.column_stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy])

    def error_px(model: CameraModel, xy_u: np.ndarray) -> float:
        ref = fwd(xy_u) * [fx, fy] + [cx, cy]
        got = model.project(np.column_stack([xy_u, np.ones(len(xy_u))]))
        e = np.linalg.norm(got - ref, axis=1)
        return float(np.inf) if not np.isfinite(e).all() else float(e.max())

    fit_uv = _image_grid(W, H, 41, 27)
    check_uv = _image_grid(W, H, 97, 61)
    xy_fit, ok_fit = _invert(fwd, to_norm(fit_uv))
    xy_chk, ok_chk = _invert(fwd, to_norm(check_uv))
    if not (ok_fit.all() and ok_chk.all()):
        raise IntrinsicsConversionError(
            f"librealsense's {name} distortion {list(coeffs)} cannot be inverted over the whole "
            f"{W}x{H} image, so no OpenCV model can stand in for it: calibrate the camera instead of "
            "using its factory intrinsics")
    xyd_fit = fwd(xy_fit)
    d5 = _fit_brown5(xy_fit, xyd_fit, fx, fy)
    m5 = CameraModel(W, H, K, d5)
    err5 = error_px(m5, xy_chk)
    if err5 <= tolerance_px:
        return IntrinsicsConversion(m5, name, coeffs, "fit-5", err5)

    from scipy.optimize import least_squares

    def resid(p):
        m = CameraModel(W, H, K, p)
        d = m.distort_normalized(xy_fit) - xyd_fit
        return np.concatenate([d[:, 0] * fx, d[:, 1] * fy])

    p0 = np.concatenate([d5, np.zeros(3)])
    sol = least_squares(resid, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=4000)
    m8 = CameraModel(W, H, K, sol.x)
    err8 = error_px(m8, xy_chk)
    if err8 <= tolerance_px:
        return IntrinsicsConversion(m8, name, coeffs, "fit-8", err8)
    def how_far(e: float) -> str:
        return f"off by {e:.3g} px" if np.isfinite(e) else "not even valid (it folds over inside the image)"

    raise IntrinsicsConversionError(
        f"librealsense's {name} distortion {list(coeffs)} has no OpenCV equivalent on this {W}x{H} "
        f"stream: the best 5-coefficient fit is {how_far(err5)} and the best 8-coefficient (rational) "
        f"fit is {how_far(err8)} somewhere in the image; {tolerance_px} px is allowed. Calibrate the "
        "camera instead of using its factory intrinsics")


def camera_model_from_rs_intrinsics(intr, tolerance_px: float = 0.05) -> CameraModel:
    """The CameraModel of `convert_intrinsics` (see there for each distortion model)."""
    return convert_intrinsics(intr, tolerance_px).model
