"""Stage 2: the mirror plane, from its own images (both methods of the paper).

Real-virtual: one image shows the board directly and in the mirror. PnP of the real board (direct)
and of the virtual board (mirrored object points, calib.paper.board_pose) gives the 3D corners of both in the
camera frame; the midpoint of a real corner and its virtual twin (same id) lies on the mirror, and
their difference is parallel to the normal.

Real-mirror: the board lies on the mirror. PnP gives its corners, which lie on a plane parallel to the
mirror, `board_thickness` closer to the camera: the mirror is that plane moved by the thickness away
from the camera (d_mirror = d_board + thickness).

All points of all images go into one SVD plane fit inside RANSAC (threshold in board units).

Entry point: `calibrate_mirror(obs, camera, ...) -> MirrorCalibration`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.errors import CalibrationError
from calib.models.camera import CameraModel
from calib.models.observations import STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, SessionObservations
from calib.models.result import MirrorPlane
from calib.paper.board_pose import MIN_CORNERS, solve_board_pose, usable_reason
from calib.models.vocab import MirrorMethod

#: Default RANSAC inlier threshold as a fraction of the mirror board's square length.
THRESHOLD_SQUARES = 0.1
#: A view whose PnP RMS exceeds this (pixels) is not used: its pose, and so its 3D points, is wrong.
MAX_VIEW_RMS_PX = 3.0
#: Fewer inlier points than this (from fewer than 1 view) and the plane is not trusted.
MIN_POINTS = 6


@dataclass(frozen=True, eq=False)
class MirrorCalibration:
    plane: MirrorPlane
    method: str  # "real-virtual", "real-mirror", or both joined by "+"
    rms: float  # RMS distance of the inlier points to the plane (board units)
    threshold: float  # RANSAC inlier threshold used (board units)
    n_inliers: int
    n_outliers: int
    points: np.ndarray  # (N, 3) camera-frame points the plane was fitted to (mirror-surface points)
    inliers: np.ndarray  # (N,) bool
    residuals: np.ndarray  # (N,) signed distances of all points to the final plane (board units)
    per_view: tuple  # dicts: stage, capture_id, method, n_points, rms_real_px, rms_virtual_px, plane_rms, ...
    skipped: tuple = ()  # dicts: capture_id, stage, reason
    normal_from_differences: np.ndarray | None = None  # real-virtual: mean direction of real->virtual
    board_thickness: float = 0.0
    diagnostics: dict = field(default_factory=dict)


def fit_plane(points: np.ndarray) -> MirrorPlane:
    """Least-squares plane through (N >= 3) points: centroid and the smallest singular vector."""
    P = np.asarray(points, float).reshape(-1, 3)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P - c, full_matrices=False)
    n = Vt[2]
    d = -float(n @ c)
    if abs(d) < 1e-12:  # plane through the camera centre: orient n arbitrarily but deterministically
        d = 0.0
    return MirrorPlane(n, d) if d != 0.0 else MirrorPlane(n if n[2] <= 0 else -n, 1e-12)


def ransac_plane(points: np.ndarray, threshold: float, iterations: int = 1000, seed: int = 0,
                 confidence: float = 0.999) -> tuple[MirrorPlane, np.ndarray]:
    """RANSAC over minimal 3-point samples, then a least-squares refit on the inliers (iterated until
    the inlier set is stable). Returns (plane, inlier mask)."""
    P = np.asarray(points, float).reshape(-1, 3)
    n_pts = len(P)
    if n_pts < 3:
        raise CalibrationError("fewer than 3 points to fit the mirror plane")
    rng = np.random.default_rng(seed)
    best_count, best_mask = -1, None
    best_err = np.inf
    needed = iterations
    i = 0
    while i < min(iterations, needed):
        i += 1
        idx = rng.choice(n_pts, 3, replace=False)
        a, b, c = P[idx]
        nrm = np.cross(b - a, c - a)
        ln = np.linalg.norm(nrm)
        if ln < 1e-12 * max(1.0, np.linalg.norm(b - a) * np.linalg.norm(c - a)):
            continue
        nrm /= ln
        dist = np.abs((P - a) @ nrm)
        mask = dist < threshold
        count = int(mask.sum())
        err = float(np.sum(np.minimum(dist, threshold) ** 2))
        if count > best_count or (count == best_count and err < best_err):
            best_count, best_mask, best_err = count, mask, err
            w = count / n_pts
            if w >= 1.0:
                needed = i
            else:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1e-12, 1 - w**3))))
    if best_mask is None or best_count < 3:
        raise CalibrationError("the mirror points are degenerate (collinear); capture the board at more positions")
    mask = best_mask
    for _ in range(10):
        plane = fit_plane(P[mask])
        new = np.abs(plane.signed_distance(P)) < threshold
        if new.sum() < 3 or np.array_equal(new, mask):
            break
        mask = new
    return fit_plane(P[mask]), mask


def calibrate_mirror(obs: SessionObservations, camera: CameraModel, *, threshold: float | None = None,
                     board_thickness: float | None = None, use_differences: bool = False,
                     min_corners: int = MIN_CORNERS, seed: int = 0) -> MirrorCalibration:
    """Fit the mirror plane to the mirror-calibration views of `obs`.

    `threshold`: RANSAC inlier distance in board units (default 0.1 x the mirror board's square).
    `board_thickness`: real-mirror only, board units; default `obs.board_thickness`.
    `use_differences`: real-virtual only; replace the fitted normal by the mean direction of the
    real-to-virtual difference vectors (inliers only) and refit the offset. Off for the paper method."""
    spec = obs.mirror_board or obs.projector_board
    thickness = float(obs.board_thickness if board_thickness is None else board_thickness)
    thr = float(THRESHOLD_SQUARES * spec.square_length if threshold is None else threshold)
    if not obs.mirror_views:
        raise CalibrationError(
            "the session has no mirror-calibration images, so the mirror plane cannot be estimated (it is not "
            "observable from the projector images alone); capture real-virtual or real-mirror images")
    skipped, per_view = [], []
    pts, owner, diffs, methods = [], [], [], set()
    for mv in obs.mirror_views:
        rec = {"stage": "mirror", "capture_id": mv.capture_id, "method": mv.method}
        if mv.method == STEP_REAL_VIRTUAL:
            r1 = usable_reason(spec, mv.real, min_corners)
            r2 = usable_reason(spec, mv.virtual, min_corners)
            if r1 or r2:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": f"real board: {r1}" if r1 else f"virtual board: {r2}"})
                continue
            if mv.virtual is not None and not mv.virtual.mirrored:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": "the virtual board is not marked as seen through the mirror"})
                continue
            common, ia, ib = np.intersect1d(mv.real.ids, mv.virtual.ids, return_indices=True)
            if len(common) < min_corners:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": f"only {len(common)} corners seen both directly and in the mirror "
                                          f"(need {min_corners}); keep the whole board visible in both"})
                continue
            pr = solve_board_pose(camera, spec, mv.real)
            pv = solve_board_pose(camera, spec, mv.virtual)
            rec.update(rms_real_px=pr.rms_px, rms_virtual_px=pv.rms_px, n_points=int(len(common)))
            if max(pr.rms_px, pv.rms_px) > MAX_VIEW_RMS_PX:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": f"board pose does not fit its corners (RMS {max(pr.rms_px, pv.rms_px):.2f} px); "
                                          f"misdetection or wrong board spec"})
                continue
            X = spec.corner_points()[common]
            Xr = pr.seen_points(X)
            Xv = pv.seen_points(X)
            pts.append((Xr + Xv) / 2)
            diffs.append(Xv - Xr)
            methods.add(MirrorMethod.REAL_VIRTUAL)
        elif mv.method == STEP_REAL_MIRROR:
            r1 = usable_reason(spec, mv.real, min_corners)
            if r1:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror", "reason": f"board: {r1}"})
                continue
            if mv.real.mirrored:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": "a real-mirror image must show the board directly, not through the mirror"})
                continue
            pr = solve_board_pose(camera, spec, mv.real)
            rec.update(rms_real_px=pr.rms_px, n_points=int(len(mv.real.ids)))
            if pr.rms_px > MAX_VIEW_RMS_PX:
                skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                                "reason": f"board pose does not fit its corners (RMS {pr.rms_px:.2f} px); "
                                          f"misdetection or wrong board spec"})
                continue
            Xc = pr.seen_points(spec.corner_points()[mv.real.ids])
            # the printed face is `thickness` in front of the mirror, towards the camera; the board's +z
            # axis points into the board (away from the camera when the face is seen), i.e. to the mirror
            into = pr.T_cam_view[:3, 2]
            if into @ Xc.mean(axis=0) < 0:
                into = -into
            pts.append(Xc + thickness * into)
            diffs.append(None)
            methods.add(MirrorMethod.REAL_MIRROR)
        else:
            skipped.append({"capture_id": mv.capture_id, "stage": "mirror",
                            "reason": f"unknown mirror-calibration method '{mv.method}'"})
            continue
        rec["_idx"] = len(pts) - 1
        per_view.append(rec)
    if not pts:
        raise CalibrationError(
            f"none of the {len(obs.mirror_views)} mirror-calibration images is usable "
            f"({'; '.join(sorted({s['reason'] for s in skipped}))}); recapture them with the whole board visible")
    P = np.concatenate(pts)
    owner = np.concatenate([np.full(len(p), k) for k, p in enumerate(pts)])
    if len(P) < MIN_POINTS:
        raise CalibrationError(f"only {len(P)} mirror points; capture more mirror-calibration images")
    plane, mask = ransac_plane(P, thr, seed=seed)
    n_diff = None
    D = [d[mask[owner == k]] for k, d in enumerate(diffs) if d is not None]
    if D:
        Dall = np.concatenate(D)
        if len(Dall):
            u = Dall / np.linalg.norm(Dall, axis=1, keepdims=True)
            u = u * np.sign(u @ plane.normal)[:, None]
            n_diff = u.mean(axis=0)
            n_diff /= np.linalg.norm(n_diff)
    if use_differences and n_diff is not None:
        d_new = -float(np.mean(P[mask] @ n_diff))
        plane = MirrorPlane(n_diff, d_new)
        mask_new = np.abs(plane.signed_distance(P)) < thr
        if mask_new.sum() >= 3:
            mask = mask_new
            plane = MirrorPlane(n_diff, -float(np.mean(P[mask] @ n_diff)))
    res = plane.signed_distance(P)
    rms = float(np.sqrt(np.mean(res[mask] ** 2)))
    for rec in per_view:
        k = rec.pop("_idx")
        sel = owner == k
        rec["n_inliers"] = int(mask[sel].sum())
        rec["plane_rms"] = float(np.sqrt(np.mean(res[sel] ** 2)))
        rec["plane_max"] = float(np.max(np.abs(res[sel])))
    diag = {"n_views_used": len(per_view)}
    if n_diff is not None:
        diag["difference_normal_angle_deg"] = float(np.degrees(np.arccos(np.clip(abs(n_diff @ plane.normal), -1, 1))))
    for a in (P, mask, res):
        a.setflags(write=False)
    if n_diff is not None:
        n_diff.setflags(write=False)
    return MirrorCalibration(plane, "+".join(sorted(methods)), rms, thr, int(mask.sum()), int((~mask).sum()), P, mask,
                             res, tuple(per_view), tuple(skipped), n_diff, thickness if MirrorMethod.REAL_MIRROR in methods else 0.0,
                             diag)
