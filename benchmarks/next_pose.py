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
"predicted" takes the position whose typical poses (3 drawn through the estimated rig) leave the least mean
predicted worst 1-sigma against its target (calib.joint.predict: every quantity of the step, not only the
grid), at its lowest pose index not taken (the operator's own pose there); "next-best" calibrates (joint) after each placement and takes the position next_position chooses on the
projector's grid, at that position's lowest pose index not taken, as the station does with --next-best
(app/station/targets.py); "oracle" calibrates with each candidate slot's own observations (the pose the
operator will hold there, which no station knows beforehand) and takes the one whose worst 1-sigma
against its target (calib.quality.confidence) is least: what choosing the pose itself could gain.
"asked" is what a station that asks for a whole pose could do (run_asked): candidate poses (3 per
position, tilted as a person would) drawn from the calibration so far, each one's exact observations
predicted through that estimate, the one whose calibration has the least worst 1-sigma against its
target taken and held by the operator exactly ("asked, sum": the least sum of the squared
1-sigma/target ratios, all the step's quantities at once; "asked, linear": the least worst, each candidate's
1-sigmas predicted by calib.joint.predict, linearised at the calibration so far, instead of calibrated,
as a live station could afford: calib.asked_pose, its candidates 15% about the boards' median
distance, seen in the part of the mirror boards were seen in so far; "asked, linear, true mirror": seen
in the whole mirror); "asked, order" takes the plan's next position with such
a pose (the pose distribution without the choice). Means over seeds of the errors against the ground
truth; in brackets, the seeds where the arm beats "order" (the asked arms: "asked, order" when that arm runs).
--follow DEG MM makes the operator hold an asked pose off by that much (1-sigma). The default arms leave out the "asked" ones
(a minute per seed): name them with --arms.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.errors import ProcamError  # noqa: E402
from calib.models.structured_light import placement_order  # noqa: E402
from calib.models.vocab import Step  # noqa: E402
from calib.pipeline import calibrate_observations  # noqa: E402
from calib.asked_pose import ask_pose, candidate_poses, mirror_seen  # noqa: E402
from calib.quality.confidence import confidence_of, targets  # noqa: E402
from calib.quality.metrics import compare  # noqa: E402
from calib.quality.next_pose import DeviceGrid, next_position, position_area  # noqa: E402
from calib.synthetic import SyntheticSession, held_pose, observe, projector_pose  # noqa: E402
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


def _slot_obs(sc, slots, noise, seed):
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    poses = [(p, by_slot[p][k]) for p, k in slots]
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, poses, sc.mirror_poses, sc.mirror_method,
                          sc.board_thickness_mm)
    return observe(ss, noise, seed, circle_centroids=True)


def _calibrate(sc, slots, noise, seed):
    return calibrate_observations(_slot_obs(sc, slots, noise, seed), "joint")


def _predicted_position(sc, slots, noise, seed, variants: int = 3):
    """The free position whose typical poses (candidates drawn through the estimated rig) leave the least
    mean predicted worst 1-sigma / target (calib.asked_pose's prediction, the pose left to the
    operator): (position, mean need)."""
    obs = _slot_obs(sc, slots, noise, seed)
    est = calibrate_observations(obs, "joint")
    best = None
    for pos in range(13):
        cands = candidate_poses(obs, est, sc.layout, sc.pattern, [pos], np.random.default_rng(seed * 1000 + pos),
                                variants, mirror_rect=mirror_seen(obs, est))
        needs = []
        for c in cands:
            a = ask_pose(obs, est, [c])
            if a is not None:
                needs.append(a.need)
        if needs and (best is None or np.mean(needs) < best[1]):
            best = (pos, float(np.mean(needs)))
    return best


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
        if arm == "predicted":
            pos = _predicted_position(sc, slots, noise, seed)[0]
            k = next((k for k in range(4) if (pos, k) not in slots), None)
            if k is None:
                raise RuntimeError(f"every pose of position {pos} taken")
            slots.append((pos, k))
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


def _held(sc, pos, T, follow, rng):
    """The pose the operator holds when asked for T (calib.synthetic.held_pose, `follow` = (deg, mm))."""
    return held_pose(sc.rig, sc.layout, sc.pattern, pos, T, follow[0], follow[1], rng)


def _asked_by_calibration(sc, arm, obs, est, poses, order, seed, variants):
    """The "asked", "asked, sum" and "asked, order" choices: each candidate calibrated with its exact
    predicted observations added (the first candidate of the plan's next position for "asked, order")."""
    rig = replace(sc.rig, camera=est.camera, projector=est.projector, T_cam_proj=np.asarray(est.T_cam_proj),
                  mirror=est.mirror if sc.rig.mirror is not None else None)
    if arm == "asked, order":
        taken = {p for p, _ in poses}
        pos = next(p for p, _ in order if p not in taken)
        return pos, projector_pose(rig, sc.layout, sc.pattern, pos, np.random.default_rng(seed * 1000 + pos))
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
        extra = _observe(sc, rig, [cand], False, 0.0, seed).projector_views
        merged = replace(obs, projector_views=obs.projector_views + extra)
        try:
            conf = confidence_of(calibrate_observations(merged, "joint"), Step.PROJECTOR)
        except ProcamError:
            continue
        ratios = [q.sigma / q.target for q in conf.quantities]
        need = float(np.sum(np.square(ratios))) if arm == "asked, sum" else max(ratios)
        if best_need is None or need < best_need:
            best, best_need = cand, need
    return best


