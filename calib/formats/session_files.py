"""The file names of a session folder, defined once.

Every module that reads or writes a session folder's files names them through this registry, so a
file is renamed (or a new one added) here alone. `PROTECTED` lists the files an output of a command
must never replace (app/commands/_outputs.py), with what each one is.
"""

from __future__ import annotations

MANIFEST = "session.json"
IMAGES_DIR = "images"
DETECTIONS = "detections.json"
GROUND_TRUTH = "ground_truth.json"
SCENE = "scene.json"
CALIBRATION = "calibration.json"
#: the default export `procam calibrate` writes beside the result (calib.export.registry)
CALIBRATION_YAML = "calibration.yaml"
VERIFICATION = "verification.json"
REPORT = "report.html"
RECALIBRATION = "recalibration.json"
#: the folder a recalibration archives the calibration it replaces in
PREVIOUS_DIR = "previous"

#: the results of a calibrated session, in the order the panel offers them
RESULTS = (CALIBRATION, CALIBRATION_YAML, VERIFICATION, REPORT, RECALIBRATION)

PROTECTED = {
    MANIFEST: "the session's manifest",
    DETECTIONS: "the session's detection cache",
    GROUND_TRUTH: "the session's ground truth",
    SCENE: "the simulated session's scene",
    VERIFICATION: "the session's verification report",
}
