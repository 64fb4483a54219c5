"""`procam bench placements`: how many board placements a calibration needs, and what it loses.

For every scenario and seed, render two sessions of the same rig and the same mirror poses: today's
circle session (the scenario's 14 mirror captures and 13 positions x 4 poses) and a structured-light one
(`--structured-placements` placements, each one coded sequence). Detect each once, then calibrate (joint)
three ways:
  (a) `circles`: every capture of the circle session;
  (b) `circles, stopped`: the captures a station stopping on confidence would have taken;
  (c) `structured, stopped`: the same with the structured-light projector step.
Stopping is emulated on the rendered captures in the order the station takes them (the mirror step
first; the projector step one pose at every pattern position before the next pose): the mirror step
takes `--mirror-first` placements; the projector step ends as soon as its 1-sigmas meet their targets
(calib.quality.confidence) or at its maximum; then mirror placements are added until the mirror normal
meets its target or the mirror step's maximum. A placement is one board position, whatever number of
images is taken there.
"""

from __future__ import annotations

import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from app.commands import _types
from calib.models.vocab import CalibrationMethod, PatternKind, RenderQuality, Step, choices
from drivers.sim.hold import MirrorHold

#: the scenarios the issue's table names (docs/BENCHMARKS.md "Placements")
SCENARIOS = ("nonoverlap-136", "nonoverlap-90", "nonoverlap-180", "nonoverlap-136-realmirror",
             "wideangle-realmirror", "direct")
VARIANTS = ("circles", "circles, stopped", "structured, stopped")
#: (metric key, column title, format)
COLUMNS = (
    ("distance", "Dist mm", "{:.3f}"),
    ("angle_deg", "Ang deg", "{:.4f}"),
    ("proj_k_px", "ProjK px", "{:.2f}"),
    ("cam_k_px", "CamK px", "{:.2f}"),
    ("cam_dist_img_px", "CamDimg px", "{:.3f}"),
    ("proj_dist_img_px", "ProjDimg px", "{:.3f}"),
    ("mirror_angle_deg", "Mir deg", "{:.4f}"),
)


def add_parser(sub) -> None:
    p = sub.add_parser("placements", help="placements a calibration needs: full circle sessions vs stopping on "
                                          "confidence, circles and structured light")
    p.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), metavar="NAME",
                   help="scenarios (default: the six of docs/BENCHMARKS.md)")
    p.add_argument("--seeds", type=_types.int_range(1, 1000), default=10, metavar="N",
                   help="seeds 0..N-1 per scenario (default %(default)s)")
    p.add_argument("--quality", choices=choices(RenderQuality), default=RenderQuality.SESSION,
                   help="render quality (default %(default)s)")
    p.add_argument("--structured-placements", type=_types.int_range(2, 52), default=8, metavar="N",
                   help="structured-light placements rendered: the projector step's maximum (default %(default)s)")
    p.add_argument("--mirror-frames", type=_types.int_range(1, 64), default=1, metavar="N",
                   help="each mirror capture the mean of N frames of the board (default 1; still, or held: "
                        "--mirror-hold): what averaging a placement's frames would give the mirror step")
    p.add_argument("--mirror-hold", choices=choices(MirrorHold), default=MirrorHold.STILL,
                   help="with --mirror-frames: the board still (default), or held as the simulated operator holds "
                        "it (by hand for real-virtual, laid still on the mirror for real-mirror), an average the "
                        "station would refuse for motion taken again")
    p.add_argument("--mirror-first", type=_types.int_range(1, 14), default=5, metavar="N",
                   help="mirror placements before the projector step (default %(default)s)")
    p.add_argument("--fraction", type=_types.float_range(0.0, 10.0, lo_open=True), default=None, metavar="F",
                   help="targets as this share of the quality gate's references (default: "
                        "calib.quality.confidence.TARGET_FRACTION)")
    p.add_argument("--workers", type=_types.workers, default=2,
                   help="render processes and detection threads (default %(default)s)")


def _ordered_projector(store, obs) -> list:
    """The projector views in the order a station takes them: one pose at every pattern position, then
    the next pose (a structured session: capture order)."""
    caps = {c.id: c for c in store.manifest.captures}

    def key(i_view):
        i, v = i_view
        meta = getattr(caps.get(v.capture_id), "meta", None) or {}
        return (int(meta.get("sim_pose_index", 0)), i)

    return [v for _, v in sorted(enumerate(obs.projector_views), key=key)]


def _calibrate(obs, mirror, projector):
    from calib.errors import ProcamError
    from calib.pipeline import calibrate_observations

    sub = replace(obs, mirror_views=tuple(mirror), projector_views=tuple(projector))
    try:
        return calibrate_observations(sub, CalibrationMethod.JOINT), None
    except ProcamError as e:
        return None, str(e).split("\n")[0]


def stop_on_confidence(store, obs, mirror_first: int, fraction: float | None = None, min_projector: int = 3):
    """(result, mirror placements, projector placements, projector confidence lines) of the emulated
    station stopping each step when confident."""
    from calib.quality.confidence import confidence_of, unconfident

    frac = fraction
    mirror = list(obs.mirror_views)
    proj = _ordered_projector(store, obs)
    m = min(mirror_first, len(mirror)) if mirror else 0
    p = min(min_projector, len(proj))
    while True:  # the projector step: one more placement until its 1-sigmas meet their targets
        result, why = _calibrate(obs, mirror[:m], proj[:p])
        conf = confidence_of(result, Step.PROJECTOR, frac) if result else unconfident(Step.PROJECTOR, why, frac)
        if conf.all_met or p >= len(proj):
            break
        p += 1
    while mirror and m < len(mirror):  # mirror placements added until the mirror normal meets its target
        if result is not None and confidence_of(result, Step.REAL_VIRTUAL, frac).all_met:
            break
        m += 1
        result, why = _calibrate(obs, mirror[:m], proj[:p])
    return result, m, p, conf.lines()


