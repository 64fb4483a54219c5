"""OpenCV FileStorage YAML (calibration.yaml): camera_matrix, camera_distortion, projector_matrix,
projector_distortion, T_cam_proj, R_cam_proj, t_cam_proj, mirror_normal, mirror_d, sizes, rms."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np


def write(result, paths, options=None) -> list[str]:
    """Write `result` to paths[0] (through a temporary file in the same folder). OpenCV represents every
    model the station makes, so there is never a warning."""
    path = Path(paths[0])
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{path.suffix}")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    fs.write("units", result.units)
    fs.write("method", result.method)
    for name, dev in (("camera", result.camera), ("projector", result.projector)):
        fs.write(f"{name}_width", dev.width)
        fs.write(f"{name}_height", dev.height)
        fs.write(f"{name}_matrix", np.array(dev.K))
        fs.write(f"{name}_distortion", np.array(dev.dist).reshape(1, -1))
    fs.write("T_cam_proj", np.array(result.T_cam_proj))
    fs.write("R_cam_proj", np.array(result.T_cam_proj[:3, :3]))
    fs.write("t_cam_proj", np.array(result.T_cam_proj[:3, 3]).reshape(3, 1))
    if result.mirror is not None:
        fs.write("mirror_normal", np.array(result.mirror.normal).reshape(3, 1))
        fs.write("mirror_d", float(result.mirror.d))
    for k, v in result.rms.items():
        if isinstance(v, (int, float)) and v is not None:
            fs.write(f"rms_{k}", float(v))
    fs.release()
    os.replace(tmp, path)
    return []
