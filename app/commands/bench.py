"""`procam bench accuracy | placements | render`: accuracy against the simulator's ground truth, the placements a
calibration needs (app/commands/_bench_placements.py), and render speed.

accuracy: for every scenario and seed, simulate a session (drivers.sim) into a temporary folder, detect
once, calibrate with every method registered in calib.pipeline.METHODS (or --methods), compare with the
ground truth (calib.quality.metrics.compare) and print the paper's metrics beside its headline numbers, with the
time each stage took.
render: frames per second of the simulated camera per render mode (see benchmarks/render_speed.py).
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

from app.commands import _types
from calib.models.vocab import CalibrationMethod, RenderQuality, choices

NAME = "bench"
HELP = "benchmarks on the simulated rig: calibration accuracy vs ground truth, render speed"
DESCRIPTION = (
    "`procam bench accuracy` simulates sessions of the named scenarios, calibrates them with each method "
    "and prints the paper's metrics (errors against the ground truth) beside the paper's headline "
    "numbers, plus per-stage timings. `procam bench render` prints the simulated camera's frames/s."
)

#: metrics printed, in order: (key of PaperMetrics, column title, format, key in PAPER_HEADLINE or None)
COLUMNS = [
    ("distance", "Dist mm", "{:.2f}", "distance"),
    ("angle_deg", "Ang deg", "{:.3f}", "angle_deg"),
    ("proj_k_px", "ProjK px", "{:.2f}", "proj_k_px"),
    ("proj_d", "ProjD", "{:.4f}", "proj_d"),
    ("cam_k_px", "CamK px", "{:.2f}", None),
    ("cam_d", "CamD", "{:.4f}", None),
    ("cam_dist_img_px", "CamDimg px", "{:.3f}", None),  # distortion error over the image (issue 18)
    ("proj_dist_img_px", "ProjDimg px", "{:.3f}", None),
    ("mirror_offset", "Mir mm", "{:.2f}", "mirror_offset"),
    ("mirror_angle_deg", "Mir deg", "{:.3f}", "mirror_angle_deg"),
    ("proj_rms_px", "ProjRMS", "{:.3f}", None),
]


def add_arguments(p) -> None:
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    a = sub.add_parser("accuracy", help="calibration accuracy on simulated sessions vs ground truth")
    a.add_argument("--scenarios", nargs="+", default=None, metavar="NAME",
                   help="scenarios (default: all; `procam simulate --list`)")
    a.add_argument("--seeds", type=_types.int_range(1, 1000), default=1, metavar="N",
                   help="seeds 0..N-1 per scenario (default %(default)s)")
    a.add_argument("--methods", default=None,
                   help="comma-separated calibration methods (default: every registered method; also "
                        "joint-bic, the joint method without the coverage criterion)")
    a.add_argument("--quality", choices=choices(RenderQuality), default=RenderQuality.SESSION,
                   help="render quality (default %(default)s)")
    a.add_argument("--noise", type=_types.noise_dn, default=None, metavar="SIGMA", help="read noise override (levels)")
    a.add_argument("--blur", type=_types.blur_px, default=None, metavar="SIGMA", help="optical blur override (px)")
    a.add_argument("--keep", metavar="DIR", default=None, help="keep the simulated sessions under DIR")
    a.add_argument("--json", metavar="FILE", default=None, help="also write every run's numbers to FILE")
    a.add_argument("--workers", type=_types.workers, default=2,
                   help="render processes and detection threads (default %(default)s)")
    from app.commands._bench_placements import add_parser as add_placements

    add_placements(sub)
    r = sub.add_parser("render", help="frames per second of the simulated camera per render mode")
    r.add_argument("--scenario", default="nonoverlap-136", help="scenario (default %(default)s)")
    r.add_argument("--frames", type=_types.int_range(1, 100000), default=20,
                   help="frames per mode (default %(default)s)")


# ---- accuracy ---------------------------------------------------------------------------------------------
#: method variants only the benchmark knows: name -> (registered method, its options). "joint-bic" is the
#: joint method with the distortion model chosen by BIC alone (no coverage criterion, issue 18's "before"),
#: measured on the very same rendered sessions as "joint".
VARIANTS: dict[str, tuple[str, dict]] = {"joint-bic": (CalibrationMethod.JOINT, {"coverage": False})}


def accuracy_runs(scenarios, seeds: int, methods, quality: str = RenderQuality.SESSION, keep=None, noise=None, blur=None,
                  workers: int = 2, log=print):
    """Simulate, detect and calibrate; returns a list of dicts (scenario, seed, method, metrics, timings)."""
    from dataclasses import replace

    from app.commands.simulate import simulate_session
    from calib.detection.detect import detect_session
    from calib.errors import ProcamError
    from calib.formats.session import SessionStore
    from calib.pipeline import calibrate_observations
    from calib.quality.metrics import compare, distortion_error_over_image
    from drivers.sim.scenarios import get_scenario

    runs = []
    tmp = None
    if keep is None:
        tmp = tempfile.TemporaryDirectory(prefix="procam-bench-")
        root = Path(tmp.name)
    else:
        root = Path(keep)
        root.mkdir(parents=True, exist_ok=True)
    try:
        for name in scenarios:
            for seed in range(seeds):
                sc = get_scenario(name, seed)
                overrides = {}
                if noise is not None:
                    overrides["read_noise_dn"] = noise
                if blur is not None:
                    overrides["blur_sigma_px"] = blur
                if overrides:
                    sc = replace(sc, render=replace(sc.render, **overrides))
                folder = root / f"{name}-seed{seed}"
                t0 = time.perf_counter()
                simulate_session(sc, folder, quality=quality, workers=workers, force=True, progress=False)
                t_sim = time.perf_counter() - t0
                t0 = time.perf_counter()
                obs = detect_session(SessionStore.open(folder), workers, cache="refresh")  # always timed
                t_det = time.perf_counter() - t0
                gt = sc.ground_truth()
                for method in methods:
                    row = {"scenario": name, "seed": seed, "method": method, "simulate_s": round(t_sim, 2),
                           "detection_s": round(t_det, 2), "skipped": len(obs.skipped),
                           "views": len(obs.projector_views), "mirror_views": len(obs.mirror_views)}
                    try:
                        base, options = VARIANTS.get(method, (method, None))
                        res = calibrate_observations(obs, base, method_options=options)
                    except ProcamError as e:
                        row["error"] = str(e)
                        log(f"  {name} seed {seed} {method}: FAILED: {e}")
                        runs.append(row)
                        continue
                    row["metrics"] = compare(res, gt).to_dict()
                    # mean distance over the image between where the estimated and the true distortion put
                    # the same ray, both with the true K (calib.quality.metrics.distortion_error_over_image)
                    row["metrics"]["cam_dist_img_px"] = distortion_error_over_image(res.camera, gt.camera)
                    row["metrics"]["proj_dist_img_px"] = distortion_error_over_image(res.projector, gt.projector)
                    row["timing_s"] = {k: v for k, v in (res.diagnostics or {}).get("timing_s", {}).items()
                                       if isinstance(v, (int, float))}
                    runs.append(row)
                    m = row["metrics"]
                    log(f"  {name} seed {seed} {method}: distance {m['distance']:.2f} mm, angle {m['angle_deg']:.3f} deg, "
                        f"ProjK {m['proj_k_px']:.2f} px ({row['views']} views, {row['skipped']} skipped)")
    finally:
        if tmp is not None:
            tmp.cleanup()
    return runs


def _fmt(x, fmt):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return fmt.format(x)


def accuracy_table(runs, seeds: int) -> str:
    """Mean over seeds of each metric, per scenario and method, with the paper's headline row."""
    from calib.quality.metrics import PAPER_HEADLINE

    head = ["scenario", "method"] + [c[1] for c in COLUMNS] + ["skipped", "time s"]
    rows = [["paper (synthetic)", CalibrationMethod.PAPER] + [_fmt(PAPER_HEADLINE.get(k), f) if k else "-" for _, _, f, k in COLUMNS]
            + ["", ""]]
    keys = []
    for r in runs:
        if (r["scenario"], r["method"]) not in keys:
            keys.append((r["scenario"], r["method"]))
    for scen, meth in keys:
        sel = [r for r in runs if r["scenario"] == scen and r["method"] == meth]
        ok = [r for r in sel if "metrics" in r]
        row = [scen, meth]
        for key, _, fmt, _ in COLUMNS:
            vals = [r["metrics"][key] for r in ok if r["metrics"].get(key) is not None]
            row.append(_fmt(sum(vals) / len(vals), fmt) if vals else "-")
        skipped = sum(r["skipped"] for r in sel) / max(len(sel), 1)
        total = [r["timing_s"].get("total", 0.0) for r in ok]
        row.append(f"{skipped:.1f}" + ("" if len(ok) == len(sel) else f" ({len(sel) - len(ok)} failed)"))
        row.append(f"{sum(total) / len(total):.1f}" if total else "-")
        rows.append(row)
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    lines = ["  ".join(h.ljust(w) if i < 2 else h.rjust(w) for i, (h, w) in enumerate(zip(head, widths)))]
    lines.append("  ".join("-" * w for w in widths))
    for r in rows:
        lines.append("  ".join(str(v).ljust(w) if i < 2 else str(v).rjust(w) for i, (v, w) in enumerate(zip(r, widths))))
    note = f"(mean over {seeds} seed{'s' if seeds != 1 else ''}; lengths in mm; paper = its headline numbers, docs/GEOMETRY.md)"
    return "\n".join(lines) + "\n" + note


