"""The options of the joint adjustment (JointOptions), read by every stage of calib.joint."""

from __future__ import annotations

from dataclasses import dataclass

PATTERN_MODELS = ("auto", "point", "conic")


@dataclass(frozen=True)
class JointOptions:
    """Options of refine_joint (all have sensible defaults).

    camera_model / projector_model: "auto" (selected per device, calib.joint.model_select) or one of
    DIST_MODELS. pattern_model: "conic" models a projected circle's observation as the centre of its
    imaged conic (what a centroid detector measures), "point" as the image of its centre; "auto" =
    conic for circle patterns, point for chessboards. loss / noise_px: robust loss of the first pass
    and its scale (None: estimated from the initial residuals). outlier_sigma: points whose residual
    exceeds this many robust sigmas of their class (and min_outlier_px) are rejected, then the problem
    is solved with the squared loss. selection: criterion of the model selection ("bic" or "lrt").
    solver: "lm" (Levenberg-Marquardt, Schur complement) or "scipy" (least_squares). fix_camera: hold
    the initial camera fixed (set when a camera is given). weighting: "class" (per observation class
    noise sigma) or "none". centroid_correction: with the conic model, the 32-point area-centroid
    correction for the lenses' curvature across a blob. tol: a solve stops when a step lowers the
    cost by less than this fraction (1e-7 of a whitened cost ~N moves the parameters by a few
    hundredths of a sigma, and the Gauss-Newton step after it by far less: results agree with
    tol=1e-9 to 1e-7 sigma, one Jacobian fewer per solve). coverage: after the BIC / LRT choice, step a
    device's model down when the coefficients it drops are not constrained where the image is used
    (calib.joint.model_select: the mean squared projection error over the image, bias + variance). shrinkage:
    with coverage, a kept k3 is pulled toward 0 by a zero-mean Gaussian prior whose width is set from the
    data (calib.joint.model_select.shrinkage_prior), instead of kept or dropped whole."""

    camera_model: str = "auto"
    projector_model: str = "auto"
    pattern_model: str = "auto"
    loss: str = "soft_l1"
    noise_px: float | None = None
    outlier_sigma: float = 5.0
    min_outlier_px: float = 0.25
    outlier_rounds: int = 3
    max_nfev: int = 60
    tol: float = 1e-7
    uncertainty: bool = True
    selection: str = "bic"
    centroid_correction: bool = True
    solver: str = "lm"
    fix_camera: bool = False
    weighting: str = "class"
    coverage: bool = True
    shrinkage: bool = False
