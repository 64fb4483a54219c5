"""Detection speed (and accuracy) on simulated sessions, stage by stage, and `procam calibrate --redetect`
against older code, pair by pair.

    python benchmarks/detection_speed.py                          # both kinds of session, this code
    python benchmarks/detection_speed.py --session DIR            # any session folder (e.g. procam simulate)
    python benchmarks/detection_speed.py --baseline-rev b00b702 --pairs 3   # A B A B against older code
    python benchmarks/detection_speed.py --reference --pairs 3    # ... and the reference pipeline's port

The two kinds of session, rendered into --work (default /tmp/procam_bench_detect) on first use:

- `mono800`: the simulator's default, nonoverlap-136 at 1280x800 (monochrome, one-channel PNGs);
- `colour1080`: the paper's protocol on the same rig with a 1920x1080 camera (~90 deg) and its images
  stored as three-channel PNGs whose channels differ by a level, as a colour camera's would: the size
  and kind of the published ProcamCalib recordings (52 projector views seen through the mirror, 14
  real-virtual mirror views of the small 22 mm board).

Both record the camera's response, so detection reads levels as light as `procam calibrate` does. The
stage table is CPU time in one process and one thread (OpenCV's pool off), per image and in total; the
sub-stages are the time spent in the detector's functions of that name (marker search, corner
refinement, circle search, centroid refinement). With the simulator's scene.json, detected points are
compared with the exact projections (pattern centres include the circle-centre bias of
docs/GEOMETRY.md, so that column is not a detection error alone).

`--baseline-rev REV` checks REV out into a temporary `git worktree` and runs the stage table and a fresh
`procam calibrate SESSION --redetect` process there and here in turns (A B A B ..., --pairs times): the
machine's drift and the other users of its cores fall on both alike. Each run reports wall time and
the CPU time of the child process (all its threads, resource.getrusage); the ratio is taken pair by
pair and its median printed. `--reference` adds benchmarks/reference_pipeline.py (OpenCV's own
detectors, calibrateCamera and stereoCalibrate, no refinement) as a third arm of each round.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: the code tree whose detector the stage table measures (a baseline worktree in --stages-of runs)
CODE = Path(os.environ.get("PROCAM_BENCH_CODE", ROOT)).resolve()
sys.path.insert(0, str(CODE))

KINDS = ("mono800", "colour1080")

#: sub-stages: detector functions whose time is summed (the last is part of the one before it)
SUB_STAGES = (("marker search (ChArUco)", "_charuco_in"), ("corner refinement", "_refine_corners"),
              ("corner checks", "_verify_corners"), ("circle search and centroids", "_find_circles"),
              ("  of which centroids", "_refine_centroids"))


def make_session(work: Path) -> Path:
    """The 66-image 1920x1080 session of the paper's protocol (one-channel PNGs), rendered once."""
    from app.commands.simulate import simulate_session
    from calib.models.camera import CameraModel
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


def make_default_session(work: Path) -> Path:
    """The simulator's default scenario at its own 1280x800, rendered once."""
    from app.commands.simulate import simulate_session
    from drivers.sim.scenarios import get_scenario

    out = work / "nonoverlap-136-800"
    if not (out / "session.json").exists():
        print(f"rendering {out} (once) ...", file=sys.stderr)
        simulate_session(get_scenario("nonoverlap-136"), out, workers=2, progress=True)
    return out


def session_of(kind: str, work: Path) -> Path:
    if kind == "mono800":
        return make_default_session(work)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from session_speed import colour_copy

    return colour_copy(make_session(work))


def truth_for(folder: Path):
    """{capture id: ExpectedPoints} from the simulator's scene.json, or None for other sessions."""
    from drivers.sim.scene_file import expected_points

    return expected_points(folder) if (folder / "scene.json").exists() else None


def stats(v):
    v = np.asarray(v, float)
    if v.size == 0:
        return "      -       -       -"
    return f"{np.median(v):7.1f} {np.percentile(v, 90):7.1f} {v.max():7.1f}"


