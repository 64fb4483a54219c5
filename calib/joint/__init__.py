"""The joint maximum-likelihood method (the default; docs/JOINT.md).

  method        one adjustment over everything the images constrain, started from the paper's
                result; the "joint" method of calib.pipeline: `calibrate_joint`, `refine_joint`
  solver        the least-squares machinery: distortion-model table, block normal equations with
                the board poses eliminated (Schur complement), robust reweighting, Levenberg-Marquardt
  model_select  each device's distortion model (likelihood-ratio tests, BIC, coverage criterion)
  uncertainty   the covariance at the solution and the 1-sigma values of calibration.json
  conic         where a detector sees a projected circle (conic centres, area centroids)

Nothing is re-exported: solver, model_select and uncertainty are imported on their own without
loading the whole method (`from calib.joint.method import calibrate_joint`).
"""
