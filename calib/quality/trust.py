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

The checks live behind this module (their public names are re-exported here): one device model's
(calib/quality/_trust_devices.py), the solved rig's (calib/quality/_trust_solution.py) and the
quality gate (calib/quality/_trust_gate.py).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from calib.models.camera import CameraModel
from calib.quality._trust_devices import (
    check_device_model,
    field_of_view_deg,
    observed_reach,
    radial_corner_scale,
    radial_fold_fraction,
)
from calib.quality._trust_gate import (
    QUALITY_CODES,
    QualityReason,
    QualityThresholds,
    check_quality,
)
from calib.quality._trust_solution import (
    check_geometry,
    check_observations,
    check_rms,
    check_uncertainty,
    correlation_condition,
    non_finite_parameters,
)

__all__ = ["CODES", "QUALITY_CODES", "QualityReason", "QualityThresholds", "TrustReason", "TrustReport",
           "TrustThresholds", "check_calibration", "check_device", "check_quality", "correlation_condition",
           "field_of_view_deg", "low_quality_lines", "radial_corner_scale", "radial_fold_fraction"]

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

    finite = non_finite_parameters(result)
    if finite:
        fail("non_finite", f"non-finite (NaN or infinite) values in {', '.join(finite)}")
        return TrustReport(tuple(reasons), metrics, th)
    reach = observed_reach(result, observations) if observations is not None else {}
    for name, dev in (("camera", result.camera), ("projector", result.projector)):
        check_device_model(name, dev, th, fail, metrics, reach.get(name, 1.0))
    check_rms(result, th, fail, metrics)
    check_geometry(result, th, fail, metrics, observations is None)
    if observations is not None:
        check_observations(result, observations, th, fail, metrics)
    check_uncertainty(result, th, fail, metrics)
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
    check_device_model(name, dev, th, lambda code, message, value=None, limit=None: reasons.append(
        TrustReason(code, message, None if value is None else float(value), limit)), metrics, reach=0.0)
    return TrustReport(tuple(reasons), metrics, th)


def low_quality_lines(result) -> list[str]:
    """The quality reasons recorded in a result's diagnostics["trust"] (by calib.pipeline's trust check),
    one line each with its code; [] when the result is not of low quality or carries no trust report."""
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    q = (diag.get("trust") or {}).get("quality") if isinstance(diag.get("trust"), dict) else None
    if not isinstance(q, dict):
        return []
    return [f"[{r.get('code')}] {r.get('message')}" for r in q.get("reasons") or [] if isinstance(r, dict)]
