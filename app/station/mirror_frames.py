"""A mirror placement captured as the mean of several frames (Plan.mirror_frames, `--mirror-frames N`).

The mirror step's 1-sigmas come from the ChArUco corners' noise: a board held still for a few frames
gives as many independent noise draws, and their mean image halves the noise at four frames
(docs/CALIBRATION.md "Several frames per mirror placement"). The frames are the next ones the camera
delivers after the frame auto-capture (or the button) chose. A board held by hand sways through them
(a pixel or so in a quarter of a second); the mean image of a board that moved a little is the board at
its mean pose, as sharp for the corner detector as a still one, so such a placement is kept. One that
moved more than MAX_MEAN_MOTION_PX between the first and the last frame (board_motion_px) is refused,
the operator asked to hold it again.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from calib.detection.structured_view import board_motion_px

#: frames read per frame wanted before giving up (a camera that stopped delivering)
MAX_READS_PER_FRAME = 30
#: a board that moved more than this over the frames is refused: up to 2 px the mean image's corners
#: were as close to the mean pose's as a still board's are to its pose, and beyond it they began to
#: drift on one rig (benchmarks/hold_motion.py, docs/BENCHMARKS.md "Holding the board"); stricter than
#: that, most placements of a hand-held board would be refused for nothing
MAX_MEAN_MOTION_PX = 1.5


@dataclass(frozen=True)
class MeanFrame:
    """The mean of a placement's frames (a Frame with the mean image), their numbers and how far the
    board moved between the first and the last; or why it was refused."""

    frame: object | None = None  # drivers.base.Frame
    frame_numbers: tuple[int, ...] = ()
    motion_px: float | None = None
    refused: str | None = None


def capture_mean(station, first_frame, first_det, count: int) -> MeanFrame:
    """`count` frames of the placement `first_frame` shows (its detection `first_det`), averaged."""
    from app.station.autocapture import detect_for_step

    fs = station.frames
    frames = [first_frame]
    for _ in range(MAX_READS_PER_FRAME * count):
        if len(frames) == count:
            break
        f = fs.grab()
        if f is not None and f.frame_number > frames[-1].frame_number and fs.accepts(f):
            frames.append(f)
    if len(frames) < count:
        return MeanFrame(refused=f"the camera gave {len(frames)} of the {count} frames of this placement; check the "
                                 "camera and hold the board again")
    m = station.machine
    last = detect_for_step(frames[-1].image, first_det.step, m.manifest, station.camera_model, frames[-1].frame_number)
    moved = board_motion_px(first_det.board, last.board)
    if not moved <= MAX_MEAN_MOTION_PX:
        how = "out of view" if not np.isfinite(moved) else f"by {moved:.1f} px"
        return MeanFrame(motion_px=float(moved), refused=f"the board moved during the {count} frames of this placement "
                                                         f"({how}): hold it still and capture it again")
    acc = np.zeros(first_frame.image.shape, np.float64)
    for f in frames:
        acc += f.image
    image = np.clip(np.rint(acc / count), 0, 255).astype(first_frame.image.dtype)
    return MeanFrame(replace(first_frame, image=image), tuple(f.frame_number for f in frames), float(moved))
