"""What the projector's latency costs a whole session on the simulated rig (docs/STATION.md, "timing").

    python benchmarks/latency.py                    # latency 0 and 150 ms, one run each
    python benchmarks/latency.py --latency 0 50 150 --runs 3

Each run is a fresh `procam session --rig sim --auto --sim-latency-ms L` process (what the README's
session command does, at the given latency). From the session's own log the table shows, median over
--runs: the process's wall time; the rig check (exposure search and latency measurement, once per
session); the capture steps (mirror and projector, from the end of the rig check to the last
capture); and the time from the last capture to the verified calibration, split into calibrate and
verify. Targets (issue 14): the capture steps within 1.3x of latency 0's (a capture waits only as long
as the latency requires); last capture to verified under 5 s at 150 ms.

The machine's load changes every number; run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINE = re.compile(r"^\[\s*([0-9.]+) s\] (.*)$")


def run_once(latency_ms: float, seed: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "s"
        cmd = [sys.executable, "-m", "app", "session", "--rig", "sim", "--auto", "--seed", str(seed),
               "--sim-latency-ms", f"{latency_ms:g}", "--out", str(out)]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"session at {latency_ms:g} ms failed (exit {p.returncode}):\n{p.stdout[-2000:]}{p.stderr[-2000:]}")
    times = {}
    last_capture = None
    for line in p.stdout.splitlines():
        m = LINE.match(line)
        if not m:
            continue
        t, text = float(m.group(1)), m.group(2)
        if text.startswith("rig check:"):
            times["checked"] = t
        elif text.startswith("captured "):
            last_capture = t
        elif text.startswith("calibrated"):
            times["calibrated"] = t
        elif text.startswith("verification passed") or text.startswith("verification failed"):
            times["verified"] = t
        elif text.startswith("new session"):
            times["start"] = t
    need = {"start", "checked", "calibrated", "verified"}
    if last_capture is None or not need <= set(times):
        raise SystemExit(f"could not read the session log at {latency_ms:g} ms:\n{p.stdout[-2000:]}")
    return {"wall": wall, "rig_check": times["checked"] - times["start"],
            "captures": last_capture - times["checked"], "calibrate": times["calibrated"] - last_capture,
            "verify": times["verified"] - times["calibrated"], "to_verified": times["verified"] - last_capture}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latency", type=float, nargs="+", default=[0.0, 150.0], metavar="MS")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    runs = {lat: [] for lat in args.latency}
    for _ in range(args.runs):  # interleaved, so that a burst of load on the machine hits every latency
        for lat in args.latency:
            runs[lat].append(run_once(lat, args.seed))
    rows = [(lat, {k: statistics.median(r[k] for r in rs) for k in rs[0]}) for lat, rs in runs.items()]
    base = rows[0][1]["captures"]
    print(f"simulated session, medians of {args.runs} run(s); times in seconds")
    print(f"{'latency ms':>10} {'wall':>7} {'rig check':>10} {'captures':>9} {'x lat 0':>8} "
          f"{'calibrate':>10} {'verify':>7} {'last capture -> verified':>25}")
    for lat, r in rows:
        print(f"{lat:>10g} {r['wall']:>7.1f} {r['rig_check']:>10.1f} {r['captures']:>9.1f} "
              f"{r['captures'] / base:>8.2f} {r['calibrate']:>10.1f} {r['verify']:>7.1f} {r['to_verified']:>25.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
