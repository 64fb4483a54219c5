"""`procam report SESSION [--out FILE.html]`: the calibration report of a saved session (docs/REPORT.md)."""

from __future__ import annotations

import time

NAME = "report"
HELP = "write a self-contained HTML report of a calibrated session (parameters, residuals, coverage, rig, verification)"
DESCRIPTION = (
    "Writes one HTML file that opens offline (figures embedded) for a session folder holding calibration.json: "
    "both devices' parameters with their 1-sigma, distortion, reprojection residuals over the camera and "
    "projector images, per-view RMS with the worst views, coverage, the rig in 3D and, when verification.json "
    "exists, the verification curves with their distances. Default output: SESSION/report.html."
)


def add_arguments(p) -> None:
    p.add_argument("session", metavar="SESSION", help="calibrated session folder (with calibration.json)")
    p.add_argument("--out", metavar="FILE.html", default=None, help="where to write the report (default SESSION/report.html)")


def run(args) -> int:
    from app.report import write_report

    t0 = time.perf_counter()
    out = write_report(args.session, args.out)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s")
    return 0
