"""The quality gate of calib.quality.trust (behind it): a trusted result far more uncertain than a full
session's is of low quality, each reason with the measured 1-sigma, the limit, the worst full
session's value and what to do (docs/CALIBRATION.md "Quality gate")."""

from __future__ import annotations

import math
from dataclasses import dataclass

from calib.models.boards import MM_PER_UNIT as _MM_PER_UNIT
from calib.quality.projection_uncertainty import large_regions, where_max

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

