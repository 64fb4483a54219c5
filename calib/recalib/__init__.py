"""On-site recalibration: check what moved, re-measure only that, compare with before.

Pure computation (docs/RECALIBRATION.md). One module and one entry function per stage:

  check.py       check_rig(previous, obs)         -> CheckReport: per part (camera intrinsics, mirror,
                                                      projector pose) whether the new observations say
                                                      it moved
  reestimate.py  reestimate(previous, obs, parts) -> Reestimate: the moved parts re-fitted (intrinsics
                                                      under a prior: prior.py)
  compare.py     compare_calibrations(prev, new)  -> dict: the change of each part with its uncertainty

_model.py holds the model and its least-squares fit that the stages share; record.py what a
recalibration keeps of its inputs.

The model is the previous calibration with small corrections of three parameter blocks:
  camera    4: fx, fy, cx, cy (px; distortion held: a refocus changes the focal length)
  mirror    3: two tilts of the normal (rad, about tangent axes of the previous normal) and d (units)
  projector 6: rotation (a Gibbs vector g, camera axes: R = R(g) R_prev, calib.transforms.update_R, the
               joint adjustment's parametrisation) and translation (units, camera frame) of T_cam_proj
and one free board pose per capture (a nuisance parameter: a Gibbs vector about its PnP start and
its translation). The re-estimate adds, by default, the
intrinsics of both devices (fx, fy, cx, cy and the distortion coefficients the previous calibration
estimated) under a Gaussian prior from the previous calibration's covariance (IntrinsicsPrior;
reestimate's `intrinsics` "prior" | "held", docs/RECALIBRATION.md for the numbers). Residuals are
whitened by the previous calibration's per-class noise sigma (uncertainty.class_sigma_px) and minimised
with scipy.optimize.least_squares; the covariance of a fitted block is s^2 (J^T J)^-1 (s^2 the variance
factor), marginal over the board poses.

The rule of the check, per part p with correction delta_p fitted from the new captures (C_new its
covariance) and C_prev the previous calibration's covariance of the same parameters:

    m2 = delta_p^T (F^2 (C_prev + C_new))^-1 delta_p,   moved when m2 > chi2.ppf(1 - ALPHA, dim p)

ALPHA = 1e-3, F = SYSTEMATIC_FACTOR = 2: docs/JOINT.md measures true errors of 1-2x the reported sigma
on rendered sessions (detection biases no residual sees), so a change must exceed twice the combined
sigma, at 99.9 % confidence, to be called a move. A change well inside the previous 1-sigma is
"unchanged" by construction.

Parts are tested in order, each with what was decided before held: the camera from every board view
(the mirror free, so that a moved mirror cannot pass for a change of focal length), then the mirror
from real-virtual captures (a board seen directly and in the mirror), then the projector from the
projected pattern. The pattern alone cannot tell a moved mirror from a moved projector (it only sees
the projector's mirror image), which is why the mirror is tested first on its own captures.
"""

from calib.recalib._model import (
    BLOCK_SIZE,
    DEFAULT_CLASS_SIGMA_PX,
    PARTS,
    TOL,
    Fit,
    fit_blocks,
    previous_covariance,
)
from calib.recalib.check import (
    ALPHA,
    SYSTEMATIC_FACTOR,
    CheckReport,
    PartCheck,
    check_rig,
    describe_change,
    describe_movement,
    merge_observations,
)
from calib.recalib.compare import compare_calibrations, projection_difference
from calib.recalib.prior import (
    INTRINSICS_MODES,
    PRIOR_EIG_FLOOR,
    IntrinsicsPrior,
    intrinsics_prior,
)
from calib.recalib.record import RecalibrationRecord, sha256_file
from calib.recalib.reestimate import (
    DEFAULT_INTRINSICS,
    DEFAULT_TARGETS,
    Reestimate,
    own_residuals,
    reestimate,
    targets_from,
    with_own_residuals,
)

__all__ = [
    "PARTS",
    "BLOCK_SIZE",
    "TOL",
    "DEFAULT_CLASS_SIGMA_PX",
    "Fit",
    "fit_blocks",
    "previous_covariance",
    "PRIOR_EIG_FLOOR",
    "INTRINSICS_MODES",
    "IntrinsicsPrior",
    "intrinsics_prior",
    "ALPHA",
    "SYSTEMATIC_FACTOR",
    "PartCheck",
    "CheckReport",
    "describe_change",
    "describe_movement",
    "check_rig",
    "merge_observations",
    "DEFAULT_TARGETS",
    "targets_from",
    "DEFAULT_INTRINSICS",
    "Reestimate",
    "reestimate",
    "own_residuals",
    "with_own_residuals",
    "projection_difference",
    "compare_calibrations",
    "sha256_file",
    "RecalibrationRecord",
]