def _row(scenario, seed, variant, result, gt, mirror_n, proj_n, error=None):
    from calib.quality.metrics import compare, distortion_error_over_image

    row = {"scenario": scenario, "seed": seed, "variant": variant, "placements": mirror_n + proj_n,
           "mirror": mirror_n, "projector": proj_n}
    if result is None:
        row["error"] = error or "no calibration"
        return row
    m = compare(result, gt).to_dict()
    m["cam_dist_img_px"] = distortion_error_over_image(result.camera, gt.camera)
    m["proj_dist_img_px"] = distortion_error_over_image(result.projector, gt.projector)
    row["metrics"] = m
    return row


def placement_runs(scenarios, seeds: int, quality: str, structured_placements: int, mirror_first: int,
                   fraction: float | None = None, workers: int = 2, log=print, mirror_frames: int = 1,
                   mirror_hold: str = MirrorHold.STILL) -> list[dict]:
    """Every (scenario, seed, variant) row: placements used and the errors against the ground truth."""
    from app.commands.simulate import simulate_session
    from calib.detection.detect import detect_session
    from drivers.sim.scenarios import get_scenario

    runs = []
    with tempfile.TemporaryDirectory(prefix="procam-placements-") as tmp:
        for name in scenarios:
            for seed in range(seeds):
                sc = get_scenario(name, seed)
                gt = sc.ground_truth()
                for pattern in (PatternKind.CIRCLES, PatternKind.STRUCTURED):
                    folder = Path(tmp) / f"{name}-{seed}-{pattern}"
                    t0 = time.perf_counter()
                    store = simulate_session(sc, folder, quality=quality, workers=workers, force=True, progress=False,
                                             structured_placements=structured_placements if pattern == PatternKind.STRUCTURED else None,
                                             mirror_frames=mirror_frames, mirror_hold=mirror_hold)
                    obs = detect_session(store, workers, cache="refresh")
                    t_sim = time.perf_counter() - t0
                    if pattern == PatternKind.CIRCLES:
                        result, why = _calibrate(obs, obs.mirror_views, obs.projector_views)
                        runs.append(_row(name, seed, VARIANTS[0], result, gt, len(obs.mirror_views),
                                         len(obs.projector_views), why))
                    result, m, p, lines = stop_on_confidence(store, obs, mirror_first, fraction)
                    variant = VARIANTS[1] if pattern == PatternKind.CIRCLES else VARIANTS[2]
                    runs.append(_row(name, seed, variant, result, gt, m, p))
                    runs[-1]["confidence"] = lines
                    refused = sum(int((c.meta or {}).get("sim_refused_averages", 0)) for c in store.manifest.captures)
                    log(f"  {name} seed {seed} {pattern}: rendered and detected in {t_sim:.0f} s; stopped at "
                        f"{m} + {p} placements" + (f"; {refused} mirror averages refused for motion and taken again"
                                                   if mirror_hold != MirrorHold.STILL else ""))
    return runs


def _fmt(x, fmt):
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def placements_table(runs) -> str:
    """Means over seeds per scenario and variant: placements (mirror + projector) and every metric."""
    head = ["scenario", "variant", "placements"] + [c[1] for c in COLUMNS]
    rows = []
    keys = list(dict.fromkeys((r["scenario"], r["variant"]) for r in runs))
    for scen, var in keys:
        sel = [r for r in runs if r["scenario"] == scen and r["variant"] == var]
        ok = [r for r in sel if "metrics" in r]
        mean = lambda xs: sum(xs) / len(xs) if xs else None  # noqa: E731
        pl = f"{mean([r['mirror'] for r in sel]):.1f} + {mean([r['projector'] for r in sel]):.1f}"
        row = [scen, var + ("" if len(ok) == len(sel) else f" ({len(sel) - len(ok)} failed)"), pl]
        for key, _, fmt in COLUMNS:
            row.append(_fmt(mean([r["metrics"][key] for r in ok if r["metrics"].get(key) is not None]), fmt))
        rows.append(row)
    widths = [max(len(str(r[i])) for r in rows + [head]) for i in range(len(head))]
    fmt_row = lambda r: "  ".join(str(v).ljust(w) if i < 2 else str(v).rjust(w)  # noqa: E731
                                  for i, (v, w) in enumerate(zip(r, widths)))
    return "\n".join([fmt_row(head), "  ".join("-" * w for w in widths)] + [fmt_row(r) for r in rows])


def run_placements(args) -> int:
    from drivers.sim.scenarios import get_scenario

    for s in args.scenarios:
        get_scenario(s)  # unknown names fail before any work
    print(f"procam bench placements: {len(args.scenarios)} scenario(s) x {args.seeds} seed(s), {args.quality} "
          "quality", file=sys.stderr)
    runs = placement_runs(args.scenarios, args.seeds, args.quality, args.structured_placements, args.mirror_first,
                          args.fraction, args.workers, log=lambda s: print(s, file=sys.stderr),
                          mirror_frames=args.mirror_frames, mirror_hold=args.mirror_hold)
    seeds = args.seeds
    print(placements_table(runs))
    print(f"(mean over {seeds} seed{'s' if seeds != 1 else ''}; placements mirror + projector; joint method)")
    return 0 if all("metrics" in r for r in runs) else 1
