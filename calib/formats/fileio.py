"""Crash-safe file writes: write to a temporary file in the same folder, fsync, rename.

The temporary file is created with mode 0666 and the process umask applies, exactly as for a plain
open(path, "w"): a file written atomically gets the same permissions as any other new file (0644
under umask 022, 0664 under 002), not tempfile.mkstemp's private 0600. A full disk (ENOSPC, EDQUOT)
becomes calib.errors.DiskFullError naming the file; the file being replaced is left intact."""

from __future__ import annotations

import errno
import os
import secrets
from pathlib import Path

from calib.errors import DiskFullError

_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
_TMP_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)


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
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))
