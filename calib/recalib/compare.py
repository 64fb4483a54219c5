"""Stage 3 of a recalibration: the change of each part with its uncertainty (compare_calibrations)."""

from __future__ import annotations

import math

import numpy as np

from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult
from calib.recalib._model import previous_covariance
from calib.recalib.check import describe_change
from calib.transforms import rotation_angle_deg


# ---- stage 3: compare -------------------------------------------------------------------------------
def projection_difference(a: CameraModel, b: CameraModel, grid: tuple[int, int] = (16, 10)) -> dict:
    """How far the same ray lands between two intrinsic models: pixels on a grid over the image,
    unprojected with `a` and projected with `b` (mean, max, and the grid of distances in px)."""
    w, h = a.size
    xs = np.linspace(0.05 * w, 0.95 * w, grid[0])
    ys = np.linspace(0.05 * h, 0.95 * h, grid[1])
    uv = np.array([[x, y] for y in ys for x in xs])
    uv2 = b.project(a.rays(uv))
    dist = np.linalg.norm(uv2 - uv, axis=1)
    return {"mean_px": float(dist.mean()), "max_px": float(dist.max()), "grid": [int(grid[0]), int(grid[1])],
            "px": dist.reshape(grid[1], grid[0]).round(4).tolist()}


def compare_calibrations(previous: CalibrationResult, new: CalibrationResult, sigma: dict | None = None) -> dict:
    """Stage 3: the change of each part from `previous` to `new` (mm/units, deg, px) with its 1-sigma
    (previous and re-estimate combined, where known), and the projection difference of the intrinsics."""
    u = previous.units
    sigma = sigma or {}
    out = {"units": u}
    T0, T1 = previous.T_cam_proj, new.T_cam_proj
    sp = describe_change("projector", np.zeros(6), previous_covariance(previous, "projector"), u)[1]
    sn = sigma.get("projector", {})
    out["projector"] = {
        f"position_change_{u}": float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])),
        "rotation_change_deg": rotation_angle_deg(T1[:3, :3] @ T0[:3, :3].T),
        f"position_sigma_{u}": math.hypot(sp[f"t_{u}"], sn.get(f"t_{u}", 0.0)),
        "rotation_sigma_deg": math.hypot(sp["rot_deg"], sn.get("rot_deg", 0.0)),
    }
    if previous.mirror is not None and new.mirror is not None:
        sp = describe_change("mirror", np.zeros(3), previous_covariance(previous, "mirror"), u)[1]
        sn = sigma.get("mirror", {})
        cosang = float(np.clip(previous.mirror.normal @ new.mirror.normal, -1, 1))
        out["mirror"] = {"normal_change_deg": math.degrees(math.acos(cosang)),
                         f"d_change_{u}": float(new.mirror.d - previous.mirror.d),
                         "normal_sigma_deg": math.hypot(sp["normal_deg"], sn.get("normal_deg", 0.0)),
                         f"d_sigma_{u}": math.hypot(sp[f"d_{u}"], sn.get(f"d_{u}", 0.0))}
    else:
        out["mirror"] = None
    sp = describe_change("camera", np.zeros(4), previous_covariance(previous, "camera"), u)[1]
    sn = sigma.get("camera", {})
    dK = np.array(new.camera.K) - np.array(previous.camera.K)
    out["camera"] = {
        "fx_change_px": float(dK[0, 0]), "fy_change_px": float(dK[1, 1]),
        "cx_change_px": float(dK[0, 2]), "cy_change_px": float(dK[1, 2]),
        "sigma_px": {k: math.hypot(sp[k], sn.get(k, 0.0)) for k in ("fx_px", "fy_px", "cx_px", "cy_px")},
        "projection_difference": projection_difference(previous.camera, new.camera),
    }
    out["projector_intrinsics"] = {"projection_difference": projection_difference(previous.projector, new.projector)}
    return out
