"""Stage 3: the projector's intrinsics and its pose relative to the camera.

Per projector view:
  1. the board pose from its ChArUco corners (PnP with the camera's intrinsics; through the mirror the
     pose of the virtual board, calib.paper.board_pose);
  2. the camera pixels of the projected pattern mapped onto the board plane EXACTLY: each pixel's ray
     (lens distortion undone by CameraModel.rays) meets the plane of the board as seen (the virtual
     board for a mirrored view), and the hit point is un-mirrored into board coordinates;
then, over all views:
  3. the projector's intrinsics by Zhang's method (cv2.calibrateCamera) on (board points, projector
     pixels);
  4. its pose once over all views: cv2.stereoCalibrate with CALIB_FIX_INTRINSIC between the camera and
     the projector on the same board points. For mirrored views the first camera is the flipped virtual
     camera V' (CameraModel.flipped(), pixels x -> (W-1)-x), which gives T_proj_V', and
     T_cam_proj = S @ FLIP_X @ T_V'_proj (docs/GEOMETRY.md). Without a mirror (the paper's overlapping
     control) the first camera is the camera itself and T_cam_proj = inv(T_proj_cam).

Entry point: `calibrate_projector(obs, camera, mirror) -> ProjectorCalibration`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType

import cv2
import numpy as np

from calib.paper.board_pose import (MIN_CORNERS, BoardPose, calibrate_zhang, outlier_limit, point_residuals, solve_board_pose,
                              usable_reason, zhang_flags)
from calib.errors import CalibrationError
from calib.models.camera import CameraModel
from calib.models.observations import VIEW_DIRECT, VIEW_MIRROR, ProjectorView, SessionObservations
from calib.models.result import MirrorPlane
from calib.transforms import FLIP_X, T_from_rvec_tvec, invert_T, make_T, rotation_angle_deg, transform_points
from calib.models.vocab import LengthUnit

#: Fewer usable projector views than this and the projector cannot be calibrated.
MIN_VIEWS = 4
#: Fewer pattern points than this in a view and it is not used.
MIN_PATTERN_POINTS = 6
#: Board pose RMS above this (pixels) means a misdetected board: the view is not used.
MAX_BOARD_RMS_PX = 3.0

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)


@dataclass(frozen=True, eq=False)
class ProjectorCalibration:
    projector: CameraModel
    T_cam_proj: np.ndarray
    T_proj_ref: np.ndarray  # what stereoCalibrate estimated: T_proj_V' (mirror) or T_proj_cam (direct)
    rms_px: float  # projector calibrateCamera RMS (pixels)
    stereo_rms_px: float  # stereoCalibrate RMS over both devices (pixels)
    per_view: tuple  # dicts: stage, capture_id, board_rms_px, proj_rms_px, stereo_cam_px, stereo_proj_px, ...
    board_poses: MappingProxyType  # capture_id -> T_cam_board (physical board)
    board_points: MappingProxyType  # capture_id -> (N, 3) board-frame pattern points (z = 0)
    mirrored: bool
    skipped: tuple = ()
    std_intrinsics: np.ndarray | None = None
    diagnostics: dict = field(default_factory=dict)


def pattern_points_on_board(camera: CameraModel, pose: BoardPose, uv: np.ndarray) -> np.ndarray:
    """Board-frame points (z = 0) seen at camera pixels `uv`, exact with lens distortion: rays through
    the pixels meet the plane of the board as seen (the virtual board when mirrored), un-mirrored."""
    rays = camera.rays(uv)
    T_view_cam = invert_T(pose.T_cam_view)
    dirs = rays @ T_view_cam[:3, :3].T
    o = T_view_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / dirs[:, 2]
    X = o + t[:, None] * dirs
    X[~(t > 0)] = np.nan
    if pose.mirrored:
        X[:, 0] = -X[:, 0]
    X[:, 2] = 0.0
    return X


def calibrate_projector(obs: SessionObservations, camera: CameraModel, mirror: MirrorPlane | None, *,
                        fix_k3: bool = False, fix_tangential: bool = False, rational: bool = False,
                        min_views: int = MIN_VIEWS, min_corners: int = MIN_CORNERS,
                        reject_outliers: bool = True) -> ProjectorCalibration:
    """Calibrate the projector (intrinsics and T_cam_proj) from the projector views of `obs`.

    With `reject_outliers`, pattern points whose projector residual after Zhang exceeds
    calib.paper.board_pose.outlier_limit (max(6 x median, 2 px)) are dropped, worst first, and Zhang rerun (a misdetected circle
    otherwise drags the intrinsics by tens of pixels); the counts are in per_view / diagnostics."""
    mirrored = obs.view == VIEW_MIRROR
    if obs.view not in (VIEW_MIRROR, VIEW_DIRECT):
        raise CalibrationError(f"unknown view '{obs.view}' (must be '{VIEW_MIRROR}' or '{VIEW_DIRECT}')")
    if mirrored and mirror is None:
        raise CalibrationError(
            "the projector images were seen through the mirror, so the mirror plane is needed to chain the "
            "projector's pose to the camera; calibrate the mirror first (capture mirror-calibration images)")
    spec = obs.projector_board
    skipped, views = [], []
    for v in obs.projector_views:
        reason = _view_reason(v, spec, mirrored, min_corners)
        if reason is not None:
            skipped.append({"capture_id": v.capture_id, "stage": "projector", "reason": reason})
            continue
        pose = solve_board_pose(camera, spec, v.board)
        if pose.rms_px > MAX_BOARD_RMS_PX:
            skipped.append({"capture_id": v.capture_id, "stage": "projector",
                            "reason": f"board pose does not fit its corners (RMS {pose.rms_px:.2f} px): "
                                      f"misdetection or wrong board spec"})
            continue
        Xb = pattern_points_on_board(camera, pose, v.pattern_cam_px)
        ok = np.all(np.isfinite(Xb), axis=1)
        if ok.sum() < MIN_PATTERN_POINTS:
            skipped.append({"capture_id": v.capture_id, "stage": "projector",
                            "reason": "the pattern's camera rays miss the board plane (board seen edge-on?)"})
            continue
        views.append((v, pose, Xb[ok], np.asarray(v.pattern_cam_px)[ok], np.asarray(v.pattern_proj_px)[ok]))
    if len(views) < min_views:
        raise CalibrationError(
            f"cannot calibrate the projector: only {len(views)} usable projector view(s) (need at least "
            f"{min_views}; the paper's protocol takes several board poses for each of the 13 pattern positions)"
            + (f"; skipped: {_summarize(skipped)}" if skipped else ""))

    # -- projector intrinsics (Zhang) --------------------------------------------------------------
    flags = zhang_flags(fix_k3, rational, fix_tangential)
    keep = [np.ones(len(X), bool) for _, _, X, _, _ in views]
    n_rejected = 0

    def zhang():
        objp = [X[k].astype(np.float32) for (_, _, X, _, _), k in zip(views, keep)]
        projp = [np.ascontiguousarray(q[k], np.float32) for (*_, q), k in zip(views, keep)]
        try:
            return objp, projp, calibrate_zhang(objp, projp, obs.projector_size, flags)
        except cv2.error as e:
            raise CalibrationError(f"projector calibration failed in OpenCV ({e.err}); the board poses are probably "
                                   f"degenerate: tilt the board differently between captures") from None

    objp, projp, (p_rms, Kp, Dp, p_rv, p_tv, std_i, p_pve) = zhang()
    for _round in range(6 if reject_outliers else 0):
        res = point_residuals(Kp, Dp, p_rv, p_tv, objp, projp)
        allres = np.concatenate(res)
        limit = outlier_limit(allres)
        if not np.any(allres > limit):
            break
        for k, r in zip(keep, res):
            # only the worst points of a view go in one round: one gross outlier drags its view's pose
            # and inflates its neighbours' residuals, which come back once it is gone
            out = (r > limit) & (r >= 0.5 * r.max())
            k[np.flatnonzero(k)[out]] = False
            n_rejected += int(out.sum())
        for i in range(len(views) - 1, -1, -1):  # a view left with too few points goes
            if keep[i].sum() < MIN_PATTERN_POINTS:
                skipped.append({"capture_id": views[i][0].capture_id, "stage": "projector",
                                "reason": f"{int((~keep[i]).sum())} of {len(keep[i])} pattern points inconsistent "
                                          f"with the other views (misdetected pattern?)"})
                del views[i], keep[i]
        if len(views) < min_views:
            raise CalibrationError(
                f"cannot calibrate the projector: only {len(views)} projector view(s) with consistent pattern "
                f"points (need at least {min_views}); check the pattern detections")
        objp, projp, (p_rms, Kp, Dp, p_rv, p_tv, std_i, p_pve) = zhang()
    views = [(v, pose, X[k], u[k], q[k], k) for (v, pose, X, u, q), k in zip(views, keep)]
    Dp = np.asarray(Dp, float).reshape(-1)
    if Dp.size not in (4, 5, 8):
        Dp = Dp[:8] if Dp.size > 8 else np.pad(Dp, (0, 5 - Dp.size))
    projector = CameraModel(obs.projector_size[0], obs.projector_size[1], Kp, Dp)

    # -- pose once over all views (stereo, intrinsics fixed) -----------------------------------------
    ref = camera.flipped() if mirrored else camera
    camp = [np.ascontiguousarray(camera.flip_points(u) if mirrored else u, np.float32) for _, _, _, u, _, _ in views]
    try:
        s_rms, _, _, _, _, R, T, _E, _F, s_rv, s_tv, s_pve = cv2.stereoCalibrateExtended(
            objp, camp, projp, np.array(ref.K), np.array(ref.dist), np.array(projector.K), np.array(projector.dist),
            obs.camera_size, None, None, flags=cv2.CALIB_FIX_INTRINSIC, criteria=_CRITERIA)
    except cv2.error as e:
        raise CalibrationError(f"stereo calibration failed in OpenCV ({e.err}); check that the projector images "
                               f"show the pattern on the board") from None
    T_proj_ref = make_T(R, np.asarray(T, float).reshape(3))
    S = mirror.reflection() if mirrored else np.eye(4)
    if mirrored:
        T_cam_proj = S @ FLIP_X @ invert_T(T_proj_ref)
    else:
        T_cam_proj = invert_T(T_proj_ref)

    # -- per-view records ------------------------------------------------------------------------------
    per_view, poses, points = [], {}, {}
    s_pve = np.asarray(s_pve, float).reshape(len(views), -1)
    for k, (v, pose, Xb, u, q, kept) in enumerate(views):
        T_cb = pose.physical(S if mirrored else None)
        poses[v.capture_id] = _ro(T_cb)
        points[v.capture_id] = _ro(Xb)
        # this view's own estimate of T_cam_proj (board pose from the camera, projector pose by PnP)
        rec = {"stage": "projector", "capture_id": v.capture_id, "pattern_position": v.pattern_position,
               "n_corners": int(len(v.board.ids)), "n_points": int(len(Xb)),
               "n_rejected_points": int((~kept).sum()), "n_rejected_corners": pose.n_outliers,
               "board_rms_px": pose.rms_px,
               "proj_rms_px": float(np.asarray(p_pve).reshape(-1)[k]),
               "stereo_cam_px": float(s_pve[k, 0]), "stereo_proj_px": float(s_pve[k, -1])}
        ok, rvec, tvec = cv2.solvePnP(Xb, np.ascontiguousarray(q, float), np.array(projector.K),
                                      np.array(projector.dist), flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            T_pb = T_from_rvec_tvec(rvec, tvec)
            T_i = T_cb @ invert_T(T_pb)
            rec["extrinsic_dev_mm" if obs.units == LengthUnit.MM else "extrinsic_dev"] = float(
                np.linalg.norm(T_i[:3, 3] - T_cam_proj[:3, 3]))
            rec["extrinsic_dev_deg"] = rotation_angle_deg(T_i[:3, :3].T @ T_cam_proj[:3, :3])
        per_view.append(rec)
    std_i = np.asarray(std_i, float).reshape(-1).copy()
    std_i.setflags(write=False)
    diag = {"n_views": len(views), "n_points": int(sum(len(X) for _, _, X, _, _, _ in views)),
            "n_rejected_points": n_rejected,
            "flags": {"fix_k3": fix_k3, "fix_tangential": fix_tangential, "rational": rational}}
    return ProjectorCalibration(projector, _ro(T_cam_proj), _ro(T_proj_ref), float(p_rms), float(s_rms),
                                tuple(per_view), MappingProxyType(poses), MappingProxyType(points), mirrored,
                                tuple(skipped), std_i, diag)


def _view_reason(v: ProjectorView, spec, mirrored: bool, min_corners: int) -> str | None:
    reason = usable_reason(spec, v.board, min_corners)
    if reason is not None:
        return f"board: {reason}"
    if bool(v.board.mirrored) != mirrored:
        return ("board seen directly in a mirrored session" if mirrored
                else "board seen through the mirror in a direct-view session")
    n = len(v.pattern_cam_px)
    if n < MIN_PATTERN_POINTS:
        return f"only {n} pattern points (need {MIN_PATTERN_POINTS})"
    if not (np.all(np.isfinite(v.pattern_cam_px)) and np.all(np.isfinite(v.pattern_proj_px))):
        return "non-finite pattern coordinates"
    return None


def _summarize(skipped) -> str:
    reasons: dict[str, int] = {}
    for s in skipped:
        reasons[s["reason"]] = reasons.get(s["reason"], 0) + 1
    return "; ".join(f"{n} x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])


def _ro(a):
    a = np.array(a, float)
    a.setflags(write=False)
    return a


__all__ = ["ProjectorCalibration", "calibrate_projector", "pattern_points_on_board", "transform_points"]
