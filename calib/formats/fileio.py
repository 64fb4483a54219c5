"""Crash-safe file writes: write to a temporary file in the same folder, fsync, rename. And the one way to
read a file a session folder holds (`read_regular`).

The temporary file is created with mode 0666 and the process umask applies, exactly as for a plain
open(path, "w"): a file written atomically gets the same permissions as any other new file (0644
under umask 022, 0664 under 002), not tempfile.mkstemp's private 0600. A full disk (ENOSPC, EDQUOT)
becomes calib.errors.DiskFullError naming the file; the file being replaced is left intact.

Everything in a session folder is untrusted: a file there may be a link (to a file elsewhere, to
/dev/zero, a loop), a hard link to a file elsewhere, a FIFO or device (reading it would block for ever),
or huge (a sparse file). `read_regular` opens without following a link and without blocking, checks with
fstat that it holds a regular file of at most the size allowed for its kind, and only then reads; every
refusal is an UnsafeFileError naming the file. A temporary file a killed writer left behind
(`.NAME.XXXXXXXX.tmp`) is removed by the next writer holding the folder (`remove_stale_temporaries`)."""

from __future__ import annotations

import errno
import fcntl
import os
import re
import secrets
import stat
from pathlib import Path

from calib.errors import DiskFullError, UnsafeFileError
from calib.formats.jsonfile import parse_json  # one parser of untrusted JSON bytes (size, UTF-8, nesting)

_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_READ_FLAGS = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | _NOFOLLOW
_TMP_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | _NOFOLLOW
#: a temporary file of _create_temp: `.NAME.` then 8 hex digits then `.tmp`
_TMP_RE = re.compile(r"\.(.+)\.[0-9a-f]{8}\.tmp")
#: the largest session.json read: a capture takes a kilobyte or two, so this holds thousands of them
MANIFEST_MAX_BYTES = 8 * 2**20
#: the largest result file read (calibration.json/yaml, verification.json, detections.json, the report)
RESULT_MAX_BYTES = 256 * 2**20


def _create_temp(path: Path) -> tuple[int, Path]:
    """A new file beside `path` (mode 0666 & ~umask, never an existing file or link)."""
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        try:
            return os.open(tmp, _TMP_FLAGS, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary file name", str(path.parent))


def atomic_write_bytes(path, data: bytes) -> None:
    """Write then rename in the same folder (and fsync), so a crash never leaves a half-written file."""
    path = Path(path)
    try:
        _write_replace(path, data)
    except OSError as e:
        if e.errno in _DISK_FULL and not isinstance(e, DiskFullError):
            raise DiskFullError(path, e.errno) from e
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def _write_replace(path: Path, data: bytes) -> None:
    fd, tmp = _create_temp(path)
    try:
        try:  # marks the temporary as being written until the rename (remove_stale_temporaries)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pass  # no flock on this file system: the temporary is written all the same
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
            os.replace(tmp, path)  # before the close that drops the flock
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def read_regular(path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of `path` when it is a regular file of at most `max_bytes` bytes, never following a link
    and never blocking; UnsafeFileError naming the file otherwise. FileNotFoundError when it is absent."""
    fd = open_regular(path, max_bytes, what)
    try:
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise UnsafeFileError(f"{what} {path} cannot be read ({e.strerror})") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # grew since fstat
        raise UnsafeFileError(_too_big(path, what, max_bytes))
    return data


def read_json(path, max_bytes: int = RESULT_MAX_BYTES, what: str = "file"):
    """Parsed JSON of a file read as read_regular reads it; FormatError when it is not UTF-8 JSON."""
    return parse_json(read_regular(path, max_bytes, what), path)


def open_regular(path, max_bytes: int, what: str = "file") -> int:
    """A read-only descriptor of `path` (the caller closes it) once fstat says it is a regular file of at
    most `max_bytes` bytes; see read_regular."""
    try:
        fd = os.open(path, _READ_FLAGS)
    except FileNotFoundError:
        raise
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise UnsafeFileError(f"{what} {path} is a link; a session folder's files are read only as plain "
                                  f"files: replace the link by the file itself") from None
        raise UnsafeFileError(f"{what} {path} cannot be read ({e.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UnsafeFileError(f"{what} {path} is not a regular file (a folder, pipe or device); "
                                  f"replace it by the file itself")
        if st.st_size > max_bytes:
            raise UnsafeFileError(_too_big(path, what, max_bytes))
    except BaseException:
        os.close(fd)
        raise
    return fd


def _too_big(path, what: str, max_bytes: int) -> str:
    return (f"{what} {path} is larger than {max_bytes / 2**20:.4g} MB, more than such a file ever holds; "
            f"it is damaged or not this session's: remove it")


def remove_stale_temporaries(folder, names=None) -> list[str]:
    """Remove the temporary files of atomic writes (to `names`, files directly in `folder`; None: any)
    that a killed writer left behind. A writer holds an flock on its temporary file until it renamed it,
    so a temporary still being written (by another process too) is left alone; so is anything that is not
    a regular file directly in `folder` (a link is never followed). Returns the removed names."""
    try:
        entries = os.listdir(folder)
    except OSError:
        return []
    return [e for e in entries if (m := _TMP_RE.fullmatch(e)) and (names is None or m.group(1) in names)
            and _remove_if_abandoned(os.path.join(folder, e))]


def _remove_if_abandoned(path: str) -> bool:
    try:
        fd = os.open(path, _READ_FLAGS)
    except OSError:
        return False
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return False
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held by a live writer: BlockingIOError
        if not _same_inode(path, fd):
            return False
        os.unlink(path)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def _same_inode(path: str, fd: int) -> bool:
    st, ft = os.lstat(path), os.fstat(fd)
    return (st.st_dev, st.st_ino) == (ft.st_dev, ft.st_ino)
