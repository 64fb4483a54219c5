"""Detection speed (and accuracy) on a simulated session: per-image time of each stage, and the wall
time of calib.detection.detect.detect_session with 1 and 2 worker processes.

    python benchmarks/detection_speed.py                      # 66 images at 1920x1080 (rendered once)
    python benchmarks/detection_speed.py --session DIR        # any session folder (e.g. procam simulate)

The default session is the paper's protocol on the nonoverlap-136 scenario (drivers/sim) with a
1920x1080 camera (~90 deg), 13 positions x 4 poses + 14 real-virtual mirror images = 66 images, as in
the published ProcamCalib recordings (52 + 14). It is rendered into --work (default
/tmp/procam_bench_detect) on first use. When the folder has the simulator's scene.json, detected points
are compared with the exact projections (board corners; pattern centres include the circle-centre bias
of docs/GEOMETRY.md, so that column is not a detection error alone).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib.detection import detect as D  # noqa: E402
from calib.formats.session import SessionStore  # noqa: E402
from calib.models.camera import CameraModel  # noqa: E402
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL, VIEW_MIRROR  # noqa: E402


def make_session(work: Path) -> Path:
    from app.commands.simulate import simulate_session
    from drivers.sim.scenarios import get_scenario

    out = work / "nonoverlap-136-1080p"
    if (out / "session.json").exists():
        return out
    sc = get_scenario("nonoverlap-136")
    cam = CameraModel.from_fov(1920, 1080, 90.0, dist=sc.rig.camera.dist)
    sc = replace(sc, rig=replace(sc.rig, camera=cam), mirror_count=14)
    print(f"rendering {out} (once) ...", file=sys.stderr)
    simulate_session(sc, out, workers=2, progress=True)
    return out


def truth_for(folder: Path):
    """{capture id: ExpectedPoints} from the simulator's scene.json, or None for other sessions."""
    from drivers.sim.scene_file import expected_points

    return expected_points(folder) if (folder / "scene.json").exists() else None


def stats(v):
    v = np.asarray(v, float)
    if v.size == 0:
        return "      -       -       -"
    return f"{np.median(v):7.1f} {np.percentile(v, 90):7.1f} {v.max():7.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--session", type=Path, help="session folder (default: render the 66-image 1080p session)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/procam_bench_detect"))
    args = ap.parse_args()
    folder = args.session or make_session(args.work)
    store = SessionStore.open(folder)
    m = store.manifest
    cv2.setNumThreads(1)
    mirrored = m.rig.view == VIEW_MIRROR
    mboard = m.mirror_board or m.projector_board
    t_read, t_board, t_pattern, t_mirror = [], [], [], []
    err_board, err_pattern, err_mirror = [], [], []
    truth = truth_for(folder)
    failures = 0
    for c in m.captures:
        t0 = time.process_time()
        gray = cv2.imread(str(store.image_path(c)), cv2.IMREAD_GRAYSCALE)
        t1 = time.process_time()
        t_read.append((t1 - t0) * 1e3)
        if gray is None:
            failures += 1
            continue
        if c.step == STEP_PROJECTOR:
            board = D._detect_board_gray(gray, m.projector_board, mirrored)
            t2 = time.process_time()
            t_board.append((t2 - t1) * 1e3)
            if not board:
                failures += 1
                continue
            pts = D._detect_pattern_gray(gray, m.pattern, mirrored, board, m.projector_board)
            t_pattern.append((time.process_time() - t2) * 1e3)
            if isinstance(pts, D.DetectionFailure):
                failures += 1
                continue
            if truth and c.id in truth:
                corners, centres, _ = truth[c.id]
                err_board.extend(np.linalg.norm(board.corners_px - corners[board.ids], axis=1))
                err_pattern.extend(np.linalg.norm(pts - centres, axis=1))
        else:
            fn = D.detect_real_virtual if c.step == STEP_REAL_VIRTUAL else D.detect_real_mirror
            mv = fn(gray, mboard, c.id)
            t_mirror.append((time.process_time() - t1) * 1e3)
            if isinstance(mv, D.DetectionFailure):
                failures += 1
                continue
            if truth and c.id in truth:
                real, _, virt = truth[c.id]
                err_mirror.extend(np.linalg.norm(mv.real.corners_px - real[mv.real.ids], axis=1))
                if virt is not None and mv.virtual is not None:
                    err_mirror.extend(np.linalg.norm(mv.virtual.corners_px - virt[mv.virtual.ids], axis=1))

    n = len(m.captures)
    w, h = m.rig.camera_size
    print(f"session {folder}: {n} images {w}x{h}, pattern {m.pattern.kind} {m.pattern.cols}x{m.pattern.rows}, "
          f"view {m.rig.view}; failed detections: {failures}")
    print()
    print("per image, CPU ms (one process)     median     p90     max")
    print(f"  read PNG (grayscale)             {stats(t_read)}")
    print(f"  ChArUco board (projector step)   {stats(t_board)}")
    print(f"  projected pattern                {stats(t_pattern)}")
    print(f"  mirror image (real [+ virtual])  {stats(t_mirror)}")
    if truth:
        print()
        print("accuracy vs exact projection, px   median     p90     max")
        print(f"  board corners (projector step)   {stats(np.array(err_board) * 100)}   (x 0.01 px)")
        print(f"  mirror-step board corners        {stats(np.array(err_mirror) * 100)}   (x 0.01 px)")
        print(f"  pattern centres (incl. bias)     {stats(np.array(err_pattern) * 100)}   (x 0.01 px)")
    print()
    print("detect_session wall time          seconds   per image")
    for workers in (1, 2):
        t0 = time.perf_counter()
        obs = D.detect_session(store, workers=workers, cache="off")  # time detection itself
        dt = time.perf_counter() - t0
        print(f"  workers={workers}                        {dt:7.2f}   {dt / n * 1e3:6.1f} ms"
              f"   ({len(obs.projector_views)} projector + {len(obs.mirror_views)} mirror views, "
              f"{len(obs.skipped)} skipped)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
