"""Is a calibration result trustworthy? One entry function: check_calibration(result) -> TrustReport.

A calibration that ran to the end is not necessarily a calibration: degenerate sessions (the same
image copied over every projector capture, wrong pattern points, too few or too similar poses) give
results with absurd parameters, huge residuals or an uncertainty far beyond what a full session gives.
calib.pipeline runs this check on every result (both methods) and raises UntrustedCalibration
(calib.errors) with the reasons when it fails, so that no such result is saved or handed on.

Each failed check is a TrustReason with a stable `code` (programs and tests match on it), a message a
user can act on, the measured value and the limit. The checks and how the limits were chosen (from the
project's simulated full sessions, `python benchmarks/trust_thresholds.py`): docs/CALIBRATION.md,
"Trust check". The limits are fields of TrustThresholds.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from calib.models.camera import CameraModel
from calib.quality.projection_uncertainty import large_regions, where_max
from calib.transforms import invert_T, rays_to_board_plane

#: length units of a session -> millimetres (limits on lengths are stated in mm)
from calib.models.boards import MM_PER_UNIT as _MM_PER_UNIT

CODES = {
    "non_finite": "a parameter or residual is NaN or infinite",
    "solve_failed": "the joint adjustment's linear algebra failed (singular or non-convergent system)",
    "focal_nonpositive": "a focal length is zero or negative",
    "focal_out_of_range": "a focal length gives an impossible field of view",
    "aspect_ratio": "fy / fx far from 1 (pixels are square)",
    "principal_point": "the principal point lies far outside the image",
    "distortion_folds": "the radial distortion folds the image (not monotonic inside it)",
    "distortion_scale": "the radial distortion shrinks or stretches the image far beyond any lens",
    "rms_high": "residuals far above the detection noise",
    "mirror_behind_camera": "the mirror plane is not in front of the camera",
    "projector_too_far": "the projector is absurdly far from the camera",
    "board_behind_projector": "boards the projector lit are behind it",
    "observations_disagree": "the result does not reproduce the pattern points it was calibrated from",
    "uncertainty_pose": "the camera-projector pose is far more uncertain than a full session's",
    "uncertainty_intrinsics": "intrinsics far more uncertain than a full session's",
    "uncertainty_mirror": "the mirror normal is far more uncertain than a full session's",
    "ill_conditioned": "the normal equations are (nearly) singular",
}


@dataclass(frozen=True)
class TrustThresholds:
    """Limits of the trust check. The RMS and uncertainty limits are about 10x the worst value of the
    simulated full sessions at 0.3 px noise (benchmarks/trust_thresholds.py; the values measured are in
    docs/CALIBRATION.md): what a full session would give with 3 px of noise."""

    fov_min_deg: float = 1.0  # the angle the image spans between its edges (either axis), lens shift included
    fov_max_deg: float = 175.0  # a pinhole model never reaches 180 deg; this far only from an absurd focal
    aspect_min: float = 0.8
    # the farthest image corner's ray over where the pinhole model puts it (radial distortion only): a strong
    # fisheye-like barrel stays near 2-3, a pincushion near 0.7; beyond these no lens bends rays
    distortion_scale_min: float = 0.2
    distortion_scale_max: float = 10.0
    aspect_max: float = 1.25
    principal_point_margin: float = 1.0  # image sizes beyond the edges (lens shift of offset projectors)
    rms_camera_px: float = 3.0  # residuals measured in camera pixels (every joint class; paper camera)
    rms_projector_px: float = 20.0  # the paper method's projector and stereo RMS (projector pixels)
    max_projector_distance_mm: float = 10000.0
    sigma_t_mm: float = 20.0  # 1-sigma of T_cam_proj's translation (all axes together) ...
    sigma_t_fraction: float = 0.02  # ... or this share of the projector's distance, whichever is larger
    observation_rms_px: float = 1.5  # the result re-derives the pattern points it was given (camera px, median view) ...
    observation_rms_factor: float = 4.0  # ... or this many times the camera-pixel RMS it recorded, if larger
    min_mirror_distance_mm: float = 1.0  # a mirror plane through the camera centre is no mirror
    sigma_rot_deg: float = 1.5  # 1-sigma of T_cam_proj's rotation
    sigma_intrinsics_px: float = 50.0  # 1-sigma of any of fx, fy, cx, cy (joint covariance) ...
    sigma_intrinsics_fraction: float = 0.05  # ... or this share of the device's fx, whichever is larger
    sigma_intrinsics_opencv_px: float = 500.0  # ... as OpenCV reports it (paper method, looser: see doc)
    sigma_mirror_normal_deg: float = 1.0
    condition_max: float = 1e8  # of the correlation matrix of the geometric parameters (not distortion)


#: quality codes (calib.quality.trust's `quality` section: low quality, not failure)
QUALITY_CODES = {
    "quality_pose_translation": "the projector's position is far more uncertain than a full session's",
    "quality_pose_rotation": "the projector's orientation is far more uncertain than a full session's",
    "quality_camera_intrinsics": "the camera's fx, fy, cx, cy are far more uncertain than a full session's",
    "quality_projector_intrinsics": "the projector's fx, fy, cx, cy are far more uncertain than a full session's",
    "quality_mirror_normal": "the mirror normal is far more uncertain than a full session's",
    "quality_camera_projection": "the camera's projection uncertainty over the image is far above a full session's",
    "quality_projector_projection": "the projector's projection uncertainty over the image is far above a full session's",
}

_ADVICE_POSES = ("take more projector captures, at more pattern positions and with more varied board tilts and "
                 "distances")
_ADVICE_INTRINSICS = ("take more poses with varied tilts (30-45 deg to each side) that bring the board into the "
                      "image corners")
_ADVICE_MIRROR = "take more mirror captures, with the board at other places and tilts on / in front of the mirror"


@dataclass(frozen=True)
class QualityThresholds:
    """Limits of the quality gate: about 2.5x the worst value of the simulated full sessions at 0.3 px noise
    (benchmarks/quality_gate.py prints them; docs/CALIBRATION.md "Quality gate"). The `reference_*`
    values are those worst full-session values, reported next to the measured 1-sigma."""

    reference_noise_px: float = 0.3  # every 1-sigma is taken at this noise per coordinate on every observation
    sigma_t_mm: float = 4.8  # 1-sigma of T_cam_proj's translation (all axes together)
    sigma_rot_deg: float = 0.385  # ... of its rotation
    sigma_camera_intrinsics_px: float = 3.2  # largest 1-sigma of the camera's fx, fy, cx, cy
    sigma_projector_intrinsics_px: float = 12.0  # ... of the projector's
    sigma_mirror_normal_deg: float = 0.26
    projection_camera_max_px: float = 9.7  # max over the image of the projection uncertainty grid
    projection_projector_max_px: float = 4.0
    # the worst of 24 simulated full sessions (8 scenarios x 3 seeds, 0.3 px noise): the pose, intrinsics
    # and mirror from `uncertainty.unit_noise` x 0.3 px (2026-12-02), the grids scaled by 0.3 px / the joint RMS
    reference_t_mm: float = 1.92
    reference_rot_deg: float = 0.154
    reference_camera_intrinsics_px: float = 1.29
    reference_projector_intrinsics_px: float = 4.79
    reference_mirror_normal_deg: float = 0.103
    reference_projection_camera_max_px: float = 3.87
    reference_projection_projector_max_px: float = 1.59


@dataclass(frozen=True)
class QualityReason:
    """One reason a trusted result is of low quality: the parameter's 1-sigma (`value`) against the
    `limit`, the worst full session's value (`reference`) and what to do (`advice`)."""

    code: str
    message: str
    value: float
    limit: float
    reference: float
    advice: str

    def to_dict(self) -> dict:
        return {"code": self.code, "message": self.message,
                "value": float(self.value) if math.isfinite(self.value) else None,
                "limit": self.limit, "reference": self.reference, "advice": self.advice}


