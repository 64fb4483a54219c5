"""Joint maximum-likelihood refinement of a whole mirror-based projector-camera session: the "joint"
method of calib.pipeline (calibrate_joint; refine_joint from a given starting point).

One least-squares adjustment over everything the images constrain (docs/JOINT.md):

* camera K (fx, fy, cx, cy) and distortion, projector K and distortion,
* the mirror plane n . x + d = 0 (normal as 2 tangent parameters around the current normal, plus d),
* every board pose in the REAL camera frame (T_cam_board; a board lying on the mirror has 3 DOF),
* T_cam_proj.

Observations, all in camera pixels (where the noise is), with the exact models of docs/GEOMETRY.md:

* ChArUco corners through the mirror: u = project_cam(S T_cam_board X);
* projected pattern points through the mirror: projector pixel q -> undistorted ray -> T_cam_proj ->
  board plane -> S -> camera; for circles optionally the centre of the imaged conic (bias-free);
* mirror-calibration images: real corners project_cam(T X), virtual corners project_cam(S T X);
  real-mirror boards are parametrised on the plane offset by the board thickness;
* direct rigs: S = I.

The stage's modules, in the order refine_joint runs them:

  assembly      build_problem: the views' observations as point sets (points), their initial board
                poses, the problem (problem: parameters, model, residuals, exact Jacobian; lens: the
                complex-safe lens model)
  solver        solve: Levenberg-Marquardt with the board poses eliminated by the Schur complement
                (solver="scipy": scipy's least_squares, trf, sparse Jacobian, x_scale='jac')
  robust        the noise sigma of each observation class, outlier rejection
  model_select  each device's distortion model
  uncertainty   the covariance at the solution and the 1-sigma values
  result        the CalibrationResult and its diagnostics

Residuals are weighted by the noise sigma of their observation class (board corners, pattern points,
mirror real / virtual corners), estimated from the residuals: a robust pass (soft-L1), outlier
rejection, then the plain squared loss on the inliers (the maximum-likelihood estimate under Gaussian
pixel noise), distortion model selection and the covariance. Non-finite numbers or a failed linear
algebra in the solver become a CalibrationError (code "non_finite" / "solve_failed"), which
calibrate_joint reports as an UntrustedCalibration.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from calib.errors import CalibrationError, UntrustedCalibration
from calib.joint import model_select, uncertainty
from calib.joint.assembly import build_problem
from calib.joint.options import JointOptions
from calib.joint.result import make_result
from calib.joint.robust import class_sigmas, reject, robust_sigma
from calib.joint.solver import DIST_MODELS, MODEL_NAMES, solve
from calib.models.camera import CameraModel
from calib.models.observations import SessionObservations
from calib.models.result import CalibrationResult
from calib.models.vocab import DistortionModel
from calib.paper.method import calibrate_paper
from calib.quality.projection_uncertainty import projection_uncertainty
from calib.quality.trust import TrustReason, check_calibration


def refine_joint(obs: SessionObservations, init: CalibrationResult, options: JointOptions = JointOptions(),
                 progress=None) -> CalibrationResult:
    """Joint maximum-likelihood refinement of every parameter of the session from `init` (usually the
    paper's sequential result). See the module docstring and docs/JOINT.md."""
    t_start = time.perf_counter()
    timing = {}
    if isinstance(init.diagnostics, dict) and isinstance(init.diagnostics.get("timing_s"), dict):
        for k, v in init.diagnostics["timing_s"].items():
            timing[f"{init.method}.{k}"] = v
    for name, val in (("camera_model", options.camera_model), ("projector_model", options.projector_model)):
        if val != "auto" and val not in DIST_MODELS:
            raise CalibrationError(f"unknown {name} '{val}' (one of auto, {', '.join(MODEL_NAMES)})")

    stages = ("joint.setup", "joint.robust", "joint.outliers_and_ml", "joint.model_selection", "joint.uncertainty")

    def tick(stage, t0):
        timing[stage] = round(time.perf_counter() - t0, 4)
        if progress is not None:
            progress(stages.index(stage) + 1, len(stages), stage)

    t0 = time.perf_counter()
    cam0 = options.camera_model if options.camera_model != "auto" else DistortionModel.FIVECOEF
    if options.fix_camera:  # keep the given camera exactly (all its coefficients)
        cam0 = DistortionModel.RATIONAL if init.camera.dist.size == 8 else DistortionModel.FIVECOEF
    proj0 = options.projector_model if options.projector_model != "auto" else DistortionModel.FIVECOEF
    prob, left_out = build_problem(obs, init, options, cam0, proj0)
    tick("joint.setup", t0)

    # ---- pass 1: robust loss ------------------------------------------------------------------
    t0 = time.perf_counter()
    x = prob.x0()
    r0 = prob.residuals(x)
    sigma0 = options.noise_px if options.noise_px else max(robust_sigma(r0), 0.05)
    prob.reset_warm_start()
    x, info1 = solve(prob, options.loss, sigma0, options.max_nfev, max(options.tol, 1e-4), options.solver)
    if prob.pattern_model == "conic" and options.centroid_correction:
        prob.update_centroid_correction(x)
    tick("joint.robust", t0)

    # ---- noise per observation class, outlier rejection, maximum-likelihood solve -------------------
    t0 = time.perf_counter()
    rejected = []
    solves = [info1]
    prob.set_class_sigmas(class_sigmas(prob, prob.raw_residuals(x), options, robust=True))
    for _round in range(max(options.outlier_rounds, 0) + 1):
        new = reject(prob, x, options.outlier_sigma, options.min_outlier_px, rejected) \
            if _round < options.outlier_rounds else 0
        if _round > 0 and not new:
            break
        x, info = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        solves.append(info)
    # the final weights: per-class RMS of the inlier residuals at the ML solution
    before = dict(prob.class_sigma)
    prob.set_class_sigmas(class_sigmas(prob, prob.raw_residuals(x), options, robust=False))
    # a class whose every residual was rejected as an outlier has no sigma any more: the weights changed
    changed = any(k not in prob.class_sigma or abs(prob.class_sigma[k] / before[k] - 1) > 0.05 for k in before)
    if prob.pattern_model == "conic" and options.centroid_correction:
        old = prob.centroid_corr.copy()
        prob.update_centroid_correction(x)
        changed |= bool(old.size and np.abs(prob.centroid_corr - old).max() > 1e-4)
    if changed:
        x, info = solve(prob, "linear", 1.0, options.max_nfev, options.tol, options.solver)
        solves.append(info)
    tick("joint.outliers_and_ml", t0)

    # ---- distortion model selection -------------------------------------------------------------
    t0 = time.perf_counter()
    selection = _guarded("the distortion model selection", model_select.select_models, prob, options)
    x = prob.x0()
    tick("joint.model_selection", t0)

    # ---- uncertainty ------------------------------------------------------------------------------
    t0 = time.perf_counter()
    unc = None
    if options.uncertainty:
        unc = _guarded("the covariance", uncertainty.joint_uncertainty, prob, x)
    tick("joint.uncertainty", t0)

    result = make_result(obs, init, prob, x, rejected, left_out, selection, unc, solves, timing)
    if unc is not None:  # the 1-sigma pixel motion over each device's image (calib.quality.projection_uncertainty)
        result = result.with_(projection_uncertainty=projection_uncertainty(result))
    timing["joint.total"] = round(time.perf_counter() - t_start, 4)
    return result


def _guarded(what: str, fn, *args):
    """fn(*args), with numpy's linear-algebra failures (which only degenerate data cause: an SVD that
    does not converge, a singular system) turned into a CalibrationError that says so."""
    try:
        return fn(*args)
    except np.linalg.LinAlgError as e:
        raise CalibrationError(f"the joint adjustment failed in {what} ({e}); the session's data are probably "
                               "degenerate (the same image in every capture, wrong pattern points, boards seen "
                               "from one pose only): check the captures", code="solve_failed") from None


def calibrate_joint(obs: SessionObservations, camera: CameraModel | None = None, progress=None,
                    options: JointOptions | None = None, **option_overrides) -> CalibrationResult:
    """The "joint" method of calib.pipeline.METHODS: the paper's sequential pipeline as the starting
    point, then refine_joint. A given `camera` is held fixed (as the paper method keeps it), unless
    fix_camera=False is passed. Keyword arguments override fields of JointOptions (camera_model=...)."""
    opts = options or JointOptions()
    if camera is not None and "fix_camera" not in option_overrides:
        option_overrides["fix_camera"] = True
    if option_overrides:
        unknown = set(option_overrides) - set(JointOptions.__dataclass_fields__)
        if unknown:
            raise CalibrationError(f"unknown joint option(s): {', '.join(sorted(unknown))}")
        opts = replace(opts, **option_overrides)
    init = calibrate_paper(obs, camera, progress)
    try:
        return refine_joint(obs, init, opts, progress)
    except CalibrationError as e:
        if e.code not in ("non_finite", "solve_failed"):
            raise
        # the refinement met NaN / inf or a singular system: report it with what is wrong with its starting
        # point, and keep that starting point (the paper method's result) for diagnosis
        start = check_calibration(init)
        report = replace(start, reasons=(TrustReason(e.code, str(e)),) + start.reasons)
        rejected = init.with_(diagnostics=dict(init.diagnostics, joint_error=str(e), trust=report.to_dict()))
        raise UntrustedCalibration(report, rejected) from None


__all__ = ["JointOptions", "build_problem", "calibrate_joint", "refine_joint", "solve"]
