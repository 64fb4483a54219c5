"""Stage 1 of a recalibration: which parts moved since the previous calibration (check_rig)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.errors import CalibrationError
from calib.models.observations import SessionObservations
from calib.models.result import CalibrationResult
from calib.recalib._model import PARTS, Fit, fit_blocks, previous_covariance
from calib.transforms import rotvec_covariance, rotvec_from_gibbs

ALPHA = 1e-3  # the check's rule: calib.recalib's docstring
SYSTEMATIC_FACTOR = 2.0


# ---- stage 1: check ---------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PartCheck:
    part: str
    status: str  # "moved" | "unchanged" | "not checked"
    change: dict  # the fitted change in physical units (px, deg, units)
    sigma: dict  # its combined 1-sigma (previous and new), same keys
    mahalanobis2: float | None
    threshold: float | None
    captures: int
    reason: str

    @property
    def moved(self) -> bool:
        return self.status == "moved"

    def to_dict(self) -> dict:
        return {"part": self.part, "status": self.status, "change": self.change, "sigma": self.sigma,
                "mahalanobis2": self.mahalanobis2, "threshold": self.threshold, "captures": self.captures,
                "reason": self.reason}


@dataclass(frozen=True, eq=False)
class CheckReport:
    parts: dict  # part -> PartCheck
    current: CalibrationResult  # the previous calibration with the parts found moved provisionally re-fitted
    rule: str = ""

    @property
    def moved(self) -> tuple[str, ...]:
        return tuple(p for p in PARTS if p in self.parts and self.parts[p].moved)

    @property
    def verdict(self) -> str:
        if any(c.status == "not checked" for c in self.parts.values()):
            return "incomplete"
        return "unchanged" if not self.moved else "moved: " + ", ".join(self.moved)

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "moved": list(self.moved), "rule": self.rule,
                "parts": {p: c.to_dict() for p, c in self.parts.items()}}


def describe_change(part: str, delta: np.ndarray, cov: np.ndarray, units: str) -> tuple[dict, dict]:
    """(change, 1-sigma) of a block's correction in physical units."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    if part in ("camera", "cam_intr", "proj_intr"):  # fx, fy, cx, cy first (distortion not described)
        keys = ("fx_px", "fy_px", "cx_px", "cy_px")
        return ({k: float(v) for k, v in zip(keys, delta)}, {k: float(v) for k, v in zip(keys, sd)})
    if part == "mirror":
        return ({"normal_deg": math.degrees(float(np.linalg.norm(delta[:2]))), f"d_{units}": float(delta[2])},
                {"normal_deg": math.degrees(float(np.sqrt(cov[0, 0] + cov[1, 1]))), f"d_{units}": float(sd[2])})
    # the rotation's Gibbs vector as a rotation vector (its norm the angle), its covariance with it
    g = np.asarray(delta[:3], float)
    cov_rot = rotvec_covariance(cov[:3, :3], g)
    return ({"rot_deg": math.degrees(float(np.linalg.norm(rotvec_from_gibbs(g)))),
             f"t_{units}": float(np.linalg.norm(delta[3:])), f"t_xyz_{units}": [float(v) for v in delta[3:]]},
            {"rot_deg": math.degrees(float(np.sqrt(np.trace(cov_rot)))),
             f"t_{units}": float(np.sqrt(np.trace(cov[3:, 3:])))})


def describe_movement(check: PartCheck, units: str) -> str:
    """A part's fitted change in physical units with its 1-sigma: what the check's statistic stands for
    ("" for a part not checked)."""
    c, s = check.change, check.sigma
    if not c:
        return ""
    if check.part == "camera":
        return (f"fx {c['fx_px']:+.2f} px, fy {c['fy_px']:+.2f} px (1-sigma {s['fx_px']:.2f}, "
                f"{s['fy_px']:.2f} px)")
    if check.part == "mirror":
        return (f"tilted {c['normal_deg']:.3f} deg, offset {c[f'd_{units}']:+.2f} {units} (1-sigma "
                f"{s['normal_deg']:.3f} deg, {s[f'd_{units}']:.2f} {units})")
    return (f"turned {c['rot_deg']:.3f} deg, shifted {c[f't_{units}']:.2f} {units} (1-sigma {s['rot_deg']:.3f} deg, "
            f"{s[f't_{units}']:.2f} {units})")


def _test(previous: CalibrationResult, fit: Fit, part: str, alpha: float, factor: float) -> PartCheck:
    from scipy.stats import chi2

    d, Cn = fit.delta[part], fit.cov[part]
    Cp = previous_covariance(previous, part)
    change, sigma = describe_change(part, d, Cp + Cn, previous.units)
    if part == "camera":  # tested on the focal lengths (what a refocus changes); cx, cy re-fitted with them
        d, Cn, Cp = d[:2], Cn[:2, :2], Cp[:2, :2]
    C = factor**2 * (Cp + Cn)
    try:
        m2 = float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        m2 = float(d @ np.linalg.pinv(C) @ d)
    thr = float(chi2.ppf(1.0 - alpha, len(d)))
    moved = m2 > thr
    reason = (f"change {m2:.1f} > {thr:.1f} (chi-square, {len(d)} dof, p < {alpha:g}) in units of {factor:g}x the "
              f"combined 1-sigma of the previous calibration and these {fit.n_views} captures" if moved else
              f"change {m2:.1f} <= {thr:.1f}: within {factor:g}x the combined 1-sigma")
    return PartCheck(part, "moved" if moved else "unchanged", change, sigma, m2, thr, fit.n_views, reason)


def check_rig(previous: CalibrationResult, obs: SessionObservations, alpha: float = ALPHA,
              factor: float = SYSTEMATIC_FACTOR) -> CheckReport:
    """Stage 1: for the camera intrinsics, the mirror and the projector pose, whether the new captures
    `obs` agree with `previous` (see the module docstring for the rule). A part without the captures
    its test needs is "not checked"."""
    parts = {}
    cur = previous
    rule = (f"moved when d^T (F^2 (C_prev + C_new))^-1 d > chi2.ppf(1 - {alpha:g}, dim), F = {factor:g}; "
            "parts tested in order camera, mirror, projector, each with the earlier verdicts held")
    # (part, blocks fitted, observations, result attribute, what to capture when it cannot be tested); the
    # camera from every board view with the mirror free (views through the mirror constrain it too)
    order = (("camera", ("camera", "mirror"), "boards", "camera", ""),
             ("mirror", ("mirror",), "mirror", "mirror", ": capture the board held between camera and mirror"),
             ("projector", ("projector",), "pattern", "T_cam_proj", ": capture the board with the pattern on it"))
    for part, blocks, data, attr, hint in order:
        if part == "mirror" and previous.mirror is None:
            continue
        try:
            fit = fit_blocks(cur, obs, blocks, data)
            parts[part] = _test(previous, fit, part, alpha, factor)
            if parts[part].moved:
                cur = cur.with_(**{attr: getattr(fit.result, attr)})
        except CalibrationError as e:
            parts[part] = PartCheck(part, "not checked", {}, {}, None, None, 0, f"{e}{hint}")
    return CheckReport(parts, cur, rule)


def merge_observations(a: SessionObservations, b: SessionObservations) -> SessionObservations:
    """The captures of `a` and `b` together (same rig and boards): the check's captures count for the
    re-estimate too."""
    from dataclasses import replace

    return replace(a, projector_views=tuple(a.projector_views) + tuple(b.projector_views),
                   mirror_views=tuple(a.mirror_views) + tuple(b.mirror_views),
                   skipped=tuple(a.skipped) + tuple(b.skipped))
