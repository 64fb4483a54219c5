"""The data the calibration works on and produces (no computation beyond their own invariants).

  camera        CameraModel: pinhole + OpenCV distortion, for the camera and the projector
  boards        CharucoSpec: ChArUco board specifications (the board frame, units)
  pattern       PatternSpec: the projected circle grid or chessboard and its positions
  structured_light  StructuredLightSpec: the Gray-code and phase-shift sequence of the structured-light step
  observations  what detection hands to the calibration: points per view, DetectionFailure, Skipped
  result        CalibrationResult and MirrorPlane, with calibration.json and the OpenCV YAML export

Nearly every module imports these, so they depend only on calib.errors, calib.transforms and
calib.formats.fileio. The most used names are re-exported by `calib` itself (CameraModel,
CharucoSpec, PatternSpec, CalibrationResult, ...); nothing is re-exported here.
"""
