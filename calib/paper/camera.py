"""Stage 1: the camera's intrinsics (Zhang's method via cv2.calibrateCamera) from the session's own
images: every ChArUco view, direct and through the mirror, in one calibration.

A board seen through the mirror is a rigid view of the mirrored board (calib.paper.board_pose), so its
corners enter the same calibrateCamera call with object points (-x, y, 0) and their ORIGINAL pixel
coordinates; the intrinsics that come out are those of the real camera, no flipping needed.

Entry point: `calibrate_camera(obs, camera=None, ...) -> CameraCalibration`. With a pre-calibrated
`camera`, nothing is estimated: the board poses and residuals are computed with it (PnP) so the
stage still reports its RMS.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import MappingProxyType

import cv2
import numpy as np

from calib.paper.board_pose import (MIN_CORNERS, BoardPose, calibrate_zhang, outlier_limit, solve_board_pose,
                              usable_reason, view_object_points, zhang_flags)
from calib.errors import CalibrationError
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import BoardObservation, SessionObservations
from calib.transforms import T_from_rvec_tvec, transform_points

#: Fewer usable board views than this and the camera cannot be calibrated from the session.
MIN_VIEWS = 3


@dataclass(frozen=True)
class BoardView:
    """One ChArUco observation of the session, with a key unique in the session."""

    key: str  # capture id, plus ":real" / ":virtual" for the two boards of a real-virtual image
    capture_id: str
    role: str  # "projector", "real", "virtual"
    spec: CharucoSpec
    obs: BoardObservation


def board_views(obs: SessionObservations) -> list[BoardView]:
    """Every board observation of a session: projector views, then mirror views (real, virtual)."""
    views = [BoardView(v.capture_id, v.capture_id, "projector", obs.projector_board, v.board)
             for v in obs.projector_views if v.board is not None]
    mspec = obs.mirror_board or obs.projector_board
    for m in obs.mirror_views:
        if m.real is not None:
            views.append(BoardView(f"{m.capture_id}:real", m.capture_id, "real", mspec, m.real))
        if m.virtual is not None:
            views.append(BoardView(f"{m.capture_id}:virtual", m.capture_id, "virtual", mspec, m.virtual))
    return views


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    camera: CameraModel
    rms_px: float  # OpenCV's RMS over all corners of all used views (pixels)
    per_view: tuple  # dicts: stage, key, capture_id, role, mirrored, n_points, rms_px, max_px
    poses: MappingProxyType  # key -> BoardPose (the board as seen; virtual board for mirrored views)
    precalibrated: bool = False
    skipped: tuple = ()  # dicts: capture_id, stage, reason
    std_intrinsics: np.ndarray | None = None  # 1-sigma of fx, fy, cx, cy, k1, k2, p1, p2, k3, ... (OpenCV)
    n_views: int = 0
    n_points: int = 0
    flags: dict = field(default_factory=dict)


def calibrate_camera(obs: SessionObservations, camera: CameraModel | None = None, *, fix_k3: bool = False,
                     rational: bool = False, fix_tangential: bool = False, min_views: int = MIN_VIEWS,
                     min_corners: int = MIN_CORNERS, reject_outlier_views: bool = True,
                     reject_outlier_points: bool = True) -> CameraCalibration:
    """Calibrate the camera from every board view of the session (or evaluate a given `camera`).

    Views with too few corners are skipped (reported in `skipped`). With `reject_outlier_views`, a view
    whose RMS is far above the others' (> max(5 x median, 2 px)) is dropped and the calibration
    rerun once: such a view is almost always a misdetection. With `reject_outlier_points`, single corners
    beyond calib.paper.board_pose.outlier_limit (max(6 x median, 2 px)) are then dropped, worst first, and the
    calibration rerun (counts in per_view[...]["n_rejected_points"])."""
    W, H = obs.camera_size
    if camera is not None and (camera.width, camera.height) != (W, H):
        raise CalibrationError(
            f"the given camera intrinsics are for {camera.width}x{camera.height} images but the session's "
            f"images are {W}x{H}; give intrinsics calibrated at the session's resolution")
    skipped, used = [], []
    for v in board_views(obs):
        reason = usable_reason(v.spec, v.obs, min_corners)
        if reason is None:
            used.append(v)
        else:
            skipped.append({"capture_id": v.capture_id, "stage": "camera", "view": v.key, "reason": reason})

    flag_info = {"fix_k3": fix_k3, "rational": rational, "fix_tangential": fix_tangential}
    if camera is not None:
        poses = {v.key: solve_board_pose(camera, v.spec, v.obs) for v in used}
        return _result(camera, None, used, poses, skipped, True, None, flag_info)

    if len(used) < min_views:
        raise CalibrationError(
            f"cannot calibrate the camera: only {len(used)} usable board view(s) (need at least {min_views}, "
            f"ideally 10 or more at varied tilts); capture more images with the whole board visible, or give "
            f"pre-calibrated intrinsics with --camera-intrinsics")
    flags = zhang_flags(fix_k3, rational, fix_tangential)

    cam, rms, poses, std = _zhang(used, (W, H), flags)
    if reject_outlier_views and len(used) > min_views:
        rms_v = np.array([poses[v.key].rms_px for v in used])
        limit = max(5.0 * float(np.median(rms_v)), 2.0)
        bad = [v for v, r in zip(used, rms_v) if r > limit]
        if bad and len(used) - len(bad) >= min_views:
            for v, r in zip(used, rms_v):
                if r > limit:
                    skipped.append({"capture_id": v.capture_id, "stage": "camera", "view": v.key,
                                    "reason": f"reprojection error {r:.2f} px after camera calibration (others: "
                                              f"median {np.median(rms_v):.2f} px): probably a misdetection"})
            used = [v for v in used if v not in bad]
            cam, rms, poses, std = _zhang(used, (W, H), flags)
    rejected: dict[str, int] = {}
    for _round in range(6 if reject_outlier_points else 0):
        limit = outlier_limit(np.concatenate([poses[v.key].residuals_px for v in used]))
        changed, kept = False, []
        for v in used:
            r = poses[v.key].residuals_px
            out = (r > limit) & (r >= 0.5 * r.max())
            if out.any():  # the worst corners of a view go first (one outlier drags its view's pose)
                changed = True
                rejected[v.key] = rejected.get(v.key, 0) + int(out.sum())
                v = replace(v, obs=BoardObservation(v.obs.ids[~out], v.obs.corners_px[~out], v.obs.mirrored))
                reason = usable_reason(v.spec, v.obs, min_corners)
                if reason is not None:
                    skipped.append({"capture_id": v.capture_id, "stage": "camera", "view": v.key,
                                    "reason": f"after dropping {rejected[v.key]} inconsistent corner(s): {reason}"})
                    continue
            kept.append(v)
        if not changed:
            break
        if len(kept) < min_views:
            raise CalibrationError(f"cannot calibrate the camera: only {len(kept)} board view(s) with consistent "
                                   f"corners (need at least {min_views}); check the board detections")
        used = kept
        cam, rms, poses, std = _zhang(used, (W, H), flags)
    return _result(cam, rms, used, poses, skipped, False, std, flag_info, rejected)


def _zhang(used: list[BoardView], size, flags):
    objp = [view_object_points(v.spec, v.obs).astype(np.float32) for v in used]
    imgp = [np.ascontiguousarray(v.obs.corners_px, np.float32) for v in used]
    try:
        rms, K, dist, rvecs, tvecs, std_i, _pve = calibrate_zhang(objp, imgp, size, flags)
    except cv2.error as e:
        raise CalibrationError(f"camera calibration failed in OpenCV ({e.err}); the board views are probably "
                               f"degenerate (all parallel to the image): capture the board at varied tilts") from None
    dist = np.asarray(dist, float).reshape(-1)
    if dist.size not in (4, 5, 8):
        dist = dist[:8] if dist.size > 8 else np.pad(dist, (0, 5 - dist.size))
    cam = CameraModel(size[0], size[1], K, dist)
    poses = {}
    for v, o, i, r, t in zip(used, objp, imgp, rvecs, tvecs):
        T = T_from_rvec_tvec(r, t)
        res = np.linalg.norm(cam.project(transform_points(T, o)) - v.obs.corners_px, axis=1)
        poses[v.key] = BoardPose(T, bool(v.obs.mirrored), res)
    return cam, float(rms), poses, np.asarray(std_i, float).reshape(-1)


def _result(cam, rms, used, poses, skipped, pre, std, flag_info, rejected=None) -> CameraCalibration:
    rejected = rejected or {}
    per_view = []
    all_res = []
    for v in used:
        p = poses[v.key]
        all_res.append(p.residuals_px if p.inliers is None else p.residuals_px[p.inliers])
        per_view.append({"stage": "camera", "key": v.key, "capture_id": v.capture_id, "role": v.role,
                         "mirrored": bool(v.obs.mirrored), "n_points": int(len(v.obs.ids)),
                         "n_rejected_points": rejected.get(v.key, 0) + p.n_outliers,
                         "rms_px": p.rms_px, "max_px": float(np.max(p.residuals_px))})
    res = np.concatenate(all_res) if all_res else np.zeros(0)
    if rms is None:
        rms = float(np.sqrt(np.mean(res**2))) if res.size else float("nan")
    if std is not None:
        std = std.copy()
        std.setflags(write=False)
    return CameraCalibration(cam, float(rms), tuple(per_view), MappingProxyType(dict(poses)), pre, tuple(skipped),
                             std, len(used), int(res.size), flag_info)
