"""BLAS threads and busy cores: the joint calibration of a few random rigs (calib.synthetic), in a
fresh process per run, with OpenBLAS's default thread count and with one thread (app/blas_threads.py),
on idle cores and with every core kept busy by another process (as the station's preview and detection
threads, or a second program, keep them).

    python benchmarks/blas_threads.py                 # 6 rigs, 2 rounds
    python benchmarks/blas_threads.py --rigs 10 --rounds 3

Runs alternate (default, one thread, default, ...) so that the machine's drift falls on both alike; the
table prints the median wall and CPU seconds of each arm.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = """
import json, sys, time, warnings
warnings.filterwarnings("ignore")
sys.path.insert(0, {repo!r})
if {limit}:
    from app.blas_threads import limit_blas_threads
    limit_blas_threads()
from calib.pipeline import calibrate_observations
from calib.synthetic import observe, random_session
data = [observe(random_session(s), 0.2, s, circle_centroids=True) for s in range({rigs})]
t, c = time.perf_counter(), time.process_time()
for o in data:
    calibrate_observations(o, "joint", trust=None)
print(json.dumps({{"wall": time.perf_counter() - t, "cpu": time.process_time() - c}}))
"""


def run_child(limit: bool, rigs: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", CHILD.format(repo=str(REPO), limit=limit, rigs=rigs)],
                         capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    cores = os.cpu_count() or 1
    rows = []
    for busy in (0, cores):
        spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
        try:
            runs = {False: [], True: []}
            for _ in range(args.rounds):
                for limit in (False, True):
                    runs[limit].append(run_child(limit, args.rigs))
        finally:
            for p in spinners:
                p.kill()
        for limit in (False, True):
            wall = statistics.median(r["wall"] for r in runs[limit])
            cpu = statistics.median(r["cpu"] for r in runs[limit])
            rows.append((f"{busy} of {cores}", "1" if limit else "default", wall, cpu))
    print(f"joint calibration of {args.rigs} random rigs, median of {args.rounds} runs per arm")
    print("| cores busy with other work | BLAS threads | wall s | CPU s |")
    print("|---|---|---|---|")
    for busy, threads, wall, cpu in rows:
        print(f"| {busy} | {threads} | {wall:.2f} | {cpu:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
