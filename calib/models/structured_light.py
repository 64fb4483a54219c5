"""The structured-light sequence the projector shows while the board stands still (issue 23).

The sequence codes every projector pixel's column and row (Moreno & Taubin 2012, with phase shifting):
  - a full-white and a full-black frame: per camera pixel, how much the projector lights it (and a
    closing full-white frame, whose board corners against the first frame's show whether the board moved);
  - per axis (columns, then rows), a reflected-binary Gray code of `cell_px`-wide stripes, each bit
    followed by its inverse: a bit is read as "pattern brighter than inverse", which needs no threshold
    and is immune to the projector's and the camera's tone curves;
  - per axis, with `phase_steps` >= 3, that many sinusoids of period `period_px` = 2 x `cell_px`, shifted
    by 1 / `phase_steps` of a period each: their phase gives the position inside a period to a small
    fraction of a pixel, and the Gray code (one bit finer than a period) says which period.
With `phase_steps` = 0 the Gray code alone goes down to 1-pixel stripes (the classical decoding, each
camera pixel gets the centre of the stripe it sees; the finest stripes are below a mirrored camera's
resolution).

Projector pixel (0, 0) is the centre of the top-left pixel: column j is lit over x in [j - 0.5, j + 0.5),
and a sinusoid's value at column j is its value at x = j.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from calib.errors import FormatError, SpecError

#: the shortest sinusoid period: below it a projector's own blur and 8 bits flatten the sinusoid
MIN_PERIOD_PX = 8
MAX_PERIOD_PX = 1024
MAX_PHASE_STEPS = 32


class Axis(str, enum.Enum):
    """Which projector coordinate a frame codes."""

    COLUMNS = "columns"  # x: the stripes are vertical
    ROWS = "rows"  # y: the stripes are horizontal


class FrameRole(str, enum.Enum):
    WHITE = "white"
    BLACK = "black"
    GRAY = "gray"  # one Gray-code bit
    GRAY_INVERSE = "gray-inverse"  # the same bit, inverted
    PHASE = "phase"  # one phase-shifted sinusoid


@dataclass(frozen=True)
class SequenceFrame:
    """One image of the sequence: its role, the axis it codes (None for white / black), and the bit
    (0 = most significant) or the phase step it shows."""

    role: FrameRole
    axis: Axis | None = None
    index: int = 0


@dataclass(frozen=True)
class StructuredLightSpec:
    """The sequence: Gray code down to `period_px / 2`-wide stripes plus `phase_steps` sinusoids of period
    `period_px` per axis (default 32 px, 8 steps: 47 frames for a 1920x1080 projector), or with
    `phase_steps` = 0 the Gray code down to 1-pixel stripes."""

    period_px: int = 32
    phase_steps: int = 8

    def __post_init__(self):
        if isinstance(self.period_px, bool) or not isinstance(self.period_px, int):
            raise SpecError(f"structured-light period_px must be an integer, got {self.period_px!r}")
        if isinstance(self.phase_steps, bool) or not isinstance(self.phase_steps, int):
            raise SpecError(f"structured-light phase_steps must be an integer, got {self.phase_steps!r}")
        if not (self.phase_steps == 0 or 3 <= self.phase_steps <= MAX_PHASE_STEPS):
            raise SpecError(f"structured-light phase_steps must be 0 (Gray code only) or 3 to {MAX_PHASE_STEPS}, "
                            f"got {self.phase_steps}")
        if self.phase_steps and not (MIN_PERIOD_PX <= self.period_px <= MAX_PERIOD_PX and self.period_px % 2 == 0):
            raise SpecError(f"structured-light period_px must be even and {MIN_PERIOD_PX} to {MAX_PERIOD_PX} px, "
                            f"got {self.period_px}")

    @property
    def phase_shifting(self) -> bool:
        return self.phase_steps > 0

    @property
    def cell_px(self) -> int:
        """Width of the finest Gray-code stripe."""
        return self.period_px // 2 if self.phase_shifting else 1

    def n_bits(self, extent_px: int) -> int:
        """Gray-code bits that number the `cell_px` stripes across `extent_px` pixels."""
        cells = -(-int(extent_px) // self.cell_px)
        return max(1, math.ceil(math.log2(cells))) if cells > 1 else 1

    def frames(self, proj_width: int, proj_height: int) -> tuple[SequenceFrame, ...]:
        """The sequence in display order."""
        out = [SequenceFrame(FrameRole.WHITE), SequenceFrame(FrameRole.BLACK)]
        for axis, extent in ((Axis.COLUMNS, proj_width), (Axis.ROWS, proj_height)):
            for b in range(self.n_bits(extent)):
                out += [SequenceFrame(FrameRole.GRAY, axis, b), SequenceFrame(FrameRole.GRAY_INVERSE, axis, b)]
            out += [SequenceFrame(FrameRole.PHASE, axis, k) for k in range(self.phase_steps)]
        # the closing white frame: its board corners against the first one's tell whether the board moved
        out.append(SequenceFrame(FrameRole.WHITE, None, 1))
        return tuple(out)

    def render(self, proj_width: int, proj_height: int, frame: SequenceFrame) -> np.ndarray:
        """(H, W) uint8 image of one frame of the sequence."""
        w, h = int(proj_width), int(proj_height)
        if w < 1 or h < 1:
            raise SpecError(f"projector size must be positive, got {w}x{h}")
        if frame.role is FrameRole.WHITE:
            return np.full((h, w), 255, np.uint8)
        if frame.role is FrameRole.BLACK:
            return np.zeros((h, w), np.uint8)
        extent = w if frame.axis is Axis.COLUMNS else h
        if frame.role is FrameRole.PHASE:
            if not 0 <= frame.index < self.phase_steps:
                raise SpecError(f"phase step {frame.index} out of range 0..{self.phase_steps - 1}")
            line = _phase_line(extent, self.period_px, self.phase_steps, frame.index)
        else:
            n = self.n_bits(extent)
            if not 0 <= frame.index < n:
                raise SpecError(f"Gray-code bit {frame.index} out of range 0..{n - 1}")
            line = _gray_line(extent, self.cell_px, n, frame.index)
            if frame.role is FrameRole.GRAY_INVERSE:
                line = 255 - line
        if frame.axis is Axis.COLUMNS:
            return np.ascontiguousarray(np.broadcast_to(line[None, :], (h, w)))
        return np.ascontiguousarray(np.broadcast_to(line[:, None], (h, w)))

    def images(self, proj_width: int, proj_height: int) -> list[np.ndarray]:
        return [self.render(proj_width, proj_height, f) for f in self.frames(proj_width, proj_height)]

    def to_dict(self) -> dict:
        return {"period_px": self.period_px, "phase_steps": self.phase_steps}

    @classmethod
    def from_dict(cls, d, where: str = "structured_light", path="<dict>") -> "StructuredLightSpec":
        if not isinstance(d, dict):
            raise FormatError(path, where, "must be an object")
        kw = {}
        for key in ("period_px", "phase_steps"):
            if key not in d:
                raise FormatError(path, f"{where}.{key}", "missing")
            if not isinstance(d[key], int) or isinstance(d[key], bool):
                raise FormatError(path, f"{where}.{key}", f"has the wrong type ({type(d[key]).__name__})")
            kw[key] = d[key]
        try:
            return cls(**kw)
        except SpecError as e:
            raise FormatError(path, where, str(e)) from None


def gray_encode(n: np.ndarray) -> np.ndarray:
    n = np.asarray(n, np.int64)
    return n ^ (n >> 1)


def gray_decode(g: np.ndarray) -> np.ndarray:
    """Inverse of gray_encode (for codes of up to 32 bits)."""
    n = np.asarray(g, np.int64).copy()
    shift = 1
    while shift < 32:
        n ^= n >> shift
        shift <<= 1
    return n


@lru_cache(maxsize=64)
def _gray_line(extent: int, cell: int, n_bits: int, bit: int) -> np.ndarray:
    code = gray_encode(np.arange(extent) // cell)
    line = np.where((code >> (n_bits - 1 - bit)) & 1, 255, 0).astype(np.uint8)
    line.setflags(write=False)
    return line


@lru_cache(maxsize=64)
def _phase_line(extent: int, period: int, steps: int, k: int) -> np.ndarray:
    x = np.arange(extent, dtype=np.float64)
    v = 0.5 + 0.5 * np.cos(2 * np.pi * (x / period - k / steps))
    line = np.round(255.0 * v).astype(np.uint8)
    line.setflags(write=False)
    return line


#: the pattern positions' order when only a few placements are taken: the corners and centre first
#: (calib.models.pattern's positions), so a few placements still spread over the projector's image
POSITION_ORDER = (0, 2, 4, 6, 8, 1, 3, 5, 7, 9, 10, 11, 12)


def placement_order(positions: int, per_position: int) -> list[tuple[int, int]]:
    """The (pattern position, pose index in that position) slots a structured projector step asks for, in
    order: one pose of each position in POSITION_ORDER, then the next pose of each, ... The position
    names where the board should stand (the circle step's pose for it); the projector shows the sequence."""
    order = [p for p in POSITION_ORDER if p < positions] + [p for p in range(len(POSITION_ORDER), positions)]
    return [(p, k) for k in range(per_position) for p in order]
