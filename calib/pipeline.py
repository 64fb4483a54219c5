"""The calibration pipeline: observations (or a session folder) in, CalibrationResult out.

Methods are registered by name in METHODS (name -> function(obs, camera, progress) -> CalibrationResult).
"paper" is the method of Vanherck et al.: camera (Zhang, all board views) -> mirror plane (RANSAC plane
fit) -> projector (Zhang on board points, then stereo with fixed intrinsics, chained through the mirror).
Another method registers itself with one line: `METHODS["joint"] = calibrate_joint`.

`progress`, when given, is called as progress(done, total, label) (the same convention as
calib.detect.detect_session); `label` names the stage.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from calib.camera import CameraModel
from calib.camera_calib import CameraCalibration, calibrate_camera
from calib.errors import CalibrationError, FormatError
from calib.mirror_calib import MirrorCalibration, calibrate_mirror
from calib.observations import VIEW_MIRROR, SessionObservations
from calib.projector_calib import ProjectorCalibration, calibrate_projector
from calib.result import CalibrationResult

Progress = Callable[[int, int, str], None]
Method = Callable[[SessionObservations, "CameraModel | None", "Progress | None"], CalibrationResult]

#: Projector views needed before any stage runs (the projector stage needs >= 4; the paper's protocol
#: takes several poses at each of 13 pattern positions).
MIN_PROJECTOR_VIEWS = 4

PAPER_STAGES = ("camera", "mirror", "projector")


def check_observations(obs: SessionObservations) -> None:
    """Fail early, with a message a user can act on, when a session cannot be calibrated at all."""
    n = len(obs.projector_views)
    if n < MIN_PROJECTOR_VIEWS:
        why = ""
        if obs.skipped:
            reasons = sorted({s.reason for s in obs.skipped})
            why = f" ({len(obs.skipped)} image(s) skipped: {'; '.join(reasons[:3])})"
        raise CalibrationError(
            f"only {n} usable projector image(s){why}; need at least {MIN_PROJECTOR_VIEWS} (the paper's protocol: "
            f"several board poses for each of the {obs.pattern.positions} pattern positions)")
    if obs.view == VIEW_MIRROR and not obs.mirror_views:
        raise CalibrationError(
            "the projector images were taken through the mirror but the session has no usable mirror-calibration "
            "images, so the mirror plane (and with it the projector's pose) cannot be estimated; capture "
            "real-virtual images (board seen directly and in the mirror) or real-mirror images (board lying on it)")


def paper_stages(obs: SessionObservations, camera: CameraModel | None = None, progress: Progress | None = None,
                 *, projector_fix_k3: bool = True, mirror_threshold: float | None = None
                 ) -> tuple[CameraCalibration, MirrorCalibration | None, ProjectorCalibration, dict]:
    """Run the paper's three stages; returns their results and the time each took (seconds)."""
    check_observations(obs)
    mirrored = obs.view == VIEW_MIRROR
    stages = [s for s in PAPER_STAGES if mirrored or s != "mirror"]
    timing = {}

    def tick(i, label):
        if progress is not None:
            progress(i, len(stages), label)

    tick(0, "starting")  # then each call names the stage just finished (done of total)
    t0 = time.perf_counter()
    cc = calibrate_camera(obs, camera)
    timing["camera"] = time.perf_counter() - t0
    tick(1, "camera")
    mc = None
    if mirrored:
        t0 = time.perf_counter()
        mc = calibrate_mirror(obs, cc.camera, threshold=mirror_threshold)
        timing["mirror"] = time.perf_counter() - t0
        tick(2, "mirror")
    t0 = time.perf_counter()
    pc = calibrate_projector(obs, cc.camera, mc.plane if mc is not None else None, fix_k3=projector_fix_k3)
    timing["projector"] = time.perf_counter() - t0
    tick(len(stages), "projector")
    return cc, mc, pc, timing


def detection_skips(obs: SessionObservations) -> list[dict]:
    return [{"capture_id": s.capture_id, "image": s.image, "stage": "detection", "reason": s.reason}
            for s in obs.skipped]


def assemble_result(obs: SessionObservations, method: str, cc: CameraCalibration, mc: MirrorCalibration | None,
                    pc: ProjectorCalibration, timing: dict) -> CalibrationResult:
    """A CalibrationResult from the paper stages' outputs (other methods may reuse it, then refine)."""
    rms = {"camera": cc.rms_px, "mirror_plane": None if mc is None else mc.rms, "projector": pc.rms_px,
           "stereo": pc.stereo_rms_px}
    per_view = list(cc.per_view) + (list(mc.per_view) if mc is not None else []) + list(pc.per_view)
    skipped = detection_skips(obs) + list(cc.skipped) + (list(mc.skipped) if mc is not None else []) + list(pc.skipped)
    diag = {
        "timing_s": {k: round(float(v), 4) for k, v in timing.items()},
        "rms_units": {"camera": "px", "mirror_plane": obs.units, "projector": "px", "stereo": "px"},
        "camera": {"precalibrated": cc.precalibrated, "n_views": cc.n_views, "n_points": cc.n_points,
                   "flags": cc.flags,
                   "std_intrinsics": None if cc.std_intrinsics is None else cc.std_intrinsics.tolist()},
        "projector": dict(pc.diagnostics, std_intrinsics=None if pc.std_intrinsics is None else pc.std_intrinsics.tolist()),
    }
    if mc is not None:
        diag["mirror"] = {"method": mc.method, "n_inliers": mc.n_inliers, "n_outliers": mc.n_outliers,
                          "threshold": mc.threshold, "board_thickness": mc.board_thickness, **mc.diagnostics}
    return CalibrationResult(camera=cc.camera, projector=pc.projector, T_cam_proj=pc.T_cam_proj,
                             mirror=None if mc is None else mc.plane, units=obs.units, method=method, rms=rms,
                             per_view=tuple(per_view), skipped=tuple(skipped), uncertainty=None, diagnostics=diag)


