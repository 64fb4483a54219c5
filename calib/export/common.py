"""What the exporters share: their options, the rig's devices with their poses, the pixels a target's
model misses (a distortion or a skew it cannot represent), lengths in metres."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.errors import ExportError
from calib.models.boards import MM_PER_UNIT
from calib.models.camera import CameraModel

#: pixels per side of the grid over the image on which the residual of an approximation is measured
RESIDUAL_GRID = (33, 21)


@dataclass(frozen=True)
class ExportOptions:
    """near_m, far_m: the clipping planes of the graphics exports (opengl, unity, threejs), metres."""

    near_m: float = 0.1
    far_m: float = 100.0

    def __post_init__(self):
        for name in ("near_m", "far_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ExportError(f"--{name[:-2]} must be a positive number of metres, got {v!r}")
        if self.far_m <= self.near_m:
            raise ExportError(f"--far ({self.far_m:g} m) must be beyond --near ({self.near_m:g} m)")


def devices(result) -> tuple[tuple[str, CameraModel, np.ndarray], ...]:
    """(name, model, T_cam_dev) of the camera (the reference) and the projector."""
    return (("camera", result.camera, np.eye(4)), ("projector", result.projector, np.asarray(result.T_cam_proj)))


def metres_per_unit(units: str) -> float:
    if units not in MM_PER_UNIT:
        raise ExportError(f"the calibration's units '{units}' are not a known length unit "
                          f"({', '.join(MM_PER_UNIT)}); lengths cannot be converted to metres")
    return MM_PER_UNIT[units] / 1000.0


def pinhole(model: CameraModel, keep_skew: bool = False) -> CameraModel:
    """`model` without distortion (and without skew unless `keep_skew`): what a pinhole-only target holds."""
    K = np.array(model.K)
    if not keep_skew:
        K[0, 1] = 0.0
    return model.with_params(K=K, dist=np.zeros(0))


def residual_px(model: CameraModel, approx: CameraModel) -> float:
    """The largest distance (px) over the image between `model`'s pixels and where `approx` projects
    the same rays: what a target holding `approx` gets wrong."""
    if np.array_equal(model.K, approx.K) and np.array_equal(model.dist5(), approx.dist5()):
        return 0.0
    nx, ny = RESIDUAL_GRID
    u, v = np.meshgrid(np.linspace(0, model.width - 1, nx), np.linspace(0, model.height - 1, ny))
    uv = np.column_stack([u.ravel(), v.ravel()])
    moved = approx.project(model.rays(uv))
    return float(np.nanmax(np.linalg.norm(moved - uv, axis=1)))


def unrepresented(name: str, model: CameraModel, approx: CameraModel, target: str) -> tuple[float, str | None]:
    """(residual px, warning or None) for device `name` written to `target` as `approx`."""
    r = residual_px(model, approx)
    if r == 0.0:
        return 0.0, None
    what = []
    if np.any(model.dist) and not np.array_equal(model.dist5(), approx.dist5()):
        what.append("lens distortion")
    if model.K[0, 1] != approx.K[0, 1]:
        what.append("skew")
    return r, (f"{name}: {target} cannot represent the {' and '.join(what)}; written without it, up to "
               f"{r:.2f} px off over the image (undistort the image first, or correct in a shader)")
