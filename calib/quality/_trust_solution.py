"""The trust check's judgement of a solved rig (behind calib.quality.trust): finite values, residuals,
where the mirror and the projector are, the pattern points re-derived from the result, and the
uncertainty and conditioning of its covariance."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from calib.models.boards import MM_PER_UNIT as _MM_PER_UNIT
from calib.models.camera import CameraModel
from calib.transforms import invert_T, rays_to_board_plane
from calib.models.vocab import CalibrationMethod

if TYPE_CHECKING:
    from calib.quality.trust import TrustThresholds


def non_finite_parameters(result) -> list[str]:
    bad = []
    for name, arr in (("camera K", result.camera.K), ("camera distortion", result.camera.dist),
                      ("projector K", result.projector.K), ("projector distortion", result.projector.dist),
                      ("T_cam_proj", result.T_cam_proj)):
        if not np.all(np.isfinite(np.asarray(arr, float))):
            bad.append(name)
    if result.mirror is not None and not (np.all(np.isfinite(result.mirror.normal)) and math.isfinite(result.mirror.d)):
        bad.append("the mirror plane")
    for k, v in (result.rms or {}).items():
        if isinstance(v, (int, float)) and not math.isfinite(v):
            bad.append(f"RMS '{k}'")
    return bad


def check_rms(result, th: TrustThresholds, fail, metrics: dict) -> None:
    rms = {k: v for k, v in (result.rms or {}).items() if isinstance(v, (int, float))}
    # joint: every class in camera pixels; paper: camera (camera px), projector and stereo (projector px),
    # mirror_plane (board units: not a pixel residual)
    for key, v in rms.items():
        if key == "mirror_plane":
            continue
        projector_px = result.method != CalibrationMethod.JOINT and key in ("projector", "stereo")
        limit = th.rms_projector_px if projector_px else th.rms_camera_px
        metrics[f"rms.{key}"] = float(v)
        if v > limit:
            unit = "projector px" if projector_px else "px"
            fail("rms_high", f"the {key} RMS of {v:.3g} {unit} is far above the detection noise (limit "
                 f"{limit:g}): the observations do not fit one rig", v, limit)


def check_geometry(result, th: TrustThresholds, fail, metrics: dict, lit_from_poses: bool = True) -> None:
    T = np.asarray(result.T_cam_proj, float)
    proj_centre = T[:3, 3]
    mm = _MM_PER_UNIT.get(result.units)
    dist = float(np.linalg.norm(proj_centre))
    metrics["projector_distance"] = dist
    if mm is not None and dist * mm > th.max_projector_distance_mm:
        fail("projector_too_far", f"the projector is {dist * mm / 1000:.3g} m from the camera (limit "
             f"{th.max_projector_distance_mm / 1000:g} m)", dist * mm, th.max_projector_distance_mm)
    if result.mirror is not None:
        n = np.asarray(result.mirror.normal, float)
        cam = result.camera
        us, vs = np.meshgrid(np.linspace(0, cam.width - 1, 9), np.linspace(0, cam.height - 1, 9))
        rays = cam.rays(np.column_stack([us.ravel(), vs.ravel()]))
        hit = float(np.mean(rays @ n < 0))  # the plane's camera side faces the camera: ray meets it at s > 0
        metrics["mirror_fraction_of_view"] = hit
        d_mm = float(result.mirror.d) * (mm if mm is not None else 1.0)
        metrics["mirror_distance_mm"] = d_mm
        if d_mm < th.min_mirror_distance_mm:
            fail("mirror_behind_camera", f"the mirror plane passes {d_mm:.3g} mm from the camera's centre: a mirror "
                 "there would reflect nothing the camera sees; the mirror estimate is wrong", d_mm,
                 th.min_mirror_distance_mm)
        elif hit == 0.0:
            fail("mirror_behind_camera", "the mirror plane is not in front of the camera (no pixel's ray meets "
                 "it): the mirror estimate is wrong", hit, 0.0)
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    poses = diag.get("board_poses")
    steps = {pv.get("capture_id"): pv.get("step") for pv in result.per_view if isinstance(pv, dict)}
    if lit_from_poses and isinstance(poses, dict) and poses:
        behind = [cid for cid, Tb in poses.items()
                  if steps.get(cid) == "projector" and not _projector_lights_board(result.projector, T, Tb)]
        metrics["boards_behind_projector"] = len(behind)
        if behind:
            fail("board_behind_projector", f"{len(behind)} board(s) the projector lit are behind it "
                 f"({', '.join(behind[:3])}{'...' if len(behind) > 3 else ''})", len(behind), 0.0)


def check_observations(result, obs, th: TrustThresholds, fail, metrics: dict) -> None:
    """Re-derive every projector view from the result alone: the board's pose from its corners (PnP with
    the result's camera, through the result's mirror when the view is mirrored), the pattern's projector
    pixels cast onto that board by the result's projector and T_cam_proj, and imaged by the camera.

    A correct result lands on the observed pattern points within the detection noise; a wrong pose, a
    wrong mirror or wrong intrinsics does not, whatever residuals the result itself records. The median
    over the views is judged, so one bad detection is not a bad calibration. The same pass tests the
    lit points themselves (the pattern's pixels on each board) for lying in front of the projector."""
    from calib.paper.board_pose import pose_from_points, pose_through_mirror

    cam, proj = result.camera, result.projector
    T = np.asarray(result.T_cam_proj, float)
    S = result.mirror.reflection() if result.mirror is not None else np.eye(4)
    corners = obs.projector_board.corner_points()
    per_view, behind = [], []
    for pv in obs.projector_views:
        ids = np.asarray(pv.board.ids, int)
        if len(ids) < 6 or len(pv.pattern_proj_px) == 0:
            continue
        uv = np.asarray(pv.board.corners_px, float)
        if pv.board.mirrored and result.mirror is None:
            continue
        X = corners[ids]
        Tb = pose_through_mirror(cam, S, X, uv) if pv.board.mirrored else pose_from_points(cam, X, uv)
        if Tb is None:
            continue
        Xb, t = rays_to_board_plane(invert_T(Tb) @ T, proj.rays(np.asarray(pv.pattern_proj_px, float)))
        if not np.all(np.isfinite(t) & (t > 0)):
            behind.append(pv.capture_id)
            continue
        Sv = S if pv.board.mirrored else np.eye(4)
        X_cam = (Sv @ Tb @ np.column_stack([Xb, np.ones(len(Xb))]).T).T[:, :3]
        with np.errstate(all="ignore"):
            pred = cam.project(X_cam)
            r = np.linalg.norm(pred - np.asarray(pv.pattern_cam_px, float), axis=1)
        per_view.append(float(np.sqrt(np.mean(r ** 2))) if np.all(np.isfinite(r)) else float("inf"))
    metrics["boards_behind_projector"] = len(behind)
    if behind:
        fail("board_behind_projector", f"{len(behind)} board(s) the projector lit are behind it: its pattern's rays "
             f"meet them behind the lens ({', '.join(behind[:3])}{'...' if len(behind) > 3 else ''})",
             len(behind), 0.0)
    if per_view:
        med = float(np.median(per_view))
        metrics["observations.pattern_rms_px"] = med if math.isfinite(med) else float("nan")
        # noisier detections re-derive less exactly: the limit grows with the residual the result recorded
        # in camera pixels (joint: every class; paper: the camera's)
        rms = result.rms if isinstance(result.rms, dict) else {}
        rec = rms.get("joint", rms.get("camera"))
        rec = float(rec) if isinstance(rec, (int, float)) and math.isfinite(rec) and rec > 0 else 0.0
        limit = max(th.observation_rms_px, th.observation_rms_factor * rec)
        metrics["observations.limit_px"] = limit
        if not med <= limit:
            fail("observations_disagree", f"cast through the result, the pattern lands {_fmt(med, 'camera px')} from "
                 f"where the camera saw it (median of {len(per_view)} views; limit {limit:.3g} px): "
                 "the poses, the mirror or the intrinsics are wrong", med, limit)


def _projector_lights_board(proj: CameraModel, T_cam_proj: np.ndarray, T_cam_board) -> bool:
    """Whether any ray of the projector's image meets the board's plane in front of the projector.

    The lit points are where the projector's rays meet the board, not the board frame's origin (a ChArUco
    corner): on a strongly tilted board near the projector that corner can lie behind the projector's
    lens plane while every lit point is far in front of it."""
    us, vs = np.meshgrid(np.linspace(0, proj.width - 1, 9), np.linspace(0, proj.height - 1, 9))
    _, t = rays_to_board_plane(invert_T(np.asarray(T_cam_board, float)) @ T_cam_proj,
                               proj.rays(np.column_stack([us.ravel(), vs.ravel()])))
    return bool(np.any(np.isfinite(t) & (t > 0)))


def check_uncertainty(result, th: TrustThresholds, fail, metrics: dict) -> None:
    unc = result.uncertainty
    mm = _MM_PER_UNIT.get(result.units, 1.0)
    if isinstance(unc, dict):
        T = unc.get("T_cam_proj") or {}
        if isinstance(T.get("t_total"), (int, float)):
            s_t = float(T["t_total"]) * mm
            metrics["sigma.t_mm"] = s_t
            # a far projector is located less precisely by the same poses: the limit grows with its distance
            lim_t = max(th.sigma_t_mm, th.sigma_t_fraction * float(np.linalg.norm(np.asarray(result.T_cam_proj,
                                                                                              float)[:3, 3])) * mm)
            if not s_t <= lim_t:  # NaN too: a covariance that could not be computed
                fail("uncertainty_pose", f"the projector's position is uncertain by {_fmt(s_t, 'mm')} (1 sigma; limit "
                     f"{lim_t:.3g} mm): the poses do not constrain it", s_t, lim_t)
        if isinstance(T.get("rot_total_deg"), (int, float)):
            s_r = float(T["rot_total_deg"])
            metrics["sigma.rot_deg"] = s_r
            if not s_r <= th.sigma_rot_deg:
                fail("uncertainty_pose", f"the projector's orientation is uncertain by {_fmt(s_r, 'deg')} (1 sigma; "
                     f"limit {th.sigma_rot_deg:g} deg)", s_r, th.sigma_rot_deg)
        for dev in ("camera", "projector"):
            u = unc.get(dev) or {}
            if u.get("fixed"):
                continue
            vals = [float(u[k]) for k in ("fx", "fy", "cx", "cy") if isinstance(u.get(k), (int, float))]
            if vals:
                s = max(vals) if all(math.isfinite(v) for v in vals) else float("inf")
                metrics[f"sigma.{dev}_intrinsics_px"] = s
                # a long focal length (a tele lens, a 4K projector) is as well determined at the same share
                f_dev = getattr(result, dev).fx
                lim = max(th.sigma_intrinsics_px, th.sigma_intrinsics_fraction * abs(float(f_dev)))
                if not s <= lim:
                    fail("uncertainty_intrinsics", f"the {dev}'s intrinsics are uncertain by up to {s:.3g} px "
                         f"(1 sigma; limit {lim:.3g} px)", s, lim)
        m = unc.get("mirror")
        if isinstance(m, dict) and isinstance(m.get("normal_deg"), (int, float)):
            s_n = float(m["normal_deg"])
            metrics["sigma.mirror_normal_deg"] = s_n
            if not s_n <= th.sigma_mirror_normal_deg:
                fail("uncertainty_mirror", f"the mirror normal is uncertain by {_fmt(s_n, 'deg')} (1 sigma; limit "
                     f"{th.sigma_mirror_normal_deg:g} deg)", s_n, th.sigma_mirror_normal_deg)
        covd = unc.get("covariance") or {}
        if covd.get("matrix") is not None:
            cov = np.asarray(covd["matrix"], float)
            names = list(covd.get("names") or [])
            # the geometry (focal lengths, principal points, T_cam_proj, the mirror): distortion coefficients
            # of a rich model are nearly degenerate with each other without harm to the projection (the
            # distortion's own sanity is the fold check), so they are left out of the condition number
            keep = [i for i, nm in enumerate(names) if ".dist" not in nm] if len(names) == len(cov) else \
                list(range(len(cov)))
            metrics["condition_all"] = correlation_condition(cov)
            c = correlation_condition(cov[np.ix_(keep, keep)])
            metrics["condition"] = c
            if not c <= th.condition_max:
                fail("ill_conditioned", f"the calibration is ill-conditioned (condition number {c:.3g} of the "
                     f"correlation of its geometric parameters, limit {th.condition_max:.0e}): some of them are "
                     "not determined by the data", c, th.condition_max)
        return
    # methods without a covariance (paper): OpenCV's 1-sigma of the intrinsics, where it reports them
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    for dev in ("camera", "projector"):
        std = (diag.get(dev) or {}).get("std_intrinsics") if isinstance(diag.get(dev), dict) else None
        if isinstance(std, list) and len(std) >= 4:
            vals = [float(v) for v in std[:4]]
            s = max(vals) if all(math.isfinite(v) for v in vals) else float("inf")
            metrics[f"sigma_opencv.{dev}_intrinsics_px"] = s
            if not s <= th.sigma_intrinsics_opencv_px:
                fail("uncertainty_intrinsics", f"the {dev}'s intrinsics are uncertain by up to {s:.3g} px (OpenCV's "
                     f"1 sigma; limit {th.sigma_intrinsics_opencv_px:g} px)", s, th.sigma_intrinsics_opencv_px)


def _fmt(v: float, unit: str) -> str:
    return f"{v:.3g} {unit}" if math.isfinite(v) else "an amount that cannot be computed (singular covariance)"


def correlation_condition(cov: np.ndarray) -> float:
    """Condition number of the correlation matrix of `cov` (scale-free: the Jacobi-scaled normal
    equations of the global parameters have the same condition number); inf when singular."""
    if cov.size == 0:
        return 1.0
    if not np.all(np.isfinite(cov)):
        return float("inf")
    s = np.sqrt(np.clip(np.diag(cov), 0, None))
    if not np.all(s > 0):
        return float("inf")
    corr = cov / s[:, None] / s[None, :]
    ev = np.linalg.eigvalsh((corr + corr.T) / 2)
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")

