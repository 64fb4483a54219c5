"""What the camera's path costs a whole session: the simulated camera read directly (`--rig sim`) and through
the OpenCV driver on its live MJPEG stream (`--rig sim-uvc`, docs/DRIVERS.md), on the same seeds.

    python benchmarks/camera_paths.py                     # seeds 0-2, both rigs
    python benchmarks/camera_paths.py --seeds 0 --rigs sim-uvc

Each run is a fresh `procam session --rig RIG --auto --seed S` process (the README's main job). The
table gives, per run, the errors against the simulator's ground truth (`procam evaluate`'s metrics:
distance, angle, projector and camera K), the verification's mean in projector px, and the process's
CPU time (its children's user + system: the machine's other load changes the wall time, not this).
Runs are interleaved by seed, so a burst of load hits both rigs.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_once(rig: str, seed: int) -> dict:
    sys.path.insert(0, str(ROOT))
    from calib.models.result import CalibrationResult
    from calib.quality.metrics import compare

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "s"
        cmd = [sys.executable, "-m", "app", "session", "--rig", rig, "--auto", "--seed", str(seed), "--out", str(out)]
        cpu0, t0 = _cpu_children(), time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall, cpu = time.perf_counter() - t0, _cpu_children() - cpu0
        if p.returncode != 0:
            raise SystemExit(f"{rig} seed {seed} failed (exit {p.returncode}):\n{p.stdout[-2000:]}{p.stderr[-2000:]}")
        m = compare(CalibrationResult.load_json(out / "calibration.json"),
                    CalibrationResult.load_json(out / "ground_truth.json"))
        v = json.loads((out / "verification.json").read_text())
        proj_px = v.get("mean_proj_px")
    return {"distance": m.distance, "angle": m.angle_deg, "proj_k": m.proj_k_px, "cam_k": m.cam_k_px,
            "verified": bool(v.get("passed")), "verify_px": proj_px, "cpu": cpu, "wall": wall}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rigs", nargs="+", default=["sim", "sim-uvc"])
    args = ap.parse_args(argv)
    print(f"{'rig':>8} {'seed':>4} {'distance mm':>11} {'angle deg':>9} {'ProjK px':>8} {'CamK px':>7} "
          f"{'verified (proj px)':>18} {'CPU s':>6} {'wall s':>6}")
    for seed in args.seeds:
        for rig in args.rigs:
            r = run_once(rig, seed)
            verified = ("yes" if r["verified"] else "NO") + f" ({r['verify_px']:.2f})"
            print(f"{rig:>8} {seed:>4} {r['distance']:>11.3f} {r['angle']:>9.4f} {r['proj_k']:>8.2f} "
                  f"{r['cam_k']:>7.2f} {verified:>18} {r['cpu']:>6.1f} {r['wall']:>6.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
