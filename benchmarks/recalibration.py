"""On-site recalibration on the simulated rig (issue 15): per bump, the check's verdict, the captures
used, the wall time and the errors against the bumped truth, next to the full session they start from.

    PYTHONPATH=$PWD python benchmarks/recalibration.py [--seed 0] [--work DIR]
"""

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def procam(*args) -> tuple[int, float]:
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True)
    if r.returncode not in (0, 1):
        sys.exit(f"procam {' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return r.returncode, time.monotonic() - t0


def errors(folder: Path) -> str:
    from calib.models.result import CalibrationResult
    from calib.quality.metrics import compare

    if not (folder / "calibration.json").exists():
        return "(no calibration.json)"
    m = compare(CalibrationResult.load_json(folder / "calibration.json"),
                CalibrationResult.load_json(folder / "ground_truth.json"))
    return (f"{m.distance:.3f} mm, {m.angle_deg:.4f} deg, CamK {m.cam_k_px:.2f} px, mirror "
            f"{m.mirror_angle_deg:.4f} deg")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None)
    a = ap.parse_args()
    work = Path(a.work or tempfile.mkdtemp(prefix="procam-recal-bench-"))
    full = work / "full"
    _, t_full = procam("session", "--rig", "sim", "--auto", "--seed", str(a.seed), "--out", str(full))
    n_full = len(json.loads((full / "session.json").read_text())["captures"])
    rows = [("full session", "-", n_full, t_full, errors(full))]
    for bump in ("none", "projector", "mirror", "camera"):
        d = work / f"recal-{bump}"
        rc, t = procam("recalibrate", str(full), "--rig", "sim", "--auto", "--seed", str(a.seed), "--sim-bump", bump,
                       "--out", str(d))
        rec = json.loads((d / "recalibration.json").read_text())
        rows.append((f"bump {bump}", rec["verdict"] + ("" if rc == 0 else " (exit 1)"), rec["captures"]["total"], t,
                     errors(d)))
    print(f"| run | verdict | captures | wall time | error against the (bumped) truth |\n|---|---|---|---|---|")
    for name, verdict, n, t, err in rows:
        print(f"| {name} | {verdict} | {n} | {t:.1f} s | {err} |")
    print(f"\n(work folder: {work})")


if __name__ == "__main__":
    main()