def run_asked(sc, arm: str, n: int, first: int, noise: float, seed: int, variants: int = 3,
              follow: tuple[float, float] = (0.0, 0.0)):
    """The station asks for a pose (position and tilt), the operator holds it: candidate poses drawn
    from the calibration so far (the rig as estimated; the mirror's extent the true one), each one's
    exact observations predicted through that estimate added to the real ones, the candidate whose
    calibration has the least worst 1-sigma against its target taken ("asked"), or the plan's next
    position with the first candidate pose ("asked, order"). The pose taken is observed through the
    true rig with noise. Returns (metrics, poses, seconds per choice)."""
    order = placement_order(13, 4)
    spent = []
    by_slot = {}
    for p, T in sc.projector_poses:
        by_slot.setdefault(p, []).append(T)
    poses = [(p, by_slot[p][k]) for p, k in order[:first]]
    for step in range(n - first):
        obs = _observe(sc, sc.rig, poses, True, noise, seed)
        est = calibrate_observations(obs, "joint")
        t0 = time.perf_counter()
        if arm.startswith("asked, linear"):  # what a station would run: calib.asked_pose
            rect = sc.rig.mirror_rect if arm.endswith("true mirror") else mirror_seen(obs, est)
            pool = []
            for pos in range(13):
                pool += candidate_poses(obs, est, sc.layout, sc.pattern, [pos], np.random.default_rng(seed * 1000 + pos),
                                        variants, mirror_rect=rect)
            asked = ask_pose(obs, est, pool)
            best = (asked.position, asked.candidate.T_cam_board)
        else:
            best = _asked_by_calibration(sc, arm, obs, est, poses, order, seed, variants)
        spent.append(time.perf_counter() - t0)
        poses.append((best[0], _held(sc, best[0], best[1], follow, np.random.default_rng(seed * 7919 + step))))
    return compare(calibrate_observations(_observe(sc, sc.rig, poses, True, noise, seed), "joint"),
                   sc.ground_truth()), poses, float(np.mean(spent)) if spent else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["nonoverlap-136", "nonoverlap-90", "direct"])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--placements", type=int, default=6)
    ap.add_argument("--first", type=int, default=4)
    ap.add_argument("--arms", nargs="+", default=["order", "next-best", "oracle"])
    ap.add_argument("--noise", type=float, default=0.05)
    ap.add_argument("--follow", type=float, nargs=2, default=[0.0, 0.0], metavar=("DEG", "MM"),
                    help="the asked arms' operator holds the asked pose off by this 1-sigma rotation and shift")
    ap.add_argument("--density", type=int, default=2, help="pattern points per circle-grid spacing (default 2)")
    args = ap.parse_args()
    print(f"{args.placements} projector placements ({args.first} in the plan's order first), pattern density "
          f"{args.density}, noise {args.noise} px, asked poses held to {args.follow[0]} deg / {args.follow[1]} mm, "
          f"{args.seeds} seeds; means (in brackets: the seeds where the arm beats order)")
    print("| scenario | arm | " + " | ".join(label for _, label in METRICS) + " | s per choice |")
    print("|---|---|" + "---|" * (len(METRICS) + 1))
    for name in args.scenarios:
        rows = {}
        for arm in args.arms:
            vals = []
            for seed in range(args.seeds):
                sc = dense(get_scenario(name, seed), args.density)
                try:
                    spent = None
                    if arm.startswith("asked"):
                        m, _, spent = run_asked(sc, arm, args.placements, args.first, args.noise, seed,
                                                follow=tuple(args.follow))
                    else:
                        m, _ = run_arm(sc, arm, args.placements, args.first, args.noise, seed)
                except (ProcamError, RuntimeError) as e:
                    print(f"  {name} seed {seed} {arm}: failed ({str(e).splitlines()[0]})", file=sys.stderr)
                    vals.append(None)
                    continue
                vals.append({k: getattr(m, k) for k, _ in METRICS} | {"choice_s": spent})
            rows[arm] = vals
        for arm, vals in rows.items():
            cells = []
            for k, _ in METRICS:
                xs = [v[k] for v in vals if v is not None and v[k] is not None]
                if not xs:
                    cells.append("-")
                    continue
                cell = f"{np.mean(xs):.3f}"
                base = "asked, order" if arm.startswith("asked") and arm != "asked, order" and "asked, order" in rows else "order"
                if arm != base and base in rows:
                    wins = sum(1 for a, b in zip(vals, rows[base]) if a and b and a[k] is not None and a[k] < b[k])
                    cell += f" ({wins})"
                cells.append(cell)
            spent = [v["choice_s"] for v in vals if v is not None and v["choice_s"] is not None]
            cells.append(f"{np.mean(spent):.1f}" if spent else "-")
            print(f"| {name} | {arm} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
