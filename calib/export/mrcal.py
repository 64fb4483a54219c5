"""mrcal .cameramodel files, one per device (mrcal.cameramodel reads them; mrcal-show-distortion-off-pinhole,
mrcal-show-projection-diff... compare them).

The file is a Python literal: lensmodel, intrinsics [fx, fy, cx, cy, distortion...], extrinsics rt_fromref
[rx, ry, rz, tx, ty, tz] (Rodrigues rotation and translation taking reference coordinates into the
device's), imagersize [W, H]. The reference is the camera (its extrinsics are zero), lengths in the
calibration's units. The lens model is OpenCV's of the same order (LENSMODEL_PINHOLE, _OPENCV4, _OPENCV5,
_OPENCV8), with mrcal's pixel convention equal to OpenCV's; mrcal has no skew term, so a skew is left
out with a warning and its residual in a comment."""

from __future__ import annotations

import cv2
import numpy as np

from calib.export.common import devices, pinhole, unrepresented
from calib.formats.fileio import atomic_write_text
from calib.transforms import invert_T

LENSMODELS = {0: "LENSMODEL_PINHOLE", 4: "LENSMODEL_OPENCV4", 5: "LENSMODEL_OPENCV5", 8: "LENSMODEL_OPENCV8"}


def _numbers(values) -> str:
    return "[ " + ", ".join(repr(float(v)) for v in values) + " ]"


def cameramodel_text(model, T_dev_ref: np.ndarray, units: str, note: str | None) -> str:
    rvec = cv2.Rodrigues(np.ascontiguousarray(T_dev_ref[:3, :3]))[0].ravel()
    intrinsics = [model.fx, model.fy, model.cx, model.cy, *model.dist]
    head = f"# {note}\n" if note else ""
    return (f"# written by procam export; reference frame: the camera; lengths in {units}\n{head}{{\n"
            f"    'lensmodel': '{LENSMODELS[model.dist.size]}',\n"
            "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
            f"    'intrinsics': {_numbers(intrinsics)},\n"
            "    # extrinsics are rt_fromref\n"
            f"    'extrinsics': {_numbers([*rvec, *T_dev_ref[:3, 3]])},\n"
            f"    'imagersize': [ {model.width}, {model.height} ],\n}}\n")


def write(result, paths, options=None) -> list[str]:
    """paths: (camera file, projector file)."""
    warnings = []
    for path, (name, model, T_cam_dev) in zip(paths, devices(result)):
        _, warning = unrepresented(name, model, pinhole(model).with_params(dist=model.dist), "mrcal")
        if warning:
            warnings.append(warning)
        atomic_write_text(path, cameramodel_text(model, invert_T(T_cam_dev), result.units, warning))
    return warnings