@dataclass(frozen=True)
class TrustReason:
    code: str
    message: str
    value: float | None = None
    limit: float | None = None

    def to_dict(self) -> dict:
        return {"code": self.code, "message": self.message,
                "value": None if self.value is None or not math.isfinite(self.value) else float(self.value),
                "limit": self.limit}


@dataclass(frozen=True)
class TrustReport:
    """Outcome of check_calibration: `reasons` (empty when trusted) and the measured `metrics`."""

    reasons: tuple[TrustReason, ...] = ()
    metrics: dict = field(default_factory=dict)
    thresholds: TrustThresholds = field(default_factory=TrustThresholds)
    accepted_by_user: bool = False
    quality: tuple[QualityReason, ...] = ()
    quality_thresholds: QualityThresholds = field(default_factory=QualityThresholds)

    @property
    def low_quality(self) -> bool:
        """Trusted (or not) but far more uncertain than a full session: see `quality`."""
        return bool(self.quality)

    @property
    def quality_codes(self) -> list[str]:
        return [r.code for r in self.quality]

    @property
    def passed(self) -> bool:
        return not self.reasons

    @property
    def codes(self) -> list[str]:
        return [r.code for r in self.reasons]

    def reasons_text(self) -> str:
        """The reasons on one line, each with its code."""
        return "; ".join(f"{r.message} [{r.code}]" for r in self.reasons)

    def to_dict(self) -> dict:
        return {"passed": self.passed, "accepted_by_user": self.accepted_by_user,
                "reasons": [r.to_dict() for r in self.reasons],
                "metrics": {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                            for k, v in self.metrics.items()},
                "thresholds": asdict(self.thresholds),
                "quality": {"low": self.low_quality, "reasons": [r.to_dict() for r in self.quality],
                            "thresholds": asdict(self.quality_thresholds)}}


