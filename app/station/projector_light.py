"""Is the projector's image still reaching the camera? (issue 24, defect 9: a projector blanked mid-session)

The projector step's pattern is seen in the camera frames while the projector shows it. When the
board is still detected but the pattern has vanished from it for several frames in a row, after it was
seen, the projector's light no longer reaches the scene: its screen blanked (DPMS, screen saver, a
lock screen), it went to sleep or its cable came loose. A pure helper: the station feeds it each
detection of the projector step and reports its episodes (once each) in the panel and the log.
"""

from __future__ import annotations

#: the operator's message while the projector's light is missing
LOST_MESSAGE = ("the projector's image no longer reaches the camera: is the projector's screen blanked, "
                "asleep or unplugged? (the board is seen, its pattern is not)")
BACK_MESSAGE = "the projector's image reaches the camera again"


class ProjectorLightWatch:
    """Episodes of a projector image that no longer reaches the camera, from the projector step's detections.

    update() takes each detection (app.station.autocapture.LiveDetection) made while the projector shows its
    pattern, or None when it shows none (another step): it returns "lost" on the frame an episode begins,
    "back" on the frame the pattern is seen again, else None. `lost` is true during an episode."""

    def __init__(self, lost_frames: int = 8):
        self.lost_frames = int(lost_frames)  # consecutive frames of a board without its pattern
        self.lost = False
        self._seen = False  # the pattern was seen since the projector began showing it
        self._missing = 0

    def reset(self) -> str | None:
        """The projector shows no pattern now: forget what was seen ("back" when an episode ends so)."""
        was = self.lost
        self.lost, self._seen, self._missing = False, False, 0
        return "back" if was else None

    def update(self, det) -> str | None:
        if det is None:
            return self.reset()
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
