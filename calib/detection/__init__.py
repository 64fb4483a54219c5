"""Detection: camera images in, points out (pure functions on numpy images).

  detect  ChArUco boards and projected patterns -> SessionObservations; entry `detect_session`
  cache   the detection results kept in the session folder (detections.json)
  response  the camera's recorded tone curve and its inverse (linearised levels for circle centroids)
  curves  a projected curve (a bright stroke) in a camera image, for the epipolar verification
  structured_light  a structured-light sequence -> per-pixel projector coordinates and validity; entry `decode_sequence`
  local_homography  projector pixels of camera points from local homographies; entry `fit_local_homographies`
  structured_view   one structured-light capture -> a ProjectorView; entry `detect_structured_view`

Nothing is re-exported: `import calib.detection.curves` must not load OpenCV's board detection
machinery, and `calib.detection.detect.detect_session` says where the code is.
"""
