"""A capture session on disk: a folder with `session.json` and lossless PNG images.

Writes are crash-safe: every image is written (atomically) before the manifest that names it, and the
manifest is replaced atomically, so a killed process leaves either the old or the new manifest, never a
half-written one. An image without a manifest entry is an orphan and is ignored.

session.json (format "procam-session", version 1):
  rig: {camera: {width, height}, projector: {width, height}, view: "mirror"|"direct",
        camera_settings: {...}, driver: "sim"|"realsense"|...}
  projector_board: CharucoSpec dict (its units are the session's); mirror_board: CharucoSpec dict or null, in
    any of the units (converted to the session's on load)
  pattern: PatternSpec dict
  mirror_method: "real-virtual" | "real-mirror" | null; board_thickness: number (board units)
  projector_blank_area: {width, gap} (board units: the projector board's blank area right of its squares,
    as `procam board --blank-area WIDTH:GAP` prints it) or null/absent (not given)
  captures: [{id, step, image, pattern_position?, pattern_points_px?, placement?, meta?}, ...], a
    structured-light capture with pattern_kind, structured_light and frames (calib.formats.session_captures)
  state: object the station uses to resume (current step, position, ...); the types of the fields it
         reads are checked at load (STATE_FIELDS), other keys are kept as they are

Everything in a session folder is untrusted (it may come from someone else): a capture's `image` must
be `images/NAME.png`, and the store never reads, hashes, writes or deletes a file whose path leads out
of the folder (a link in images/ pointing elsewhere is refused for reading; deleting a capture removes
the link, never what it points to). Every file is read through calib.formats.fileio.read_regular (no
link, FIFO or device; a size cap), an image only once its PNG header gives the camera's size
(read_image_file). Non-finite numbers (NaN, Infinity, 1e400) are refused anywhere in
the manifest. A store opened for writing holds the folder's lock (calib.formats.session_lock).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from calib.errors import FormatError, SessionError, UnsafeFileError
from calib.formats import session_files
from calib.formats.fileio import (MANIFEST_MAX_BYTES, atomic_write_bytes, parse_json, read_regular,
                                  remove_stale_temporaries)
from calib.formats.session_captures import IMAGE_RE, Capture, capture_from_dict, typed
from calib.formats.session_lock import SessionLock
from calib.formats.session_lock import acquire as _acquire_lock
from calib.models.boards import CharucoSpec
from calib.models.observations import STEP_PROJECTOR, STEPS, VIEW_DIRECT, VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.models.vocab import MirrorMethod, Step, choices

FORMAT = "procam-session"
VERSION = 1
MANIFEST = session_files.MANIFEST
IMAGES_DIR = session_files.IMAGES_DIR
MIRROR_METHODS = choices(MirrorMethod)
MAX_IMAGE_SIDE = 100_000  # pixels: a width or height above this is a corrupt field, not a camera
#: the top-level keys of session.json; another key (from a newer program) may hold at most UNKNOWN_MAX_BYTES
MANIFEST_KEYS = ("format", "version", "rig", "projector_board", "mirror_board", "pattern", "mirror_method",
                 "board_thickness", "projector_blank_area", "captures", "state")
UNKNOWN_MAX_BYTES = 64 * 1024
#: the most frames a mirror placement may average (Plan.mirror_frames)
MAX_MIRROR_FRAMES = 64

_NUMBER = (int, float)
#: the `state` fields the station reads on resume, with their types (None: may be null); other keys are kept
STATE_FIELDS = {
    "step": (str,), "pattern_position": (int, None), "pose_index": (int, None), "target": (dict, None),
    "retake": (dict, None), "mirror_method": (str, None), "camera_intrinsics": (str, None), "plan": (dict, None),
    "calibrated": (bool,), "result_stale": (bool,), "verified": (bool, None), "updated_unix_s": (*_NUMBER, None),
    "rig_request": (dict, None), "method": (str, None), "simulated": (bool,), "scenario": (str, None),
    "seed": (int, None),
}
_TARGET_FIELDS = {"step": (str,), "pattern_position": (int, None), "pose_index": (int,)}
_RIG_REQUEST_FIELDS = {"kind": (str,), "scenario": (str,), "seed": (int,), "quality": (str,)}


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
class SessionManifest:
    rig: RigInfo
    projector_board: CharucoSpec
    pattern: PatternSpec
    mirror_board: CharucoSpec | None = None
    mirror_method: str | None = None
    board_thickness: float = 0.0
    captures: tuple[Capture, ...] = ()
    state: dict = field(default_factory=dict)
    #: (width, gap) of the projector board's blank area in board units; None: not given
    blank_area: tuple[float, float] | None = None

    def __post_init__(self):
        # Every length of a session is in the projector board's units (the units of the result): a mirror
        # board declared in other units is the same physical board, so its lengths are converted, never
        # read as numbers in the session's units.
        if self.mirror_board is not None and self.mirror_board.units != self.projector_board.units:
            object.__setattr__(self, "mirror_board", self.mirror_board.in_units(self.projector_board.units))

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
            "projector_blank_area": None if self.blank_area is None else
            {"width": float(self.blank_area[0]), "gap": float(self.blank_area[1])},
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
        _check_unknown_bulk(d, path)
        bad = _non_finite(d)
        if bad is not None:
            raise FormatError(path, bad[0], f"is not a finite number ({bad[1]})")
        if need(d, "version", "", int) > VERSION:
            raise FormatError(path, "version", f"is newer ({d['version']}) than this program reads ({VERSION})")
        rig = need(d, "rig", "", dict)
        cam = need(rig, "camera", "rig.", dict)
        proj = need(rig, "projector", "rig.", dict)
        sizes = []
        for obj, where in ((cam, "rig.camera."), (proj, "rig.projector.")):
            w, h = need(obj, "width", where, int), need(obj, "height", where, int)
            if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
                raise FormatError(path, f"{where}width",
                                  f"width and height must be positive (at most {MAX_IMAGE_SIDE} pixels)")
            sizes.append((w, h))
        view = need(rig, "view", "rig.", str)
        if view not in (VIEW_MIRROR, VIEW_DIRECT):
            raise FormatError(path, "rig.view", f"must be '{VIEW_MIRROR}' or '{VIEW_DIRECT}', got '{view}'")
        settings = rig.get("camera_settings", {}) or {}
        if not isinstance(settings, dict):
            raise FormatError(path, "rig.camera_settings", "must be an object")
        driver = rig.get("driver", "unknown")
        if not isinstance(driver, str):
            raise FormatError(path, "rig.driver", f"has the wrong type ({type(driver).__name__})")
        rig_info = RigInfo(sizes[0], sizes[1], view, settings, driver)
        pboard = CharucoSpec.from_dict(need(d, "projector_board", ""), "projector_board", path)
        mb = d.get("mirror_board")
        mboard = None if mb is None else CharucoSpec.from_dict(mb, "mirror_board", path)
        pattern = PatternSpec.from_dict(need(d, "pattern", ""), "pattern", path)
        ew, eh = pattern.extent_px()
        if ew > sizes[1][0] or eh > sizes[1][1]:
            raise FormatError(path, "pattern.spacing_px", f"a {pattern.cols}x{pattern.rows} pattern with spacing "
                              f"{pattern.spacing_px:g} px spans {ew:.0f}x{eh:.0f} px, more than the "
                              f"{sizes[1][0]}x{sizes[1][1]} projector image")
        method = d.get("mirror_method")
        if method is not None and method not in MIRROR_METHODS:
            raise FormatError(path, "mirror_method", f"must be one of {MIRROR_METHODS} or null, got '{method}'")
        thickness = d.get("board_thickness", 0.0)
        if not isinstance(thickness, (int, float)) or isinstance(thickness, bool) or thickness < 0:
            raise FormatError(path, "board_thickness", "must be a number >= 0 (board units)")
        blank = _blank_area(d.get("projector_blank_area"), path)
        caps = need(d, "captures", "", list)
        captures, seen = [], set()
        for i, c in enumerate(caps):
            cap = capture_from_dict(c, i, pattern, sizes[1], path)
            if cap.id in seen:
                raise FormatError(path, f"captures[{i}].id", f"duplicate capture id '{cap.id}'")
            seen.add(cap.id)
            captures.append(cap)
        state = d.get("state")
        state = {} if state is None else state
        _check_state(state, path)
        return cls(rig_info, pboard, pattern, mboard, method, float(thickness), tuple(captures), state, blank)


def _blank_area(v, path) -> tuple[float, float] | None:
    """session.json's projector_blank_area: null/absent, or {width > 0, gap >= 0} in board units."""
    if v is None:
        return None
    if not isinstance(v, dict):
        raise FormatError(path, "projector_blank_area", "must be an object {width, gap} (board units) or null")
    out = []
    for key, least in (("width", 0.0), ("gap", 0.0)):
        x = v.get(key)
        if not isinstance(x, (int, float)) or isinstance(x, bool) or x < least or (key == "width" and x == 0):
            raise FormatError(path, f"projector_blank_area.{key}",
                              f"must be a number {'> 0' if key == 'width' else '>= 0'} (board units)")
        out.append(float(x))
    return out[0], out[1]


