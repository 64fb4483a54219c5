"""Frames per second of the simulated camera (1280x800) per render mode. Not a timed test: run it.

    python benchmarks/render_speed.py [--scenario nonoverlap-136] [--frames 30]
"""

import argparse

from app.commands.bench import render_speed

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nonoverlap-136")
    ap.add_argument("--frames", type=int, default=30)
    a = ap.parse_args()
    print(f"{'mode':<24} {'frames/s':>8}  first start")
    for mode, fps, warm in render_speed(a.scenario, a.frames):
        print(f"{mode:<24} {fps:8.1f}  {warm:.1f} s")