def timing_table(runs) -> str:
    """Mean time (seconds) of simulation, detection and each calibration stage, per scenario and method."""
    keys = []
    for r in runs:
        if (r["scenario"], r["method"]) not in keys:
            keys.append((r["scenario"], r["method"]))
    head = ["scenario", "method", "simulate", "detection", "calibrate", "stages (calibrate)"]
    rows = []
    for scen, meth in keys:
        sel = [r for r in runs if r["scenario"] == scen and r["method"] == meth and "timing_s" in r]
        if not sel:
            continue

        def mean(vals):
            vals = [v for v in vals if v is not None]
            return sum(vals) / len(vals) if vals else None

        stages = []
        for r in sel:
            for k in r["timing_s"]:
                if k not in stages and k not in ("total", "detection") and not k.endswith(".total"):
                    stages.append(k)
        parts = []
        for k in stages:
            v = mean([r["timing_s"].get(k) for r in sel])
            if v is not None:
                parts.append(f"{k} {v:.2f}")
        total = mean([r["timing_s"].get("total") for r in sel])
        rows.append([scen, meth, f"{mean([r['simulate_s'] for r in sel]):.1f}", f"{mean([r['detection_s'] for r in sel]):.1f}",
                     "-" if total is None else f"{total:.1f}", ", ".join(parts)])
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    right = (2, 3, 4)
    fmt = lambda r: "  ".join(str(v).rjust(w) if i in right else str(v).ljust(w)  # noqa: E731
                              for i, (v, w) in enumerate(zip(r, widths))).rstrip()
    lines = [fmt(head), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows]
    return "\n".join(lines) + "\n(seconds per session; stage times as the methods report them in diagnostics.timing_s)"


