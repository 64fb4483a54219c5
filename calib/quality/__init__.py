"""How good is a calibration result.

  trust                   is it trustworthy, without ground truth (absurd parameters, residuals,
                          uncertainty far beyond a full session's, ill-conditioning) and the quality
                          gate; entry `check_calibration`, run on every result by calib.pipeline
                          (its checks behind it: _trust_devices, _trust_solution, _trust_gate)
  projection_uncertainty  how far a ray's pixel moves at 1 sigma, over each device's image
  metrics                 the paper's metrics of a result against ground truth
  verdict                 the overall verdict (trust check + quality gate) the panel and the report show first
  coverage                how much of an image the observations cover (one definition for panel and report)

Nothing is re-exported.
"""
