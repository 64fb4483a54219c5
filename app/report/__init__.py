"""`procam report`: one self-contained HTML file describing a saved, calibrated session (docs/REPORT.md).

data.py gathers what is shown (calibration.json, verification.json, the detections and the residuals
recomputed from them), figures.py draws the figures (matplotlib, Agg), page.py writes the page.
"""

from __future__ import annotations

from pathlib import Path

from calib.formats import session_files
from calib.formats.fileio import atomic_write_text

from .data import ReportError, gather

DEFAULT_NAME = session_files.REPORT


def default_out(session_dir, calibration_path=None) -> Path:
    """SESSION/report.html for SESSION/calibration.json; report-paper.html for calibration-paper.json
    (calibrate's name for a second method's result); report-NAME.html for any other NAME.json."""
    if calibration_path is None:
        return Path(session_dir) / DEFAULT_NAME
    stem = Path(calibration_path).stem
    if stem == "calibration":
        return Path(session_dir) / DEFAULT_NAME
    return Path(session_dir) / f"report-{stem.removeprefix('calibration-')}.html"


def write_report(session_dir, out_path=None, calibration_path=None) -> Path:
    """Write the report of the calibrated session in `session_dir` to `out_path` (default
    `default_out`), atomically, for the calibration in `calibration_path` (default
    SESSION/calibration.json). Returns the path written. Raises ReportError (no calibration, not this
    session's calibration, an output that is not .html), SessionError or FormatError with a one-line
    reason."""
    from .page import render

    session_dir = Path(session_dir)
    out = Path(out_path) if out_path is not None else default_out(session_dir, calibration_path)
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReportError(f"the report is HTML: give --out a file name ending in .html, not {out}")
    if out.is_dir():
        raise ReportError(f"--out {out} is a folder; give a file name such as {out / DEFAULT_NAME}")
    data = gather(session_dir, calibration_path)  # before writing: a bad session leaves nothing behind
    if not out.parent.is_dir():
        raise ReportError(f"cannot write {out}: the folder {out.parent} does not exist")
    text = render(data)
    try:
        atomic_write_text(out, text)
    except OSError as e:
        raise ReportError(f"cannot write {out}: {e.strerror or e}") from None
    return out


__all__ = ["write_report", "default_out", "ReportError", "DEFAULT_NAME"]
