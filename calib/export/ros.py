"""ROS camera_info YAML (camera_calibration_parsers' format), one file per device.

Each file is what a camera_info_manager loads for a monocular camera: image size, camera_name, K (row-major
3x3), distortion_model with D, R = identity and P = [K | 0] (the raw image is not rectified against the
other device). The camera-projector pose is not part of camera_info (ROS carries it in tf): the projector's
file states it in a comment, as the arguments of tf2_ros's static_transform_publisher. ROS represents
every model the station makes (plumb_bob for 0, 4 or 5 coefficients, rational_polynomial for 8)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib.export.common import devices, metres_per_unit
from calib.formats.fileio import atomic_write_text


def distortion_model(dist: np.ndarray) -> tuple[str, list[float]]:
    """ROS's distortion model name and D: plumb_bob takes exactly 5 coefficients, rational_polynomial 8."""
    d = [float(x) for x in dist]
    if len(d) == 8:
        return "rational_polynomial", d
    return "plumb_bob", d + [0.0] * (5 - len(d))


def _matrix(name: str, rows: int, cols: int, values) -> str:
    data = ", ".join(repr(float(x)) for x in np.asarray(values, float).ravel())
    return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]\n"


def camera_info_yaml(name: str, model, note: str = "") -> str:
    """The camera_info YAML text of one device."""
    dm, d = distortion_model(model.dist)
    P = np.hstack([model.K, np.zeros((3, 1))])
    return (note + f"image_width: {model.width}\nimage_height: {model.height}\ncamera_name: {name}\n"
            + _matrix("camera_matrix", 3, 3, model.K) + f"distortion_model: {dm}\n"
            + _matrix("distortion_coefficients", 1, len(d), d) + _matrix("rectification_matrix", 3, 3, np.eye(3))
            + _matrix("projection_matrix", 3, 4, P))


def tf_note(T_cam_proj: np.ndarray, units: str) -> str:
    """Comment lines giving the projector's pose in the camera's optical frame for tf."""
    t = T_cam_proj[:3, 3] * metres_per_unit(units)
    q = Rotation.from_matrix(T_cam_proj[:3, :3]).as_quat()  # x, y, z, w
    args = " ".join(repr(float(v)) for v in [*t, *q])
    return ("# pose of the projector in the camera's optical frame (x right, y down, z forward; metres):\n"
            f"# ros2 run tf2_ros static_transform_publisher {args} camera projector\n"
            "# (x y z qx qy qz qw parent child)\n")


def write(result, paths, options=None) -> list[str]:
    """paths: (camera file, projector file)."""
    for path, (name, model, T) in zip(paths, devices(result)):
        note = tf_note(T, result.units) if name == "projector" else ""
        atomic_write_text(path, camera_info_yaml(name, model, note))
    return []
