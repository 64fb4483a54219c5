"""The 1-sigmas the joint adjustment would report with more observations, without solving
(predict_uncertainty).

The covariance is linearised at a joint result: its parameters, its distortion models, its noise per
observation class and variance factor, its k3 priors, over the observations it was calibrated from plus
predicted ones (a board pose the station could ask for, its exact observations through the estimated
rig). Choosing among candidate poses this way costs one Jacobian each, where calibrating with each
candidate costs a whole adjustment; the prediction leaves out what a real capture would also change
(the solution moving, the models re-selected, outliers), which is why it ranks candidates and does
not replace the calibration after the capture.
"""

from __future__ import annotations

from dataclasses import replace

from calib.errors import CalibrationError
from calib.joint.assembly import build_problem
from calib.joint.options import JointOptions
from calib.joint.uncertainty import joint_uncertainty
from calib.models.observations import SessionObservations
from calib.models.result import CalibrationResult
from calib.models.vocab import CalibrationMethod, DistortionModel
from calib.quality.projection_uncertainty import projection_uncertainty


def _priors(selection) -> dict:
    """{global parameter name: precision} of the k3 shrinkage priors a model selection kept."""
    out = {}
    if not isinstance(selection, dict):
        return out
    for dev in ("camera", "projector"):
        rep = selection.get(dev)
        sh = (rep.get("coverage") or {}).get("shrinkage") if isinstance(rep, dict) else None
        if isinstance(sh, dict) and isinstance(sh.get("param"), str) and sh.get("precision") is not None:
            out[sh["param"]] = float(sh["precision"])
    return out


def predict_uncertainty(obs: SessionObservations, result: CalibrationResult,
                        options: JointOptions = JointOptions()) -> CalibrationResult:
    """`result` with the uncertainty and projection-uncertainty grids the joint adjustment would give
    for `obs` (the observations `result` was calibrated from, plus predicted ones), linearised at
    `result`. The views `result` solved start from its board poses; new views from PnP under it.

    CalibrationError when `result` is not a joint result with an uncertainty (nothing to linearise)."""
    unc = result.uncertainty if isinstance(result.uncertainty, dict) else None
    diag = result.diagnostics if isinstance(result.diagnostics, dict) else {}
    if result.method != CalibrationMethod.JOINT or unc is None or not unc.get("class_sigma_px"):
        raise CalibrationError("predicting the uncertainty needs a joint calibration with its uncertainty "
                               "(calibrate with --method joint first)")
    fixed = bool((unc.get("camera") or {}).get("fixed"))
    opts = replace(options, fix_camera=fixed, pattern_model=diag.get("pattern_model", options.pattern_model))
    cam_model = DistortionModel(diag.get("camera_model", DistortionModel.FIVECOEF))
    proj_model = DistortionModel(diag.get("projector_model", DistortionModel.FIVECOEF))
    prob, _left_out = build_problem(obs, result, opts, cam_model, proj_model)
    poses = diag.get("board_poses") if isinstance(diag.get("board_poses"), dict) else {}
    start = prob.board_poses(prob.x0())
    start.update({cid: T for cid, T in poses.items() if cid in start})
    prob.set_board_poses(start)
    prob.set_class_sigmas({k: float(v) for k, v in unc["class_sigma_px"].items()})
    prob.prior = _priors(diag.get("model_selection"))
    predicted = joint_uncertainty(prob, prob.x0(), variance_factor=float(unc.get("variance_factor", 1.0)))
    out = result.with_(uncertainty=predicted)
    return out.with_(projection_uncertainty=projection_uncertainty(out))


__all__ = ["predict_uncertainty"]