# ---- the stage table (in this process, on the code of CODE) ----------------------------------------------
def measure_stages(folder: Path, with_truth: bool = True) -> dict:
    """Per-image CPU ms of each stage, seconds per sub-stage, and (with the truth) the point errors."""
    import cv2

    # module names of the code before the calib/ subpackages too (a --baseline-rev that old)
    D = _module("calib.detection.detect", "calib.detect")
    SessionStore = _module("calib.formats.session", "calib.session").SessionStore
    obs = _module("calib.models.observations", "calib.observations")
    STEP_PROJECTOR, STEP_REAL_VIRTUAL, VIEW_MIRROR = obs.STEP_PROJECTOR, obs.STEP_REAL_VIRTUAL, obs.VIEW_MIRROR

    store = SessionStore.open(folder)
    m = store.manifest
    cv2.setNumThreads(1)
    # the detector's functions by stage module (older code kept them all in one module, D)
    stages = [mod for mod in (_module("calib.detection.charuco"), _module("calib.detection.pattern")) if mod] or [D]
    detect_board = getattr(D, "_detect_board_gray", D.detect_board)
    detect_pattern = getattr(D, "_detect_pattern_gray", D.detect_pattern)
    # code that reads the camera's response gets it, as detect_session passes it; older code has none
    takes = "response" in inspect.signature(detect_board).parameters
    recorded = _module("calib.detection.response")
    response = {"response": recorded.recorded_response(m.rig.camera_settings)} if takes else {}
    sub = defaultdict(float)
    for _, name in SUB_STAGES:
        for mod in stages:
            fn = getattr(mod, name, None)
            if fn is not None:
                setattr(mod, name, _timed(fn, name, sub))
    mirrored = m.rig.view == VIEW_MIRROR
    mboard = m.mirror_board or m.projector_board
    t = defaultdict(list)
    err = defaultdict(list)
    truth = truth_for(folder) if with_truth else None
    failures = 0
    for c in m.captures:
        data = np.fromfile(str(store.image_path(c)), np.uint8)
        t0 = time.process_time()
        gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        t1 = time.process_time()
        t["read"].append((t1 - t0) * 1e3)
        if c.step == STEP_PROJECTOR:
            board = detect_board(gray, m.projector_board, mirrored, **response)
            t2 = time.process_time()
            t["board"].append((t2 - t1) * 1e3)
            if isinstance(board, D.DetectionFailure):
                failures += 1
                continue
            pts = detect_pattern(gray, m.pattern, mirrored, board, m.projector_board, **response)
            t["pattern"].append((time.process_time() - t2) * 1e3)
            if isinstance(pts, D.DetectionFailure):
                failures += 1
                continue
            if truth and c.id in truth:
                corners, centres, _ = truth[c.id]
                err["board"].extend(np.linalg.norm(board.corners_px - corners[board.ids], axis=1))
                err["pattern"].extend(np.linalg.norm(pts - centres, axis=1))
        else:
            fn = D.detect_real_virtual if c.step == STEP_REAL_VIRTUAL else D.detect_real_mirror
            mv = fn(gray, mboard, c.id, **response)
            t["mirror"].append((time.process_time() - t1) * 1e3)
            if isinstance(mv, D.DetectionFailure):
                failures += 1
                continue
            if truth and c.id in truth:
                real, _, virt = truth[c.id]
                err["mirror"].extend(np.linalg.norm(mv.real.corners_px - real[mv.real.ids], axis=1))
                if virt is not None and mv.virtual is not None:
                    err["mirror"].extend(np.linalg.norm(mv.virtual.corners_px - virt[mv.virtual.ids], axis=1))
    return {"images": len(m.captures), "size": list(m.rig.camera_size), "failures": failures,
            "per_image_ms": {k: list(v) for k, v in t.items()}, "sub_s": dict(sub),
            "err_px": {k: [float(x) for x in v] for k, v in err.items()}}


def _module(*names):
    """The first of the dotted module names that imports from CODE's tree, or None (an editable install
    of another tree can supply names CODE does not have: those are not CODE's)."""
    import importlib

    for name in names:
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        if CODE in Path(mod.__file__).resolve().parents:
            return mod
    return None


