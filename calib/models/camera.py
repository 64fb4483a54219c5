"""Pinhole camera with Brown-Conrady (optionally rational) distortion, OpenCV's model.

Pixel (0, 0) is the centre of the top-left pixel. Distortion coefficients are in OpenCV order
[k1, k2, p1, p2, k3, k4, k5, k6]; 0, 4, 5 or 8 of them. A projector is modelled as an inverse camera
with the same class.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from calib.errors import FormatError

_ALLOWED_DIST = (0, 4, 5, 8)


def _frozen_array(a, shape=None) -> np.ndarray:
    a = np.array(a, dtype=float)
    if shape is not None:
        a = a.reshape(shape)
    a.setflags(write=False)
    return a


#: the largest image side (px) a camera or projector file may state: beyond any sensor or projector
MAX_IMAGE_SIDE = 65536


def _non_number(value) -> str | None:
    """None when `value` is a number or (nested) list of numbers, else a description of the first other thing."""
    if isinstance(value, np.ndarray):
        return None if value.dtype.kind in "iuf" else f"an array of {value.dtype}"
    if isinstance(value, (np.integer, np.floating)):
        return None
    if isinstance(value, (list, tuple)):
        for v in value:
            bad = _non_number(v)
            if bad is not None:
                return bad
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f"{type(value).__name__} {value!r}"[:60]
    return None


#: the largest magnitude of a number in a calibration file's geometry (pixels, distortion coefficients,
#: lengths): beyond it, arithmetic on the value overflows or loses every digit of the others
MAX_MAGNITUDE = 1e12


def read_numbers(value, path, where: str, shape: tuple | None = None) -> np.ndarray:
    """`value` from a file (untrusted) as a float array: JSON numbers only, of `shape` when given, each
    finite and at most MAX_MAGNITUDE in size; else a FormatError naming the element, e.g. camera.K[0][0]."""
    bad = _non_number(value)
    if bad is not None:
        raise FormatError(path, where, f"must hold numbers only, got {bad}")
    want = "a number" if shape == () else "a list of numbers" if shape is None else \
        f"a {'x'.join(map(str, shape))} list of numbers"
    try:
        a = np.array(value, float)
    except (TypeError, ValueError):
        raise FormatError(path, where, f"must be {want}") from None
    if shape is not None and a.shape != shape:
        raise FormatError(path, where, f"must be {want}, got shape {a.shape}")
    out = np.argwhere(~(np.abs(a) <= MAX_MAGNITUDE))
    if len(out):
        at = tuple(int(i) for i in out[0])
        raise FormatError(path, where + "".join(f"[{i}]" for i in at),
                          f"must be a finite number no larger than {MAX_MAGNITUDE:g} in size, got {float(a[at]):g}")
    return a


@dataclass(frozen=True, eq=False)
class CameraModel:
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "K", _frozen_array(self.K, (3, 3)))
        d = _frozen_array(self.dist).reshape(-1)
        if d.size not in _ALLOWED_DIST:
            raise ValueError(f"distortion must have 0, 4, 5 or 8 coefficients, got {d.size}")
        object.__setattr__(self, "dist", d)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, cx=None, cy=None, dist=()) -> "CameraModel":
        f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        cx = (width - 1) / 2.0 if cx is None else cx
        cy = (height - 1) / 2.0 if cy is None else cy
        return cls(width, height, [[f, 0, cx], [0, f, cy], [0, 0, 1]], dist)

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def dist5(self) -> np.ndarray:
        """Distortion padded/truncated to OpenCV's 5 coefficients (for APIs that want a fixed length)."""
        d = np.zeros(max(5, self.dist.size))
        d[: self.dist.size] = self.dist
        return d

    def with_params(self, K=None, dist=None) -> "CameraModel":
        return CameraModel(self.width, self.height, self.K if K is None else K, self.dist if dist is None else dist)

    # ---- mirrored views ---------------------------------------------------------------------------
    def flipped(self) -> "CameraModel":
        """The model of the horizontally flipped image (docs/GEOMETRY.md): cx' = (W-1) - cx, p2' = -p2.

        Radial terms are unchanged. Flipping twice gives the original model back."""
        K = np.array(self.K)
        K[0, 2] = (self.width - 1) - K[0, 2]
        K[0, 1] = -K[0, 1]
        d = np.array(self.dist)
        if d.size >= 4:
            d[3] = -d[3]
        return CameraModel(self.width, self.height, K, d)

    def flip_points(self, uv: np.ndarray) -> np.ndarray:
        """Map pixel coordinates between an image and its horizontal flip: x -> (W-1) - x."""
        uv = np.array(uv, float).reshape(-1, 2)
        uv[:, 0] = (self.width - 1) - uv[:, 0]
        return uv

    # ---- projection -----------------------------------------------------------------------------
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion to normalized (undistorted) coordinates x/z, y/z. (N, 2) -> (N, 2)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        d = np.zeros(8)
        d[: self.dist.size] = self.dist
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([xd, yd])

    def normalized_to_pixels(self, xy_d: np.ndarray) -> np.ndarray:
        K = self.K
        xy_d = np.asarray(xy_d, float).reshape(-1, 2)
        u = K[0, 0] * xy_d[:, 0] + K[0, 1] * xy_d[:, 1] + K[0, 2]
        v = K[1, 1] * xy_d[:, 1] + K[1, 2]
        return np.column_stack([u, v])

    @cached_property
    def max_radius(self) -> float:
        """Largest normalized radius the model is valid for: 1.25 x that of the image corners. Beyond
        it a polynomial distortion model can fold far-away points back into the image."""
        c = np.array([[-0.5, -0.5], [self.width - 0.5, -0.5], [-0.5, self.height - 0.5],
                      [self.width - 0.5, self.height - 0.5]])
        return 1.25 * float(np.linalg.norm(self.undistort_normalized(c), axis=1).max())

    def project(self, X_dev: np.ndarray) -> np.ndarray:
        """Pixels of (N, 3) points given in this device's frame. Points behind the device, or so far
        outside the field of view that the distortion model is meaningless, give NaN."""
        X = np.asarray(X_dev, float).reshape(-1, 3)
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = X[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        if self.dist.size and np.any(self.dist):
            xy[np.einsum("ij,ij->i", xy, xy) > self.max_radius**2] = np.nan
        return self.normalized_to_pixels(self.distort_normalized(xy))

    def undistort_normalized(self, uv: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Normalized undistorted coordinates (x/z, y/z) of pixels. (N, 2) -> (N, 2).

        OpenCV's fixed-point iteration as a start, then Newton steps on distort_normalized, so that
        project(rays(uv)) returns uv to ~1e-9 px wherever the distortion is invertible."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        Kinv = np.linalg.inv(self.K)
        target = uv @ Kinv[:2, :2].T + Kinv[:2, 2]  # distorted normalized coordinates
        if self.dist.size == 0 or not np.any(self.dist):
            return target
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, criteria=crit).reshape(-1, 2)
        h = 1e-7
        for _ in range(iterations):
            f = self.distort_normalized(xy) - target
            if np.nanmax(np.abs(f)) < 1e-13:
                break
            jx = (self.distort_normalized(xy + [h, 0]) - self.distort_normalized(xy - [h, 0])) / (2 * h)
            jy = (self.distort_normalized(xy + [0, h]) - self.distort_normalized(xy - [0, h])) / (2 * h)
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            dx = (jy[:, 1] * f[:, 0] - jy[:, 0] * f[:, 1]) / det
            dy = (-jx[:, 1] * f[:, 0] + jx[:, 0] * f[:, 1]) / det
            xy = xy - np.column_stack([dx, dy])
        return xy

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Unit ray directions (device frame) through pixels. (N, 2) -> (N, 3)."""
        xy = self.undistort_normalized(uv)
        r = np.column_stack([xy, np.ones(len(xy))])
        return r / np.linalg.norm(r, axis=1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv, float).reshape(-1, 2)
        return (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= -0.5 + margin_px)
            & (uv[:, 0] <= self.width - 0.5 - margin_px)
            & (uv[:, 1] >= -0.5 + margin_px)
            & (uv[:, 1] <= self.height - 0.5 - margin_px)
        )

    # ---- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "camera", path="<dict>") -> "CameraModel":
        """A camera from a file's dict (untrusted): every number a JSON number (a string, a boolean or null
        is not one, though numpy would convert them), finite and no larger than MAX_MAGNITUDE, the image
        size a positive integer no larger than MAX_IMAGE_SIDE, K's last row (0, 0, 1), fx and fy not 0. Values that are numbers but absurd (a negative focal
        length) load: the trust check says what is wrong with them."""
        if not isinstance(d, dict):
            raise FormatError(path, where, f"must be an object with width, height, K and dist, got {type(d).__name__}")
        for key in ("width", "height", "K", "dist"):
            if key not in d:
                raise FormatError(path, f"{where}.{key}", "missing")
        K = read_numbers(d["K"], path, f"{where}.K", (3, 3))
        dist = read_numbers(d["dist"], path, f"{where}.dist").reshape(-1)
        if dist.size not in _ALLOWED_DIST:
            raise FormatError(path, f"{where}.dist", f"must have 0, 4, 5 or 8 coefficients, got {dist.size}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]):
            raise FormatError(path, f"{where}.K", f"its last row must be [0, 0, 1], got {K[2].tolist()}")
        for i, name in ((0, "fx"), (1, "fy")):
            if K[i, i] == 0:
                raise FormatError(path, f"{where}.K[{i}][{i}]", f"is the focal length {name}: it must not be 0 "
                                  "(0 px sends every ray to one pixel)")
        for key in ("width", "height"):
            v = d[key]
            if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= MAX_IMAGE_SIDE:
                raise FormatError(path, f"{where}.{key}", f"must be a positive integer up to {MAX_IMAGE_SIDE}, "
                                  f"got {v!r}")
        return cls(d["width"], d["height"], K, dist)
