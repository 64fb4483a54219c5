"""Wall time of `procam calibrate` on a 66-image 1920x1080 session, detection included, stage by stage.

    python benchmarks/session_speed.py                 # the simulated session of detection_speed.py
    python benchmarks/session_speed.py --colour        # the same images stored as colour PNGs
    python benchmarks/session_speed.py --session DIR   # any session folder
    python benchmarks/session_speed.py --method paper  # the paper's method instead of the default

Each run is a fresh `procam calibrate --redetect` process (what a user waits for: interpreter start,
imports, reading and detecting every image, calibrating, writing calibration.json and .yaml). The
table shows the median over --runs of the stage times the command records in calibration.json
(diagnostics.timing_s) and of the process's wall time; then the same without --redetect, when the
session's detections.json holds every capture's detections from the runs before.

The simulated camera is monochrome, so its captures are stored as one-channel PNGs; `--colour` makes a
copy whose three channels differ by one grey level (as a colour camera's would), so that the PNGs stay
three-channel and the cost of decoding colour images shows.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def colour_copy(folder: Path) -> Path:
    """A copy of the session whose images are 3-channel PNGs (B and R one level off G, clipped)."""
    import shutil

    out = folder.with_name(folder.name + "-colour")
    if (out / "session.json").exists():
        return out
    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(folder, tmp)
    for png in sorted((tmp / "images").glob("*.png")):
        g = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        bgr = np.dstack([np.clip(g.astype(int) + 1, 0, 255), g, np.clip(g.astype(int) - 1, 0, 255)]).astype(np.uint8)
        ok, buf = cv2.imencode(".png", bgr)
        png.write_bytes(buf.tobytes())
    tmp.rename(out)
    return out


def run_once(folder: Path, method: str, workers: int, redetect: bool = True) -> tuple[float, dict]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "calibration.json"
        cmd = [sys.executable, "-m", "app.cli", "calibrate", str(folder), "--no-progress", "--method", method,
               "--workers", str(workers), "--out", str(out)] + (["--redetect"] if redetect else [])
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"procam calibrate failed:\n{proc.stderr}")
        timing = json.loads(out.read_text())["diagnostics"]["timing_s"]
    return wall, timing


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--session", type=Path, help="session folder (default: the 66-image 1080p simulated session)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/procam_bench_detect"))
    ap.add_argument("--colour", action="store_true", help="use a colour-PNG copy of the session")
    ap.add_argument("--method", default="joint")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    if args.session is None:
        from detection_speed import make_session

        folder = make_session(args.work)
    else:
        folder = args.session
    if args.colour:
        folder = colour_copy(folder)
    runs = [run_once(folder, args.method, args.workers) for _ in range(args.runs)]
    walls = [w for w, _ in runs]
    keys = list(runs[0][1])
    n_img = len(json.loads((folder / "session.json").read_text())["captures"])
    print(f"session {folder} ({n_img} images), method {args.method}, workers {args.workers}, "
          f"median of {args.runs} fresh `procam calibrate` processes")
    print()
    print("stage                              seconds")
    for k in keys:
        if k in ("total", "detection"):
            continue
        print(f"  {k:32s} {statistics.median(t[k] for _, t in runs):6.2f}")
    det = statistics.median(t["detection"] for _, t in runs)
    cal = statistics.median(t["total"] for _, t in runs)
    both = statistics.median(t["detection"] + t["total"] for _, t in runs)
    print(f"  {'detection (all images)':32s} {det:6.2f}")
    print(f"  {'calibration (all stages)':32s} {cal:6.2f}")
    print(f"  {'detection + calibration':32s} {both:6.2f}")
    print(f"  {'procam calibrate, process wall':32s} {statistics.median(walls):6.2f}"
          f"   (min {min(walls):.2f}, max {max(walls):.2f})")
    warm = [run_once(folder, args.method, args.workers, redetect=False) for _ in range(args.runs)]
    print()
    print("again, with the detections kept in the session (detections.json: nothing decoded)")
    print(f"  {'detection (cache)':32s} {statistics.median(t['detection'] for _, t in warm):6.2f}")
    print(f"  {'procam calibrate, process wall':32s} {statistics.median(w for w, _ in warm):6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
