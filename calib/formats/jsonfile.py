"""Untrusted JSON files (session.json, calibration.json, a camera's intrinsics): bytes to a Python value,
or a FormatError naming the file and what is wrong (too large, not UTF-8, not JSON, nested too deeply).

What the values mean is checked by each file's own reader (SessionManifest.from_dict,
CalibrationResult.from_dict, CameraModel.from_dict)."""

from __future__ import annotations

import json
from pathlib import Path

from calib.errors import FormatError

#: the largest JSON file read: far beyond any calibration or session of the station (a full session's
#: calibration.json with every residual is a few MB)
MAX_JSON_BYTES = 256 * 1024 * 1024
#: the deepest nesting accepted: the station's files nest a few levels; deeper data would make the code
#: that walks it (saving, the report) exhaust Python's stack
MAX_JSON_DEPTH = 64


def read_json_file(path, max_bytes: int = MAX_JSON_BYTES, what: str = "file"):
    """The parsed content of the JSON file `path`: a regular file read as calib.formats.fileio.read_regular
    reads it (no link, FIFO or device; at most `max_bytes`), then parse_json."""
    from calib.formats.fileio import read_regular  # fileio imports parse_json from here

    path = Path(path)
    try:
        raw = read_regular(path, max_bytes, what)
    except FileNotFoundError:
        raise FormatError(path, "<file>", "cannot be read: it does not exist") from None
    except OSError as e:
        raise FormatError(path, "<file>", f"cannot be read: {e.strerror or e}") from None
    return parse_json(raw, path)


def parse_json(raw: bytes, path):
    """`raw` (a file's bytes) parsed as UTF-8 JSON, nesting at most MAX_JSON_DEPTH levels."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        bad = f"byte 0x{raw[e.start]:02x} at offset {e.start}"
        raise FormatError(path, "<file>", f"is not a text file (a zip?): {bad} is not UTF-8; save it as UTF-8 "
                          "JSON") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(path, "<file>", f"is not valid JSON (line {e.lineno}: {e.msg})") from None
    except RecursionError:
        raise _too_deep(path) from None
    except ValueError as e:  # an integer of thousands of digits
        raise FormatError(path, "<file>", f"is not valid JSON ({e})") from None
    if not _depth_within(data, MAX_JSON_DEPTH):
        raise _too_deep(path)
    return data


def _too_deep(path) -> FormatError:
    return FormatError(path, "<file>", f"nests more than {MAX_JSON_DEPTH} levels deep: it is not a station file")


def _depth_within(value, limit: int) -> bool:
    """Whether lists and objects in `value` nest at most `limit` levels (iterative: no recursion to exhaust)."""
    stack = [(value, 1)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, (list, dict)):
            if depth > limit:
                return False
            stack.extend((c, depth + 1) for c in (v.values() if isinstance(v, dict) else v))
    return True
