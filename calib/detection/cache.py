"""The detection stage's results kept in the session folder (`detections.json`), so that a session is
decoded and detected once: calibrating it again (another method, another camera model, after a
retake) detects only the captures that are new or changed.

An entry is used only when all of these still hold; otherwise that capture is detected again:
- the detector is the same: the SHA-1 of the detection modules' source (`_DETECTION_MODULES`:
  detect, cache, response, boards, pattern, observations) and OpenCV's version (`detector_fingerprint`; any
  change to that code invalidates every entry);
- the image is the same: the SHA-1 of the PNG file's bytes;
- the job is the same: step, mirrored or not, board and pattern specs, camera size (`job_key`);
- this installation wrote it: each entry carries an HMAC-SHA256 (`mac`) over its capture id and
  content, keyed with a random secret created once for this user (`installation_key`), so a forged or
  edited entry (or one from another machine) is detected again, with one warning;
- what it holds fits the capture: result kind for the capture's step, ids in the board's range, as many
  pattern points as the pattern has, pixels inside the image (`decode_result`).

Images are hashed from the bytes calib.detection.session_jobs read through SessionStore.image_path, which refuses a
path leading out of the session folder; the cache file itself is read only when it is a plain file in
the folder (a link is ignored with a warning, never followed).

The file is a cache, not a record: a missing, unreadable or malformed one is ignored (with a warning
naming the problem) and rewritten; it is written atomically (calib.formats.fileio) and only holds detection
results, so deleting it loses nothing. Layout: docs/FORMATS.md.
"""

from __future__ import annotations

import hashlib
import hmac
import importlib.util
import json
import os
import secrets
import stat
import warnings
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from calib.errors import SessionError
from calib.formats import session_files
from calib.formats.fileio import RESULT_MAX_BYTES, atomic_write_text, read_regular
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL, BoardObservation, DetectionFailure, MirrorView

CACHE_FILE = session_files.DETECTIONS
FORMAT = "procam-detections"
VERSION = 1
#: the environment variable naming the key file (tests point it at a temporary folder)
KEY_ENV = "PROCAM_CACHE_KEY_FILE"
_KEY_BYTES = 32


#: the modules whose code decides what detection returns (their source is fingerprinted), by dotted
#: name so that the file is found wherever the module lives
_DETECTION_MODULES = ("calib.detection.charuco", "calib.detection.pattern", "calib.detection.mirror_views",
                      "calib.detection.session_jobs", "calib.detection.imaging", "calib.detection.cache",
                      "calib.detection.response", "calib.models.boards", "calib.models.pattern",
                      "calib.models.observations")


@lru_cache(maxsize=1)
def detector_fingerprint() -> str:
    """Identifies the detection code: SHA-1 of the sources of _DETECTION_MODULES and OpenCV's version."""
    h = hashlib.sha1(cv2.__version__.encode())
    for name in _DETECTION_MODULES:
        h.update(Path(importlib.util.find_spec(name).origin).read_bytes())
    return h.hexdigest()


def job_key(step: str, mirrored: bool, board, pattern, camera_size, response=None) -> str:
    """What a capture's detection depends on besides its image and the detector (`response`: the
    camera's recorded tone curve, calib.detection.response; absent from the key when not recorded)."""
    spec = {"step": step, "mirrored": bool(mirrored), "board": board.to_dict(),
            "pattern": None if pattern is None else pattern.to_dict(), "camera_size": list(camera_size)}
    if response is not None:
        spec["response"] = response.to_dict()
    return hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()


def image_digest(data) -> str:
    """SHA-1 of an image file's bytes (hashlib releases the GIL: digests run in parallel threads)."""
    return hashlib.sha1(memoryview(np.ascontiguousarray(data))).hexdigest()


# ---- this installation's key ------------------------------------------------------------------------
def key_path() -> Path:
    """Where the cache key lives: $PROCAM_CACHE_KEY_FILE, else procam-station/cache.key in the user's
    config folder ($XDG_CONFIG_HOME, default ~/.config)."""
    if os.environ.get(KEY_ENV):
        return Path(os.environ[KEY_ENV])
    base = os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config"
    return Path(base) / "procam-station" / "cache.key"


