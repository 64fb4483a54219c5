"""The calibration pipeline: observations (or a session folder) in, CalibrationResult out.

Methods are registered by name in METHODS (name -> function(obs, camera, progress) -> CalibrationResult):
"paper" is the method of Vanherck et al. (calib.paper.method), "joint" the paper's result refined by one joint
maximum-likelihood adjustment (calib.joint.method). Every result passes the trust check (calib.quality.trust) before
it is returned: an untrusted calibration raises UntrustedCalibration instead.

`progress`, when given, is called as progress(done, total, label) (the same convention as
calib.detection.detect.detect_session); `label` names the stage.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from calib.errors import CalibrationError, FormatError, UntrustedCalibration
from calib.joint.method import calibrate_joint
from calib.models.camera import CameraModel
from calib.models.observations import SessionObservations
from calib.models.result import CalibrationResult
from calib.models.vocab import CalibrationMethod
from calib.paper.method import Progress, calibrate_paper
from calib.quality.trust import check_calibration

Method = Callable[[SessionObservations, "CameraModel | None", "Progress | None"], CalibrationResult]

#: name -> function(obs, camera, progress) -> CalibrationResult
METHODS: dict[str, Method] = {CalibrationMethod.PAPER: calibrate_paper, CalibrationMethod.JOINT: calibrate_joint}


#: what calibrate_observations / calibrate_session do with the trust check (calib.quality.trust): "check" raises
#: UntrustedCalibration for a result that fails it; "accept" keeps the result with the reasons recorded
#: in diagnostics["trust"] (an expert's override, `procam calibrate --accept-untrusted`); None skips it
#: (benchmarks that study the methods themselves).
TRUST_MODES = ("check", "accept", None)


def apply_trust_check(result: CalibrationResult, trust: str | None = "check",
                      observations: SessionObservations | None = None) -> CalibrationResult:
    """The result with its trust report in diagnostics["trust"]; raises UntrustedCalibration (carrying
    the report and that result) when it fails and `trust` is "check". With the `observations` it came
    from, the check also casts them through the result (calib.quality.trust)."""
    if trust not in TRUST_MODES:
        raise CalibrationError(f"unknown trust mode '{trust}' (check, accept or None)")
    if trust is None:
        return result
    report = check_calibration(result, observations=observations)
    if not report.passed and trust == "accept":
        report = replace(report, accepted_by_user=True)
    result = result.with_(diagnostics=dict(result.diagnostics, trust=report.to_dict()))
    if not report.passed and trust == "check":
        raise UntrustedCalibration(report, result)
    return result


def calibrate_observations(obs: SessionObservations, method: str = CalibrationMethod.JOINT, camera: CameraModel | None = None,
                           progress: Progress | None = None, method_options: dict | None = None,
                           trust: str | None = "check") -> CalibrationResult:
    """Calibrate from detected observations with a registered method; `camera` skips the camera stage.
    The result passes the trust check (`trust`, see TRUST_MODES) before it is returned."""
    fn = METHODS.get(method)
    if fn is None:
        raise CalibrationError(f"unknown calibration method '{method}' (available: {', '.join(sorted(METHODS))})")
    t0 = time.perf_counter()
    result = fn(obs, camera, progress, **method_options) if method_options else fn(obs, camera, progress)
    diag = dict(result.diagnostics)
    timing = dict(diag.get("timing_s", {}))
    timing["total"] = round(time.perf_counter() - t0, 4)
    diag["timing_s"] = timing
    copies = {s.capture_id: s.copy_of for s in obs.skipped if s.copy_of}
    if copies:  # counted once (calib.detection.detect): said apart from the other skipped captures
        diag["copies"] = copies
    return apply_trust_check(result.with_(diagnostics=diag), trust, obs)


def calibrate_session(folder, method: str = CalibrationMethod.JOINT, camera_intrinsics=None, workers: int = 2,
                      progress: Progress | None = None, detect_progress: Progress | None = None,
                      method_options: dict | None = None, detect_cache: str = "use",
                      trust: str | None = "check") -> CalibrationResult:
    """Detect and calibrate a session folder. `camera_intrinsics`: None, a CameraModel, or a file
    (calibration.json or OpenCV YAML, see load_camera_intrinsics). `detect_progress` (default:
    `progress`) follows detection, `progress` the calibration stages. `detect_cache`: "use" (reuse
    the detections of earlier runs kept in the session folder), "refresh" or "off" (detect_session).
    `trust`: the trust check (TRUST_MODES); an untrusted result raises UntrustedCalibration."""
    from calib.detection.detect import detect_session
    from calib.formats.session import SessionStore

    store = SessionStore.open(folder)
    t0 = time.perf_counter()
    obs = detect_session(store, workers, detect_progress if detect_progress is not None else progress,
                         cache=detect_cache)
    t_detect = time.perf_counter() - t0
    camera = camera_intrinsics
    if camera is not None and not isinstance(camera, CameraModel):
        camera = load_camera_intrinsics(camera, obs.camera_size)
    result = calibrate_observations(obs, method, camera, progress, method_options, trust=None)
    images = {c.id: c.image for c in store.manifest.captures}
    skipped = []
    for s in result.skipped:
        s = dict(s)
        if not s.get("image"):
            s["image"] = images.get(s.get("capture_id"), "")
        skipped.append(s)
    diag = dict(result.diagnostics)
    diag["timing_s"] = dict(diag.get("timing_s", {}), detection=round(t_detect, 4))
    diag["session"] = str(Path(folder))
    return apply_trust_check(result.with_(skipped=tuple(skipped), diagnostics=diag), trust, obs)


# ---- camera intrinsics from a file ------------------------------------------------------------------
_K_KEYS = ("camera_matrix", "cameraMatrix", "K")
_D_KEYS = ("distortion_coefficients", "camera_distortion", "dist_coeffs", "distCoeffs", "D")
_W_KEYS = ("image_width", "camera_width", "width")
_H_KEYS = ("image_height", "camera_height", "height")


def load_camera_intrinsics(path, image_size: tuple[int, int] | None = None) -> CameraModel:
    """Camera intrinsics from a calibration.json (its "camera") or an OpenCV FileStorage YAML/XML with
    camera_matrix and distortion_coefficients (also accepted: camera_distortion, dist_coeffs) and
    optionally image_width / image_height (or camera_width / camera_height). Without a size in the file,
    `image_size` is used. Intrinsics the trust check refuses (a negative focal length, a distortion that
    folds the image) are a FormatError with its reasons: a calibration from them would blame the images."""
    from calib.quality.trust import check_device

    camera = _read_camera_intrinsics(Path(path), image_size)
    report = check_device("camera", camera)
    if not report.passed:
        raise FormatError(path, "camera", f"holds intrinsics no camera has ({report.reasons_text()}): give the camera's own "
                          "calibration, or let the calibration estimate the camera's intrinsics")
    return camera


def _read_camera_intrinsics(path: Path, image_size) -> CameraModel:
    """load_camera_intrinsics without the trust check."""
    if not path.exists():
        raise FormatError(path, "<file>", "does not exist")
    if not path.is_file():
        raise FormatError(path, "<file>", "is not a regular file (a folder?); give a calibration.json or OpenCV YAML")
    if path.suffix.lower() == ".json":
        from calib.formats.jsonfile import read_json_file
        from calib.models.result import CalibrationResult

        data = read_json_file(path)
        if not isinstance(data, dict):
            raise FormatError(path, "<root>", "must be a JSON object")
        if "T_cam_proj" in data:  # a whole calibration: checked as every calibration file is
            return CalibrationResult.from_dict(data, path).camera
        cam = data.get("camera", data)
        if isinstance(cam, dict) and "width" not in cam and image_size is not None and "K" in cam:
            cam = dict(cam, width=image_size[0], height=image_size[1])
        return CameraModel.from_dict(cam, "camera" if "camera" in data else "<root>", path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV's parser fails either way on a file that is not YAML/XML
        raise FormatError(path, "<file>", "is neither JSON nor an OpenCV FileStorage YAML/XML file") from None
    if not fs.isOpened():
        raise FormatError(path, "<file>", "is neither JSON nor an OpenCV FileStorage YAML/XML file")
    try:
        K = _first_mat(fs, _K_KEYS)
        if K is None or K.shape != (3, 3):
            raise FormatError(path, "camera_matrix", "missing or not a 3x3 matrix")
        D = _first_mat(fs, _D_KEYS)
        if D is None:
            raise FormatError(path, "distortion_coefficients", "missing (also looked for camera_distortion)")
        D = D.reshape(-1)
        if D.size not in (0, 4, 5, 8):
            if D.size > 8 and not np.any(D[8:]):
                D = D[:8]
            elif D.size < 5:
                D = np.pad(D, (0, 5 - D.size))
            else:
                raise FormatError(path, "distortion_coefficients", f"has {D.size} coefficients (need 4, 5 or 8)")
        w = _first_real(fs, _W_KEYS)
        h = _first_real(fs, _H_KEYS)
    finally:
        fs.release()
    if w is None or h is None:
        if image_size is None:
            raise FormatError(path, "image_width", "missing, and no image size to assume")
        w, h = image_size
    size = {k: int(v) if float(v).is_integer() else v for k, v in (("width", w), ("height", h))}
    return CameraModel.from_dict(dict(size, K=K.tolist(), dist=D.tolist()), "camera", path)


def _first_mat(fs, keys):
    for k in keys:
        node = fs.getNode(k)
        if not node.empty():
            m = node.mat()
            if m is not None:
                return np.asarray(m, float)
    return None


def _first_real(fs, keys):
    for k in keys:
        node = fs.getNode(k)
        if not node.empty() and (node.isInt() or node.isReal()):
            return node.real()
    return None