def run_accuracy(args) -> int:
    import json

    from calib.errors import SpecError
    from calib.pipeline import METHODS
    from drivers.sim.scenarios import get_scenario, scenario_names

    scenarios = args.scenarios or scenario_names()
    for s in scenarios:
        get_scenario(s)  # unknown names fail before any work
    methods = [m.strip() for m in args.methods.split(",")] if args.methods else list(METHODS)
    unknown = [m for m in methods if m not in METHODS and m not in VARIANTS]
    if unknown:
        raise SpecError(f"unknown method(s) {', '.join(unknown)} (registered: {', '.join(METHODS)}; "
                        f"benchmark variants: {', '.join(VARIANTS)})")
    if args.seeds < 1:
        raise SpecError("--seeds must be >= 1")
    if args.workers < 1:
        raise SpecError("--workers must be >= 1")
    from app.commands._outputs import check_output_file, check_output_folder

    if args.json:
        check_output_file(args.json, "--json")
    if args.keep:
        check_output_folder(args.keep, "--keep")
    print(f"procam bench accuracy: {len(scenarios)} scenario(s) x {args.seeds} seed(s), methods {', '.join(methods)}",
          file=sys.stderr)
    runs = accuracy_runs(scenarios, args.seeds, methods, args.quality, args.keep, args.noise, args.blur,
                         args.workers, log=lambda s: print(s, file=sys.stderr))
    print(accuracy_table(runs, args.seeds))
    print()
    print(timing_table(runs))
    if args.json:
        from calib.formats.fileio import atomic_write_text

        from app.commands._outputs import write_error

        try:
            atomic_write_text(args.json, json.dumps(runs, indent=1) + "\n")
        except OSError as e:
            raise write_error(args.json, e) from None
    return 0 if all("metrics" in r for r in runs) else 1


