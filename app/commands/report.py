"""`procam report SESSION [--calibration FILE] [--out FILE.html]`: the calibration report of a saved
session (docs/REPORT.md)."""

from __future__ import annotations

import time
from pathlib import Path

NAME = "report"
HELP = "write a self-contained HTML report of a calibrated session (parameters, residuals, coverage, rig, verification)"
DESCRIPTION = (
    "Writes one HTML file that opens offline (figures embedded) for a session folder holding calibration.json: "
    "both devices' parameters with their 1-sigma, distortion, reprojection residuals over the camera and "
    "projector images, per-view RMS with the worst views, coverage, the rig in 3D and, when verification.json "
    "verified this calibration, the verification curves with their distances."
)


def add_arguments(p) -> None:
    p.add_argument("session", metavar="SESSION", help="calibrated session folder (with calibration.json)")
    p.add_argument("--calibration", metavar="FILE", default=None,
                   help="calibration to report (default: SESSION/calibration.json; e.g. SESSION/calibration-paper.json)")
    p.add_argument("--out", metavar="FILE.html", default=None,
                   help="where to write the report (default: SESSION/report.html; report-paper.html for "
                        "calibration-paper.json)")


def run(args) -> int:
    from app.commands._outputs import check_output_file
    from app.report import ReportError, default_out, write_report

    out = Path(args.out) if args.out else default_out(args.session, args.calibration)
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReportError(f"--out {out}: the report is an HTML file, name it *.html (e.g. {out.with_suffix('.html')})")
    check_output_file(out, "--out", inputs=[args.calibration])  # before any work: never a session's file
    t0 = time.perf_counter()
    out = write_report(args.session, out, args.calibration)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s")
    return 0
