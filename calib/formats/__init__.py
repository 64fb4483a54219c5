"""Readers and writers of the station's files (everything else in calib/ does no I/O).

  session       a capture session folder: session.json and its lossless PNG images
  session_lock  one program writes a session folder at a time (.procam.lock)
  fileio        crash-safe writes (temporary file, fsync, rename)
  jsonfile      untrusted JSON files to values (size, UTF-8, nesting checked; the meaning is each reader's)
  procamcalib   importer of recordings of the published reference implementation

calibration.json is read and written by its dataclass (calib.models.result), detections.json by
the detector (calib.detection.cache). Nothing is re-exported.
"""
