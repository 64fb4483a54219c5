"""02: render a capture session of the simulated rig, calibrate it from its images, compare with truth.

The same as `procam simulate nonoverlap-136 --out DIR && procam calibrate DIR && procam evaluate
DIR/calibration.json DIR/ground_truth.json`, from Python.

    python examples/02_simulate_calibrate_evaluate.py [OUT_DIR]
"""

import sys
import tempfile
from pathlib import Path

from app.cli import main as procam
from calib.models.result import CalibrationResult
from calib.pipeline import calibrate_session
from calib.quality.metrics import compare

out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp()) / "session"
procam(["simulate", "nonoverlap-136", "--out", str(out), "--seed", "3"])

result = calibrate_session(out, method="joint")
truth = CalibrationResult.load_json(out / "ground_truth.json")
print(compare(result, truth).format_table())
print("skipped:", [s["capture_id"] if isinstance(s, dict) and "capture_id" in s else s for s in result.skipped])
