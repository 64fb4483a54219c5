"""What a session asks for: the capture plan (how many captures each step takes) and the target (the
one capture asked for next). Both are stored in session.json's `state`, so a resumed session keeps them."""

from __future__ import annotations

from dataclasses import dataclass
from calib.models.vocab import MirrorMethod


_SWITCHES = ("stop_on_confidence", "next_best", "ask_pose")


@dataclass(frozen=True)
class Plan:
    """How many captures each step asks for. The projector step takes `poses_per_position` board poses
    at each of the pattern's positions (PatternSpec.positions), or `structured_placements` placements
    when it shows the structured-light sequence."""

    poses_per_position: int = 4
    real_virtual_captures: int = 14
    real_mirror_captures: int = 14
    min_real_virtual: int = 3
    # real-mirror: at least 3 placements of the board on the mirror (each capture a new place and angle):
    # with one, the mirror's normal rests on a single board's tilt (docs/JOINT.md#several-real-mirror-placements)
    min_real_mirror: int = 3
    min_projector_captures: int = 6
    # end the projector step once its 1-sigmas meet their targets (calib.quality.confidence), the counts
    # above then maximums; its poses are asked one at every pattern position before the next
    stop_on_confidence: bool = False
    # stopping on confidence, the mirror step takes this many captures before the projector step (the mirror
    # normal can be judged only with projector captures), then more after it until the normal is confident
    mirror_first: int = 5
    # a structured-light projector step (PatternKind.STRUCTURED): at most this many board placements, each
    # the whole coded sequence (calib.models.structured_light); with stop_on_confidence at least the minimum,
    # which is what a calibration needs (calib.paper.method.MIN_PROJECTOR_VIEWS: fewer cannot be judged)
    structured_placements: int = 6
    min_structured_placements: int = 4
    # with stop_on_confidence: once a calibration of the captures so far is known, ask for the pattern
    # position where the projector's projection uncertainty is largest (calib.quality.next_pose) instead
    # of the plan's order
    next_best: bool = False
    # with stop_on_confidence: once the captures so far are calibrated, ask for a whole board pose (pattern
    # position and tilt) whose predicted observations leave the step's worst 1-sigma least
    # (calib.asked_pose); the panel dashes the board's outline where it is to be held
    ask_pose: bool = False
    # each mirror placement the mean of this many frames of the board held still (app/station/mirror_frames.py)
    mirror_frames: int = 1

    def mirror_captures(self, method: str) -> int:
        return self.real_virtual_captures if method == MirrorMethod.REAL_VIRTUAL else self.real_mirror_captures

    def mirror_before_projector(self, method: str) -> int:
        """Mirror captures taken before the projector step: all of them, or (stop_on_confidence) the first."""
        total = self.mirror_captures(method)
        return min(max(self.mirror_first, self.min_mirror(method)), total) if self.stop_on_confidence else total

    def min_mirror(self, method: str) -> int:
        need = self.min_real_virtual if method == MirrorMethod.REAL_VIRTUAL else self.min_real_mirror
        return min(need, self.mirror_captures(method))  # a plan asking for fewer captures needs only those

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    @classmethod
    def from_dict(cls, d: dict | None) -> Plan:
        d = d or {}
        return cls(**{k: (bool(v) if k in _SWITCHES else int(v)) for k, v in d.items()
                      if k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class Target:
    """The capture the station asks for next: which step, at which pattern position, which pose."""

    step: str
    pattern_position: int | None
    pose_index: int

    def to_dict(self) -> dict:
        return {"step": self.step, "pattern_position": self.pattern_position, "pose_index": self.pose_index}

    @classmethod
    def from_dict(cls, d) -> Target | None:
        if not isinstance(d, dict) or "step" not in d:
            return None
        pos = d.get("pattern_position")
        return cls(str(d["step"]), None if pos is None else int(pos), int(d.get("pose_index", 0)))