_TYPE_WORDS = {str: "a string", int: "an integer", float: "a number", bool: "true or false", dict: "an object",
               None: "null"}


def _check_fields(obj: dict, fields: dict, where: str, path) -> None:
    for key, types in fields.items():
        if key in obj and not typed(obj[key], types):
            names = " or ".join(_TYPE_WORDS[t] for t in types if not (t is int and float in types))
            raise FormatError(path, f"{where}{key}", f"must be {names}, got {json.dumps(obj[key])[:40]}")


def _check_state(state, path) -> None:
    """FormatError naming `state.<field>` when a field the station reads on resume has the wrong type."""
    if not isinstance(state, dict):
        raise FormatError(path, "state", "must be an object")
    _check_fields(state, STATE_FIELDS, "state.", path)
    for key in ("target", "retake"):
        if isinstance(state.get(key), dict):
            _check_fields(state[key], _TARGET_FIELDS, f"state.{key}.", path)
            if state[key].get("step") not in STEPS:
                raise FormatError(path, f"state.{key}.step", f"must be one of {STEPS}")
    if state.get("mirror_method") is not None and state["mirror_method"] not in MIRROR_METHODS:
        raise FormatError(path, "state.mirror_method", f"must be one of {MIRROR_METHODS} or null")
    if isinstance(state.get("rig_request"), dict):
        _check_fields(state["rig_request"], _RIG_REQUEST_FIELDS, "state.rig_request.", path)
    for key, value in (state.get("plan") or {}).items():
        if key in ("stop_on_confidence", "next_best", "ask_pose"):  # the plan's switches (app.station.plan.Plan)
            if not isinstance(value, bool):
                raise FormatError(path, f"state.plan.{key}", "must be true or false")
            continue
        if not typed(value, (int,)) or value < 0 or (key == "poses_per_position" and value < 1):
            raise FormatError(path, f"state.plan.{key}", "must be a whole number >= 0 (poses_per_position >= 1)")
        if key == "mirror_frames" and not 1 <= value <= MAX_MIRROR_FRAMES:
            raise FormatError(path, "state.plan.mirror_frames", f"must be 1 to {MAX_MIRROR_FRAMES} (frames per mirror placement)")


