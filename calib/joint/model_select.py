"""Distortion model selection per device: none / k1 / k1k2 / 5coef / rational (calib.joint.solver.DIST_MODELS).

The paper always uses 5 coefficients. Starting from that, a device's model is

* simplified to the simplest of none / k1 / k1k2 that is NOT significantly worse than 5coef: a
  likelihood-ratio (Wald) test, W = (RSS_simple - RSS_5) / sigma^2 ~ chi2(dropped coefficients), keeps
  the simpler model when its p-value is above `alpha_drop` (0.05) -- so a coefficient that the data do
  show (even a k3 of -0.02 under 0.3 px noise) is kept, because dropping it biases everything else;
* enriched to rational only when the three extra coefficients are highly significant: W = (RSS_5 -
  RSS_rational) / sigma^2 with p-value below `alpha_add` (0.001). The rational terms are nearly
  degenerate with k1..k3, so they need strong evidence; on Brown-Conrady data they are picked with
  probability 0.001.

sigma^2 = RSS_5 / (N - P) from the 5-coefficient fit. The BIC (N ln(RSS/N) + P ln N) of every candidate
is reported too, and selection="bic" uses it instead (more parsimonious: it drops small real
coefficients under noise).

How the RSS of each candidate is obtained: the joint problem is solved once with 5 coefficients per
device. Around that solution the least-squares problem is quadratic to first order, with the board
poses eliminated by the Schur complement; the Jacobian is taken with the rational model's 8
coefficients (the extra three at 0). For every pair (camera model, projector model) the RSS is the
minimum of that quadratic model with the coefficients the candidate does not have held at zero (a
Wald test for simpler models, a score test for the rational one; exact for a linear problem). The
chosen pair is then fitted for real (full nonlinear adjustment) and the test repeated on the actual
RSS; if it no longer holds, the 5-coefficient model is kept. A model forced by the user is kept.

Coverage (options.coverage, the default): the residuals only judge a coefficient where there are
observations. After the BIC / LRT choice, a model with k3 is weighed again over the whole image
(coverage_choice: estimated mean squared projection error, bias + variance, from the same quadratic
model) against the same model without its highest radial orders (DistortionModel.FOURCOEF = k1 k2 p1 p2, OpenCV's
CALIB_FIX_K3); the simpler one replaces it when it is predicted at least 10% better. Such a choice is
refitted for real and kept (the BIC confirmation would undo it). docs/JOINT.md has the measurements.

k3 shrinkage (options.shrinkage, off by default): instead of keeping or dropping a 5coef model's k3 whole,
a zero-mean Gaussian prior whose width the data set (empirical Bayes over the image: shrinkage_prior)
pulls it toward 0 in one more solve; the prior stays in the covariance. Measured better on the wide-angle
corner-poor sessions and worse on one real-mirror session's weakly seen real k3 (docs/JOINT.md).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from calib.joint.solver import DIST_MODELS, SELECTION_MODELS, normal_blocks, solve
from calib.models.camera import CameraModel
from calib.models.vocab import DistortionModel
from calib.quality.projection_uncertainty import grid_pixels, motion_fields


def chi2_sf(x: float, k: int) -> float:
    """P(X > x) for X ~ chi-squared with k (integer >= 1) degrees of freedom: the regularised upper
    incomplete gamma Q(k/2, x/2), summed in closed form (Q(1/2, y) = erfc(sqrt y), Q(1, y) = e^-y,
    Q(s + 1, y) = Q(s, y) + y^s e^-y / Gamma(s + 1)). Exact to rounding for the few degrees of freedom
    a distortion-model test has; scipy.stats would cost a second of import for one function."""
    if k < 1 or int(k) != k:
        raise ValueError(f"degrees of freedom must be a positive integer, got {k}")
    if x <= 0:
        return 1.0
    y = x / 2.0
    s, q = (0.5, math.erfc(math.sqrt(y))) if k % 2 else (1.0, math.exp(-y))
    while s < k / 2.0:
        q += math.exp(s * math.log(y) - y - math.lgamma(s + 1.0))
        s += 1.0
    return min(max(q, 0.0), 1.0)


RSS_FLOOR_PX2 = 1e-6
ALPHA_DROP = 0.05
ALPHA_ADD = 0.001


def _n_extra(rich, base) -> int:
    return sum(len(DIST_MODELS[a]) - len(DIST_MODELS[b]) for a, b in ((rich.cam_model, base.cam_model),
                                                                       (rich.proj_model, base.proj_model)))


def bic(rss: float, n: int, p: int) -> float:
    return float(n * np.log(max(rss / n, RSS_FLOOR_PX2)) + p * np.log(n))


def _reduced_system(prob, x):
    """(S, g): Schur-reduced J^T J and J^T r over the global parameters at x (poses eliminated)."""
    Jg, Jl = prob.jacobian_blocks(x)
    r = prob.residuals(x)
    A, B, D, g_g, g_p = normal_blocks(prob, Jg, Jl, np.ones_like(r), r)
    Dinv = np.linalg.inv(D)
    E = np.einsum("vij,vjg->vig", Dinv, B)
    S = A - np.einsum("vkg,vkh->gh", B, E)
    g = g_g - np.einsum("vkg,vk->g", E, g_p)
    return S, g, float(r @ r), r.size


def _quadratic_solution(S, g, rss0, theta0, constrained):
    """(minimum, minimiser D) of rss0 + 2 g.D + D^T S D with D_c = -theta0_c for the constrained
    indices c."""
    n = len(g)
    c = np.asarray(sorted(constrained), int)
    f = np.setdiff1d(np.arange(n), c)
    dc = -theta0[c]
    gf = g[f] + S[np.ix_(f, c)] @ dc
    s = np.sqrt(np.clip(np.diag(S)[f], 1e-300, None))
    Sff = S[np.ix_(f, f)] / s[:, None] / s[None, :]
    df = -np.linalg.lstsq(Sff, gf / s, rcond=1e-13)[0] / s
    val = rss0 + 2 * g[c] @ dc + dc @ S[np.ix_(c, c)] @ dc + gf @ df
    D = np.zeros(n)
    D[c], D[f] = dc, df
    return float(max(val, 0.0)), D


def _quadratic_rss(S, g, rss0, theta0, constrained):
    """Minimum of rss0 + 2 g.D + D^T S D with D_c = -theta0_c for the constrained indices c."""
    return _quadratic_solution(S, g, rss0, theta0, constrained)[0]


#: grid over which the coverage criterion averages the projection error
COVERAGE_GRID = (32, 18)
#: the models the coverage criterion weighs, by the model the BIC / LRT chose
COVERAGE_CANDIDATES = {
    DistortionModel.FIVECOEF: (DistortionModel.FOURCOEF, DistortionModel.FIVECOEF),
    DistortionModel.RATIONAL: (DistortionModel.FOURCOEF, DistortionModel.FIVECOEF, DistortionModel.RATIONAL),
}
#: a simpler model replaces the chosen one only when its estimated error over the image is lower by this
#: fraction: the bias estimate is itself noisy, and a smaller difference is a coin toss (measured: a true
#: projector k3 of 0.08 seen over the whole image ties within 0.2%; the wide-angle corner-poor camera's k3
#: costs 24-96%)
COVERAGE_MARGIN = 0.10


def _free_covariance(S, free: np.ndarray, sigma2: float) -> np.ndarray:
    """sigma^2 (S_ff)^-1 of the free global parameters (Jacobi-scaled for conditioning)."""
    s = np.sqrt(np.clip(np.diag(S)[free], 1e-300, None))
    Sff = S[np.ix_(free, free)] / s[:, None] / s[None, :]
    return sigma2 * np.linalg.pinv(Sff, hermitian=True) / s[:, None] / s[None, :]


def coverage_choice(prob, S, g, rss0, theta0, sigma2, dev: str, chosen: tuple[str, str], idx: dict) -> dict | None:
    """The coverage criterion for one device (dev "camera" / "projector"), the other device's model held at
    its choice: among the chosen model and the ones without its highest radial orders
    (COVERAGE_CANDIDATES), the one with the smallest estimated mean
    squared projection error over the image (a focused information criterion, Mallows' Cp over the
    image): MSE_m = max(B_m - (V_ref - V_m), 0) + V_m, where B_m is the mean squared pixel difference
    over the image between model m's and the chosen model's solutions, V the mean over the image of the
    projection variance (trace of the 2x2 covariance of a ray's pixel, the part a rotation of the device
    would absorb removed: calib.quality.projection_uncertainty), and V_ref - V_m the variance of that difference
    for nested least-squares models. A coefficient the data do not constrain where the image is used
    adds variance there (V) and is dropped unless the bias it removes (B) is larger.
    The simpler model is taken only when its MSE is below (1 - COVERAGE_MARGIN) times the chosen one's.
    Returns {"chosen", "reference", "margin", "candidates": [{"model", "bias2_px2", "var_px2", "mse_px2"}]} or None
    when the chosen model has nothing below it to consider."""
    prefix = "cam" if dev == "camera" else "proj"
    ref = chosen[0] if dev == "camera" else chosen[1]
    other = chosen[1] if dev == "camera" else chosen[0]
    # only the highest radial orders are candidates to drop (k3, and k4..k6 of the rational model): they
    # are what extrapolates into the places without data. Dropping lower orders too (k1k2: p1, p2 with
    # k3) was measured to hurt: on one of 10 real-mirror sessions of the D455-like camera the criterion's
    # noisy bias estimate dropped its real tangential terms, and the scenario's mean errors over the 10
    # sessions grew by 30-60%.
    cands = list(COVERAGE_CANDIDATES.get(ref, ()))
    if len(cands) < 2:
        return None
    st = prob.state
    K4 = st.cam_K if dev == "camera" else st.proj_K
    d8 = st.cam_d if dev == "camera" else st.proj_d
    size = prob.obs.camera_size if dev == "camera" else prob.obs.projector_size
    model = CameraModel(size[0], size[1], [[K4[0], 0, K4[2]], [0, K4[1], K4[3]], [0, 0, 1]], d8)
    pnames = [f"{prefix}.{p}" for p in ("fx", "fy", "cx", "cy")] + [f"{prefix}.dist{i}" for i in DIST_MODELS[ref]]
    cols = [0, 1, 2, 3] + [4 + i for i in DIST_MODELS[ref]]
    rows = [idx[n] for n in pnames]
    xs, ys = grid_pixels(size[0], size[1], COVERAGE_GRID)
    X, Y = np.meshgrid(xs, ys)
    M = motion_fields(model, cols, np.column_stack([X.ravel(), Y.ravel()]))  # (N, 2, k)
    M = M[np.all(np.isfinite(M.reshape(len(M), -1)), axis=1)]
    Mf = M.reshape(-1, len(cols))
    other_prefix = "proj" if dev == "camera" else "cam"

    def constrained(m):
        c = [idx[f"{prefix}.dist{i}"] for i in range(8) if f"{prefix}.dist{i}" in idx and i not in DIST_MODELS[m]]
        c += [idx[f"{other_prefix}.dist{i}"] for i in range(8)
              if f"{other_prefix}.dist{i}" in idx and i not in DIST_MODELS[other]]
        return c

    sol, var = {}, {}
    n = len(g)
    for m in cands:
        c = constrained(m)
        _, D = _quadratic_solution(S, g, rss0, theta0, c)
        free = np.setdiff1d(np.arange(n), np.asarray(c, int))
        cov = np.zeros((n, n))
        cov[np.ix_(free, free)] = _free_covariance(S, free, sigma2)
        C = cov[np.ix_(rows, rows)]
        sol[m] = (theta0 + D)[rows]
        var[m] = float(np.einsum("ik,kl,il->", Mf, C, Mf) / len(M))
    out = []
    for m in cands:
        diff = Mf @ (sol[m] - sol[ref])
        b2 = float(diff @ diff / len(M))
        mse = max(b2 - (var[ref] - var[m]), 0.0) + var[m]
        out.append({"model": m, "bias2_px2": b2, "var_px2": var[m], "mse_px2": mse})
    best = min(out, key=lambda c: (c["mse_px2"], len(DIST_MODELS[c["model"]])))
    ref_mse = next(c["mse_px2"] for c in out if c["model"] == ref)
    chosen_m = best["model"] if best["mse_px2"] < (1.0 - COVERAGE_MARGIN) * ref_mse else ref
    return {"chosen": chosen_m, "reference": ref, "margin": COVERAGE_MARGIN, "candidates": out}


def shrinkage_prior(S, g, theta0, sigma2, cov: dict, dev: str, chosen: tuple[str, str], idx: dict) -> dict | None:
    """k3 shrinkage (options.shrinkage) for a device whose coverage reference is 5coef: an empirical-Bayes
    zero-mean Gaussian prior on k3, in place of the coverage criterion's keep-or-drop.

    In the quadratic model, a prior k3 ~ N(0, tau^2) moves the whole solution from the 5coef one toward
    the 4coef one (k3 = 0) by the fraction w = var_k3 / (var_k3 + tau^2) (the other parameters follow
    through their correlation with k3). Over the image, the expected squared error of that combination
    is V_5 - 2 w V_d + w^2 (F + V_d), with V_d = V_5 - V_4 the variance of the difference between the two
    solutions and F its true squared bias, smallest at w = V_d / (F + V_d). F is estimated without bias
    by B - V_d (B, the observed mean squared difference over the image: coverage_choice), so
    w = V_d / B, i.e. tau^2 = var_k3 (B / V_d - 1): the prior is as wide as the data show k3 to be beyond
    its own noise. For one coefficient B / V_d is its z^2: k3 is multiplied by 1 - 1 / z^2, and dropped
    (w = 1) when z^2 <= 1. Returns {"param", "weight_to_zero", "z2", "k3_5coef", "k3_sigma",
    "prior_sigma", "precision"} (precision in the whitened cost's units: 1 / tau^2 of the unit-variance
    problem; infinite when dropped), or None when the reference is not 5coef."""
    if cov is None or cov["reference"] != DistortionModel.FIVECOEF:
        return None
    c = {x["model"]: x for x in cov["candidates"]}
    vd = c[DistortionModel.FIVECOEF]["var_px2"] - c[DistortionModel.FOURCOEF]["var_px2"]
    b2 = c[DistortionModel.FOURCOEF]["bias2_px2"]
    w = 1.0 if vd <= 0 or b2 <= vd else vd / b2
    prefix, other_prefix = ("cam", "proj") if dev == "camera" else ("proj", "cam")
    other = chosen[1] if dev == "camera" else chosen[0]
    free5 = DIST_MODELS[DistortionModel.FIVECOEF]
    cons = [idx[f"{prefix}.dist{i}"] for i in range(8) if f"{prefix}.dist{i}" in idx and i not in free5]
    cons += [idx[f"{other_prefix}.dist{i}"] for i in range(8)
             if f"{other_prefix}.dist{i}" in idx and i not in DIST_MODELS[other]]
    _, D = _quadratic_solution(S, g, 0.0, theta0, cons)
    free = np.setdiff1d(np.arange(len(theta0)), np.asarray(cons, int))
    k = idx[f"{prefix}.dist4"]
    j = int(np.nonzero(free == k)[0][0])
    var_unit = float(_free_covariance(S, free, 1.0)[j, j])
    out = {"param": f"{prefix}.dist4", "weight_to_zero": float(w), "z2": float(b2 / vd) if vd > 0 else 0.0,
           "k3_5coef": float(theta0[k] + D[k]), "k3_sigma": float(np.sqrt(sigma2 * var_unit))}
    if w >= 1.0:
        out.update({"prior_sigma": 0.0, "precision": float("inf")})
    else:
        out.update({"prior_sigma": float(np.sqrt(sigma2 * var_unit * (1.0 - w) / w)),
                    "precision": float(w / (1.0 - w) / var_unit)})
    return out


def select_models(prob, options) -> dict:
    """Choose the distortion models of prob's camera and projector (prob is left fitted with the
    chosen pair). Returns the report stored in result.diagnostics["model_selection"]."""
    report = {"criterion": "BIC = N ln(RSS/N) + P ln N on the joint residuals (squared loss, inliers)",
              "method": "RSS of each candidate from the quadratic model of the joint problem around the "
                        "5-coefficient solution (Wald / score test), chosen pair refitted to confirm"}
    auto = {"camera": options.camera_model == "auto" and not prob.fix_camera,
            "projector": options.projector_model == "auto"}
    base = prob.state.copy()
    prob.prior = {}  # calib.joint.solver.prior_terms: the k3 shrinkage's priors, set at the end
    priors = {}
    if not any(auto.values()):
        for dev in ("camera", "projector"):
            report[dev] = {"chosen": base.cam_model if dev == "camera" else base.proj_model, "forced": True,
                           "reason": "camera intrinsics given and held fixed" if dev == "camera" and prob.fix_camera
                           else "forced by the user"}
        return report
    # the richest parametrisation for the devices being selected
    rich = base.copy()
    if auto["camera"]:
        rich.cam_model = DistortionModel.RATIONAL
    if auto["projector"]:
        rich.proj_model = DistortionModel.RATIONAL
    prob.set_state(rich)
    x_rich = prob.x0()
    S, g, rss0, n = _reduced_system(prob, x_rich)
    names = prob.global_names
    idx = {nm: i for i, nm in enumerate(names)}
    n_pose = prob.n_params - prob.n_global

    def constrained_for(cm, pm):
        c = []
        for prefix, model, full in (("cam", cm, rich.cam_model), ("proj", pm, rich.proj_model)):
            for i in DIST_MODELS[full]:
                if i not in DIST_MODELS[model]:
                    c.append(idx[f"{prefix}.dist{i}"])
        return c

    cam_opts = SELECTION_MODELS if auto["camera"] else (base.cam_model,)
    proj_opts = SELECTION_MODELS if auto["projector"] else (base.proj_model,)
    table = {}
    for cm, pm in itertools.product(cam_opts, proj_opts):
        c = constrained_for(cm, pm)
        rss = _quadratic_rss(S, g, rss0, x_rich[:prob.n_global], c)
        p = prob.n_global - len(c) + n_pose
        table[(cm, pm)] = {"rss_px2": rss, "n_params": p, "bic": bic(rss, n, p)}
    sigma2 = max(rss0 / max(n - (prob.n_global - _n_extra(rich, base) + n_pose), 1), RSS_FLOOR_PX2)
    report["sigma_px"] = float(np.sqrt(sigma2))
    report["alpha_drop"], report["alpha_add"] = ALPHA_DROP, ALPHA_ADD

    def lrt_choice(dev, other):
        """The LRT rule above for one device, the other device's model fixed."""
        def key(name):
            return (name, other) if dev == "camera" else (other, name)

        ref = table[key(DistortionModel.FIVECOEF)]["rss_px2"]
        tests = {}
        for name in (DistortionModel.NONE, DistortionModel.K1, DistortionModel.K1K2):
            k = 5 - len(DIST_MODELS[name])
            W = max(table[key(name)]["rss_px2"] - ref, 0.0) / sigma2
            tests[name] = (W, k, float(chi2_sf(W, k)))
        W = max(ref - table[key(DistortionModel.RATIONAL)]["rss_px2"], 0.0) / sigma2
        tests[DistortionModel.RATIONAL] = (W, 3, float(chi2_sf(W, 3)))
        for name in (DistortionModel.NONE, DistortionModel.K1, DistortionModel.K1K2):
            if tests[name][2] > ALPHA_DROP:
                return name, tests
        add_k456 = tests[DistortionModel.RATIONAL][2] < ALPHA_ADD
        return (DistortionModel.RATIONAL if add_k456 else DistortionModel.FIVECOEF), tests

    if options.selection == "bic":
        best = min(table, key=lambda k: table[k]["bic"])
        tests_by_dev = {}
    else:
        cm, pm = base.cam_model, base.proj_model
        tests_by_dev = {}
        if auto["camera"]:
            cm, tests_by_dev["camera"] = lrt_choice("camera", pm)
        if auto["projector"]:
            pm, tests_by_dev["projector"] = lrt_choice("projector", cm)
        if auto["camera"]:  # the camera's choice with the projector at its final model
            cm, tests_by_dev["camera"] = lrt_choice("camera", pm)
        best = (cm, pm)

    def device_report(dev):
        if not auto[dev]:
            why = "camera intrinsics given and held fixed" if dev == "camera" and prob.fix_camera else "forced by the user"
            return {"chosen": best[0] if dev == "camera" else best[1], "forced": True, "reason": why}
        other = best[1] if dev == "camera" else best[0]
        cands = []
        for name in SELECTION_MODELS:
            key = (name, other) if dev == "camera" else (other, name)
            t = table[key]
            cands.append({"model": name, "n_coeffs": len(DIST_MODELS[name]), "rss_px2": t["rss_px2"],
                          "rms_px": float(np.sqrt(2 * t["rss_px2"] / n)), "bic": t["bic"]})
            if dev in tests_by_dev and name in tests_by_dev[dev]:
                W, k, pv = tests_by_dev[dev][name]
                cands[-1].update({"lrt_W": W, "lrt_dof": k, "p_value": pv})
        chosen = best[0] if dev == "camera" else best[1]
        bbic = min(c["bic"] for c in cands)
        for c in cands:
            c["delta_bic"] = c["bic"] - bbic
        ch = next(c for c in cands if c["model"] == chosen)
        if options.selection == "bic":
            why = [f"'{chosen}' has the lowest BIC"]
            simpler = [c for c in cands if c["n_coeffs"] < ch["n_coeffs"]]
            richer = [c for c in cands if c["n_coeffs"] > ch["n_coeffs"]]
            if simpler:
                s_ = max(simpler, key=lambda c: c["n_coeffs"])
                why.append(f"the simpler '{s_['model']}' leaves more residual (RSS {s_['rss_px2']:.5g} vs "
                           f"{ch['rss_px2']:.5g} px^2: dBIC +{s_['delta_bic']:.1f})")
            if richer:
                c = min(richer, key=lambda c: c["n_coeffs"])
                why.append(f"the richer '{c['model']}' lowers the RSS by only {ch['rss_px2'] - c['rss_px2']:.3g} "
                           f"px^2 for {c['n_coeffs'] - ch['n_coeffs']} more coefficient(s) (dBIC +{c['delta_bic']:.1f})")
        else:
            tests = tests_by_dev[dev]
            why = []
            for name in (DistortionModel.NONE, DistortionModel.K1, DistortionModel.K1K2):
                W, k, pv = tests[name]
                if name == chosen:
                    why.append(f"'{name}' is not significantly worse than 5coef (W = {W:.2f} on {k} dof, "
                               f"p = {pv:.3g} > {ALPHA_DROP})")
                    break
                why.append(f"'{name}' is significantly worse than 5coef (W = {W:.1f} on {k} dof, p = {pv:.2g})")
            if chosen in (DistortionModel.FIVECOEF, DistortionModel.RATIONAL):
                W, k, pv = tests[DistortionModel.RATIONAL]
                if chosen == DistortionModel.RATIONAL:
                    why.append(f"the rational terms are highly significant (W = {W:.1f} on 3 dof, p = {pv:.2g} "
                               f"< {ALPHA_ADD})")
                else:
                    why.append(f"the rational terms are not needed (W = {W:.2f} on 3 dof, p = {pv:.3g} >= "
                               f"{ALPHA_ADD})")
        return {"chosen": chosen, "forced": False, "reason": "; ".join(why), "candidates": cands}

    report["camera"] = device_report("camera")
    report["projector"] = device_report("projector")
    coverage_changed = False
    if getattr(options, "coverage", False):
        sigma2_w = max(rss0 / max(n - prob.n_params, 1), RSS_FLOOR_PX2)
        for dev in ("camera", "projector"):
            if not auto[dev]:
                continue
            cov = coverage_choice(prob, S, g, rss0, x_rich[:prob.n_global], sigma2_w, dev, best, idx)
            if cov is None:
                continue
            report[dev]["coverage"] = cov
            sh = shrinkage_prior(S, g, x_rich[:prob.n_global], sigma2_w, cov, dev, best, idx) \
                if getattr(options, "shrinkage", False) else None
            if sh is not None:  # the prior decides in place of the margin rule
                cov["shrinkage"] = sh
                cov["chosen"] = DistortionModel.FOURCOEF if sh["weight_to_zero"] >= 1.0 else DistortionModel.FIVECOEF
                if cov["chosen"] == DistortionModel.FIVECOEF:
                    priors[sh["param"]] = sh["precision"]
                    report[dev]["reason"] += (
                        f"; k3 shrinkage: k3 {sh['k3_5coef']:+.4g} (1-sigma {sh['k3_sigma']:.2g}, z^2 = "
                        f"{sh['z2']:.2f} over the image) pulled toward 0 by a zero-mean Gaussian prior of sigma "
                        f"{sh['prior_sigma']:.2g} set from the data (weight toward 0: {sh['weight_to_zero']:.2f})")
            if cov["chosen"] != cov["reference"]:
                c = {x_["model"]: x_ for x_ in cov["candidates"]}
                a, r_ = c[cov["chosen"]], c[cov["reference"]]
                report[dev]["reason"] += (
                    f"; k3 shrinkage: '4coef' instead, the bias k3 would remove over the image is no larger than "
                    f"its variance there (z^2 = {sh['z2']:.2f} <= 1): the prior width set from the data is zero"
                ) if sh is not None else (
                    f"; coverage criterion: '{cov['chosen']}' instead, its estimated mean squared projection error "
                    f"over the image is {a['mse_px2']:.3g} px^2 against {r_['mse_px2']:.3g} for '{cov['reference']}' "
                    f"(whose extra coefficients are not constrained where the image is used: variance "
                    f"{r_['var_px2']:.3g} px^2)")
                report[dev]["chosen"] = cov["chosen"]
                best = (cov["chosen"], best[1]) if dev == "camera" else (best[0], cov["chosen"])
                coverage_changed = True
    # confirm by a real fit of the chosen pair
    base_key = (base.cam_model, base.proj_model)
    if best != base_key:
        st = base.copy()
        st.cam_model, st.proj_model = best
        for key, model in (("cam_d", best[0]), ("proj_d", best[1])):
            d = getattr(st, key)
            mask = np.ones(8, bool)
            mask[list(DIST_MODELS[model])] = False
            d[mask] = 0.0
        prob.set_state(st)
        x, info = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        fitted = prob.state.copy()
        r = prob.residuals(x)
        rss_fit = float(r @ r)
        bic_fit = bic(rss_fit, r.size, prob.n_params)
        prob.set_state(base)
        r0 = prob.residuals(prob.x0())
        bic_base = bic(float(r0 @ r0), r0.size, prob.n_params)
        k_drop = k_add = 0
        for a_, b_ in ((best[0], base.cam_model), (best[1], base.proj_model)):
            diff = len(DIST_MODELS[a_]) - len(DIST_MODELS[b_])
            k_add += max(diff, 0)
            k_drop += max(-diff, 0)
        refit = {"models": list(best), "rss_px2": rss_fit, "bic": bic_fit, "base_models": list(base_key),
                 "base_rss_px2": float(r0 @ r0), "base_bic": bic_base}
        if coverage_changed:
            keep = True
            refit["test"] = "chosen by the coverage criterion (mean squared projection error over the image)"
        elif options.selection == "bic" or (k_add and k_drop):
            keep = bic_fit <= bic_base
            refit["test"] = "BIC of the refit vs the 5-coefficient fit"
        elif k_drop:
            W = max(rss_fit - float(r0 @ r0), 0.0) / sigma2
            pv = float(chi2_sf(W, k_drop))
            keep = pv > ALPHA_DROP
            refit["test"] = f"refit W = {W:.2f} on {k_drop} dof, p = {pv:.3g} (keep if > {ALPHA_DROP})"
        else:
            W = max(float(r0 @ r0) - rss_fit, 0.0) / sigma2
            pv = float(chi2_sf(W, k_add))
            keep = pv < ALPHA_ADD
            refit["test"] = f"refit W = {W:.2f} on {k_add} dof, p = {pv:.3g} (keep if < {ALPHA_ADD})"
        report["refit"] = refit
        if keep:
            prob.set_state(fitted)
            refit["kept"] = True
        else:
            refit["kept"] = False
            for dev, m in (("camera", base.cam_model), ("projector", base.proj_model)):
                if report[dev]["chosen"] != m:
                    report[dev]["reason"] += f"; but the refit does not confirm it ({refit['test']}), so '{m}' is kept"
                    report[dev]["chosen"] = m
    else:
        prob.set_state(base)
    if priors:  # the kept k3 under its shrinkage prior: one more solve, and the covariance includes the prior
        prob.prior = priors
        x, _ = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        m = prob.unpack(x)
        for dev, key in (("camera", "cam_d"), ("projector", "proj_d")):
            sh = report[dev].get("coverage", {}).get("shrinkage") if isinstance(report.get(dev), dict) else None
            if sh is not None and sh["param"] in priors:
                sh["k3_final"] = float(np.real(m[key][4]))
    return report
