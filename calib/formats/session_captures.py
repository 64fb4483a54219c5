"""One capture of a session folder: its record in session.json (`Capture`) and the checks a record read
from disk must pass (`capture_from_dict`).

A capture is one image (a circle or chessboard projector capture, a mirror capture) or, for a
structured-light projector capture, the sequence's frames of one board placement (docs/FORMATS.md):
  {id, step, image, pattern_position?, pattern_points_px?, placement?, meta?}
  {id, step: "projector", image, pattern_kind: "structured", structured_light: {period_px, phase_steps},
   frames: ["images/ID-f00.png", ...], placement?, meta?}   (image is the first frame, the white one)
`placement` numbers the board's positions: the captures taken while the board stood in one place share
it, and a capture without one is a placement of its own.

Every path is untrusted: it must be `images/NAME.png` (no folder, no `..`, not absolute); links are
checked when a file is read (calib.formats.session.SessionStore.file_path).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from calib.errors import FormatError
from calib.models.observations import STEP_PROJECTOR, STEPS
from calib.models.structured_light import StructuredLightSpec
from calib.models.vocab import PatternKind

#: the only form a capture's `id` may take: it is printed, named in reports and matched against the cache,
#: so no separators, spaces or control characters
CAPTURE_ID_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
#: the only form a capture's `image` (and a frame) may take: a PNG file directly in the images folder
IMAGE_RE = re.compile(r"images/[A-Za-z0-9_][A-Za-z0-9_.-]{0,200}\.png")
#: more frames than any sequence has (calib.models.structured_light: 47 for 1920x1080): a corrupt list
MAX_FRAMES = 200


@dataclass(frozen=True, eq=False)
class Capture:
    id: str
    step: str
    image: str  # path relative to the session folder
    pattern_position: int | None = None
    pattern_points_px: np.ndarray | None = None  # projector pixels of the shown pattern points
    meta: dict = field(default_factory=dict)
    placement: int | None = None  # the board's position it was taken in (None: a placement of its own)
    structured_light: StructuredLightSpec | None = None  # a structured-light capture's sequence
    frames: tuple[str, ...] = ()  # its frames, in the sequence's order (paths relative to the folder)

    @property
    def structured(self) -> bool:
        return self.structured_light is not None

    def to_dict(self) -> dict:
        d = {"id": self.id, "step": self.step, "image": self.image}
        if self.pattern_position is not None:
            d["pattern_position"] = int(self.pattern_position)
        if self.pattern_points_px is not None:
            d["pattern_points_px"] = np.asarray(self.pattern_points_px, float).tolist()
        if self.structured_light is not None:
            d["pattern_kind"] = PatternKind.STRUCTURED.value
            d["structured_light"] = self.structured_light.to_dict()
            d["frames"] = list(self.frames)
        if self.placement is not None:
            d["placement"] = int(self.placement)
        if self.meta:
            d["meta"] = self.meta
        return d


def placements(captures) -> int:
    """How many positions the operator put the board in for these captures (module docstring)."""
    return len({("placement", c.placement) if c.placement is not None else ("capture", c.id) for c in captures})


def typed(value, types: tuple) -> bool:
    """`value` is one of `types` (None in `types` allows null; a bool is not an int or float)."""
    if value is None:
        return None in types
    if isinstance(value, bool):
        return bool in types
    return isinstance(value, tuple(t for t in types if t is not None))


def _need(obj, key, where, path, typ=None):
    if not isinstance(obj, dict) or key not in obj:
        raise FormatError(path, f"{where}{key}", "missing")
    v = obj[key]
    if typ is not None and (not isinstance(v, typ) or isinstance(v, bool)):
        raise FormatError(path, f"{where}{key}", f"has the wrong type ({type(v).__name__})")
    return v


def _file(value, where: str, path) -> str:
    if not isinstance(value, str) or not IMAGE_RE.fullmatch(value):
        shown = value[:80] if isinstance(value, str) else type(value).__name__
        raise FormatError(path, where, f"must name a file in the session's images folder (images/NAME.png), "
                                       f"got {shown!r}")
    return value


def capture_from_dict(c, i: int, pattern, projector_size: tuple[int, int], path) -> Capture:
    """The capture record `c` (captures[i] of session.json `path`) of a session with this PatternSpec and
    projector; FormatError naming the field that is wrong."""
    where = f"captures[{i}]."
    cid = _need(c, "id", where, path, str)
    if not CAPTURE_ID_RE.fullmatch(cid):
        raise FormatError(path, f"{where}id", f"must be 1 to 64 letters, digits, '-', '_' or '.' (not "
                          f"starting with '-' or '.'), got {cid[:40]!r}")
    step = _need(c, "step", where, path, str)
    if step not in STEPS:
        raise FormatError(path, f"{where}step", f"must be one of {STEPS}, got '{step}'")
    image = _file(_need(c, "image", where, path, str), f"{where}image", path)
    pos = c.get("pattern_position")
    if pos is not None and not typed(pos, (int,)):
        raise FormatError(path, f"{where}pattern_position", "must be an integer")
    if pos is not None and not 0 <= pos < pattern.positions:
        raise FormatError(path, f"{where}pattern_position",
                          f"is {pos}, the pattern has positions 0..{pattern.positions - 1}")
    placement = c.get("placement")
    if placement is not None and (not typed(placement, (int,)) or placement < 0):
        raise FormatError(path, f"{where}placement", "must be a whole number >= 0")
    spec, frames = _structured(c, where, step, image, path)
    pts = c.get("pattern_points_px")
    if step == STEP_PROJECTOR and pts is None and spec is None:
        raise FormatError(path, f"{where}pattern_points_px", "missing (projector captures need the shown points)")
    if pts is not None:
        pts = _points(pts, f"{where}pattern_points_px", pattern, projector_size, path)
    meta = c.get("meta", {})
    if not isinstance(meta, dict):
        raise FormatError(path, f"{where}meta", "must be an object")
    if "pose_index" in meta and not typed(meta["pose_index"], (int,)):
        raise FormatError(path, f"{where}meta.pose_index", "must be an integer")
    return Capture(cid, step, image, pos, pts, meta, placement, spec, frames)


def _structured(c: dict, where: str, step: str, image: str, path):
    """(StructuredLightSpec, frames) of a structured-light capture record, (None, ()) for another."""
    kind = c.get("pattern_kind")
    if kind is None:
        if "frames" in c or "structured_light" in c:
            raise FormatError(path, f"{where}pattern_kind", f"missing (a capture with frames is "
                                                           f"'{PatternKind.STRUCTURED.value}')")
        return None, ()
    if kind != PatternKind.STRUCTURED.value:
        raise FormatError(path, f"{where}pattern_kind", f"must be '{PatternKind.STRUCTURED.value}' (or absent: the "
                                                       f"session's pattern), got {str(kind)[:40]!r}")
    if step != STEP_PROJECTOR:
        raise FormatError(path, f"{where}pattern_kind", f"a structured-light capture belongs to the "
                                                       f"'{STEP_PROJECTOR}' step, not '{step}'")
    spec = StructuredLightSpec.from_dict(_need(c, "structured_light", where, path), f"{where}structured_light", path)
    raw = _need(c, "frames", where, path, list)
    if not 0 < len(raw) <= MAX_FRAMES:
        raise FormatError(path, f"{where}frames", f"must list 1 to {MAX_FRAMES} frames, got {len(raw)}")
    frames = tuple(_file(f, f"{where}frames[{k}]", path) for k, f in enumerate(raw))
    if len(set(frames)) != len(frames):
        raise FormatError(path, f"{where}frames", "names a file twice")
    if frames[0] != image:
        raise FormatError(path, f"{where}image", "must be the first of its frames (the white frame)")
    return spec, frames


def _points(pts, where: str, pattern, projector_size, path) -> np.ndarray:
    try:
        pts = np.array(pts, float).reshape(-1, 2)
    except (TypeError, ValueError):
        raise FormatError(path, where, "must be a list of [x, y] pairs") from None
    if len(pts) != pattern.n_points:
        raise FormatError(path, where, f"has {len(pts)} points, the pattern has {pattern.n_points}")
    pw, ph = projector_size
    if np.any(np.abs(pts - (pw / 2, ph / 2)) > (1.5 * pw, 1.5 * ph)):
        raise FormatError(path, where, f"has points far outside the {pw}x{ph} projector image")
    return pts
