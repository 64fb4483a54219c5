"""Files the panel reads because an operator typed their path (the camera intrinsics of "Skip camera
step"). A path typed in a browser is untrusted: the station reads it only when it names a regular file
on the station's own machine, reached without symbolic links, no larger than MAX_BYTES, with one of the
suffixes an intrinsics file has. What was read is copied into the session, so the session stands alone
(it is recorded by that copy, never by the outside path). The rule is in docs/STATION.md.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from calib.errors import FormatError, ProcamError, SessionError
from calib.formats.fileio import atomic_write_bytes

MAX_BYTES = 1 << 20  # an intrinsics file is a few kB
INTRINSICS_SUFFIXES = (".json", ".yaml", ".yml", ".xml")
#: the copy in the session folder, suffix kept (it tells the reader JSON from OpenCV FileStorage)
GIVEN_CAMERA_STEM = "given_camera"


def _refuse(path, why: str) -> SessionError:
    return SessionError(f"intrinsics file {path}: {why}")


def read_operator_file(path, suffixes=INTRINSICS_SUFFIXES) -> bytes:
    """The bytes of the file an operator named, or SessionError saying which rule it breaks."""
    text = str(path).strip()
    if not text:
        raise _refuse("(none)", "give the path of a calibration.json or OpenCV YAML on the station's machine")
    p = Path(os.path.expanduser(text))
    if not p.is_absolute():
        p = Path.cwd() / p
    if p.suffix.lower() not in suffixes:
        raise _refuse(p, f"is not an intrinsics file (give a {', '.join(suffixes)} file)")
    walked = Path(p.anchor)
    for part in p.parts[1:]:
        walked = walked / part
        try:
            st = os.lstat(walked)
        except FileNotFoundError:
            raise _refuse(p, "does not exist") from None
        except OSError as e:
            raise _refuse(p, f"cannot be read ({e.strerror or e})") from None
        if stat.S_ISLNK(st.st_mode):
            raise _refuse(p, f"goes through the link {walked}; give the real path")
    if stat.S_ISDIR(st.st_mode):
        raise _refuse(p, "is a folder, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise _refuse(p, "is not a regular file")
    if st.st_size > MAX_BYTES:
        raise _refuse(p, f"is {st.st_size} bytes; an intrinsics file is at most {MAX_BYTES} bytes")
    try:
        with open(p, "rb") as f:
            return f.read(MAX_BYTES + 1)
    except OSError as e:
        raise _refuse(p, f"cannot be read ({e.strerror or e})") from None


def copy_into_session(folder, path, data: bytes) -> str:
    """Write `data` read from `path` into the session folder; the copy's name (relative to the folder)."""
    name = GIVEN_CAMERA_STEM + Path(str(path).strip()).suffix.lower()
    atomic_write_bytes(Path(folder) / name, data)
    return name


def checked_intrinsics(path, camera_size) -> bytes:
    """The bytes of an operator's intrinsics file once they load as a camera of `camera_size` (read
    once: what is checked is what gets copied); SessionError or FormatError naming the file otherwise."""
    import tempfile

    from app.station.machine import load_intrinsics

    data = read_operator_file(path)
    with tempfile.TemporaryDirectory(prefix="procam-intrinsics-") as tmp:
        probe = Path(tmp) / Path(str(path).strip()).name
        probe.write_bytes(data)
        try:
            load_intrinsics(probe, camera_size)
        except FormatError as e:  # its message names the temporary copy: name the operator's file
            where = "" if e.field.startswith("<") else f"field '{e.field}': "  # "<file>", "<root>": the whole file
            raise _refuse(str(path).strip(), where + e.problem) from None
        except ProcamError as e:
            raise _refuse(str(path).strip(), str(e).replace(str(probe), "").lstrip(": ") or type(e).__name__) from None
    return data
