"""The joint maximum-likelihood method (the default; docs/JOINT.md).

  method        the stage's entry: calibrate_joint (the "joint" method of calib.pipeline: the paper's
                result as the starting point, then refine_joint), refine_joint (one adjustment over
                everything the images constrain)
  options       JointOptions
  assembly      build_problem: the session's observations, the initial board poses, the problem
  points        the observations as frozen point sets (CornerSet, PatternSet; subset(mask))
  problem       JointProblem: parameter layout, model of every observation, residuals, exact Jacobian
  lens          the complex-safe lens model (distortion, projection, undistortion)
  solver        the least-squares machinery: distortion-model table, block normal equations with
                the board poses eliminated (Schur complement), robust reweighting, Levenberg-Marquardt
  robust        the noise sigma of each observation class, outlier rejection
  model_select  each device's distortion model (likelihood-ratio tests, BIC, coverage criterion)
  uncertainty   the covariance at the solution and the 1-sigma values of calibration.json
  result        the CalibrationResult and its diagnostics
  conic         where a detector sees a projected circle (conic centres, area centroids)

Rotations are Gibbs vectors about the current estimate (calib.transforms, the parametrisation the
recalibration shares). Nothing is re-exported: solver, model_select and uncertainty are imported on
their own without loading the whole method (`from calib.joint.method import calibrate_joint`).
"""