def check_calibration(result, thresholds: TrustThresholds | None = None,
                      quality_thresholds: QualityThresholds | None = None, observations=None) -> TrustReport:
    """Check a CalibrationResult (any method) for the failures listed in CODES, and its quality
    (QUALITY_CODES); never raises on a bad result (that is what the report is for). With the
    `observations` it was calibrated from (calib.models.observations.SessionObservations), the result
    must also reproduce them (observations_disagree) and the lit points are the pattern's own."""
    th = thresholds or TrustThresholds()
    qth = quality_thresholds or QualityThresholds()
    reasons: list[TrustReason] = []
    metrics: dict = {}

    def fail(code, message, value=None, limit=None):
        reasons.append(TrustReason(code, message, None if value is None else float(value), limit))

    finite = _finite_parameters(result)
    if finite:
        fail("non_finite", f"non-finite (NaN or infinite) values in {', '.join(finite)}")
        return TrustReport(tuple(reasons), metrics, th)
    reach = _observed_reach(result, observations) if observations is not None else {}
    for name, dev in (("camera", result.camera), ("projector", result.projector)):
        _check_device(name, dev, th, fail, metrics, reach.get(name, 1.0))
    _check_rms(result, th, fail, metrics)
    _check_geometry(result, th, fail, metrics, observations is None)
    if observations is not None:
        _check_observations(result, observations, th, fail, metrics)
    _check_uncertainty(result, th, fail, metrics)
    quality = check_quality(result, metrics, qth)
    return TrustReport(tuple(reasons), metrics, th, quality=quality, quality_thresholds=qth)


def check_device(name: str, dev: CameraModel, thresholds: TrustThresholds | None = None) -> TrustReport:
    """The device checks of check_calibration for one camera or projector model alone (intrinsics given
    from a file, before they are used): focal lengths, field of view, aspect, principal point, distortion
    scale. Not the folds: a polynomial may fold beyond the points it was fitted to without harm, and which
    those are is known only with the observations (check_calibration judges it then)."""
    th = thresholds or TrustThresholds()
    reasons: list[TrustReason] = []
    metrics: dict = {}
    _check_device(name, dev, th, lambda code, message, value=None, limit=None: reasons.append(
        TrustReason(code, message, None if value is None else float(value), limit)), metrics, reach=0.0)
    return TrustReport(tuple(reasons), metrics, th)


# ---- quality gate ------------------------------------------------------------------------------------
#: quality metric -> its key in `uncertainty.unit_noise` (calib.joint.uncertainty)
_UNIT_KEYS = {"t_mm": "t_total", "rot_deg": "rot_total_deg"}
_UNIT_FIELDS = ("t_total", "rot_total_deg", "camera_intrinsics_px", "projector_intrinsics_px", "mirror_normal_deg")


