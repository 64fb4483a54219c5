"""The structured-light projector step of the station (PatternKind.STRUCTURED, docs/STRUCTURED_LIGHT.md).

A placement is one board position the operator holds still while the projector shows the whole coded
sequence (calib.models.structured_light.StructuredLightSpec). While the operator places the board the
projector shows the sequence's white frame and auto-capture watches the board alone; when it says the
board is still and in a new place, `capture_sequence` shows every frame of the sequence in turn, each
captured with the presentation gating of any capture (a frame counts only if its exposure began after
the image became visible), and compares the board's ChArUco corners in the opening and closing white
frames: a board that moved is refused with the reason, nothing is written, and the operator is asked to
hold that placement again.

The slots asked for come from calib.models.structured_light.placement_order (the circle step's poses,
one per pattern position before the next), so the simulated operator places the board as `procam
simulate --projector-pattern structured` does. A capture records its slot in meta (`slot_position`,
`pose_index`); session.json records its placement (docs/FORMATS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.models.observations import STEP_PROJECTOR, VIEW_MIRROR
from calib.models.structured_light import StructuredLightSpec, placement_order
from calib.models.vocab import PatternKind

#: the sequence the station shows (the spec docs/STRUCTURED_LIGHT.md measures)
STATION_SPEC = StructuredLightSpec()
#: frames to wait for one sequence image before giving up on the camera (a frame rate, not a time)
MAX_FRAMES_PER_IMAGE = 30


def is_structured(manifest) -> bool:
    return getattr(manifest.pattern, "kind", None) == PatternKind.STRUCTURED.value


def slot_of(capture) -> tuple[int | None, int]:
    """The (pattern position, pose index) slot a structured capture filled."""
    pos = capture.meta.get("slot_position", capture.meta.get("sim_pattern_position"))
    return (None if pos is None else int(pos)), int(capture.meta.get("pose_index", capture.meta.get("sim_pose_index", 0)))


def structured_target(machine):
    """The next placement of a structured projector step, or None when it is complete: the plan's
    `structured_placements` taken, or (stop_on_confidence) at least `min_structured_placements` and the
    step confident."""
    from app.station.plan import Target

    plan = machine.plan
    caps = machine.captures_of(STEP_PROJECTOR)
    if len(caps) >= plan.structured_placements:
        return None
    conf = machine.projector_confidence
    if plan.stop_on_confidence and conf is not None and conf.all_met and len(caps) >= plan.min_structured_placements:
        return None
    taken = {slot_of(c) for c in caps}
    slots = placement_order(machine.positions, max(plan.poses_per_position, 1) + len(caps))
    for pos, k in slots:
        if (pos, k) not in taken:
            return Target(STEP_PROJECTOR, pos, k)
    return None


def min_projector_captures(machine) -> int:
    """The fewest projector captures the step's confidence is judged on."""
    plan = machine.plan
    return plan.min_structured_placements if is_structured(machine.manifest) else plan.min_projector_captures


@dataclass(frozen=True)
class SequenceResult:
    """A captured sequence: its frames (display order) and their records, or why it was refused."""

    frames: tuple[np.ndarray, ...] = ()
    frame_numbers: tuple[int, ...] = ()
    motion_px: float | None = None
    duration_s: float = 0.0  # from the first image shown to the last frame (the rig's clock)
    refused: str | None = None


class SequenceCapture:
    """Shows a structured-light sequence on the station's projector and captures a frame of each image."""

    def __init__(self, station, spec: StructuredLightSpec = STATION_SPEC):
        self.station = station
        self.spec = spec
        self._images: list[np.ndarray] | None = None

    def images(self) -> list[np.ndarray]:
        if self._images is None:
            w, h = self.station.projector_size
            self._images = self.spec.images(w, h)
        return self._images

    def white(self) -> np.ndarray:
        """The image shown while the operator places the board (the sequence's opening frame)."""
        return self.images()[0]

    def _frame_of(self, visible_s: float):
        """The first camera frame exposed after `visible_s` (the station's timing rule)."""
        fs = self.station.frames
        fs.changed(visible_s)
        for _ in range(MAX_FRAMES_PER_IMAGE):
            frame = fs.grab()
            if frame is not None and fs.accepts(frame):
                return frame
        return None

    def run(self, first_frame) -> SequenceResult:
        """Capture the sequence, `first_frame` (a frame accepted while the white image was shown) its
        opening frame; refuse it when a frame does not arrive or the board moved."""
        from calib.detection.detect import detect_board
        from calib.detection.structured_view import MAX_MOTION_PX, board_motion_px

        st = self.station
        t0 = st.clock.now()
        frames, numbers = [first_frame.image], [first_frame.frame_number]
        images = self.images()
        for k, image in enumerate(images[1:], start=2):
            visible = st._show(image)
            frame = self._frame_of(visible)
            if frame is None:
                st._shown = None
                return SequenceResult(refused=f"no camera frame for image {k} of {len(images)} of the sequence; "
                                              "check the camera and hold the board for this placement again")
            frames.append(frame.image)
            numbers.append(frame.frame_number)
        duration = st.clock.now() - t0
        st._shown = None  # the white image again for the next placement
        man = st.machine.manifest
        mirrored = man.rig.view == VIEW_MIRROR
        first = detect_board(frames[0], man.projector_board, mirrored)
        last = detect_board(frames[-1], man.projector_board, mirrored)
        moved = board_motion_px(first, last)
        if not moved <= MAX_MOTION_PX:
            how = "out of view" if not np.isfinite(moved) else f"by {moved:.1f} px"
            return SequenceResult(motion_px=float(moved), duration_s=duration,
                                  refused=f"the board moved during the sequence ({how} between its opening and "
                                          "closing white frames): hold it still for this placement again")
        return SequenceResult(tuple(frames), tuple(numbers), float(moved), duration)