def installation_key() -> bytes:
    """The secret that signs this installation's cache entries, created (random, mode 0600) on first use."""
    return _key_at(str(key_path()))


@lru_cache(maxsize=4)
def _key_at(path: str) -> bytes:
    try:
        if not os.path.lexists(path):
            _create_key(Path(path))
        return _read_key(path)
    except (OSError, ValueError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        warnings.warn(f"the detection cache key {path} is unusable ({why}); detections are kept for this run "
                      f"only: delete or fix that file (or set {KEY_ENV})", RuntimeWarning, stacklevel=4)
        return secrets.token_bytes(_KEY_BYTES)


def _create_key(path: Path) -> None:
    """Write a new key without ever replacing one: a private temporary file, then a hard link to the
    name (which fails if another process made the key first: that key is then used)."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(secrets.token_bytes(_KEY_BYTES))
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
    finally:
        tmp.unlink(missing_ok=True)


def _read_key(path: str) -> bytes:
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise ValueError("it is not a plain file")
        if st.st_mode & 0o077:
            raise ValueError(f"others may read or write it (mode {stat.S_IMODE(st.st_mode):o}, needs 600)")
        key = f.read(_KEY_BYTES + 1)
    if len(key) != _KEY_BYTES:
        raise ValueError(f"it does not hold a {_KEY_BYTES}-byte key")
    return key


def entry_mac(capture_id: str, entry: dict) -> str:
    """HMAC-SHA256, with this installation's key, of a capture's entry (without its `mac`)."""
    body = {k: v for k, v in entry.items() if k != "mac"}
    msg = json.dumps([capture_id, body], sort_keys=True, separators=(",", ":"))
    return hmac.new(installation_key(), msg.encode(), hashlib.sha256).hexdigest()


def _verified(capture_id: str, entry) -> bool:
    mac = entry.get("mac") if isinstance(entry, dict) else None
    try:
        return isinstance(mac, str) and hmac.compare_digest(mac, entry_mac(capture_id, entry))
    except (TypeError, ValueError, RecursionError):  # content JSON cannot hold: not written by us
        return False


# ---- results <-> JSON ----------------------------------------------------------------------------
def _board_to(b: BoardObservation | None):
    if b is None:
        return None
    return {"ids": [int(i) for i in b.ids], "corners_px": np.asarray(b.corners_px, float).tolist(),
            "mirrored": bool(b.mirrored)}


def _points(value, n: int | None, size, what: str) -> np.ndarray:
    """(N, 2) finite pixel coordinates inside a `size` (w, h) image; `n` the count required, if any."""
    a = np.asarray(value, float)
    if a.ndim != 2 or a.shape[1] != 2 or (n is not None and len(a) != n):
        want = "pairs" if n is None else f"{n} pairs"
        raise ValueError(f"{what} holds {a.shape} values, not {want} of pixel coordinates")
    if not np.all(np.isfinite(a)) or np.any(a < -0.5) or np.any(a > np.subtract(size, 0.5)):
        raise ValueError(f"{what} holds points outside the {size[0]}x{size[1]} image")
    return a


def _board_from(d, board, mirrored: bool, size, what: str) -> BoardObservation:
    if not isinstance(d, dict) or d.get("mirrored") is not mirrored:
        raise ValueError(f"{what} is not a board {'seen in' if mirrored else 'seen outside'} the mirror")
    ids = d["ids"]
    if not isinstance(ids, list) or not all(type(i) is int and 0 <= i < board.n_corners for i in ids) \
            or len(set(ids)) != len(ids):
        raise ValueError(f"{what}'s ids are not distinct corner ids 0..{board.n_corners - 1}")
    return BoardObservation(np.asarray(ids, int), _points(d["corners_px"], len(ids), size, what), mirrored)


def encode_result(result) -> dict:
    """A detect_session job result (DetectionFailure, (board, pattern points) or MirrorView) -> JSON."""
    if isinstance(result, DetectionFailure):
        return {"failure": result.reason}
    if isinstance(result, MirrorView):
        return {"mirror": {"capture_id": result.capture_id, "method": result.method,
                           "real": _board_to(result.real), "virtual": _board_to(result.virtual)}}
    board, pts = result
    pts = np.asarray(pts, float)
    # rows kept: a circle capture's (N, 2) centres, a structured capture's (N, 5) (structured_session)
    return {"board": _board_to(board), "pattern_px": (pts if pts.ndim == 2 else pts.reshape(-1, 2)).tolist()}


def decode_result(d, capture_id: str, step: str, mirrored: bool, board, pattern, size):
    """Inverse of encode_result for capture `capture_id` of `step` (its board and pattern specs, the
    camera `size`): raises ValueError when the entry does not fit that capture."""
    try:
        if not isinstance(d, dict):
            raise ValueError("the result is not an object")
        if "failure" in d:
            if not isinstance(d["failure"], str):
                raise ValueError("the failure's reason is not text")
            return DetectionFailure(d["failure"])
        if step == STEP_PROJECTOR:
            return (_board_from(d["board"], board, mirrored, size, "the board"),
                    _points(d["pattern_px"], pattern.n_points, size, "the pattern"))
        m = d["mirror"]
        if not isinstance(m, dict) or m.get("method") != step or m.get("capture_id") != capture_id:
            raise ValueError(f"it is not a {step} result of capture {capture_id}")
        real = _board_from(m["real"], board, False, size, "the real board")
        virtual = (_board_from(m["virtual"], board, True, size, "the virtual board")
                   if step == STEP_REAL_VIRTUAL else None)
        if step != STEP_REAL_VIRTUAL and m["virtual"] is not None:
            raise ValueError(f"a {step} result holds a virtual board")
        return MirrorView(capture_id, step, real, virtual)
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"malformed entry ({e.__class__.__name__}: {e})") from None


# ---- the file ------------------------------------------------------------------------------------
def load(folder) -> dict:
    """{capture id: entry (without its mac)} usable with the current detector and written by this
    installation; {} (and a warning) when the file is missing fields or is not JSON; {} silently when
    it is absent or from another detector. Entries whose MAC does not verify are left out, with one
    warning."""
    path = Path(folder) / CACHE_FILE
    if not os.path.lexists(path):
        return {}
    try:
        try:  # never a file elsewhere through a link, nor a FIFO that would block
            raw = read_regular(path, RESULT_MAX_BYTES, "detection cache")
        except SessionError as e:
            raise ValueError(f"it is not a plain file of the session folder ({e})") from None
        data = json.loads(raw.decode("utf-8"))
        if not isinstance(data, dict):
            raise ValueError("it is not a JSON object")
        if data.get("format") != FORMAT:
            raise ValueError(f"field 'format' is not '{FORMAT}'")
        if data.get("version") != VERSION:
            raise ValueError(f"field 'version' is {data.get('version')!r}, not {VERSION}")
        caps = data["captures"]
        if not isinstance(caps, dict):
            raise ValueError("field 'captures' is not an object")
        if data.get("detector") != detector_fingerprint():
            return {}  # detected by other code: every capture is detected again
    except (OSError, ValueError, KeyError, AttributeError, RecursionError) as e:
        msg = str(e) if not isinstance(e, KeyError) else f"field {e} is missing"
        warnings.warn(f"ignoring the detection cache {path}: {msg}; detecting every image again",
                      RuntimeWarning, stacklevel=3)
        return {}
    good = {str(k): {f: x for f, x in v.items() if f != "mac"} for k, v in caps.items() if _verified(str(k), v)}
    if len(good) < len(caps):
        warnings.warn(f"{len(caps) - len(good)} of the {len(caps)} entries of the detection cache {path} were not "
                      f"written by this station (forged, edited or from another machine): detecting those images "
                      f"again", RuntimeWarning, stacklevel=3)
    return good


def save(folder, entries: dict) -> None:
    """Write the cache atomically, each entry signed (entry_mac); a folder that cannot be written
    (read-only media) is left alone."""
    signed = {cid: dict(e, mac=entry_mac(cid, e)) for cid, e in entries.items()}
    data = {"format": FORMAT, "version": VERSION, "detector": detector_fingerprint(),
            "opencv": cv2.__version__, "captures": signed}
    try:
        atomic_write_text(Path(folder) / CACHE_FILE, json.dumps(data, separators=(",", ":")) + "\n")
    except OSError as e:
        warnings.warn(f"could not write the detection cache in {folder} ({e.strerror}); the next run detects "
                      f"every image again", RuntimeWarning, stacklevel=3)