def _unit_noise(u) -> dict | None:
    """calibration.json's `uncertainty.unit_noise` (untrusted when read from a file): used only when every
    field is absent, null or a finite number >= 0 (a NaN, a negative, a string or a boolean would bend
    the gate's verdict); otherwise None, and the gate scales by the RMS instead."""
    if not isinstance(u, dict):
        return None
    for k in _UNIT_FIELDS:
        v = u.get(k)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            return None
    return u

def check_quality(result, metrics: dict, qth: QualityThresholds) -> tuple[QualityReason, ...]:
    """The quality reasons of a result, from the 1-sigma metrics the uncertainty check measured (joint
    covariance) and the result's projection-uncertainty grid.

    The gate judges the geometry of the session (how many and how varied the poses, how much of the
    images they cover), not the detection noise: each 1-sigma is taken at the reference noise
    (`qth.reference_noise_px`, the noise of the simulated full sessions the limits come from) on every
    observation: from the joint covariance recomputed with 1 px on every observation
    (`uncertainty.unit_noise`) times the reference noise; for a result without it (older files, a
    recalibration) by sqrt(2) x reference_noise / the joint RMS (the RMS is a per-point 2D norm), and the
    projection-uncertainty grids by reference_noise / the joint RMS, as their limits were derived. (The RMS scaling judged a session
    whose ChArUco corners were cleaner than its circles as thinner than it was: the joint RMS fell,
    the pattern's share of the pose's uncertainty did not.) The scaled values go
    into `metrics` ("quality.*"). Methods without a covariance (paper) have nothing to judge: no reasons."""
    out: list[QualityReason] = []
    rms = (result.rms or {}).get("joint") if isinstance(result.rms, dict) else None
    if not isinstance(rms, (int, float)) or not math.isfinite(rms) or rms <= 0:
        return ()
    scale = qth.reference_noise_px / float(rms)
    metrics["quality.noise_scale"] = scale
    unc = result.uncertainty if isinstance(result.uncertainty, dict) else {}
    unit = _unit_noise(unc.get("unit_noise"))
    if unit is not None:
        metrics["quality.scaled_by"] = "unit_noise"

    def at_reference(key, raw):
        """The 1-sigma at the reference noise: from the covariance with the same noise on every
        observation when the result has it (joint, `uncertainty.unit_noise`), else scaled by the RMS."""
        u = unit.get(_UNIT_KEYS.get(key, key)) if unit is not None else None
        if isinstance(u, (int, float)):
            return float(u) * qth.reference_noise_px * (_MM_PER_UNIT.get(result.units, 1.0) if key == "t_mm" else 1.0)
        if key.startswith("projection_"):  # the grids' limits were derived with the RMS scaling itself
            return raw * scale
        # the joint RMS is a per-point 2D norm, sqrt(2) x the per-coordinate noise the limits assume
        # (the 24 full sessions: unit-noise values 1.38-1.39 x the RMS-scaled ones)
        return raw * scale * math.sqrt(2.0)

    def low(code, key, what, raw, limit, reference, unit_name, advice):
        value = at_reference(key, raw)
        metrics[f"quality.{key}"] = value
        if not value <= limit:  # NaN / inf too
            shown = (f"{raw:.3g} {unit_name} (1 sigma at this session's {rms:.3g} px RMS; {value:.3g} {unit_name} at "
                     f"{qth.reference_noise_px:g} px of noise" if math.isfinite(value) else
                     "an amount that cannot be computed (singular covariance")
            out.append(QualityReason(code, f"LOW QUALITY: {what} is uncertain by {shown}; limit {limit:g} {unit_name}, "
                                     f"worst full session {reference:g} {unit_name}): {advice}",
                                     float(value), limit, reference, advice))

    m = metrics
    if "sigma.t_mm" in m:
        low("quality_pose_translation", "t_mm", "the projector's position", m["sigma.t_mm"], qth.sigma_t_mm,
            qth.reference_t_mm, "mm", _ADVICE_POSES)
    if "sigma.rot_deg" in m:
        low("quality_pose_rotation", "rot_deg", "the projector's orientation", m["sigma.rot_deg"], qth.sigma_rot_deg,
            qth.reference_rot_deg, "deg", _ADVICE_POSES)
    for dev, lim, ref in (("camera", qth.sigma_camera_intrinsics_px, qth.reference_camera_intrinsics_px),
                          ("projector", qth.sigma_projector_intrinsics_px, qth.reference_projector_intrinsics_px)):
        if f"sigma.{dev}_intrinsics_px" in m:
            low(f"quality_{dev}_intrinsics", f"{dev}_intrinsics_px", f"the {dev}'s fx, fy, cx, cy (largest)",
                m[f"sigma.{dev}_intrinsics_px"], lim, ref, "px", _ADVICE_INTRINSICS)
    if "sigma.mirror_normal_deg" in m:
        low("quality_mirror_normal", "mirror_normal_deg", "the mirror normal", m["sigma.mirror_normal_deg"],
            qth.sigma_mirror_normal_deg, qth.reference_mirror_normal_deg, "deg", _ADVICE_MIRROR)
    pu = getattr(result, "projection_uncertainty", None)
    if isinstance(pu, dict):
        for dev, lim, ref in (("camera", qth.projection_camera_max_px, qth.reference_projection_camera_max_px),
                              ("projector", qth.projection_projector_max_px,
                               qth.reference_projection_projector_max_px)):
            g = pu.get(dev)
            if not isinstance(g, dict) or g.get("fixed") or not isinstance(g.get("max_px"), (int, float)):
                continue
            places = large_regions(g, lim / scale) or [where_max(g) or "the image"]
            low(f"quality_{dev}_projection", f"projection_{dev}_max_px",
                f"where the {dev} projects a ray (max over the image, at the {where_max(g)})", float(g["max_px"]),
                lim, ref, "px", f"{_ADVICE_INTRINSICS}; above the limit at: {', '.join(places)}")
    return tuple(out)


