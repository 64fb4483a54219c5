"""The trust check's judgement of one camera or projector model (behind calib.quality.trust): focal
lengths and field of view, aspect, principal point, and a radial distortion that folds the image or
bends its rays beyond any lens."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from calib.models.camera import CameraModel

if TYPE_CHECKING:
    from calib.quality.trust import TrustThresholds


def _image_corners(dev: CameraModel) -> np.ndarray:
    """The outer corners of a device's image (pixel centres at integers: the edges at -0.5 and size - 0.5)."""
    return np.array([[-0.5, -0.5], [dev.width - 0.5, -0.5], [-0.5, dev.height - 0.5],
                     [dev.width - 0.5, dev.height - 0.5]])


def _normalised_radius(dev: CameraModel, uv: np.ndarray) -> float:
    """The largest distance of pixels `uv` from the principal point in focal lengths (distorted radius)."""
    m = (np.asarray(uv, float).reshape(-1, 2) - [dev.cx, dev.cy]) / [dev.fx, dev.fy]
    return float(np.max(np.hypot(m[:, 0], m[:, 1])))


def observed_reach(result, obs) -> dict:
    """How far out each device's observations reach, as a fraction of the distance to its image's farthest
    corner (the radius radial_fold_fraction measures in): a distortion polynomial is only determined where
    there are observations, so it may bend back beyond them without harm to any pixel that was measured."""
    cam_px = [np.asarray(pv.board.corners_px, float).reshape(-1, 2) for pv in obs.projector_views]
    cam_px += [np.asarray(pv.pattern_cam_px, float).reshape(-1, 2) for pv in obs.projector_views]
    for mv in obs.mirror_views:
        for b in (mv.real, getattr(mv, "virtual", None)):
            if b is not None:
                cam_px.append(np.asarray(b.corners_px, float).reshape(-1, 2))
    proj_px = [np.asarray(pv.pattern_proj_px, float).reshape(-1, 2) for pv in obs.projector_views]
    out = {}
    for name, dev, pts in (("camera", result.camera, cam_px), ("projector", result.projector, proj_px)):
        if not pts:
            continue
        uv = np.concatenate(pts)
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv) == 0 or dev.fx <= 0 or dev.fy <= 0:
            continue
        r_max = _normalised_radius(dev, _image_corners(dev))
        out[name] = min(1.0, _normalised_radius(dev, uv) / r_max) if r_max > 0 else 1.0
    return out


def check_device_model(name: str, dev: CameraModel, th: TrustThresholds, fail, metrics: dict,
                  reach: float = 1.0) -> None:
    w, h = dev.width, dev.height
    fx, fy, cx, cy = dev.fx, dev.fy, dev.cx, dev.cy
    metrics[f"{name}.fx_per_width"] = fx / w
    metrics[f"{name}.aspect"] = fy / fx if fx else float("nan")
    if fx <= 0 or fy <= 0:
        fail("focal_nonpositive", f"the {name}'s focal length is not positive (fx {fx:.4g}, fy {fy:.4g} px)",
             min(fx, fy), 0.0)
        return
    # the field of view is the angle between the image's edges seen from the lens: with the principal
    # point where it is (a projector's lens shift puts it near or beyond an edge), not fx / width
    for axis, f, c, n in (("fx", fx, cx, w), ("fy", fy, cy, h)):
        span = field_of_view_deg(f, c, n)
        metrics[f"{name}.fov_{axis[1]}_deg"] = span
        if not th.fov_min_deg <= span <= th.fov_max_deg:
            fail("focal_out_of_range", f"the {name}'s {axis} of {f:.4g} px gives a {span:.3g} deg field of view "
                 f"across its {n} px (outside {th.fov_min_deg:g}-{th.fov_max_deg:g} deg: no {name} has it)", span,
                 th.fov_max_deg if span > th.fov_max_deg else th.fov_min_deg)
    if not th.aspect_min <= fy / fx <= th.aspect_max:
        fail("aspect_ratio", f"the {name}'s fy / fx = {fy / fx:.3g} (pixels are square: expected near 1)",
             fy / fx, th.aspect_max if fy / fx > 1 else th.aspect_min)
    m = th.principal_point_margin
    if not (-m * w <= cx <= (1 + m) * w and -m * h <= cy <= (1 + m) * h):
        fail("principal_point", f"the {name}'s principal point ({cx:.4g}, {cy:.4g}) px is far outside its "
             f"{w}x{h} image", None, m)
    scale = radial_corner_scale(dev)
    metrics[f"{name}.distortion_corner_scale"] = scale
    if scale is not None and not th.distortion_scale_min <= scale <= th.distortion_scale_max:
        fail("distortion_scale", f"the {name}'s radial distortion moves the image corners' rays {scale:.3g} times "
             f"as far from the axis as no distortion would (outside {th.distortion_scale_min:g}-"
             f"{th.distortion_scale_max:g}: no lens does that)", scale,
             th.distortion_scale_max if scale > th.distortion_scale_max else th.distortion_scale_min)
    fold = radial_fold_fraction(dev)
    metrics[f"{name}.fold_at_fraction_of_corner_radius"] = fold
    metrics[f"{name}.observed_fraction_of_corner_radius"] = reach
    if fold is not None and fold < reach:
        where = "the image corners" if reach >= 1.0 else f"the farthest observation ({100 * reach:.0f}% of that)"
        fail("distortion_folds", f"the {name}'s radial distortion folds the image: the mapping stops "
             f"increasing at {100 * fold:.0f}% of the distance to the image corners, inside {where}", fold, reach)


