"""The capture a projector step asks for next (SessionMachine.target): the circle grid's poses at every
pattern position, in the plan's order or, stopping on confidence, one pose at every position before the
next; the structured-light step's placements are app.station.structured_step's."""

from __future__ import annotations

from app.station.plan import Target
from calib.models.observations import STEP_PROJECTOR


def free_pose(caps, n: int) -> int | None:
    """The lowest pose index below `n` none of `caps` took."""
    used = {c.meta.get("pose_index") for c in caps}
    return next((k for k in range(n) if k not in used), None)


def circle_target(machine) -> Target | None:
    """The next pose of a circle (or chessboard) projector step, None when it is complete."""
    plan = machine.plan
    caps = machine.captures_of(STEP_PROJECTOR)
    counts = machine.position_counts()

    def at(p: int) -> Target:
        mine = [c for c in caps if c.pattern_position == p]
        return Target(STEP_PROJECTOR, p, free_pose(mine, plan.poses_per_position + len(mine)))

    if not plan.stop_on_confidence:
        return next((at(p) for p in range(machine.positions) if counts[p] < plan.poses_per_position), None)
    conf = machine.projector_confidence
    if conf is not None and conf.all_met and len(caps) >= plan.min_projector_captures:
        return None  # confident (at least the plan's minimum): the counts were maximums
    return next((at(p) for k in range(plan.poses_per_position) for p in range(machine.positions) if counts[p] <= k),
                None)
