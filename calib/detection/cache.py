"""The detection stage's results kept in the session folder (`detections.json`), so that a session is
decoded and detected once: calibrating it again (another method, another camera model, after a
retake) detects only the captures that are new or changed.

An entry is used only when all of these still hold; otherwise that capture is detected again:
- the detector is the same: the SHA-1 of the detection modules' source (`_DETECTION_MODULES`:
  detect, cache, boards, pattern, observations) and OpenCV's version (`detector_fingerprint`; any
  change to that code invalidates every entry);
- the image is the same: the SHA-1 of the PNG file's bytes;
- the job is the same: step, mirrored or not, board and pattern specs, camera size (`job_key`).

Images are hashed from the bytes calib.detection.detect read through SessionStore.image_path, which refuses a
path leading out of the session folder; the cache file itself is read only when it is a plain file in
the folder (a link is ignored with a warning, never followed).

The file is a cache, not a record: a missing, unreadable or malformed one is ignored (with a warning
naming the problem) and rewritten; it is written atomically (calib.formats.fileio) and only holds detection
results, so deleting it loses nothing. Layout: docs/FORMATS.md.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import warnings
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from calib.errors import SessionError
from calib.formats.fileio import RESULT_MAX_BYTES, atomic_write_text, read_regular
from calib.models.observations import BoardObservation, DetectionFailure, MirrorView

CACHE_FILE = "detections.json"
FORMAT = "procam-detections"
VERSION = 1


#: the modules whose code decides what detection returns (their source is fingerprinted), by dotted
#: name so that the file is found wherever the module lives
_DETECTION_MODULES = ("calib.detection.detect", "calib.detection.cache", "calib.models.boards",
                      "calib.models.pattern", "calib.models.observations")


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


# ---- results <-> JSON ----------------------------------------------------------------------------
def _board_to(b: BoardObservation | None):
    if b is None:
        return None
    return {"ids": [int(i) for i in b.ids], "corners_px": np.asarray(b.corners_px, float).tolist(),
            "mirrored": bool(b.mirrored)}


def _board_from(d) -> BoardObservation | None:
    if d is None:
        return None
    corners = np.asarray(d["corners_px"], float).reshape(-1, 2)
    return BoardObservation(np.asarray(d["ids"], int).reshape(-1), corners, bool(d["mirrored"]))


def encode_result(result) -> dict:
    """A detect_session job result (DetectionFailure, (board, pattern points) or MirrorView) -> JSON."""
    if isinstance(result, DetectionFailure):
        return {"failure": result.reason}
    if isinstance(result, MirrorView):
        return {"mirror": {"capture_id": result.capture_id, "method": result.method,
                           "real": _board_to(result.real), "virtual": _board_to(result.virtual)}}
    board, pts = result
    return {"board": _board_to(board), "pattern_px": np.asarray(pts, float).reshape(-1, 2).tolist()}


def decode_result(d: dict):
    """Inverse of encode_result. Raises KeyError/TypeError/ValueError on a malformed entry."""
    if "failure" in d:
        return DetectionFailure(str(d["failure"]))
    if "mirror" in d:
        m = d["mirror"]
        return MirrorView(str(m["capture_id"]), str(m["method"]), _board_from(m["real"]), _board_from(m["virtual"]))
    return _board_from(d["board"]), np.asarray(d["pattern_px"], float).reshape(-1, 2)


# ---- the file ------------------------------------------------------------------------------------
def load(folder) -> dict:
    """{capture id: entry} usable with the current detector; {} (and a warning) when the file is
    missing fields or is not JSON; {} silently when it is absent or from another detector."""
    path = Path(folder) / CACHE_FILE
    if not os.path.lexists(path):
        return {}
    try:
        try:  # never a file elsewhere through a link, nor a FIFO that would block
            raw = read_regular(path, RESULT_MAX_BYTES, "detection cache")
        except SessionError as e:
            raise ValueError(f"it is not a plain file of the session folder ({e})") from None
        data = json.loads(raw.decode("utf-8"))
        if data.get("format") != FORMAT:
            raise ValueError(f"field 'format' is not '{FORMAT}'")
        if data.get("version") != VERSION:
            raise ValueError(f"field 'version' is {data.get('version')!r}, not {VERSION}")
        caps = data["captures"]
        if not isinstance(caps, dict):
            raise ValueError("field 'captures' is not an object")
        if data.get("detector") != detector_fingerprint():
            return {}  # detected by other code: every capture is detected again
        return {str(k): v for k, v in caps.items() if isinstance(v, dict)}
    except (OSError, ValueError, KeyError, AttributeError, RecursionError) as e:
        msg = str(e) if not isinstance(e, KeyError) else f"field {e} is missing"
        warnings.warn(f"ignoring the detection cache {path}: {msg}; detecting every image again",
                      RuntimeWarning, stacklevel=3)
        return {}


def save(folder, entries: dict) -> None:
    """Write the cache atomically; a folder that cannot be written (read-only media) is left alone."""
    data = {"format": FORMAT, "version": VERSION, "detector": detector_fingerprint(),
            "opencv": cv2.__version__, "captures": entries}
    try:
        atomic_write_text(Path(folder) / CACHE_FILE, json.dumps(data, separators=(",", ":")) + "\n")
    except OSError as e:
        warnings.warn(f"could not write the detection cache in {folder} ({e.strerror}); the next run detects "
                      f"every image again", RuntimeWarning, stacklevel=3)
