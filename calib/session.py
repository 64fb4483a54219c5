"""A capture session on disk: a folder with `session.json` and lossless PNG images.

Writes are crash-safe: every image is written (atomically) before the manifest that names it, and the
manifest is replaced atomically, so a killed process leaves either the old or the new manifest, never a
half-written one. An image without a manifest entry is an orphan and is ignored.

session.json (format "procam-session", version 1):
  rig: {camera: {width, height}, projector: {width, height}, view: "mirror"|"direct",
        camera_settings: {...}, driver: "sim"|"realsense"|...}
  projector_board: CharucoSpec dict; mirror_board: CharucoSpec dict or null
  pattern: PatternSpec dict
  mirror_method: "real-virtual" | "real-mirror" | null; board_thickness: number (board units)
  captures: [{id, step, image, pattern_position?, pattern_points_px?, meta?}, ...]
  state: free-form object the station uses to resume (current step, position, ...)
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from calib.boards import CharucoSpec
from calib.errors import FormatError, SessionError
from calib.fileio import atomic_write_bytes, atomic_write_text
from calib.observations import STEP_PROJECTOR, STEPS, VIEW_DIRECT, VIEW_MIRROR
from calib.pattern import PatternSpec

FORMAT = "procam-session"
VERSION = 1
MANIFEST = "session.json"
IMAGES_DIR = "images"
MIRROR_METHODS = ("real-virtual", "real-mirror")


@dataclass(frozen=True)
class RigInfo:
    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    view: str = VIEW_MIRROR
    camera_settings: dict = field(default_factory=dict)
    driver: str = "unknown"

    def to_dict(self) -> dict:
        return {
            "camera": {"width": self.camera_size[0], "height": self.camera_size[1]},
            "projector": {"width": self.projector_size[0], "height": self.projector_size[1]},
            "view": self.view,
            "camera_settings": self.camera_settings,
            "driver": self.driver,
        }


@dataclass(frozen=True, eq=False)
class Capture:
    id: str
    step: str
    image: str  # path relative to the session folder
    pattern_position: int | None = None
    pattern_points_px: np.ndarray | None = None  # projector pixels of the shown pattern points
    meta: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {"id": self.id, "step": self.step, "image": self.image}
        if self.pattern_position is not None:
            d["pattern_position"] = int(self.pattern_position)
        if self.pattern_points_px is not None:
            d["pattern_points_px"] = np.asarray(self.pattern_points_px, float).tolist()
        if self.meta:
            d["meta"] = self.meta
        return d


@dataclass(frozen=True, eq=False)
class SessionManifest:
    rig: RigInfo
    projector_board: CharucoSpec
    pattern: PatternSpec
    mirror_board: CharucoSpec | None = None
    mirror_method: str | None = None
    board_thickness: float = 0.0
    captures: tuple[Capture, ...] = ()
    state: dict = field(default_factory=dict)

    @property
    def units(self) -> str:
        return self.projector_board.units

    def captures_of(self, step: str) -> list[Capture]:
        return [c for c in self.captures if c.step == step]

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "rig": self.rig.to_dict(),
            "projector_board": self.projector_board.to_dict(),
            "mirror_board": None if self.mirror_board is None else self.mirror_board.to_dict(),
            "pattern": self.pattern.to_dict(),
            "mirror_method": self.mirror_method,
            "board_thickness": self.board_thickness,
            "captures": [c.to_dict() for c in self.captures],
            "state": self.state,
        }

    @classmethod
    def from_dict(cls, d, path="<dict>") -> "SessionManifest":
        def need(obj, key, where, typ=None):
            if not isinstance(obj, dict) or key not in obj:
                raise FormatError(path, f"{where}{key}", "missing")
            v = obj[key]
            if typ is not None and (not isinstance(v, typ) or isinstance(v, bool)):
                raise FormatError(path, f"{where}{key}", f"has the wrong type ({type(v).__name__})")
            return v

        if not isinstance(d, dict):
            raise FormatError(path, "<root>", "must be a JSON object")
        if d.get("format") != FORMAT:
            raise FormatError(path, "format", f"must be '{FORMAT}'")
        if need(d, "version", "", int) > VERSION:
            raise FormatError(path, "version", f"is newer ({d['version']}) than this program reads ({VERSION})")
        rig = need(d, "rig", "", dict)
        cam = need(rig, "camera", "rig.", dict)
        proj = need(rig, "projector", "rig.", dict)
        sizes = []
        for obj, where in ((cam, "rig.camera."), (proj, "rig.projector.")):
            w, h = need(obj, "width", where, int), need(obj, "height", where, int)
            if w <= 0 or h <= 0:
                raise FormatError(path, f"{where}width", "width and height must be positive")
            sizes.append((w, h))
        view = need(rig, "view", "rig.", str)
        if view not in (VIEW_MIRROR, VIEW_DIRECT):
            raise FormatError(path, "rig.view", f"must be '{VIEW_MIRROR}' or '{VIEW_DIRECT}', got '{view}'")
        rig_info = RigInfo(sizes[0], sizes[1], view, rig.get("camera_settings", {}) or {}, rig.get("driver", "unknown"))
        pboard = CharucoSpec.from_dict(need(d, "projector_board", ""), "projector_board", path)
        mb = d.get("mirror_board")
        mboard = None if mb is None else CharucoSpec.from_dict(mb, "mirror_board", path)
        pattern = PatternSpec.from_dict(need(d, "pattern", ""), "pattern", path)
        method = d.get("mirror_method")
        if method is not None and method not in MIRROR_METHODS:
            raise FormatError(path, "mirror_method", f"must be one of {MIRROR_METHODS} or null, got '{method}'")
        thickness = d.get("board_thickness", 0.0)
        if not isinstance(thickness, (int, float)) or isinstance(thickness, bool) or thickness < 0:
            raise FormatError(path, "board_thickness", "must be a number >= 0 (board units)")
        caps = need(d, "captures", "", list)
        captures, seen = [], set()
        for i, c in enumerate(caps):
            where = f"captures[{i}]."
            cid = need(c, "id", where, str)
            if cid in seen:
                raise FormatError(path, f"{where}id", f"duplicate capture id '{cid}'")
            seen.add(cid)
            step = need(c, "step", where, str)
            if step not in STEPS:
                raise FormatError(path, f"{where}step", f"must be one of {STEPS}, got '{step}'")
            image = need(c, "image", where, str)
            pos = c.get("pattern_position")
            if pos is not None and (not isinstance(pos, int) or isinstance(pos, bool)):
                raise FormatError(path, f"{where}pattern_position", "must be an integer")
            pts = c.get("pattern_points_px")
            if step == STEP_PROJECTOR and pts is None:
                raise FormatError(path, f"{where}pattern_points_px", "missing (projector captures need the shown points)")
            if pts is not None:
                try:
                    pts = np.array(pts, float).reshape(-1, 2)
                except (TypeError, ValueError):
                    raise FormatError(path, f"{where}pattern_points_px", "must be a list of [x, y] pairs") from None
                if len(pts) != pattern.n_points:
                    raise FormatError(path, f"{where}pattern_points_px",
                                      f"has {len(pts)} points, the pattern has {pattern.n_points}")
            meta = c.get("meta", {})
            if not isinstance(meta, dict):
                raise FormatError(path, f"{where}meta", "must be an object")
            captures.append(Capture(cid, step, image, pos, pts, meta))
        state = d.get("state", {}) or {}
        return cls(rig_info, pboard, pattern, mboard, method, float(thickness), tuple(captures), state)


def _storage_form(image: np.ndarray) -> np.ndarray:
    """The array a capture is stored as: a 3-channel image whose channels are all equal (a monochrome
    camera, the simulator) is stored with one channel. Lossless (cv2.IMREAD_COLOR reads it back as the
    same 3 equal channels); the PNG is a third of the size and decodes about twice as fast, which is
    most of the cost of reading a session."""
    if image.ndim == 3 and image.shape[2] == 3 and np.array_equal(image[..., 0], image[..., 1]) \
            and np.array_equal(image[..., 1], image[..., 2]):
        return np.ascontiguousarray(image[..., 0])
    return image


class SessionStore:
    """A session folder. Every mutation writes its image(s) first, then the manifest, atomically."""

    def __init__(self, folder: Path, manifest: SessionManifest):
        self.folder = Path(folder)
        self._manifest = manifest

    @property
    def manifest(self) -> SessionManifest:
        return self._manifest

    @classmethod
    def create(cls, folder, manifest: SessionManifest, exist_ok: bool = False) -> "SessionStore":
        folder = Path(folder)
        if (folder / MANIFEST).exists() and not exist_ok:
            raise SessionError(f"{folder} already holds a session; resume it or choose another folder")
        (folder / IMAGES_DIR).mkdir(parents=True, exist_ok=True)
        store = cls(folder, manifest)
        store._write_manifest()
        return store

    @classmethod
    def open(cls, folder) -> "SessionStore":
        folder = Path(folder)
        path = folder / MANIFEST
        if not folder.is_dir():
            raise SessionError(f"session folder {folder} does not exist")
        if not path.exists():
            raise SessionError(f"{folder} is not a session: it has no {MANIFEST}")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(path, "<file>", f"is not valid JSON (line {e.lineno}: {e.msg})") from None
        return cls(folder, SessionManifest.from_dict(data, path))

    def _write_manifest(self) -> None:
        atomic_write_text(self.folder / MANIFEST, json.dumps(self._manifest.to_dict(), indent=1) + "\n")

    def update(self, **changes) -> None:
        """Replace manifest fields (rig, state, mirror_method, ...) and write the manifest."""
        self._manifest = replace(self._manifest, **changes)
        self._write_manifest()

    def next_id(self, step: str) -> str:
        prefix = {"projector": "p", "mirror-real-virtual": "mrv", "mirror-real-mirror": "mrm"}[step]
        used = [int(m.group(1)) for c in self._manifest.captures if (m := re.fullmatch(prefix + r"(\d+)", c.id))]
        taken = {p.stem for p in (self.folder / IMAGES_DIR).glob(prefix + "*.png")}
        n = max(used, default=-1) + 1
        while f"{prefix}{n:04d}" in taken:  # never overwrite an orphan image of a crashed write
            n += 1
        return f"{prefix}{n:04d}"

    def add_capture(self, step: str, image: np.ndarray, pattern_position: int | None = None,
                    pattern_points_px: np.ndarray | None = None, meta: dict | None = None) -> Capture:
        """Write the image, then the manifest naming it. Returns the capture once both are on disk."""
        cid = self.next_id(step)
        rel = f"{IMAGES_DIR}/{cid}.png"
        ok, buf = cv2.imencode(".png", _storage_form(image))
        if not ok:
            raise SessionError(f"could not encode capture {cid} as PNG")
        atomic_write_bytes(self.folder / rel, buf.tobytes())
        cap = Capture(cid, step, rel, pattern_position,
                      None if pattern_points_px is None else np.asarray(pattern_points_px, float), meta or {})
        self._manifest = replace(self._manifest, captures=self._manifest.captures + (cap,))
        self._write_manifest()
        return cap

    def delete_capture(self, capture_id: str) -> None:
        """Drop a capture from the manifest (first), then remove its image file."""
        caps = self._manifest.captures
        match = [c for c in caps if c.id == capture_id]
        if not match:
            raise SessionError(f"no capture '{capture_id}' in this session")
        self._manifest = replace(self._manifest, captures=tuple(c for c in caps if c.id != capture_id))
        self._write_manifest()
        try:
            (self.folder / match[0].image).unlink()
        except FileNotFoundError:
            pass

    def image_path(self, capture: Capture) -> Path:
        return self.folder / capture.image

    def load_image(self, capture: Capture, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
        """Read a capture's image; SessionError naming the file when it is missing or unreadable."""
        path = self.image_path(capture)
        if not path.exists():
            raise SessionError(f"image {path} of capture '{capture.id}' is missing")
        img = cv2.imread(str(path), flags)
        if img is None:
            raise SessionError(f"image {path} of capture '{capture.id}' cannot be decoded")
        return img