def _timed(fn, name, into):
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            into[name] += time.process_time() - t0
    return wrapper


STAGE_ROWS = (("read", "read PNG (decoded to grey)"), ("board", "ChArUco board (projector step)"),
              ("pattern", "projected pattern"), ("mirror", "mirror image (real + virtual)"))


def print_stage_table(res: dict) -> None:
    w, h = res["size"]
    print(f"  {res['images']} images {w}x{h}, failed detections: {res['failures']}")
    print("  per image, CPU ms (one thread)      median     p90     max    total s")
    total = 0.0
    for key, label in STAGE_ROWS:
        v = res["per_image_ms"].get(key, [])
        total += sum(v) / 1e3
        print(f"    {label:32s} {stats(v)} {sum(v) / 1e3:8.2f}")
    print(f"    {'all stages':32s} {'':23s} {total:8.2f}")
    print("  sub-stages, CPU s")
    for label, name in SUB_STAGES:
        if name in res["sub_s"]:
            print(f"    {label:32s} {res['sub_s'][name]:8.2f}")
    if res["err_px"]:
        print("  accuracy vs exact projection, 0.01 px   median     p90     max")
        for key, label in (("board", "board corners (projector step)"), ("mirror", "mirror-step board corners"),
                           ("pattern", "pattern centres (incl. bias)")):
            print(f"    {label:32s}     {stats(np.array(res['err_px'].get(key, [])) * 100)}")


def stage_total_s(res: dict) -> float:
    return sum(sum(v) for v in res["per_image_ms"].values()) / 1e3


# ---- runs in child processes (for the pairs) ---------------------------------------------------------------
def _child(cmd, cwd: Path, env=None) -> tuple[subprocess.CompletedProcess, float, float]:
    """(completed process, wall s, CPU s of the child: user + system of all its threads)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode not in (0, 3):  # 3: LOW QUALITY, still a calibration
        raise SystemExit(f"{' '.join(map(str, cmd))} failed in {cwd}:\n{proc.stderr[-2000:]}")
    return proc, wall, cpu


def stages_in(tree: Path, folder: Path) -> dict:
    """The stage table of the code in `tree`, measured by this script in a child process."""
    env = dict(os.environ, PROCAM_BENCH_CODE=str(tree))
    proc, _, _ = _child([sys.executable, str(Path(__file__).resolve()), "--stages-of", str(folder)], tree, env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def calibrate_in(tree: Path, folder: Path, workers: int) -> dict:
    """A fresh `procam calibrate --redetect` with the code of `tree`: wall, CPU and its own stage times."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "calibration.json"
        cmd = [sys.executable, "-m", "app.cli", "calibrate", str(folder), "--no-progress", "--redetect",
               "--workers", str(workers), "--out", str(out)]
        _, wall, cpu = _child(cmd, tree)
        timing = json.loads(out.read_text())["diagnostics"]["timing_s"]
    return {"wall": wall, "cpu": cpu, "detection": timing.get("detection", float("nan")),
            "calibration": timing.get("total", float("nan"))}


def reference_in(folder: Path) -> dict:
    """benchmarks/reference_pipeline.py on the session: wall, CPU and its stage times."""
    cmd = [sys.executable, str(ROOT / "benchmarks" / "reference_pipeline.py"), str(folder), "--json"]
    proc, wall, cpu = _child(cmd, ROOT)
    own = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"wall": wall, "cpu": cpu, "detection": own["detection_s"], "calibration": own["calibration_s"]}


class Baseline:
    """REV checked out into a temporary git worktree, removed again on exit."""

    def __init__(self, rev: str):
        self.rev = rev
        self.tmp = tempfile.mkdtemp(prefix="procam-baseline-")
        self.tree = Path(self.tmp) / "tree"

    def __enter__(self) -> Path:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(self.tree), self.rev],
                       check=True, capture_output=True, text=True)
        return self.tree

    def __exit__(self, *exc):
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(self.tree)],
                       capture_output=True, text=True)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], capture_output=True, text=True)
        shutil.rmtree(self.tmp, ignore_errors=True)


def _med(rows, key):
    return statistics.median(r[key] for r in rows)


