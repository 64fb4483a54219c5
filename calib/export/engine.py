"""A virtual camera per device for a game engine or real-time graphics tool: its lens (focal length,
sensor, lens shift) and its pose relative to the camera, in the engine's axes and metres (one JSON file).

Per engine (ENGINES): the axes (a diagonal sign flip from OpenCV's x right, y down, z forward) and how
a lens is described.
- unity: left-handed, x right, y up, z forward; a physical camera (Camera.usePhysicalProperties) with
  focalLength and sensorSize in mm, lensShift as a fraction of the sensor (+x right, +y up) and
  gateFit None, so its projection has m00 = 2 f / sensor_x, m11 = 2 f / sensor_y, m02 = 2 shift_x,
  m12 = 2 shift_y.
- threejs: right-handed, x right, y up, the camera looking down -z; a PerspectiveCamera (vertical fov
  in degrees, aspect) over a larger symmetric frustum of which setViewOffset takes the image (three.js
  has no vertical lens shift otherwise).
The camera is at the origin with no rotation; the projector's position and quaternion [x, y, z, w] are
given in that frame. Neither engine has lens distortion or skew: they are left out with a warning and
their residual in px in the file."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib.export.common import devices, metres_per_unit, pinhole, unrepresented
from calib.formats.fileio import atomic_write_text

#: the sensor width given to Unity (mm): only the ratio of focal length to sensor matters
SENSOR_WIDTH_MM = 36.0
#: three.js's default filmGauge (mm), for which focal_length_mm is given (camera.setFocalLength)
FILM_GAUGE_MM = 35.0


def unity_lens(model, near: float, far: float) -> dict:
    """Unity's physical camera of `model`'s pinhole part (no skew)."""
    f_mm = model.fx * SENSOR_WIDTH_MM / model.width
    return {"usePhysicalProperties": True, "focalLength": f_mm,
            "sensorSize": [SENSOR_WIDTH_MM, model.height * f_mm / model.fy],
            "lensShift": [0.5 - (model.cx + 0.5) / model.width, (model.cy + 0.5) / model.height - 0.5],
            "gateFit": "None", "nearClipPlane": near, "farClipPlane": far,
            "resolution": [model.width, model.height]}


def threejs_lens(model, near: float, far: float) -> dict:
    """three.js PerspectiveCamera arguments and view offset of `model`'s pinhole part (no skew).

    setViewOffset sets the camera's aspect to fullWidth / fullHeight, so the view's horizontal numbers
    are the image's pixels scaled by fy / fx (square pixels): only their ratios enter the projection."""
    cx, cy = model.cx + 0.5, model.cy + 0.5  # the principal point from the image's top-left corner
    hx, hy = max(cx, model.width - cx), max(cy, model.height - cy)
    square = model.fy / model.fx
    fov_deg = math.degrees(2 * math.atan(hy / model.fy))
    aspect = (hx * square) / hy
    film_height = FILM_GAUGE_MM / max(aspect, 1.0)
    return {"fov": fov_deg, "aspect": aspect, "near": near, "far": far,
            "view": {"fullWidth": 2 * hx * square, "fullHeight": 2 * hy, "offsetX": (hx - cx) * square,
                     "offsetY": hy - cy, "width": model.width * square, "height": model.height},
            "filmGauge": FILM_GAUGE_MM, "focalLength": 0.5 * film_height / math.tan(math.radians(fov_deg) / 2)}


@dataclass(frozen=True)
class Engine:
    name: str
    axes: tuple[float, float, float]  # the engine's axes from OpenCV's: a sign per axis
    description: str
    lens: object  # lens(model, near, far) -> dict


ENGINES = {
    "unity": Engine("Unity", (1.0, -1.0, 1.0), "left-handed: x right, y up, z forward (the camera looks along +z)",
                    unity_lens),
    "threejs": Engine("three.js", (1.0, -1.0, -1.0),
                      "right-handed: x right, y up, z back (the camera looks along -z)", threejs_lens),
}


def pose(T_cam_dev: np.ndarray, axes, metres: float) -> dict:
    """The device's position and rotation in the engine's world (the camera's frame in engine axes)."""
    A = np.diag(axes)
    R = A @ T_cam_dev[:3, :3] @ A
    return {"position": (A @ T_cam_dev[:3, 3] * metres).tolist(),
            "quaternion": Rotation.from_matrix(R).as_quat().tolist()}


def write(engine_key: str, result, paths, options) -> list[str]:
    """paths: (the JSON file,)."""
    engine = ENGINES[engine_key]
    metres = metres_per_unit(result.units)
    out = {"format": f"procam-{engine_key}", "version": 1, "engine": engine.name, "axes": engine.description,
           "units": "m", "reference": "camera"}
    warnings = []
    for name, model, T_cam_dev in devices(result):
        residual, warning = unrepresented(name, model, pinhole(model), engine.name)
        warnings += [warning] if warning else []
        out[name] = {"lens": engine.lens(model, options.near_m, options.far_m),
                     **pose(np.asarray(T_cam_dev, float), engine.axes, metres),
                     "distortion_residual_px": residual, "warning": warning}
    atomic_write_text(paths[0], json.dumps(out, indent=2) + "\n")
    return warnings