# ---- render speed -----------------------------------------------------------------------------------------
MODES = {
    "live": (RenderQuality.LIVE, {}),
    "live, noise+blur off": (RenderQuality.LIVE, {"read_noise_dn": 0.0, "electrons_per_dn": 0.0, "blur_sigma_px": 0.0}),
    "session (3x3 AA)": (RenderQuality.SESSION, {}),
}


def render_speed(scenario: str = "nonoverlap-136", frames: int = 20, modes=None) -> list[tuple[str, float, float]]:
    """[(mode, frames/s, warm-up s)] of SimCamera.get_frame with the board in view and a pattern shown."""
    from drivers.sim.rig import open_sim_rig

    out = []
    for mode in modes or MODES:
        quality, settings = MODES[mode]
        rig = open_sim_rig(scenario, quality=quality, ideal=True, **settings)  # rendering only: no 30 fps clock
        t0 = time.perf_counter()
        rig.camera.start()
        warm = time.perf_counter() - t0
        sc = rig.scenario
        W, H = rig.projector.size
        n = max(1, frames if quality == RenderQuality.LIVE else max(3, frames // 5))
        t0 = time.perf_counter()
        for i in range(n):
            pos = i % sc.pattern.positions
            if i % 5 == 0:
                rig.operator.request_pose("projector", pos, 0)
                rig.projector.show(sc.pattern.render(W, H, pos)[0])
            rig.camera.get_frame()
        dt = time.perf_counter() - t0
        out.append((mode, n / dt, warm))
    return out


def run_render(args) -> int:
    from drivers.sim.scenarios import get_scenario

    from calib.errors import SpecError

    if args.frames < 1:
        raise SpecError("--frames must be >= 1")
    sc = get_scenario(args.scenario)
    W, H = sc.rig.camera.size
    print(f"simulated camera {W}x{H}, scenario {args.scenario}, board in view, pattern shown")
    for mode, fps, warm in render_speed(args.scenario, args.frames):
        print(f"{mode:<24} {fps:6.1f} frames/s   (first start {warm:.1f} s)")
    return 0


def run(args) -> int:
    if args.bench == "render":
        return run_render(args)
    if args.bench == "placements":
        from app.commands._bench_placements import run_placements

        return run_placements(args)
    return run_accuracy(args)