def run_pairs(folders: dict, baseline: Path | None, rev: str | None, reference: bool, pairs: int,
              workers: int) -> None:
    arms = [("this code", ROOT)] + ([(f"baseline {rev}", baseline)] if baseline is not None else [])
    for kind, folder in folders.items():
        print(f"\n== {kind}: {folder}")
        stage_runs = defaultdict(list)
        cal_runs = defaultdict(list)
        for _ in range(pairs):  # one round: every arm once, in the same order (A B [R] A B [R] ...)
            for name, tree in arms[::-1]:
                stage_runs[name].append(stages_in(tree, folder))
                cal_runs[name].append(calibrate_in(tree, folder, workers))
            if reference:
                cal_runs["reference pipeline"].append(reference_in(folder))
        print(f"  detection stages, CPU s in one thread (median of {pairs})")
        header = "    " + f"{'stage':34s}" + "".join(f"{n:>18s}" for n, _ in arms)
        print(header + ("   ratio (pairs)" if baseline is not None else ""))
        for key, label in STAGE_ROWS + (("all", "all stages"),):
            vals = {}
            for n, _ in arms:
                if key == "all":
                    vals[n] = [stage_total_s(r) for r in stage_runs[n]]
                else:
                    vals[n] = [sum(r["per_image_ms"].get(key, [])) / 1e3 for r in stage_runs[n]]
            line = f"    {label:34s}" + "".join(f"{statistics.median(vals[n]):18.2f}" for n, _ in arms)
            if baseline is not None:
                a, b = vals[arms[0][0]], vals[arms[1][0]]
                line += f"   {statistics.median(x / y for x, y in zip(a, b) if y > 0):6.2f}" if any(b) else "      -"
            print(line)
        print(f"  `procam calibrate --redetect --workers {workers}`, fresh process (median of {pairs})")
        names = [n for n, _ in arms] + (["reference pipeline"] if reference else [])
        print("    " + f"{'':34s}" + "".join(f"{n:>20s}" for n in names))
        for key, label in (("detection", "detection s (its own timer)"), ("calibration", "calibration s"),
                           ("wall", "process wall s"), ("cpu", "process CPU s")):
            print(f"    {label:34s}" + "".join(f"{_med(cal_runs[n], key):20.2f}" for n in names))
        me = cal_runs[arms[0][0]]
        for other in names[1:]:
            for key in ("wall", "cpu"):
                r = [a[key] / b[key] for a, b in zip(me, cal_runs[other])]
                print(f"    this code / {other}, {key}: median {statistics.median(r):.2f} "
                      f"(pairs {', '.join(f'{x:.2f}' for x in r)})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--session", type=Path, help="one session folder (default: both kinds, rendered once)")
    ap.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS), help="the kinds of session")
    ap.add_argument("--work", type=Path, default=Path("/tmp/procam_bench_detect"))
    ap.add_argument("--baseline-rev", help="older code (a git revision) to compare with, pair by pair")
    ap.add_argument("--reference", action="store_true", help="also run benchmarks/reference_pipeline.py")
    ap.add_argument("--pairs", type=int, default=3, help="rounds of A B [R] runs (default 3)")
    ap.add_argument("--workers", type=int, default=2, help="detection threads of procam calibrate (default 2)")
    ap.add_argument("--stages-of", type=Path, help=argparse.SUPPRESS)  # child mode: one stage table as JSON
    args = ap.parse_args()
    if args.stages_of is not None:
        print(json.dumps(measure_stages(args.stages_of, with_truth=False)))
        return 0
    folders = {"session": args.session} if args.session else {k: session_of(k, args.work) for k in args.kinds}
    for kind, folder in folders.items():
        print(f"== {kind}: {folder} (this code)")
        print_stage_table(measure_stages(folder))
    if args.baseline_rev or args.reference:
        if args.baseline_rev:
            with Baseline(args.baseline_rev) as tree:
                run_pairs(folders, tree, args.baseline_rev, args.reference, args.pairs, args.workers)
        else:
            run_pairs(folders, None, None, args.reference, args.pairs, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