# ---- checks ------------------------------------------------------------------------------------------
def _finite_parameters(result) -> list[str]:
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


def _image_corners(dev: CameraModel) -> np.ndarray:
    """The outer corners of a device's image (pixel centres at integers: the edges at -0.5 and size - 0.5)."""
    return np.array([[-0.5, -0.5], [dev.width - 0.5, -0.5], [-0.5, dev.height - 0.5],
                     [dev.width - 0.5, dev.height - 0.5]])


def _normalised_radius(dev: CameraModel, uv: np.ndarray) -> float:
    """The largest distance of pixels `uv` from the principal point in focal lengths (distorted radius)."""
    m = (np.asarray(uv, float).reshape(-1, 2) - [dev.cx, dev.cy]) / [dev.fx, dev.fy]
    return float(np.max(np.hypot(m[:, 0], m[:, 1])))


def _observed_reach(result, obs) -> dict:
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


def _check_device(name: str, dev: CameraModel, th: TrustThresholds, fail, metrics: dict,
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


def _check_rms(result, th: TrustThresholds, fail, metrics: dict) -> None:
    rms = {k: v for k, v in (result.rms or {}).items() if isinstance(v, (int, float))}
    # joint: every class in camera pixels; paper: camera (camera px), projector and stereo (projector px),
    # mirror_plane (board units: not a pixel residual)
    for key, v in rms.items():
        if key == "mirror_plane":
            continue
        projector_px = result.method != "joint" and key in ("projector", "stereo")
        limit = th.rms_projector_px if projector_px else th.rms_camera_px
        metrics[f"rms.{key}"] = float(v)
        if v > limit:
            unit = "projector px" if projector_px else "px"
            fail("rms_high", f"the {key} RMS of {v:.3g} {unit} is far above the detection noise (limit "
                 f"{limit:g}): the observations do not fit one rig", v, limit)


def _check_geometry(result, th: TrustThresholds, fail, metrics: dict, lit_from_poses: bool = True) -> None:
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


def _check_observations(result, obs, th: TrustThresholds, fail, metrics: dict) -> None:
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


def _check_uncertainty(result, th: TrustThresholds, fail, metrics: dict) -> None:
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


def low_quality_lines(result) -> list[str]:
    """The quality reasons recorded in a result's diagnostics["trust"] (by calib.pipeline's trust check),
    one line each with its code; [] when the result is not of low quality or carries no trust report."""
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    q = (diag.get("trust") or {}).get("quality") if isinstance(diag.get("trust"), dict) else None
    if not isinstance(q, dict):
        return []
    return [f"[{r.get('code')}] {r.get('message')}" for r in q.get("reasons") or [] if isinstance(r, dict)]