def calibrate_paper(obs: SessionObservations, camera: CameraModel | None = None,
                    progress: Progress | None = None) -> CalibrationResult:
    """The paper's method (Vanherck et al. 2025), stage by stage."""
    cc, mc, pc, timing = paper_stages(obs, camera, progress)
    return assemble_result(obs, "paper", cc, mc, pc, timing)


#: name -> function(obs, camera, progress) -> CalibrationResult
METHODS: dict[str, Method] = {"paper": calibrate_paper}

from calib.joint import calibrate_joint  # noqa: E402  (paper first, then one joint refinement: docs/JOINT.md)

METHODS["joint"] = calibrate_joint


def calibrate_observations(obs: SessionObservations, method: str = "joint", camera: CameraModel | None = None,
                           progress: Progress | None = None, method_options: dict | None = None) -> CalibrationResult:
    """Calibrate from detected observations with a registered method; `camera` skips the camera stage."""
    fn = METHODS.get(method)
    if fn is None:
        raise CalibrationError(f"unknown calibration method '{method}' (available: {', '.join(sorted(METHODS))})")
    t0 = time.perf_counter()
    result = fn(obs, camera, progress, **method_options) if method_options else fn(obs, camera, progress)
    diag = dict(result.diagnostics)
    timing = dict(diag.get("timing_s", {}))
    timing["total"] = round(time.perf_counter() - t0, 4)
    diag["timing_s"] = timing
    return result.with_(diagnostics=diag)


def calibrate_session(folder, method: str = "joint", camera_intrinsics=None, workers: int = 2,
                      progress: Progress | None = None, detect_progress: Progress | None = None,
                      method_options: dict | None = None, detect_cache: str = "use") -> CalibrationResult:
    """Detect and calibrate a session folder. `camera_intrinsics`: None, a CameraModel, or a file
    (calibration.json or OpenCV YAML, see load_camera_intrinsics). `detect_progress` (default:
    `progress`) follows detection, `progress` the calibration stages. `detect_cache`: "use" (reuse
    the detections of earlier runs kept in the session folder), "refresh" or "off" (detect_session)."""
    from calib.detect import detect_session
    from calib.session import SessionStore

    store = SessionStore.open(folder)
    t0 = time.perf_counter()
    obs = detect_session(store, workers, detect_progress if detect_progress is not None else progress,
                         cache=detect_cache)
    t_detect = time.perf_counter() - t0
    camera = camera_intrinsics
    if camera is not None and not isinstance(camera, CameraModel):
        camera = load_camera_intrinsics(camera, obs.camera_size)
    result = calibrate_observations(obs, method, camera, progress, method_options)
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
    return result.with_(skipped=tuple(skipped), diagnostics=diag)


# ---- camera intrinsics from a file ------------------------------------------------------------------
_K_KEYS = ("camera_matrix", "cameraMatrix", "K")
_D_KEYS = ("distortion_coefficients", "camera_distortion", "dist_coeffs", "distCoeffs", "D")
_W_KEYS = ("image_width", "camera_width", "width")
_H_KEYS = ("image_height", "camera_height", "height")


def load_camera_intrinsics(path, image_size: tuple[int, int] | None = None) -> CameraModel:
    """Camera intrinsics from a calibration.json (its "camera") or an OpenCV FileStorage YAML/XML with
    camera_matrix and distortion_coefficients (also accepted: camera_distortion, dist_coeffs) and
    optionally image_width / image_height (or camera_width / camera_height). Without a size in the file,
    `image_size` is used."""
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "<file>", "does not exist")
    if path.suffix.lower() == ".json":
        import json

        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(path, "<file>", f"is not valid JSON (line {e.lineno}: {e.msg})") from None
        if not isinstance(data, dict):
            raise FormatError(path, "<root>", "must be a JSON object")
        cam = data.get("camera", data)
        if isinstance(cam, dict) and "width" not in cam and image_size is not None and "K" in cam:
            cam = dict(cam, width=image_size[0], height=image_size[1])
        return CameraModel.from_dict(cam, "camera" if "camera" in data else "<root>", path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error:
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
    return CameraModel(int(w), int(h), K, D)


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