def _check_unknown_bulk(d: dict, path) -> None:
    """FormatError naming a top-level key this program does not know that holds more than a note: it is
    not read, and it is not written back, but checking and parsing it would cost time and memory."""
    for key in d.keys() - set(MANIFEST_KEYS):
        try:
            size = len(json.dumps(d[key]))
        except (RecursionError, ValueError):
            size = UNKNOWN_MAX_BYTES + 1
        if size > UNKNOWN_MAX_BYTES:
            raise FormatError(path, str(key)[:80], f"is not a field of a session and holds {size} bytes (more than "
                                                   f"{UNKNOWN_MAX_BYTES}); remove it")


def _non_finite(data) -> tuple[str, str] | None:
    """(field, value) of the first NaN or infinite number in parsed JSON (1e400 parses as infinity). A
    field's name is spelt out only for the one found: building every name as it goes would cost the
    nesting depth at every value, quadratic in deeply nested junk."""
    todo = [(None, data)]  # (the (parent, key) it is under, value)
    while todo:
        where, v = todo.pop()
        if isinstance(v, float) and not math.isfinite(v):
            return _field_name(where), str(v)
        if isinstance(v, dict):
            todo.extend(((where, k), x) for k, x in reversed(v.items()))
        elif isinstance(v, list):
            todo.extend(((where, i), x) for i, x in reversed(list(enumerate(v))))
    return None


