"""The joint adjustment's noise model and outlier rejection: the noise sigma of each observation class
from the residuals (robust or RMS), and the rejection of points whose whitened residual is too large
(with the views left with too few corners)."""

from __future__ import annotations

import numpy as np

from calib.joint.options import JointOptions
from calib.joint.points import KIND_NAMES
from calib.joint.problem import JointProblem

#: the fewest points of a class that give it a sigma of its own (fewer take the pooled sigma)
MIN_CLASS_POINTS = 20
#: the fewest corners a view keeps after rejection (a board lying on the mirror: its 3 DOF need fewer)
MIN_CORNERS_LEFT, MIN_CORNERS_LEFT_ON_MIRROR = 6, 3


def robust_sigma(r: np.ndarray) -> float:
    """The normalised median absolute deviation of r (a Gaussian's sigma; 0 for no residuals)."""
    if r.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def class_sigmas(prob: JointProblem, r_px: np.ndarray, options: JointOptions, robust: bool) -> dict:
    """Noise sigma (px, per coordinate) of each observation class: robust (MAD) or RMS of the residuals,
    each divided by its point's relative noise (a point with a sigma of its own, PatternSet.rel), so the
    class's sigma is that of its median point. weighting="none" pools all classes; classes with fewer
    than 20 points take the pooled value."""
    floor = 1e-3
    r_px = r_px / np.repeat(prob.relative_noise(), 2)
    pooled = robust_sigma(r_px) if robust else float(np.sqrt(np.mean(r_px ** 2))) if r_px.size else 1.0
    pooled = max(pooled, floor)
    out = {}
    for name, m in prob.class_masks().items():
        rr = np.stack([r_px[0::2][m], r_px[1::2][m]], axis=1).reshape(-1)
        if options.weighting == "none" or m.sum() < MIN_CLASS_POINTS:
            out[name] = pooled
        else:
            v = robust_sigma(rr) if robust else float(np.sqrt(np.mean(rr ** 2)))
            out[name] = max(v, floor)
    return out


def reject(prob: JointProblem, x: np.ndarray, k: float, min_px: float, rejected: list) -> int:
    """Drop points whose whitened residual norm exceeds k robust sigmas and whose pixel residual exceeds
    min_px (and views left with fewer than 6 corners); append a record per dropped point to `rejected`.
    Returns the number of points dropped."""
    corners, pattern = prob.corners, prob.pattern
    nc = len(corners)
    rw = prob.residuals(x)
    rp = rw * prob.row_scale
    sig = max(robust_sigma(rw), 1e-12)
    ew = np.hypot(rw[0::2], rw[1::2]) / sig
    e = np.hypot(rp[0::2], rp[1::2])
    bad = (ew > k) & (e > min_px)
    if not bad.any():
        return 0
    keep_c = ~bad[:nc]
    keep_p = ~bad[nc:]
    # a pose needs at least 6 corners to stay determined; otherwise drop the whole view
    counts = np.bincount(corners.pose[keep_c], minlength=len(prob.poses))
    weak = np.where(prob.on_mirror, counts < MIN_CORNERS_LEFT_ON_MIRROR, counts < MIN_CORNERS_LEFT)
    scale = prob.point_sigma * sig
    for kind, keep, pts in (("corner", keep_c, corners), ("pattern", keep_p, pattern)):
        off = 0 if kind == "corner" else nc
        for i in np.nonzero(~keep)[0]:
            j = off + i
            rejected.append({
                "capture_id": prob.captures[pts.cid[i]],
                "kind": KIND_NAMES[pts.kind[i]] if kind == "corner" else "pattern",
                "point": int(pts.pid[i]), "residual_px": round(float(e[j]), 4),
                "reason": f"residual {e[j]:.3g} px = {ew[j]:.1f} robust sigma ({scale[j]:.3g} px) of its class "
                          f"> {k:g} sigma"})
    if weak.any():
        for v in np.nonzero(weak)[0]:
            rejected.append({"capture_id": prob.poses[v].capture_id, "kind": "view", "point": -1,
                             "residual_px": None,
                             "reason": f"view dropped: only {int(counts[v])} ChArUco corners left after rejection"})
        keep_c &= ~weak[corners.pose]
        keep_p &= ~weak[pattern.pose]
    prob.subset(keep_c, keep_p, weak)
    return int(bad.sum())
