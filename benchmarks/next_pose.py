"""The next-best placement against the plan's order: a structured-sized projector step (a few
placements) whose last placements go where calib.quality.next_pose says, or in placement_order's order.

    python benchmarks/next_pose.py [--scenarios nonoverlap-136 nonoverlap-90 direct] [--seeds 10]
                                   [--placements 6] [--first 4] [--noise 0.05] [--density 2]
                                   [--arms order next-best oracle "asked, order" asked]

Exact-geometry synthetic observations (calib.synthetic.observe, circle centroids, Gaussian noise) of each
scenario: its mirror views, and projector placements drawn from its 13 x 4 projector poses (slot =
pattern position, pose index), each with a circle grid `--density` times as dense as the scenario's over
the same extent (a stand-in for a structured placement's points all over the board). Every arm takes
placement_order's first `--first` slots; then "order" takes the next slots of placement_order;
"next-best" calibrates (joint) after each placement and takes the position next_position chooses on the
projector's grid, at that position's lowest pose index not taken, as the station does with --next-best
(app/station/targets.py); "oracle" calibrates with each candidate slot's own observations (the pose the
operator will hold there, which no station knows beforehand) and takes the one whose worst 1-sigma
against its target (calib.quality.confidence) is least: what choosing the pose itself could gain.
"asked" is what a station that asks for a whole pose could do (run_asked): candidate poses (3 per
position, tilted as a person would) drawn from the calibration so far, each one's exact observations
predicted through that estimate, the one whose calibration has the least worst 1-sigma against its
target taken and held by the operator exactly; "asked, order" takes the plan's next position with such
a pose (the pose distribution without the choice). Means over seeds of the errors against the ground
truth; in brackets, the seeds where the arm beats "order". The default arms leave out the "asked" ones
(a minute per seed): name them with --arms.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.errors import ProcamError  # noqa: E402
from calib.models.structured_light import placement_order  # noqa: E402
from calib.models.vocab import Step  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.quality.confidence import confidence_of, targets  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.quality.next_pose import DeviceGrid, next_position, position_area  # noqa: E402
from calib.synthetic import SyntheticSession, observe, projector_pose  # noqa: E402
from drivers.sim.scenarios import get_scenario  # noqa: E402

METRICS = (("distance", "distance mm"), ("angle_deg", "angle deg"), ("proj_k_px", "ProjK px"),
           ("cam_k_px", "CamK px"), ("mirror_angle_deg", "mirror deg"))


def dense(sc, density: int):
    """The scenario with a pattern `density` times as dense over the same extent (a structured placement
    decodes points all over the board, not one circle grid)."""
    if density <= 1:
        return sc
    p = sc.pattern
    pattern = replace(p, cols=p.cols * density, rows=(p.rows - 1) * density + 1, spacing_px=p.spacing_px / density,
                      radius_px=p.radius_px / density)
    return replace(sc, pattern=pattern)


def _calibrate(sc, slots, noise, seed):
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    poses = [(p, by_slot[p][k]) for p, k in slots]
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, poses, sc.mirror_poses, sc.mirror_method,
                          sc.board_thickness_mm)
    return calibrate_observations(observe(ss, noise, seed, circle_centroids=True), "joint")


def _grids(sc, result):
    W, H = sc.rig.projector.width, sc.rig.projector.height
    return [DeviceGrid("projector", result.projection_uncertainty["projector"],
                       {p: position_area(sc.pattern, W, H, p) for p in range(sc.pattern.positions)},
                       targets(Step.PROJECTOR)["projection_projector_max_px"])]


def run_arm(sc, arm: str, n: int, first: int, noise: float, seed: int):
    order = placement_order(13, 4)
    slots = list(order[:first])
    while len(slots) < n:
        if arm == "order":
            slots.append(next(s for s in order if s not in slots))
            continue
        if arm == "oracle":  # each candidate calibrated with the rest: the least worst 1-sigma / target
            free = {}
            for p, k in order:
                if (p, k) not in slots:
                    free.setdefault(p, (p, k))
            best_slot, best_need = None, None
            for cand in free.values():
                try:
                    conf = confidence_of(_calibrate(sc, slots + [cand], noise, seed), Step.PROJECTOR)
                except ProcamError:
                    continue
                need = max(q.sigma / q.target for q in conf.quantities)
                if best_need is None or need < best_need:
                    best_slot, best_need = cand, need
            slots.append(best_slot)
            continue
        result = _calibrate(sc, slots, noise, seed)
        taken = Counter(p for p, _ in slots)
        best = next_position(_grids(sc, result), range(13), taken)
        k = next(k for k in range(4) if (best.position, k) not in slots)
        slots.append((best.position, k))
    return compare(_calibrate(sc, slots, noise, seed), sc.ground_truth()), slots


def _observe(sc, rig, poses, mirror: bool, noise, seed):
    ss = SyntheticSession(rig, sc.layout, sc.mirror_board, sc.pattern, poses, sc.mirror_poses if mirror else [],
                          sc.mirror_method, sc.board_thickness_mm)
    return observe(ss, noise, seed, circle_centroids=True)


def run_asked(sc, arm: str, n: int, first: int, noise: float, seed: int, variants: int = 3):
    """The station asks for a pose (position and tilt), the operator holds it: candidate poses drawn
    from the calibration so far (the rig as estimated; the mirror's extent the true one), each one's
    exact observations predicted through that estimate added to the real ones, the candidate whose
    calibration has the least worst 1-sigma against its target taken ("asked"), or the plan's next
    position with the first candidate pose ("asked, order"). The pose taken is observed through the
    true rig with noise."""
    order = placement_order(13, 4)
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    poses = [(p, by_slot[p][k]) for p, k in order[:first]]
    for step in range(n - first):
        obs = _observe(sc, sc.rig, poses, True, noise, seed)
        est = calibrate_observations(obs, "joint")
        rig = replace(sc.rig, camera=est.camera, projector=est.projector, T_cam_proj=np.asarray(est.T_cam_proj),
                      mirror=est.mirror if sc.rig.mirror is not None else None)
        taken = {p for p, _ in poses}
        if arm == "asked, order":
            pos = next(p for p, _ in order if p not in taken)
            cands = [(pos, projector_pose(rig, sc.layout, sc.pattern, pos, np.random.default_rng(seed * 1000 + pos)))]
        else:
            cands = []
            for pos in range(13):
                rng = np.random.default_rng(seed * 1000 + pos)
                for _k in range(variants):
                    try:
                        cands.append((pos, projector_pose(rig, sc.layout, sc.pattern, pos, rng)))
                    except RuntimeError:
                        break
        best, best_need = None, None
        for cand in cands:
            if len(cands) == 1:
                best = cand
                break
            extra = _observe(sc, rig, [cand], False, 0.0, seed).projector_views
            merged = replace(obs, projector_views=obs.projector_views + extra)
            try:
                conf = confidence_of(calibrate_observations(merged, "joint"), Step.PROJECTOR)
            except ProcamError:
                continue
            need = max(q.sigma / q.target for q in conf.quantities)
            if best_need is None or need < best_need:
                best, best_need = cand, need
        poses.append(best)
    return compare(calibrate_observations(_observe(sc, sc.rig, poses, True, noise, seed), "joint"),
                   sc.ground_truth()), poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["nonoverlap-136", "nonoverlap-90", "direct"])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--placements", type=int, default=6)
    ap.add_argument("--first", type=int, default=4)
    ap.add_argument("--arms", nargs="+", default=["order", "next-best", "oracle"])
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--density", type=int, default=2, help="pattern points per circle-grid spacing (default 2)")
    args = ap.parse_args()
    print(f"{args.placements} projector placements ({args.first} in the plan's order first), pattern density "
          f"{args.density}, noise {args.noise} px, "
          f"{args.seeds} seeds; means (in brackets: the seeds where the arm beats order)")
    print("| scenario | arm | " + " | ".join(label for _, label in METRICS) + " |")
    print("|---|---|" + "---|" * len(METRICS))
    for name in args.scenarios:
        rows = {}
        for arm in args.arms:
            vals = []
            for seed in range(args.seeds):
                sc = dense(get_scenario(name, seed), args.density)
                try:
                    run = run_asked if arm.startswith("asked") else run_arm
                    m, _ = run(sc, arm, args.placements, args.first, args.noise, seed)
                except (ProcamError, RuntimeError) as e:
                    print(f"  {name} seed {seed} {arm}: failed ({str(e).splitlines()[0]})", file=sys.stderr)
                    vals.append(None)
                    continue
                vals.append({k: getattr(m, k) for k, _ in METRICS})
            rows[arm] = vals
        for arm, vals in rows.items():
            cells = []
            for k, _ in METRICS:
                xs = [v[k] for v in vals if v is not None and v[k] is not None]
                if not xs:
                    cells.append("-")
                    continue
                cell = f"{np.mean(xs):.3f}"
                if arm != "order":
                    wins = sum(1 for a, b in zip(vals, rows["order"]) if a and b and a[k] is not None and a[k] < b[k])
                    cell += f" ({wins})"
                cells.append(cell)
            print(f"| {name} | {arm} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
