"""Is the projector's image still reaching the camera? (a projector blanked mid-session)

The projector step's pattern is seen in the camera frames while the projector shows it. When the
board is still detected but the pattern of the current target, seen on it before, has vanished for
about a second and a half, either the board moved off the pattern or the projector's light no longer
reaches the scene: its screen blanked (DPMS, screen saver, a lock screen), it went to sleep or its
cable came loose. The camera cannot tell the two apart (it sees the projector's light only on the
board), so the message names both. A pure helper: the station feeds it each detection of the
projector step with its target, and reports its episodes (once each) in the panel and the log.
"""

from __future__ import annotations

#: the operator's message while the projector's light is missing
LOST_MESSAGE = ("the board no longer shows the projector's pattern it showed a moment ago: if the board has "
                "not moved off the pattern, the projector's image no longer reaches the camera (is its screen "
                "blanked, asleep or unplugged?)")
BACK_MESSAGE = "the projector's image reaches the camera again"


class ProjectorLightWatch:
    """Episodes of a projector image that no longer reaches the camera, from the projector step's detections.

    update() takes each detection (app.station.autocapture.LiveDetection) made while the projector shows its
    pattern with the target it is shown for, or None when it shows none (another step): it returns "lost"
    on the frame an episode begins, "back" on the frame the pattern is seen again, else None. `lost` is
    true during an episode. A new target (another pattern position or pose) starts afresh: its pattern
    has to be seen first."""

    def __init__(self, lost_frames: int = 45):  # about 1.5 s of a 30 fps camera: longer than a hand's tremor
        self.lost_frames = int(lost_frames)  # consecutive frames of a board without its pattern
        self.lost = False
        self._seen = False  # the pattern was seen since the projector began showing it
        self._missing = 0
        self._target = None

    def reset(self) -> str | None:
        """The projector shows no pattern now: forget what was seen ("back" when an episode ends so)."""
        was = self.lost
        self.lost, self._seen, self._missing = False, False, 0
        return "back" if was else None

    def update(self, det, target=None) -> str | None:
        if det is None:
            return self.reset()
        if target != self._target:  # another pattern or pose: what was seen of the last says nothing
            self.lost, self._seen, self._missing, self._target = False, False, 0, target
        if det.board is None:
            return None  # no board, no evidence either way (it may be moving or out of view)
        failure = det.failure or ""
        pattern_gone = det.pattern_px is None and failure.startswith("pattern:")
        if not pattern_gone:  # the pattern is on the board: its light arrives
            self._seen = True
            self._missing = 0
            if self.lost:
                self.lost = False
                return "back"
            return None
        if not self._seen:
            return None
        self._missing += 1
        if self._missing >= self.lost_frames and not self.lost:
            self.lost = True
            return "lost"
        return None
