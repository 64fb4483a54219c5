"""The structured-light projector step of the station (PatternKind.STRUCTURED, docs/STRUCTURED_LIGHT.md).

A placement is one board position the operator holds still while the projector shows the whole coded
sequence (calib.models.structured_light.StructuredLightSpec). While the operator places the board the
projector shows the sequence's white frame and auto-capture watches the board alone; when it says the
board is still and in a new place, `capture_sequence` shows every frame of the sequence in turn, each
captured with the presentation gating of any capture (a frame counts only if its exposure began after
the image became visible), and compares the board's ChArUco corners in the opening and closing white
frames: a board that moved is refused with the reason, nothing is written, and the operator is asked to
hold that placement again.

The slots asked for are app.station.targets' (calib.models.structured_light.placement_order's, the
circle step's poses, one per pattern position before the next, as `procam simulate --projector-pattern
structured` places them; stopping on confidence, the next-best position once a grid is known). A capture records its slot in meta (`slot_position`,
`pose_index`); session.json records its placement (docs/FORMATS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calib.models.observations import VIEW_MIRROR
from calib.models.structured_light import StructuredLightSpec
from calib.models.vocab import PatternKind

#: the sequence the station shows (the spec docs/STRUCTURED_LIGHT.md measures)
STATION_SPEC = StructuredLightSpec()
#: frames to wait for one sequence image before giving up on the camera (a frame rate, not a time)
MAX_FRAMES_PER_IMAGE = 30


def _exposure_s(frame, period_s: float) -> float:
    """A frame's exposure time (its meta's `exposure_us`; a whole period when the driver does not say)."""
    us = frame.meta.get("exposure_us") if isinstance(frame.meta, dict) else None
    return float(us) * 1e-6 if isinstance(us, (int, float)) and us > 0 else period_s


def _visible(projector, ticket) -> float | None:
    """When the image of an already shown ticket became visible; None if it never was."""
    from drivers.errors import DeviceError

    try:
        return projector.wait_presented(ticket, timeout_s=0.5)
    except DeviceError:
        return None


def is_structured(manifest) -> bool:
    return getattr(manifest.pattern, "kind", None) == PatternKind.STRUCTURED.value


def slot_of(capture) -> tuple[int | None, int]:
    """The (pattern position, pose index) slot a structured capture filled."""
    pos = capture.meta.get("slot_position", capture.meta.get("sim_pattern_position"))
    return (None if pos is None else int(pos)), int(capture.meta.get("pose_index", capture.meta.get("sim_pose_index", 0)))


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
    scheduled: int = 0  # images captured on the schedule of frame periods (the others shown one by one)
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

    def _pipelined(self, first_frame, images) -> list:
        """Show the images on a schedule of whole frame periods, without waiting each one's latency:
        image k is kept from the first frame whose exposure lies wholly inside the time it is visible (the
        projector's own presentation times, read once the schedule is through). Images left without
        such a frame are None (a camera that cannot time its frames: all of them)."""
        st = self.station
        fs, clock, projector = st.frames, st.clock, st.rig.projector
        n = len(images)
        got: list = [first_frame] + [None] * (n - 1)
        probe = fs.grab()
        if probe is None or first_frame.exposure_start_s is None or probe.exposure_start_s is None \
                or probe.frame_number <= first_frame.frame_number:
            return got
        period = (probe.exposure_start_s - first_frame.exposure_start_s) / (probe.frame_number - first_frame.frame_number)
        exposure = _exposure_s(probe, period)
        refresh = 1.0 / max(float(getattr(projector, "refresh_hz", 60.0) or 60.0), 1.0)
        # the projector's latency as measured (settle_s) errs long, never short, by up to about a refresh
        # period or two: a frame must end that much before the next image's measured time (the sequential
        # capture never meets the next image, so it does not care)
        guard = 2.0 * refresh
        margin = 0.5 * refresh  # the expected times ignore each presentation's wait for its refresh
        # each image held whole frame periods: the first frame starting `margin` after it is visible ends,
        # with the guard, before the next image is (the schedule keeps the frames' phase, so a hold that
        # misses once misses every image)
        hold = period * math.ceil((period + margin + exposure + guard) / period - 1e-6)
        tickets = [None] * n
        shown_at = [None] * n
        tickets[1], shown_at[1] = projector.show(images[1]), clock.now()
        st.shown_ticket = tickets[1]
        latency = projector.wait_presented(tickets[1], timeout_s=st.options.frame_timeout_s) - shown_at[1]
        k_show, t_next, k_want = 2, shown_at[1] + hold, 1

        def first_starting_after(t: float) -> int:  # frame numbers follow the camera's period
            return probe.frame_number + math.ceil((t - probe.exposure_start_s) / period - 1e-9)

        while k_want < n:
            if k_show < n and clock.now() >= t_next:
                tickets[k_show], shown_at[k_show] = projector.show(images[k_show]), clock.now()
                st.shown_ticket = tickets[k_show]
                t_next = shown_at[k_show] + hold
                k_show += 1
                continue
            # only the frame each image needs is read (the others are never asked of the camera), and
            # only when it arrives before the next image is due
            number = max(first_starting_after(shown_at[k_want] + latency + margin), fs.last_frame + 1)
            arrives = probe.exposure_start_s + (number - probe.frame_number + 1) * period
            if k_want >= k_show or (k_show < n and arrives > t_next):
                clock.sleep(max(0.0, t_next - clock.now()))
                continue
            fs.seen(number - 1)
            frame = fs.grab()
            if frame is None or frame.exposure_start_s is None:
                break
            start = frame.exposure_start_s
            until = shown_at[k_want + 1] + latency if k_want + 1 < k_show else shown_at[k_want] + latency + hold
            if start >= shown_at[k_want] + latency + margin - 1e-9 and start + exposure <= until - guard:
                got[k_want] = frame
            k_want += 1
        # the projector's own times: a frame counts only wholly inside its image's visible time
        visible = [None] + [_visible(projector, t) for t in tickets[1:]]
        for k in range(1, n):
            f = got[k]
            if f is None:
                continue
            end_ok = k + 1 >= n or (visible[k + 1] is not None
                                    and f.exposure_start_s + _exposure_s(f, period) <= visible[k + 1] - guard)
            if visible[k] is None or f.exposure_start_s < visible[k] or not end_ok:
                got[k] = None
        return got

    def run(self, first_frame, first_board) -> SequenceResult:
        """Capture the sequence, `first_frame` (a frame accepted while the white image was shown, its
        board `first_board` as detected live) its opening frame; refuse it when a frame does not arrive
        or the board moved."""
        from calib.detection.detect import detect_board
        from calib.detection.structured_view import board_motion_px, motion_refusal

        st = self.station
        t0 = st.clock.now()
        images = self.images()
        got = self._pipelined(first_frame, images)
        scheduled = sum(f is not None for f in got[1:])
        frames, numbers = [first_frame.image], [first_frame.frame_number]
        for k, image in enumerate(images[1:], start=2):
            # an image the schedule left without a frame wholly inside its time: shown alone and waited for
            frame = got[k - 1] or self._frame_of(st._show(image))
            if frame is None:
                st._shown = None
                return SequenceResult(refused=f"no camera frame for image {k} of {len(images)} of the sequence; "
                                              "check the camera and hold the board for this placement again")
            frames.append(frame.image)
            numbers.append(frame.frame_number)
        duration = st.clock.now() - t0
        st._shown = None  # the white image again for the next placement
        man = st.machine.manifest
        last = detect_board(frames[-1], man.projector_board, man.rig.view == VIEW_MIRROR)
        moved = board_motion_px(first_board, last)
        refused = motion_refusal(moved)
        if refused is not None:
            return SequenceResult(motion_px=float(moved), duration_s=duration, refused=refused)
        return SequenceResult(tuple(frames), tuple(numbers), float(moved), duration, scheduled)
