"""What the simulated stream's JPEG does to detection (`--rig sim-uvc`, drivers/sim/stream.py): the same
rendered captures detected as rendered and after the stream's JPEG encoding.

    python benchmarks/stream_jpeg.py                      # quality 95 (the stream's), seed 0
    python benchmarks/stream_jpeg.py --quality 95 100 --seed 1

A session is rendered with `procam simulate` (PNG, lossless); a copy has every image replaced by its
JPEG round trip at each quality (cv2.imencode as the stream server encodes). Each capture is detected in
both (calib.detection.detect.detect_capture, as the station does) and the points found in both are
compared: the RMS and the largest shift of the ChArUco corners and of the projected pattern's points, in
camera px. The calibration's accuracy through the stream is in benchmarks/camera_paths.py.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _points(result) -> dict:
    """{(kind, id): (x, y)} of one capture's detection."""
    from calib.models.observations import BoardObservation, MirrorView

    out = {}

    def board(kind, obs):
        if isinstance(obs, BoardObservation):
            for i, p in zip(obs.ids, obs.corners_px):
                out[(kind, int(i))] = p

    if isinstance(result, MirrorView):
        board("real", result.real)
        board("virtual", result.virtual)
    elif isinstance(result, tuple) and len(result) == 2:
        board("board", result[0])
        pts = getattr(result[1], "pattern_cam_px", result[1])
        for i, p in enumerate(np.asarray(pts, float).reshape(-1, 2)):
            out[("pattern", i)] = p
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quality", type=int, nargs="+", default=[95])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    from calib.detection.detect import detect_capture
    from calib.formats.session import SessionStore

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "png"
        subprocess.run([sys.executable, "-m", "app", "simulate", "nonoverlap-136", "--seed", str(args.seed),
                        "--quality", "live", "--out", str(src), "--no-progress"], cwd=ROOT, check=True,
                       capture_output=True)
        store = SessionStore.open(src)
        ref = {c.id: _points(detect_capture(store, c.id)) for c in store.manifest.captures}
        print(f"seed {args.seed}, {len(ref)} captures; points found in both, camera px")
        print(f"{'JPEG quality':>12} {'corners rms':>11} {'corners max':>11} {'pattern rms':>11} {'pattern max':>11} "
              f"{'lost':>5}")
        for q in args.quality:
            dst = Path(tmp) / f"q{q}"
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("detections.json"))
            for png in (dst / "images").glob("*.png"):
                img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
                ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])
                cv2.imwrite(str(png), cv2.imdecode(buf, cv2.IMREAD_UNCHANGED))
            jstore = SessionStore.open(dst)
            d = {"board": [], "pattern": []}
            lost = 0
            for c in jstore.manifest.captures:
                got = _points(detect_capture(jstore, c.id))
                for k, p in ref[c.id].items():
                    if k not in got:
                        lost += 1
                        continue
                    d["pattern" if k[0] == "pattern" else "board"].append(float(np.hypot(*(got[k] - p))))
            b, p = np.asarray(d["board"]), np.asarray(d["pattern"])
            print(f"{q:>12} {np.sqrt((b ** 2).mean()):>11.3f} {b.max():>11.3f} {np.sqrt((p ** 2).mean()):>11.3f} "
                  f"{p.max():>11.3f} {lost:>5}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
