"""The paper's sequential method (Vanherck et al. 2025): camera (Zhang, all board views) -> mirror plane
(RANSAC plane fit) -> projector (Zhang on board points, then stereo with fixed intrinsics, chained
through the mirror). calib.pipeline registers it as the "paper" method; calib.joint.method starts from it.

`progress`, when given, is called as progress(done, total, label); `label` names the stage.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from calib.errors import CalibrationError
from calib.models.camera import CameraModel
from calib.models.observations import VIEW_MIRROR, SessionObservations
from calib.models.result import CalibrationResult
from calib.paper.camera import CameraCalibration, calibrate_camera
from calib.paper.mirror import MirrorCalibration, calibrate_mirror
from calib.paper.projector import ProjectorCalibration, calibrate_projector
from calib.models.vocab import CalibrationMethod

Progress = Callable[[int, int, str], None]

#: Projector views needed before any stage runs (the projector stage needs >= 4; the paper's protocol
#: takes several poses at each of 13 pattern positions).
MIN_PROJECTOR_VIEWS = 4

PAPER_STAGES = ("camera", "mirror", "projector")


def check_observations(obs: SessionObservations) -> None:
    """Fail early, with a message a user can act on, when a session cannot be calibrated at all."""
    bad = non_finite_captures(obs)
    if bad:
        raise CalibrationError(
            f"non-finite (NaN or infinite) pixel coordinates in {len(bad)} capture(s): {', '.join(bad[:5])}"
            f"{' ...' if len(bad) > 5 else ''}; the session's pattern points or detections are corrupt: retake "
            "or delete these captures", code="non_finite")
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


def non_finite_captures(obs: SessionObservations) -> list[str]:
    """Ids of the captures whose observations (board corners, pattern points on either side) hold NaN or
    infinity."""

    def finite(*arrays):
        return all(a is None or np.all(np.isfinite(np.asarray(a, float))) for a in arrays)

    bad = []
    for pv in obs.projector_views:
        if not finite(None if pv.board is None else pv.board.corners_px, pv.pattern_cam_px, pv.pattern_proj_px):
            bad.append(pv.capture_id)
    for mv in obs.mirror_views:
        if not finite(*(None if b is None else b.corners_px for b in (mv.real, mv.virtual))):
            bad.append(mv.capture_id)
    return bad


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
    return [{"capture_id": s.capture_id, "image": s.image, "stage": "detection", "reason": s.reason,
             **({"copy_of": s.copy_of} if s.copy_of else {})} for s in obs.skipped]


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
    return assemble_result(obs, CalibrationMethod.PAPER, cc, mc, pc, timing)
