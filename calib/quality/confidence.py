"""How well the captures so far constrain what each capture step measures, against a full session's:
the basis for ending a step when the calibration is confident instead of after a fixed count
(docs/CALIBRATION.md "Stopping when confident").

A step is confident when every 1-sigma it constrains is at or below its target:
- the mirror steps: the mirror normal (deg);
- the projector step: the projector's position (mm) and orientation (deg), the largest 1-sigma of the
  projector's fx, fy, cx, cy and of the camera's (px), and the projection uncertainty over each device's
  image (the max of its grid, px: distortion and intrinsics together).

The 1-sigmas are the joint adjustment's own (its covariance at the session's measured noise), so a rig
with cleaner observations becomes confident with fewer placements and a noisier one needs more. The
targets are `TARGET_FRACTION` of the quality gate's references (calib.quality._trust_gate
QualityThresholds.reference_*: the worst of the simulated full sessions at 0.3 px of noise, a pessimistic
noise): `benchmarks` and `procam bench placements` measure which fraction keeps a stopped session as
accurate as a full one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from calib.models.boards import MM_PER_UNIT
from calib.models.vocab import Step
from calib.quality._trust_gate import QualityThresholds

#: share of the quality gate's reference 1-sigma (worst full session at 0.3 px) a step must reach
TARGET_FRACTION = 0.07


@dataclass(frozen=True)
class Quantity:
    """One 1-sigma a step constrains, its target and unit."""

    key: str
    label: str
    unit: str
    sigma: float  # inf when the calibration could not give it
    target: float

    @property
    def met(self) -> bool:
        return math.isfinite(self.sigma) and self.sigma <= self.target

    def line(self) -> str:
        shown = "-" if not math.isfinite(self.sigma) else f"{self.sigma:.3g}"
        return f"{self.label}: {shown} {self.unit} (target {self.target:.3g}){'' if self.met else ' not yet'}"


@dataclass(frozen=True)
class Confidence:
    """The confidence of one step: its quantities, and why there are none (a calibration that failed)."""

    step: str
    quantities: tuple[Quantity, ...]
    reason: str | None = None  # set when the calibration of the captures so far failed (unconfident)
    outlook: str | None = None  # a mirror step not yet confident: what limits it, what more would give

    @property
    def all_met(self) -> bool:
        return self.reason is None and bool(self.quantities) and all(q.met for q in self.quantities)

    def lines(self) -> list[str]:
        return (([f"not yet: {self.reason}"] if self.reason else []) + [q.line() for q in self.quantities]
                + ([self.outlook] if self.outlook and not self.all_met else []))


# (key, label, unit, reference attribute of QualityThresholds)
_MIRROR = (("mirror_normal_deg", "mirror normal", "deg", "reference_mirror_normal_deg"),)
_PROJECTOR = (
    ("t_mm", "projector position", "mm", "reference_t_mm"),
    ("rot_deg", "projector orientation", "deg", "reference_rot_deg"),
    ("projector_intrinsics_px", "projector fx, fy, cx, cy", "px", "reference_projector_intrinsics_px"),
    ("camera_intrinsics_px", "camera fx, fy, cx, cy", "px", "reference_camera_intrinsics_px"),
    ("projection_projector_max_px", "projector over its image", "px", "reference_projection_projector_max_px"),
    ("projection_camera_max_px", "camera over its image", "px", "reference_projection_camera_max_px"),
)


def _step_quantities(step: str):
    return _PROJECTOR if step == Step.PROJECTOR else _MIRROR


def targets(step: str, fraction: float | None = None,
            thresholds: QualityThresholds | None = None) -> dict[str, float]:
    """{quantity key: target 1-sigma} of a step (`fraction` None: TARGET_FRACTION)."""
    th = thresholds or QualityThresholds()
    fraction = TARGET_FRACTION if fraction is None else fraction
    return {key: fraction * getattr(th, ref) for key, _, _, ref in _step_quantities(step)}


def sigmas(result) -> dict[str, float]:
    """The 1-sigma values a result carries (its joint covariance at the measured noise, its projection
    uncertainty grids); inf where it has none."""
    inf = math.inf
    unc = result.uncertainty if isinstance(result.uncertainty, dict) else {}
    pose = unc.get("T_cam_proj") or {}
    mm = MM_PER_UNIT.get(result.units, 1.0)

    def intrinsics(dev):
        d = unc.get(dev) or {}
        vals = [d.get(k) for k in ("fx", "fy", "cx", "cy")]
        if d.get("fixed"):
            return 0.0  # given, not estimated: nothing for this session to constrain
        return max(vals) if all(isinstance(v, (int, float)) for v in vals) else inf

    def grid_max(dev):
        g = ((result.projection_uncertainty or {}).get(dev) or {}) if isinstance(result.projection_uncertainty, dict) else {}
        if g.get("fixed"):
            return 0.0
        v = g.get("max_px")
        return float(v) if isinstance(v, (int, float)) else inf

    mirror = unc.get("mirror") or {}
    t = pose.get("t_total")
    r = pose.get("rot_total_deg")
    return {
        "mirror_normal_deg": float(mirror["normal_deg"]) if isinstance(mirror.get("normal_deg"), (int, float)) else inf,
        "t_mm": float(t) * mm if isinstance(t, (int, float)) else inf,
        "rot_deg": float(r) if isinstance(r, (int, float)) else inf,
        "projector_intrinsics_px": intrinsics("projector"),
        "camera_intrinsics_px": intrinsics("camera"),
        "projection_projector_max_px": grid_max("projector"),
        "projection_camera_max_px": grid_max("camera"),
    }


#: the outlook's "more placements": a few, enough to tell which step's placements would help more
OUTLOOK_PLACEMENTS = 4


def mirror_outlook(result) -> str | None:
    """What limits the mirror normal's 1-sigma and what more placements would bring it to, from the joint
    result's outlook (calib.joint.uncertainty: each further placement assumed as informative as the mean
    of the session's placements of that step); None without one."""
    unc = result.uncertainty if isinstance(getattr(result, "uncertainty", None), dict) else {}
    m = unc.get("mirror") or {}
    given = m.get("normal_deg_given_camera")
    if not isinstance(given, (int, float)):
        return None
    whole = m.get("normal_deg")
    if isinstance(whole, (int, float)) and given >= 0.95 * whole:  # a given camera, or one well known
        parts = [f"the mirror views' own share {given:.3g} deg (nearly all of it)"]
    else:
        parts = [f"the mirror views' own share {given:.3g} deg (the rest comes from the camera's intrinsics "
                 "and distortion)"]
    k = OUTLOOK_PLACEMENTS
    for step in ("mirror", "projector"):
        more = m.get(f"normal_deg_with_more_{step}") or []
        if len(more) >= k and isinstance(more[k - 1], (int, float)):
            parts.append(f"{k} more {step} placements: about {more[k - 1]:.3g} deg")
    return "mirror normal outlook: " + "; ".join(parts)


def confidence_of(result, step: str, fraction: float | None = None,
                  thresholds: QualityThresholds | None = None) -> Confidence:
    """The confidence of `step` in a calibrated result (a mirror step's with its outlook)."""
    got = sigmas(result)
    goal = targets(step, fraction, thresholds)
    return Confidence(step, tuple(Quantity(key, label, unit, got[key], goal[key])
                                  for key, label, unit, _ in _step_quantities(step)),
                      outlook=None if step == Step.PROJECTOR else mirror_outlook(result))


def unconfident(step: str, reason: str, fraction: float | None = None,
                thresholds: QualityThresholds | None = None) -> Confidence:
    """The confidence of a step whose captures so far do not calibrate (`reason`): nothing met."""
    goal = targets(step, fraction, thresholds)
    return Confidence(step, tuple(Quantity(key, label, unit, math.inf, goal[key])
                                  for key, label, unit, _ in _step_quantities(step)), reason=reason)
