"""The verification's frames (behind app/verification.py): a camera frame exposed after a projector
image became visible, the black and white references every check shares, and frames as grey light."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app._verification_report import VerificationError
from calib.detection.curves import lit_region
from calib.detection.response import CameraResponse
from drivers.clock import clock_of


class Grabber:
    """Shows an image and returns the (mean of `average`) camera frame(s) exposed after it became
    visible: frames whose exposure started at or after the time `wait_presented` returns (presentation
    + the projector's measured latency). A camera that cannot time its frames (exposure_start_s None)
    skips `settle_frames` frames after the one seen when the image was presented instead.
    `seen` keeps (frame_number, projector ticket) of every frame used, for tests."""

    def __init__(self, camera, projector, settle_frames: int = 1, average: int = 1, timeout_s: float = 3.0):
        self.camera, self.projector = camera, projector
        self.settle_frames, self.average, self.timeout_s = int(settle_frames), max(1, int(average)), timeout_s
        self.last = None
        self.seen: list[tuple[int, int]] = []

    def grab(self, image: np.ndarray) -> np.ndarray:
        ticket = self.projector.show(image)
        visible_s = self.projector.wait_presented(ticket, timeout_s=self.timeout_s)
        if self.last is None:
            self.last = self.camera.get_frame(self.timeout_s).frame_number
        acc, n, skip = None, 0, self.settle_frames
        clock = clock_of(self.projector)
        deadline = clock.now() + self.timeout_s
        while n < self.average:
            f = self.camera.get_frame(self.timeout_s, newer_than=self.last)
            self.last = f.frame_number
            early = f.exposure_start_s < visible_s if f.exposure_start_s is not None else skip > 0
            if early:
                skip -= 1
                if clock.now() > deadline:
                    raise VerificationError(f"no camera frame exposed after the projector's image became visible "
                                            f"within {self.timeout_s:g} s: check the camera's frame times")
                continue
            img = f.image.astype(np.float32)
            acc = img if acc is None else acc + img
            n += 1
            self.seen.append((int(f.frame_number), int(ticket)))
        return acc / self.average if self.average > 1 else acc


_LEVELS = np.arange(256, dtype=np.float64)


def grey(img: np.ndarray, response: CameraResponse | None = None) -> np.ndarray:
    """(H, W) float32 light: the mean of the channels, as calib.detection.curves reads a BGR frame. With
    the camera's `response` (tone curve, not linear), each channel's levels are linearised first (the
    curve's inverse, interpolated in CameraResponse.lut: averaged frames have fractional levels), so the
    stripe signal divides light, not encoded levels, and its validity threshold (a fraction of the
    white's rise) sees the print's black squares as the few percent of the light they are, not the
    ~20 % of the levels the curve lifts them to: left out, their noisy signal no longer pulls the
    centre line (most of the gain, docs/VERIFICATION.md). The only place the verification's frames
    become grey light. (Averaged frames are averaged before they are linearised: a noise-sized error.)"""
    a = np.asarray(img)
    if response is not None and not response.linear:
        a = np.interp(a, _LEVELS, response.lut())
    return a.astype(np.float32).mean(axis=2) if a.ndim == 3 else a.astype(np.float32)


def draw_stroke(size, curve: np.ndarray, stroke_px: float) -> np.ndarray:
    from drivers.projector_images import draw_polylines

    return draw_polylines(tuple(size), [curve], thickness_px=float(stroke_px), antialias=True)


@dataclass(frozen=True, eq=False)
class ReferenceFrames:
    """The frames every check shares: projector black and full white (as the camera delivered them), the
    lit region, and the camera's response the frames' light is read with (None: the levels as they are)."""

    off: np.ndarray
    white: np.ndarray
    lit: np.ndarray  # bool mask of what the projector lights brightly, as the camera sees it (its levels)
    response: CameraResponse | None = None

    def light(self) -> tuple[np.ndarray, np.ndarray]:
        """(off, white) as grey float32 light, linearised by `response` (see grey)."""
        return grey(self.off, self.response), grey(self.white, self.response)


def capture_references(camera, projector, settle_frames: int = 1, average: int = 1, grabber=None,
                       response: CameraResponse | None = None) -> ReferenceFrames:
    """Capture the black and white reference frames (the board must be in place and still). `response`:
    the camera's tone curve (calib.detection.response), kept with the frames: every signal formed from
    them is then linear light (None: encoded levels, as before responses were recorded)."""
    W, H = projector.size
    g = grabber or Grabber(camera, projector, settle_frames, average)
    white = g.grab(np.full((H, W), 255, np.uint8))
    off = g.grab(np.zeros((H, W), np.uint8))
    return ReferenceFrames(off, white, lit_region(off, white), response)
