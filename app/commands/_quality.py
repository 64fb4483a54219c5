"""The quality gate's exit status (calib.quality.trust, "quality"): shared by `procam calibrate` and `procam session`.

Exit codes of the commands: 0 good, 1 verification failed, 2 an error (or an untrusted result, not
written), 3 a LOW QUALITY calibration (trusted and written, but far more uncertain than a full session)."""

from __future__ import annotations

import sys

EXIT_LOW_QUALITY = 3


def report_low_quality(result, file=None) -> bool:
    """Print the low-quality reasons of a result (stderr by default); True when there were any."""
    from calib.quality.trust import low_quality_lines

    lines = low_quality_lines(result)
    if lines:
        out = file or sys.stderr
        print(f"LOW QUALITY calibration (written, usable, but far more uncertain than a full session; exit code "
              f"{EXIT_LOW_QUALITY}):", file=out)
        for line in lines:
            print("  " + line, file=out)
    return bool(lines)