def field_of_view_deg(f: float, c: float, n: int) -> float:
    """The angle (deg) between the rays through the two edges (-0.5 and n - 0.5 px) of an image axis of
    focal length f and principal point c, pinhole model."""
    return float(np.degrees(np.arctan((c + 0.5) / f) + np.arctan((n - 0.5 - c) / f)))


def _radial_curve(dev: CameraModel, samples: int = 4000):
    """(r, r_d, denominator, farthest corner's r_d) of the radial distortion r -> r_d = r (1 + k1 r^2 + k2 r^4
    + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6), r up to a ray 89.4 deg off-axis (or 10x the corner's r_d)."""
    d = np.zeros(8)
    dist = np.asarray(dev.dist, float).reshape(-1)[:8]
    d[: dist.size] = dist
    k1, k2, _p1, _p2, k3, k4, k5, k6 = d
    rd_max = _normalised_radius(dev, _image_corners(dev))
    r = np.linspace(0.0, max(100.0, 10 * rd_max), samples * 25)
    r2 = r * r
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rd = r * num / den
    return r, rd, den, rd_max


def radial_fold_fraction(dev: CameraModel, samples: int = 4000) -> float | None:
    """None when the radial distortion (_radial_curve) increases until r_d reaches the farthest image corner
    (every pixel is one ray); else the fraction of that corner radius (in r_d) at which it stops increasing
    (the image folds there)."""
    r, rd, den, rd_max = _radial_curve(dev, samples)
    reached = np.nonzero(rd >= rd_max)[0]
    stop = int(reached[0]) if len(reached) else len(r) - 1
    seg_rd, seg_den = rd[: stop + 1], den[: stop + 1]
    bad = np.nonzero((np.diff(seg_rd) <= 0) | ~np.isfinite(seg_rd[1:]) | (seg_den[1:] <= 0))[0]
    if len(bad) == 0 and len(reached):
        return None
    at = seg_rd[bad[0]] if len(bad) else np.nanmax(seg_rd)
    return float(max(at, 0.0) / rd_max) if np.isfinite(at) else 0.0


def radial_corner_scale(dev: CameraModel) -> float | None:
    """The undistorted radius of the farthest image corner over its distorted one (1 without distortion):
    how much the radial distortion widens (> 1) or narrows (< 1) the field of view; None when the distortion
    never reaches that corner (radial_fold_fraction says so)."""
    r, rd, _den, rd_max = _radial_curve(dev)
    reached = np.nonzero(rd >= rd_max)[0]
    if not len(reached) or not rd_max > 0:
        return None
    i = int(reached[0])
    if i == 0:
        return 1.0
    # linear between the samples either side of the corner
    r_corner = r[i - 1] + (r[i] - r[i - 1]) * (rd_max - rd[i - 1]) / (rd[i] - rd[i - 1])
    return float(r_corner / rd_max)

