"""Calibration accuracy on simulated sessions vs ground truth: a wrapper of `procam bench accuracy`.

    python benchmarks/accuracy.py [--scenarios nonoverlap-136 direct] [--seeds 3] [--methods paper,joint]
"""

import sys

from app.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", "accuracy", *sys.argv[1:]]))
