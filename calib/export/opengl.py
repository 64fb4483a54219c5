"""OpenGL projection and view matrices of each device (one JSON file), for a renderer that draws what
the projector should show (or what the camera sees).

OpenGL's eye space looks down -z with +y up: a point of a device's OpenCV frame (x right, y down,
z forward) is (x, -y, -z) there (GL_FROM_CV). The world is the camera's frame in OpenGL's axes (so the
camera's view matrix is the identity), in metres. `projection` maps eye space to clip space such that,
with glViewport(0, 0, W, H) and the image's row 0 at the top of the window, OpenCV pixel (u, v)
(pixel centres at integers) is window (u + 0.5, H - 0.5 - v): the principal point is off-centre as the
calibration says and the y-flip is in the matrix. Matrices are written column-major (16 numbers, as
glUniformMatrix4fv with transpose = GL_FALSE and three.js's Matrix4.fromArray take them). OpenGL has no
lens distortion (nor skew): it is left out with a warning and its residual in px in the file."""

from __future__ import annotations

import json

import numpy as np

from calib.export.common import devices, metres_per_unit, pinhole, unrepresented
from calib.formats.fileio import atomic_write_text
from calib.transforms import invert_T

GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def projection_matrix(model, near: float, far: float) -> np.ndarray:
    """The 4x4 (row-major here) OpenGL projection of `model`'s pinhole part, clipping at near, far."""
    W, H = model.width, model.height
    return np.array([
        [2 * model.fx / W, -2 * model.K[0, 1] / W, 1 - 2 * (model.cx + 0.5) / W, 0.0],
        [0.0, 2 * model.fy / H, 2 * (model.cy + 0.5) / H - 1, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0],
    ])


def view_matrix(T_cam_dev: np.ndarray, metres: float) -> np.ndarray:
    """World (the camera's frame in OpenGL axes, metres) to the device's OpenGL eye space."""
    T = np.array(T_cam_dev, float)
    T[:3, 3] *= metres
    return GL_FROM_CV @ invert_T(T) @ GL_FROM_CV


def column_major(M: np.ndarray) -> list[float]:
    return [float(x) for x in np.asarray(M).T.ravel()]


def write(result, paths, options) -> list[str]:
    """paths: (the JSON file,)."""
    metres = metres_per_unit(result.units)
    out = {"format": "procam-opengl", "version": 1, "units": "m", "near": options.near_m, "far": options.far_m,
           "matrix_order": "column-major", "world": "the camera's frame in OpenGL axes (x right, y up, z back)"}
    warnings = []
    for name, model, T_cam_dev in devices(result):
        residual, warning = unrepresented(name, model, pinhole(model, keep_skew=True), "OpenGL")
        warnings += [warning] if warning else []
        out[name] = {"width": model.width, "height": model.height,
                     "projection": column_major(projection_matrix(model, options.near_m, options.far_m)),
                     "view": column_major(view_matrix(T_cam_dev, metres)),
                     "distortion_residual_px": residual, "warning": warning}
    atomic_write_text(paths[0], json.dumps(out, indent=2) + "\n")
    return warnings
