"""The capture a projector step asks for next (SessionMachine.target).

The circle (or chessboard) step: the circle grid's poses at every pattern position, in the plan's order
or, stopping on confidence, one pose at every position before the next. The structured-light step: its
placements (calib.models.structured_light.placement_order's slots) up to the plan's count, or fewer
when confident. With Plan.next_best (stopping on confidence), once a calibration of the captures so far
gave the projector's projection-uncertainty grid, the position asked for next is the one a board would
help most (calib.quality.next_pose; within the circle step's round of positions); before that, and
without it, the plan's order. With Plan.ask_pose, the position of the whole pose asked for
(app/station/asked.py), when one was computed after the captures there are now; else the plan's order.
"""

from __future__ import annotations

from collections import Counter

from app.station.plan import Target
from app.station.structured_step import slot_of
from calib.models.observations import STEP_PROJECTOR
from calib.models.structured_light import placement_order
from calib.models.vocab import Step
from calib.quality.confidence import targets
from calib.quality.next_pose import DeviceGrid, NextPlacement, next_position, position_area


def free_pose(caps, n: int) -> int | None:
    """The lowest pose index below `n` none of `caps` took."""
    used = {c.meta.get("pose_index") for c in caps}
    return next((k for k in range(n) if k not in used), None)


def uncertainty_grids(machine) -> list[DeviceGrid]:
    """The projector's grid of the latest calibration (Plan.next_best), with the board's area at each
    pattern position and the projector's target; [] when none is known."""
    pu = machine.projection_uncertainty
    if not machine.plan.next_best or not isinstance(pu, dict) or not isinstance(pu.get("projector"), dict):
        return []
    man = machine.manifest
    W, H = man.rig.projector_size
    areas = {p: position_area(man.pattern, W, H, p) for p in range(machine.positions)}
    return [DeviceGrid("projector", pu["projector"], areas, targets(Step.PROJECTOR)["projection_projector_max_px"])]


def _best(machine, candidates: list[int], taken) -> NextPlacement | None:
    """The next-best position among `candidates`, when the plan asks for it and a grid is known."""
    grids = uncertainty_grids(machine)
    return next_position(grids, candidates, taken) if grids and candidates else None


def _asked_position(machine, candidates: list[int]) -> int | None:
    """The asked pose's position (Plan.ask_pose), when one applies to the captures there are now and
    stands among `candidates`."""
    a = getattr(machine, "asked", None)
    if not machine.plan.ask_pose or a is None or a.for_captures != len(machine.captures_of(STEP_PROJECTOR)):
        return None
    return a.position if a.position in candidates else None


def candidate_positions(machine) -> list[int]:
    """The pattern positions a projector step stopping on confidence may ask for next (the circle step's
    current round; the structured step's free positions, in the plan's order); [] when the step is
    complete or does not stop on confidence (its order is fixed)."""
    plan = machine.plan
    caps = machine.captures_of(STEP_PROJECTOR)
    if not plan.stop_on_confidence:
        return []
    if machine.structured:
        if len(caps) >= plan.structured_placements:
            return []
        return list(_structured_free(machine, caps))
    return _circle_round(machine, machine.position_counts())


def _circle_round(machine, counts) -> list[int]:
    """The circle step's current round, stopping on confidence: the positions with the fewest poses,
    one pose at every position before the next ([] when every position has its poses)."""
    for k in range(machine.plan.poses_per_position):
        round_ = [p for p in range(machine.positions) if counts[p] <= k]
        if round_:
            return round_
    return []


def _structured_free(machine, caps) -> dict[int, int]:
    """{position: its lowest free pose index}, positions in placement_order's order."""
    taken = {slot_of(c) for c in caps}
    first: dict[int, int] = {}
    for pos, k in placement_order(machine.positions, max(machine.plan.poses_per_position, 1) + len(caps)):
        if (pos, k) not in taken:
            first.setdefault(pos, k)
    return first


def _confident(machine, n: int, minimum: int) -> bool:
    conf = machine.projector_confidence
    return bool(machine.plan.stop_on_confidence and conf is not None and conf.all_met and n >= minimum)


def circle_choice(machine) -> tuple[Target | None, NextPlacement | None]:
    """The next pose of a circle (or chessboard) projector step (None when it is complete), and the
    next-best choice that placed it (None: the plan's order did)."""
    plan = machine.plan
    caps = machine.captures_of(STEP_PROJECTOR)
    counts = machine.position_counts()

    def at(p: int) -> Target:
        mine = [c for c in caps if c.pattern_position == p]
        return Target(STEP_PROJECTOR, p, free_pose(mine, plan.poses_per_position + len(mine)))

    if not plan.stop_on_confidence:
        return next((at(p) for p in range(machine.positions) if counts[p] < plan.poses_per_position), None), None
    if _confident(machine, len(caps), plan.min_projector_captures):
        return None, None  # confident (at least the plan's minimum): the counts were maximums
    round_ = _circle_round(machine, counts)
    if not round_:
        return None, None
    asked = _asked_position(machine, round_)
    if asked is not None:
        return at(asked), None
    best = _best(machine, round_, dict(enumerate(counts)))
    return at(round_[0] if best is None else best.position), best


def structured_choice(machine) -> tuple[Target | None, NextPlacement | None]:
    """The next placement of a structured projector step, or None when it is complete: the plan's
    `structured_placements` taken, or (stop_on_confidence) at least `min_structured_placements` and the
    step confident; and the next-best choice that placed it (None: placement_order's order did)."""
    plan = machine.plan
    caps = machine.captures_of(STEP_PROJECTOR)
    if len(caps) >= plan.structured_placements:
        return None, None
    if _confident(machine, len(caps), plan.min_structured_placements):
        return None, None
    first = _structured_free(machine, caps)  # each position's lowest free pose index, in the plan's order
    if not first:
        return None, None
    asked = _asked_position(machine, list(first))
    if asked is not None:
        return Target(STEP_PROJECTOR, asked, first[asked]), None
    best = _best(machine, list(first), Counter(p for p, _ in {slot_of(c) for c in caps}))
    pos = next(iter(first)) if best is None else best.position
    return Target(STEP_PROJECTOR, pos, first[pos]), best


def projector_choice(machine) -> tuple[Target | None, NextPlacement | None]:
    """The projector step's next target and the next-best choice behind it."""
    return structured_choice(machine) if machine.structured else circle_choice(machine)
