"""`procam report`: one self-contained HTML file describing a saved, calibrated session (docs/REPORT.md).

data.py gathers what is shown (calibration.json, verification.json, the detections and the residuals
recomputed from them), figures.py draws the figures (matplotlib, Agg), page.py writes the page.
"""

from __future__ import annotations

from pathlib import Path

from calib.fileio import atomic_write_text

from .data import ReportError, gather

DEFAULT_NAME = "report.html"


def write_report(session_dir, out_path=None) -> Path:
    """Write the report of the calibrated session in `session_dir` to `out_path` (default
    SESSION/report.html), atomically. Returns the path written. Raises ReportError (no
    calibration.json, not this session's calibration), SessionError or FormatError with a one-line
    reason."""
    from .page import render

    session_dir = Path(session_dir)
    out = Path(out_path) if out_path is not None else session_dir / DEFAULT_NAME
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReportError(f"the report is HTML: give --out a file name ending in .html, not {out}")
    if out.is_dir():
        raise ReportError(f"--out {out} is a folder; give a file name such as {out / DEFAULT_NAME}")
    data = gather(session_dir)  # before touching the output: a bad session leaves nothing behind
    if not out.parent.is_dir():
        raise ReportError(f"cannot write {out}: the folder {out.parent} does not exist")
    text = render(data)
    try:
        atomic_write_text(out, text)
    except OSError as e:
        raise ReportError(f"cannot write {out}: {e.strerror or e}") from None
    return out


__all__ = ["write_report", "ReportError", "DEFAULT_NAME"]