def _field_name(where) -> str:
    parts = []
    while where is not None:
        where, key = where
        parts.append(f"[{key}]" if isinstance(key, int) else f".{key}")
    return "".join(reversed(parts)).lstrip(".")


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
    """A session folder. Every mutation writes its image(s) first, then the manifest, atomically; the
    in-memory manifest changes only once the write succeeded.

    A store that writes holds the folder's lock (calib.formats.session_lock): `create` and `open(lock=True)` take
    it at once, a store opened to read takes it at its first write (and refuses to write if session.json
    changed on disk since it was read). `close()` (or the end of a `with` block) gives it back."""

    def __init__(self, folder: Path, manifest: SessionManifest, lock: SessionLock | None = None,
                 manifest_sha1: str | None = None):
        self.folder = Path(folder)
        self._manifest = manifest
        self._lock = lock
        self._disk_sha1 = manifest_sha1  # of the session.json this store read or last wrote

    @property
    def manifest(self) -> SessionManifest:
        return self._manifest

    @property
    def locked(self) -> bool:
        return self._lock is not None and self._lock.held

    def close(self) -> None:
        """Give back the folder's lock (the store can still be read)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> "SessionStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @classmethod
    def create(cls, folder, manifest: SessionManifest, exist_ok: bool = False) -> "SessionStore":
        """A new session in `folder` (created if needed), locked for this process."""
        folder = Path(folder)
        if os.path.lexists(folder / MANIFEST) and not exist_ok:
            raise SessionError(f"{folder} already holds a session; resume it or choose another folder")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise SessionError(f"cannot create the session folder {folder} ({e.strerror})") from None
        held = _lock(folder)
        try:
            if os.path.lexists(folder / MANIFEST) and not exist_ok:  # again, now that this process holds the folder
                raise SessionError(f"{folder} already holds a session; resume it or choose another folder")
            store = cls(folder, manifest, held)
            store._images_dir()
            store._write_manifest(manifest)
        except BaseException:
            held.release()
            raise
        return store

    @classmethod
    def open(cls, folder, lock: bool = False) -> "SessionStore":
        """Open a session folder: to read, or with `lock=True` to write (SessionError when another process
        has it open for writing)."""
        folder = Path(folder)
        path = folder / MANIFEST
        if not folder.is_dir():
            raise SessionError(f"session folder {folder} does not exist")
        if not os.path.lexists(path):
            raise SessionError(f"{folder} is not a session: it has no {MANIFEST}")
        held = _lock(folder) if lock else None
        try:
            raw = _read_manifest_bytes(path)
            return cls(folder, SessionManifest.from_dict(parse_json(raw, path), path), held,
                       hashlib.sha1(raw).hexdigest())
        except BaseException:
            if held is not None:
                held.release()
            raise

    # ---- writing --------------------------------------------------------------------------------
    def _ensure_lock(self) -> None:
        """Hold the folder's lock before writing; a store opened to read takes it now, and writes only if
        session.json is still the one it read (another program may have written it since)."""
        if self.locked:
            return
        held = _lock(self.folder)
        try:
            raw = _read_manifest_bytes(self.folder / MANIFEST) if os.path.lexists(self.folder / MANIFEST) else b""
        except BaseException:
            held.release()
            raise
        if self._disk_sha1 is not None and hashlib.sha1(raw).hexdigest() != self._disk_sha1:
            held.release()
            raise SessionError(f"{self.folder / MANIFEST} changed since this program read it (another program "
                               f"wrote it): open the session again")
        self._lock = held

    def _write_manifest(self, manifest: SessionManifest) -> None:
        """Write `manifest` (atomically), then make it this store's manifest."""
        self._ensure_lock()
        data = (json.dumps(manifest.to_dict(), indent=1) + "\n").encode("utf-8")
        atomic_write_bytes(self.folder / MANIFEST, data)
        self._disk_sha1 = hashlib.sha1(data).hexdigest()
        self._manifest = manifest

    def update(self, **changes) -> None:
        """Replace manifest fields (rig, state, mirror_method, ...) and write the manifest."""
        self._write_manifest(replace(self._manifest, **changes))

    def _images_dir(self) -> Path:
        """The images folder (created if missing); SessionError if it is a link leading out of the folder."""
        d = self.folder / IMAGES_DIR
        if not d.is_symlink() and not d.exists():
            try:
                d.mkdir()
            except OSError as e:
                raise SessionError(f"cannot create {d} ({e.strerror})") from None
        if not self._inside(d):
            raise SessionError(f"{d} leads out of the session folder (a link): captures are written only inside it")
        if not d.is_dir():
            raise SessionError(f"{d} is not a folder")
        return d

    def next_id(self, step: str, structured: bool = False) -> str:
        prefix = "s" if structured else {Step.PROJECTOR: "p", Step.REAL_VIRTUAL: "mrv", Step.REAL_MIRROR: "mrm"}[step]
        used = [int(m.group(1)) for c in self._manifest.captures if (m := re.fullmatch(prefix + r"(\d+)", c.id))]
        # a structured capture's frames are ID-fNN.png
        taken = {p.stem.split("-f")[0] for p in (self.folder / IMAGES_DIR).glob(prefix + "*.png")}
        n = max(used, default=-1) + 1
        while f"{prefix}{n:04d}" in taken:  # never overwrite an orphan image of a crashed write
            n += 1
        return f"{prefix}{n:04d}"

    def _write_png(self, cid: str, rel: str, image: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", _storage_form(image))
        if not ok:
            raise SessionError(f"could not encode capture {cid} as PNG")
        atomic_write_bytes(self.folder / rel, buf.tobytes())

    def add_capture(self, step: str, image: np.ndarray, pattern_position: int | None = None,
                    pattern_points_px: np.ndarray | None = None, meta: dict | None = None,
                    placement: int | None = None) -> Capture:
        """Write the image, then the manifest naming it. Returns the capture once both are on disk."""
        self._ensure_lock()
        self._images_dir()
        cid = self.next_id(step)
        rel = f"{IMAGES_DIR}/{cid}.png"
        self._write_png(cid, rel, image)
        cap = Capture(cid, step, rel, pattern_position,
                      None if pattern_points_px is None else np.asarray(pattern_points_px, float), meta or {},
                      placement)
        self._write_manifest(replace(self._manifest, captures=self._manifest.captures + (cap,)))
        return cap

    def add_structured_capture(self, images, spec, placement: int | None = None,
                               meta: dict | None = None) -> Capture:
        """A structured-light projector capture (calib.models.structured_light.StructuredLightSpec `spec`):
        every frame of `images` written first, then the manifest naming them."""
        self._ensure_lock()
        self._images_dir()
        cid = self.next_id(STEP_PROJECTOR, structured=True)
        frames = tuple(f"{IMAGES_DIR}/{cid}-f{k:02d}.png" for k in range(len(images)))
        for rel, image in zip(frames, images, strict=True):
            self._write_png(cid, rel, image)
        cap = Capture(cid, STEP_PROJECTOR, frames[0], meta=meta or {}, placement=placement, structured_light=spec,
                      frames=frames)
        self._write_manifest(replace(self._manifest, captures=self._manifest.captures + (cap,)))
        return cap

    def delete_capture(self, capture_id: str) -> None:
        """Drop a capture from the manifest (first), then remove its image file. Only a file directly in
        the session's own images folder is removed; a link there is removed itself, never what it points to."""
        caps = self._manifest.captures
        match = [c for c in caps if c.id == capture_id]
        if not match:
            raise SessionError(f"no capture '{capture_id}' in this session")
        self._write_manifest(replace(self._manifest, captures=tuple(c for c in caps if c.id != capture_id)))
        d = self.folder / IMAGES_DIR
        for rel in match[0].frames or (match[0].image,):
            if not IMAGE_RE.fullmatch(rel) or not self._inside(d):
                continue  # not a file of this folder's own images folder: left alone
            try:
                os.unlink(self.folder / rel)  # unlink never follows a link
            except (FileNotFoundError, IsADirectoryError, PermissionError):
                pass

    # ---- reading --------------------------------------------------------------------------------
    def _inside(self, path: Path) -> bool:
        """`path`, with every link followed, is inside the session folder."""
        try:
            return Path(path).resolve().is_relative_to(self.folder.resolve())
        except (OSError, RuntimeError):  # a link loop
            return False

    def image_path(self, capture: Capture) -> Path:
        """The capture's image file; SessionError when its path, links followed, leads out of the session
        folder (said the same whether or not anything exists there)."""
        return self.file_path(capture, capture.image)

    def file_path(self, capture: Capture, rel: str) -> Path:
        """File `rel` (its image or one of its frames) of `capture`, checked as image_path checks."""
        if not IMAGE_RE.fullmatch(rel):
            raise SessionError(f"capture '{capture.id}': image path {rel[:80]!r} is not in the session's "
                               f"images folder; refused")
        path = self.folder / rel
        if not self._inside(path):
            raise SessionError(f"capture '{capture.id}': image {rel} is a link leading out of the session "
                               f"folder; refused")
        return path

    def read_image_bytes(self, capture: Capture) -> bytes:
        """A capture's PNG file, checked before it is decoded (read_image_file); SessionError naming the
        file when it is missing, not a plain file, too large or not the session camera's size."""
        path = self.image_path(capture)
        try:
            return read_image_file(path, self._manifest.rig.camera_size)
        except FileNotFoundError:
            raise SessionError(f"image {path} of capture '{capture.id}' is missing") from None

    def load_image(self, capture: Capture, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
        """Read a capture's image; SessionError naming the file when it is missing or unreadable."""
        data = self.read_image_bytes(capture)
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
        if img is None:
            raise SessionError(f"image {self.folder / capture.image} of capture '{capture.id}' cannot be decoded")
        return img


#: a PNG file starts with this signature, then its IHDR chunk: length, "IHDR", width, height (big-endian)
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def image_max_bytes(camera_size: tuple[int, int]) -> int:
    """The largest PNG file a capture of this camera can be: 16-bit RGBA stored uncompressed (8 bytes a
    pixel), one filter byte a row and the zlib and chunk overheads, with a megabyte to spare."""
    w, h = camera_size
    return 8 * w * h + h + 2**20


def png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG file's header, or None when `data` does not start like a PNG file."""
    if len(data) < 24 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def read_image_file(path, camera_size: tuple[int, int]) -> bytes:
    """The bytes of a capture image `path` of a camera of `camera_size`: a regular file (no link, FIFO or
    device), no larger than such a PNG can be, whose PNG header gives the camera's size; so nothing is
    decoded into more memory than the camera's image. UnsafeFileError otherwise (FileNotFoundError when
    it is absent)."""
    data = read_regular(path, image_max_bytes(camera_size), "image")
    problem = image_header_problem(data, camera_size, path)
    if problem is not None:
        raise UnsafeFileError(problem if problem.startswith("image unreadable") else f"{problem} ({path})")
    return data


def image_header_problem(data, camera_size: tuple[int, int], path) -> str | None:
    """Why the bytes `data` of image file `path` cannot be a capture of a camera of `camera_size` (not a
    PNG, another size), from the header alone; None when they can."""
    size = png_size(bytes(data[:24]))
    if size is None:
        return f"image unreadable: {path} is not a PNG file"
    if size != tuple(camera_size):
        return f"image is {size[0]}x{size[1]}, the session's camera is {camera_size[0]}x{camera_size[1]}"
    return None


def _lock(folder: Path) -> SessionLock:
    """Take the folder's lock and remove what writers of the folder killed while writing left behind
    (temporary files of session.json and of images)."""
    held = _acquire_lock(folder)
    remove_stale_temporaries(folder, (MANIFEST,))
    if not os.path.islink(folder / IMAGES_DIR):
        remove_stale_temporaries(folder / IMAGES_DIR)
    return held


def _read_manifest_bytes(path: Path) -> bytes:
    try:
        return read_regular(path, MANIFEST_MAX_BYTES, "session manifest")
    except FileNotFoundError:
        raise SessionError(f"{path.parent} is not a session: it has no {MANIFEST}") from None


def read_manifest_json(folder):
    """The parsed session.json of `folder` (read as read_regular reads, not checked as a manifest):
    UnsafeFileError, SessionError or FormatError when it cannot be read as JSON."""
    path = Path(folder) / MANIFEST
    return parse_json(_read_manifest_bytes(path), path)

