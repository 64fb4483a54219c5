"""Detection: camera images in, points out (pure functions on numpy images).

  charuco  ChArUco boards in an image -> BoardObservation; entry `detect_board`
  pattern  a projected circle grid or chessboard in an image -> camera pixels; entry `detect_pattern`
  mirror_views  the mirror step's views (real and virtual board, board on the mirror); entries
          `detect_real_virtual`, `detect_real_mirror`
  session_jobs  every capture of a session folder, in threads -> SessionObservations; entry `detect_session`
  imaging  helpers the stages share (gray images, the mirror flip, per-thread OpenCV objects)
  detect  the entry functions above under one name, for their callers
  cache   the detection results kept in the session folder (detections.json)
  response  the camera's recorded tone curve and its inverse (linearised levels for circle centroids)
  curves  a projected curve (a bright stroke) in a camera image, for the epipolar verification
  structured_light  a structured-light sequence -> per-pixel projector coordinates and validity; entry `decode_sequence`
  local_homography  projector pixels of camera points from local homographies; entry `fit_local_homographies`
  structured_view   one structured-light capture -> a ProjectorView; entry `detect_structured_view`

Nothing is re-exported: `import calib.detection.curves` must not load OpenCV's board detection
machinery, and `calib.detection.session_jobs.detect_session` says where the code is.
"""
