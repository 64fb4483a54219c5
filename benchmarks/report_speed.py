"""Time of `procam report` on the default session (nonoverlap-136: 52 projector + 14 mirror captures,
1280x800), each run a fresh process as a user would start it; prints a table.

    python benchmarks/report_speed.py [--session DIR] [--runs 5] [--work /tmp/procam_bench_report]

Without --session the default scenario is simulated, calibrated and verified into --work on first use.
Also prints the time of each part of one in-process report (gathering, every section's figures).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def procam(*args) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "app", *args], cwd=ROOT, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"procam {' '.join(args)} failed:\n{r.stdout}{r.stderr}")
    return r


def default_session(work: Path) -> Path:
    folder = work / "nonoverlap-136"
    if not (folder / "calibration.json").exists():
        procam("simulate", "nonoverlap-136", "--out", str(folder), "--no-progress", "--force")
        procam("calibrate", str(folder), "--no-progress")
    if not (folder / "verification.json").exists():
        procam("verify", str(folder), "--rig", "sim")
    return folder


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--session", type=Path, default=None)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--work", type=Path, default=Path("/tmp/procam_bench_report"))
    args = ap.parse_args()
    folder = args.session or default_session(args.work)
    out = args.work / "report.html"
    args.work.mkdir(parents=True, exist_ok=True)
    times = []
    for _ in range(args.runs):
        t0 = time.perf_counter()
        procam("report", str(folder), "--out", str(out))
        times.append(time.perf_counter() - t0)
    from app.report import page
    from app.report.data import gather

    t0 = time.perf_counter()
    d = gather(folder)
    parts = [("gather (calibration, detections, residuals)", time.perf_counter() - t0)]
    for f in (page._summary, page._parameters, page._distortion, page._residuals, page._per_view, page._coverage,
              page._rig, page._verification):
        t0 = time.perf_counter()
        f(d)
        parts.append((f.__name__.strip("_"), time.perf_counter() - t0))
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    print(f"session {folder} ({len(d.store.manifest.captures)} captures), load average {load:.1f}")
    print(f"| what | seconds |\n|---|---|")
    print(f"| `procam report` (whole process), median of {len(times)} | {statistics.median(times):.2f} "
          f"(min {min(times):.2f}, max {max(times):.2f}) |")
    for name, t in parts:
        print(f"| {name} | {t:.2f} |")
    print(f"report size {out.stat().st_size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
