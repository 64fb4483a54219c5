"""The renderer's photometry (behind drivers/sim/render.py, docs/SIMULATOR.md "Photometric realism"):
the camera's tone curve and its inverse, the projector's defocus blur, the lens's vignetting."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from calib.detection.response import BT709_OFFSET as _TOE_OFFSET
from calib.models.camera import CameraModel
from drivers.sim._render_rays import normalized_grid, undistort_exact


def encode_gamma(light: np.ndarray, gamma: float) -> np.ndarray:
    """A camera's tone curve: relative light in [0, 1] -> relative level, V = (1 + a) L^(1/gamma) - a
    above a threshold and a straight line through 0 below it, joined with the same value and slope
    (BT.709's construction; gamma = 1 / 0.45 gives BT.709). gamma = 1 returns `light` unchanged."""
    if gamma == 1.0:
        return light
    p = 1.0 / gamma
    a = _TOE_OFFSET  # with exponent 0.45: BT.709 itself
    t = (a / ((1 + a) * (1 - p))) ** (1 / p)
    slope = (1 + a) * p * t ** (p - 1)
    L = np.asarray(light, np.float32)
    hi = np.float32(1 + a) * np.power(np.maximum(L, np.float32(t)), np.float32(p)) - np.float32(a)
    return np.where(L < t, np.float32(slope) * L, hi).astype(np.float32)


LUT_STEPS = 256  # linear levels per 8-bit level in the encoding table


@lru_cache(maxsize=4)
def encode_lut(gamma: float) -> np.ndarray:
    """uint8 output level of each linear level k / LUT_STEPS (0..255): the tone curve and the 8-bit
    rounding as one table. A pixel lands within 1/512 of a linear level of its exact value, so it differs
    from the exact rounding by one level only right at a rounding threshold (under 2 % of pixels in the
    steepest part of the curve, near black, where the noise is several levels)."""
    lin = np.arange(255 * LUT_STEPS + 1, dtype=np.float32) / np.float32(255 * LUT_STEPS)
    out = np.clip(255.0 * encode_gamma(lin, gamma) + 0.5, 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out


def decode_gamma(level: np.ndarray, gamma: float) -> np.ndarray:
    """The inverse of encode_gamma: relative level -> relative light (the detector's own inverse,
    calib.detection.response, so the simulator and the correction share one curve)."""
    if gamma == 1.0:
        return level
    from calib.detection.response import CameraResponse

    return CameraResponse("bt709", float(gamma)).decode(level).astype(np.float32)


def defocus_sigma_px(depth_mm, aperture_mm: float, focus_mm: float, f_px: float):
    """Thin-lens defocus of a projector focused at `focus_mm`: the circle of confusion of a point at
    `depth_mm` (along the axis) has diameter aperture * f * |1/depth - 1/focus| in image pixels; the
    returned Gaussian sigma is that of a uniform disc of this diameter (diameter / 4)."""
    return np.float32(aperture_mm * f_px / 4.0) * np.abs(np.float32(1.0) / depth_mm - np.float32(1.0 / focus_mm))


def vignetting_map(camera: CameraModel, corner: float) -> np.ndarray:
    """Relative irradiance per pixel, (H, W) float32: 1 on the optical axis, cos^4 of the ray's angle
    rescaled so that the farthest image corner receives `corner` (a lens whose cos^4 fall-off the
    image processor partly corrects keeps this shape with a smaller depth)."""
    nx, ny = normalized_grid(camera, 1)
    c4 = 1.0 / (1.0 + nx.astype(np.float64) ** 2 + ny.astype(np.float64) ** 2) ** 2  # cos^4 of the angle
    W, H = camera.size
    ends = undistort_exact(camera, np.array([[0.0, 0.0], [W - 1.0, 0.0], [0.0, H - 1.0], [W - 1.0, H - 1.0]]))
    c4_corner = float((1.0 / (1.0 + (ends ** 2).sum(axis=1)) ** 2).min())
    v = 1.0 - (1.0 - corner) * (1.0 - c4) / (1.0 - c4_corner)
    return np.maximum(v, 0.0).astype(np.float32)
