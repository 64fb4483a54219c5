"""Stage 2 of a recalibration: the moved parts re-fitted, the intrinsics under a prior (reestimate)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.errors import CalibrationError
from calib.models.observations import SessionObservations
from calib.models.result import CalibrationResult
from calib.recalib._model import (
    PARTS,
    Fit,
    _class_sigma,
    _initial_pose,
    _pose_start,
    _pose_T,
    _residuals,
    _views,
    fit_blocks,
)
from calib.recalib.check import describe_change
from calib.recalib.prior import (
    INTRINSICS_MODES,
    _dist_index,
    _stored_covariance,
    intrinsics_prior,
)
from calib.transforms import rotvec_covariance, tangent_basis

#: 1-sigma targets of a re-estimate where the previous calibration reports none (see targets_from)
DEFAULT_TARGETS = {"projector_t": 0.5, "projector_rot_deg": 0.05, "mirror_normal_deg": 0.05, "mirror_d": 0.5,
                   "camera_f_px": 1.0}


# ---- stage 2: re-estimate ---------------------------------------------------------------------------
def targets_from(previous: CalibrationResult) -> dict:
    """The 1-sigma a re-estimated part must reach: the previous calibration's own 1-sigma of that part
    (a recalibration at least as certain as the calibration it replaces); DEFAULT_TARGETS where the
    previous calibration reports none (or held the part fixed)."""
    u = previous.uncertainty if isinstance(previous.uncertainty, dict) else {}
    out = dict(DEFAULT_TARGETS)

    def pos(v):
        return isinstance(v, (int, float)) and math.isfinite(v) and v > 0

    t = u.get("T_cam_proj") or {}
    if pos(t.get("t_total")):
        out["projector_t"] = float(t["t_total"])
    if pos(t.get("rot_total_deg")):
        out["projector_rot_deg"] = float(t["rot_total_deg"])
    m = u.get("mirror") or {}
    if pos(m.get("normal_deg")):
        out["mirror_normal_deg"] = float(m["normal_deg"])
    if pos(m.get("d")):
        out["mirror_d"] = float(m["d"])
    c = u.get("camera") or {}
    if pos(c.get("fx")) and pos(c.get("fy")):
        out["camera_f_px"] = max(float(c["fx"]), float(c["fy"]))
    return out


_USE = {"camera": "boards", "mirror": "mirror", "projector": "pattern"}


#: how a re-estimate treats the intrinsics of the parts it does not re-fit (docs/RECALIBRATION.md,
#: "Intrinsics: held or prior", for the numbers behind the default)
DEFAULT_INTRINSICS = "prior"


_SIGMA_KEY = {"cam_intr": "camera_intrinsics", "proj_intr": "projector_intrinsics"}


@dataclass(frozen=True, eq=False)
class Reestimate:
    result: CalibrationResult
    parts: tuple[str, ...]
    sigma: dict  # part -> 1-sigma of the re-estimated parameters (describe_change keys)
    targets: dict
    reached: bool
    missing: tuple[str, ...]  # targets not reached, as sentences
    intrinsics: str = "held"  # the mode used: "held" | "prior" (see reestimate)
    intrinsics_note: str = ""
    #: under the prior: targets whose 1-sigma stays above the target only because of the previous
    #: intrinsics' uncertainty (the captures' own share is below it: more captures cannot help), as sentences
    floor: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {"parts": list(self.parts), "intrinsics": self.intrinsics, "intrinsics_note": self.intrinsics_note,
                "sigma": self.sigma, "targets": self.targets, "reached": self.reached, "missing": list(self.missing),
                "limited_by_previous_intrinsics": list(self.floor)}


def _missing(p: str, s: dict, targets: dict, u: str) -> list[str]:
    out = []
    if p == "camera" and max(s["fx_px"], s["fy_px"]) > targets["camera_f_px"]:
        out.append(f"camera focal length 1-sigma {max(s['fx_px'], s['fy_px']):.2f} px > "
                   f"{targets['camera_f_px']:.2f} px")
    if p == "mirror":
        if s["normal_deg"] > targets["mirror_normal_deg"]:
            out.append(f"mirror normal 1-sigma {s['normal_deg']:.3f} deg > {targets['mirror_normal_deg']:.3f} deg")
        if s[f"d_{u}"] > targets["mirror_d"]:
            out.append(f"mirror offset 1-sigma {s[f'd_{u}']:.3f} {u} > {targets['mirror_d']:.3f} {u}")
    if p == "projector":
        if s["rot_deg"] > targets["projector_rot_deg"]:
            out.append(f"projector rotation 1-sigma {s['rot_deg']:.3f} deg > {targets['projector_rot_deg']:.3f} deg")
        if s[f"t_{u}"] > targets["projector_t"]:
            out.append(f"projector position 1-sigma {s[f't_{u}']:.3f} {u} > {targets['projector_t']:.3f} {u}")
    return out


def reestimate(previous: CalibrationResult, obs: SessionObservations, parts, targets: dict | None = None,
               method: str = "recalibration", intrinsics: str = DEFAULT_INTRINSICS,
               prior_from: CalibrationResult | None = None) -> Reestimate:
    """Stage 2: re-fit only `parts` from the captures `obs`, with the 1-sigma of each and whether it
    reached `targets` (default: targets_from(previous)). `previous` is where the model starts (the
    check's `current`); `prior_from` the calibration whose values and covariance make the prior
    (default `previous`).

    intrinsics "held": the parts one after the other (camera, mirror, projector), each from the
    captures that see it, everything else held at `previous`. "prior": the camera first when it moved
    (re-fitted freely, as held), then the mirror and the projector together from their captures, with
    the intrinsics of both devices free under the Gaussian prior of the previous covariance (the
    camera's only when it did not move): their previous uncertainty propagates into the 1-sigma of the
    re-estimated parts. "prior" falls back to "held" (said in `intrinsics_note`) when the previous
    calibration stored no covariance."""
    if intrinsics not in INTRINSICS_MODES:
        raise CalibrationError(f"unknown intrinsics mode '{intrinsics}' ({' or '.join(INTRINSICS_MODES)})")
    prior_from = prior_from or previous
    targets = {**targets_from(prior_from), **(targets or {})}
    cur, sigma, missing, fits, floor = previous, {}, [], [], []
    u = previous.units
    note = ""
    todo = [p for p in PARTS if p in parts]
    rest = [p for p in todo if p != "camera"]
    prior = None
    if intrinsics == "prior":
        devices = ("proj",) if "camera" in todo else ("cam", "proj")
        if "projector" not in rest:
            devices = tuple(d for d in devices if d != "proj")  # the mirror's captures do not see the projector
        prior = intrinsics_prior(prior_from, previous, devices) if rest and devices else None
        if not rest or not devices:
            intrinsics, note = "held", "nothing to constrain by a prior (the camera re-fitted freely)"
        elif prior is None:
            intrinsics, note = "held", "the previous calibration stored no covariance of the intrinsics: held"
        else:
            note = (f"{', '.join(prior.blocks)} free under the previous covariance as a prior "
                    f"({prior.n} parameters, {prior.floored} eigenvalue(s) floored)")
    groups = [(p,) for p in todo] if prior is None else ([("camera",)] if "camera" in todo else []) + [tuple(rest)]
    for group in groups:
        use = "mirror+pattern" if len(group) > 1 else _USE[group[0]]
        with_prior = prior if group != ("camera",) else None
        if with_prior is not None:  # the prior's offset from where this fit starts
            with_prior = intrinsics_prior(prior_from, cur, tuple(b.split("_")[0] for b in prior.blocks))
        fit = fit_blocks(cur, obs, group, use, prior=with_prior)
        fits.append(fit)
        cur = fit.result
        for p in fit.delta:
            _, s = describe_change(p, fit.delta[p], fit.cov[p], u)
            sigma[_SIGMA_KEY.get(p, p)] = s
            if p not in PARTS:
                continue
            over = _missing(p, s, targets, u)
            if over and fit.cov_data is not None and p in fit.cov_data:
                # the captures' own share: where it meets the target, the rest is the previous intrinsics'
                # uncertainty (the prior), which no further capture of this part lowers
                _, s_data = describe_change(p, fit.delta[p], fit.cov_data[p], u)
                still = _missing(p, s_data, targets, u)
                floor += [f"{m} (from the captures alone: within the target; the rest is the previous "
                          "intrinsics' uncertainty)" for m in over if _same_quantity(m, still) is None]
                over = [m for m in over if _same_quantity(m, still) is not None]
            missing += over
    diag = dict(previous.diagnostics) if isinstance(previous.diagnostics, dict) else {}
    diag["recalibration"] = {"reestimated": todo, "intrinsics": intrinsics, "sigma": sigma}
    result = cur.with_(method=method, diagnostics=diag)
    result = _with_updated_uncertainty(result, prior_from, fits, intrinsics)
    return Reestimate(result, tuple(todo), sigma, targets, not missing, tuple(missing), intrinsics, note,
                      tuple(floor))


def _same_quantity(sentence: str, others: list[str]) -> str | None:
    """The sentence of `others` about the same quantity as `sentence` (both from _missing: the text before
    "1-sigma" names it), or None."""
    name = sentence.split(" 1-sigma")[0]
    return next((o for o in others if o.split(" 1-sigma")[0] == name), None)


# ---- the recalibrated result's uncertainty ----------------------------------------------------------
def _tilts_at_result(fit: Fit, result: CalibrationResult) -> np.ndarray:
    """The Jacobian A that re-expresses a fit's parameters about `result` (cov = A cov_fit A^T): the
    identity but for the mirror's tilts, taken from the tangent basis at the fitted normal to the one at
    the result's normal (calib.transforms.tangent_basis at two normals), where a stored covariance has them."""
    A = np.eye(len(fit.names))
    names = list(fit.names)
    if "mirror.tilt_1" in names and result.mirror is not None:
        i = names.index("mirror.tilt_1")
        u1, u2 = tangent_basis(fit.result.mirror.normal)  # at the fitted normal (the fit's start is < 1 deg away)
        e1, e2 = tangent_basis(result.mirror.normal)
        A[i:i + 2, i:i + 2] = [[e1 @ u1, e1 @ u2], [e2 @ u1, e2 @ u2]]
    return A


def _with_updated_uncertainty(result: CalibrationResult, previous: CalibrationResult, fits: list,
                              intrinsics: str) -> CalibrationResult:
    """`result` with an `uncertainty` that says what it is: the previous calibration's covariance with the
    rows and columns of every re-fitted parameter replaced by the re-estimate's (their correlation with
    the parameters not re-fitted set to 0: the fits held those), the 1-sigma summaries recomputed from
    it, the projection-uncertainty grids and the trust/quality report recomputed too. Without a stored
    covariance only the summaries of the re-estimated parts are replaced."""
    u = dict(previous.uncertainty) if isinstance(previous.uncertainty, dict) else None
    if u is None:
        return result
    u["unit_noise"] = None  # the previous session's geometry, not this one's: the gate scales by the RMS
    stored = _stored_covariance(previous)
    if stored is not None:
        names, M = stored
        M = M.copy()
        idx = {n: i for i, n in enumerate(names)}
        for fit in fits:
            keep = [k for k, n in enumerate(fit.names) if n in idx]
            A = _tilts_at_result(fit, result)
            C = (A @ fit.cov_global @ A.T)[np.ix_(keep, keep)]
            ii = [idx[fit.names[k]] for k in keep]
            M[ii, :] = 0.0
            M[:, ii] = 0.0
            M[np.ix_(ii, ii)] = C
        sd = np.sqrt(np.clip(np.diag(M), 0, None))

        def dev(prefix, old):
            if not isinstance(old, dict) or old.get("fixed") or f"{prefix}.fx" not in idx:
                return old
            new = dict(old)
            for k in ("fx", "fy", "cx", "cy"):
                new[k] = float(sd[idx[f"{prefix}.{k}"]])
            dist = list(old.get("dist") or [])
            for n in names:
                i = _dist_index(n) if n.startswith(f"{prefix}.dist") else None
                if i is not None and i < len(dist):
                    dist[i] = float(sd[idx[n]])
            new["dist"] = dist
            return new

        u["camera"] = dev("cam", u.get("camera"))
        u["projector"] = dev("proj", u.get("projector"))
        ri = [idx.get(f"T_cam_proj.rot_{a}") for a in "xyz"]
        ti = [idx.get(f"T_cam_proj.t_{a}") for a in "xyz"]
        if None not in ri + ti:
            cr, ct = rotvec_covariance(M[np.ix_(ri, ri)]), M[np.ix_(ti, ti)]
            u["T_cam_proj"] = {"t": np.sqrt(np.diag(ct)).tolist(), "t_total": float(np.sqrt(np.trace(ct))),
                               "rot_deg": np.degrees(np.sqrt(np.diag(cr))).tolist(),
                               "rot_total_deg": float(np.degrees(np.sqrt(np.trace(cr))))}
        mi = [idx.get("mirror.tilt_1"), idx.get("mirror.tilt_2"), idx.get("mirror.d")]
        if None not in mi and isinstance(u.get("mirror"), dict):
            u["mirror"] = {"normal_deg": float(np.degrees(np.sqrt(M[mi[0], mi[0]] + M[mi[1], mi[1]]))),
                           "d": float(sd[mi[2]])}
        u["covariance"] = dict(u["covariance"], matrix=M.tolist())
    else:
        for fit in fits:
            for p in fit.free:
                _, s = describe_change(p, fit.delta[p], fit.cov[p], previous.units)
                if p == "projector":
                    u["T_cam_proj"] = {"t_total": s[f"t_{previous.units}"], "rot_total_deg": s["rot_deg"]}
                elif p == "mirror":
                    u["mirror"] = {"normal_deg": s["normal_deg"], "d": s[f"d_{previous.units}"]}
    u["recalibration"] = {"intrinsics": intrinsics, "reestimated": sorted({p for f in fits for p in f.free}),
                          "note": "the re-fitted parameters' covariance from the recalibration's captures"
                                  + (" and the intrinsics prior" if intrinsics == "prior" else
                                     " with everything else held exact") + "; the rest the previous calibration's"}
    from calib.quality.projection_uncertainty import projection_uncertainty
    from calib.quality.trust import check_calibration

    out = result.with_(uncertainty=u)
    if previous.projection_uncertainty is not None:
        out = out.with_(projection_uncertainty=projection_uncertainty(out))
    diag = dict(out.diagnostics) if isinstance(out.diagnostics, dict) else {}
    diag["trust"] = check_calibration(out).to_dict()
    return out.with_(diagnostics=diag)


# ---- the recalibration's own residuals ------------------------------------------------------------
#: diagnostics of the previous calibration that describe its own captures (names this session lacks)
_PREVIOUS_CAPTURE_KEYS = ("worst_points", "board_poses", "rejected", "n_rejected", "views_left_out", "n_points",
                          "n_residuals", "sigma_px")


def own_residuals(cal: CalibrationResult, obs: SessionObservations) -> dict:
    """`cal`'s reprojection residuals (px) on this session's captures, each board pose fitted with the
    calibration held: "rms" per kind ("board", "pattern", "mirror_real", "mirror_virtual", "joint"),
    "per_view" (capture_id, step, n_points, rms_px, as a calibration's), "worst_views", and "dof" and
    "variance_factor" of the whitened residuals (6 pose parameters per view)."""
    from scipy.optimize import least_squares

    unit = dict.fromkeys(("board", "pattern", "mirror_real", "mirror_virtual"), 1.0)
    sig = _class_sigma(cal)
    per_view, e2 = [], {k: [] for k in unit}
    n_res, rw2 = 0, 0.0
    for v in _views(obs, "mirror+pattern"):
        mirror_view = v.real is not None and v.virtual is not None
        try:
            T0 = _initial_pose(cal, v)
            sol = least_squares(lambda p: _residuals(cal, v, _pose_T(T0, p), sig, mirror_view), _pose_start(T0))
        except Exception:  # no board pose: the capture has no residual to show (as the fits leave it out)
            per_view.append({"capture_id": v.capture_id, "step": "mirror" if mirror_view else "projector",
                             "n_points": 0, "rms_px": None})
            continue
        r = _residuals(cal, v, _pose_T(T0, sol.x), unit, mirror_view)
        n_res, rw2 = n_res + r.size, rw2 + float(sol.fun @ sol.fun)
        pts = r[0::2] ** 2 + r[1::2] ** 2
        kinds = [("mirror_real" if mirror_view else "board", v.real), ("mirror_virtual" if mirror_view else "board",
                                                                         v.virtual)]
        i = 0
        for kind, ob in kinds:
            if ob is not None:
                e2[kind].append(pts[i:i + len(ob.ids)])
                i += len(ob.ids)
        e2["pattern"].append(pts[i:])
        per_view.append({"capture_id": v.capture_id, "step": "mirror" if mirror_view else "projector",
                         "n_points": int(pts.size), "rms_px": float(np.sqrt(pts.mean())) if pts.size else None})
    every = [a for k in e2 for a in e2[k]]
    rms = {k: float(np.sqrt(np.concatenate(a).mean())) for k, a in (("joint", every), *e2.items())
           if a and np.concatenate(a).size}
    dof = max(n_res - 6 * sum(1 for p in per_view if p["n_points"]), 1)
    worst = sorted((p for p in per_view if p["rms_px"] is not None), key=lambda p: -p["rms_px"])[:5]
    return {"rms": rms, "per_view": per_view, "worst_views": worst, "dof": dof, "variance_factor": rw2 / dof}


def with_own_residuals(result: CalibrationResult, obs: SessionObservations, reestimated: bool) -> CalibrationResult:
    """`result` with this session's residuals in place of the previous calibration's (RMS, per-view,
    worst views; the previous session's per-capture diagnostics dropped). Re-estimated, its uncertainty
    came from these captures: their degrees of freedom and variance factor too."""
    own = own_residuals(result, obs)
    diag = {k: v for k, v in (result.diagnostics or {}).items() if k not in _PREVIOUS_CAPTURE_KEYS}
    diag["worst_views"] = own["worst_views"]
    u = result.uncertainty
    if reestimated and isinstance(u, dict):
        u = dict(u, dof=own["dof"], variance_factor=own["variance_factor"])
    return result.with_(rms=own["rms"], per_view=tuple(own["per_view"]), diagnostics=diag, uncertainty=u)
