"""One process at a time writes a session folder: the lock file `.procam.lock` in the folder.

A program that writes a session (the station, `procam session`, `--resume`, `procam simulate`, the
ProcamCalib import: everything that writes session.json or images/) holds an OS lock (`fcntl.flock`)
on the lock file for as long as it has the session open. A second process is refused with a
SessionError naming the holder (pid, host, start time, read from the file). The kernel drops the lock
when its holder exits, however it exits (a crash, SIGKILL), so a lock file left behind by a dead
process is stale: the next program takes it over and records itself in it. On a file system without
flock the pid in the file decides: a live process of this host keeps the folder, a dead one does not.

Within one process the lock is shared: several SessionStore objects on one folder take it once, and it
is released (and the file removed) when the last of them is closed or garbage-collected. Readers
(`procam calibrate`, `verify`, `evaluate`, `bench`) do not lock: they never write session.json or
images, and what they write is a whole file replaced atomically (calibration.json, the detection cache)."""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import stat
import sys
import threading
import time
import weakref
from pathlib import Path

from calib.errors import SessionError

LOCK_FILE = ".procam.lock"

_REGISTRY_LOCK = threading.Lock()
_held: dict[tuple[int, int], "_Held"] = {}  # (st_dev, st_ino) of the folder -> this process's lock on it


class _Held:
    def __init__(self, fd: int, path: Path, previous: dict | None):
        self.fd = fd
        self.path = path
        self.previous = previous
        self.count = 0


class SessionLock:
    """This process's hold on a session folder; `release()` (or garbage collection) gives it back.
    `took_over` is the stale holder's record when a dead process's lock was taken over, else None."""

    def __init__(self, key, held: _Held):
        self._key = key
        self.path = held.path
        self.took_over = held.previous
        self._finalizer = weakref.finalize(self, _release, key)

    def release(self) -> None:
        if self._finalizer.detach() is not None:  # released once, whoever asks again
            with _REGISTRY_LOCK:
                _release_held(self._key)
                _drain()

    @property
    def held(self) -> bool:
        return self._finalizer.alive


#: keys whose SessionLock was garbage-collected while the registry was busy, released by its holder
_pending: list = []


def _release(key) -> None:
    """A SessionLock's finalizer (garbage collection, exit). A collection can run inside acquire() in this
    very thread, the registry lock held: waiting for it there would never return (seen in a CI run). So
    a finalizer never waits: when the registry is busy, the release is queued and done by the holder
    before it lets go (_drain)."""
    _pending.append(key)
    _drain_if_free()


def _drain_if_free() -> None:
    if _pending and _REGISTRY_LOCK.acquire(blocking=False):
        try:
            _drain()
        finally:
            _REGISTRY_LOCK.release()


def _drain() -> None:
    """The queued releases (the registry lock held)."""
    while _pending:
        _release_held(_pending.pop())


def _release_held(key) -> None:
    """One hold of `key` given back (the registry lock held); the last one unlocks and removes the file."""
    h = _held.get(key)
    if h is None:
        return
    h.count -= 1
    if h.count > 0:
        return
    del _held[key]
    try:  # remove the file while still holding the lock (acquire checks it locked the file on disk)
        if _same_file(h.path, h.fd):
            os.unlink(h.path)
    except OSError:
        pass
    os.close(h.fd)


def _same_file(path: Path, fd: int) -> bool:
    try:
        st = os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    ft = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (ft.st_dev, ft.st_ino)


def read_holder(folder) -> dict | None:
    """The record in a folder's lock file ({pid, host, since, command}), or None."""
    try:
        fd = os.open(Path(folder) / LOCK_FILE, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0))
    except OSError:
        return None
    try:
        return _read_fd(fd) if stat.S_ISREG(os.fstat(fd).st_mode) else None
    finally:
        os.close(fd)


def _parse(data: bytes) -> dict | None:
    try:
        d = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return d if isinstance(d, dict) else None


def _read_fd(fd: int) -> dict | None:
    try:
        return _parse(os.pread(fd, 4096, 0))
    except OSError:
        return None


def _alive(pid) -> bool:
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def describe(folder, holder: dict | None) -> str:
    """The one-line refusal for a folder held by `holder`."""
    if not holder or not isinstance(holder.get("pid"), int):
        who = "another process"
    else:
        who = f"pid {holder['pid']}"
        if holder.get("host") not in (None, socket.gethostname()):
            who += f" on {holder['host']}"
        if isinstance(holder.get("since"), str):
            who += f" since {holder['since']}"
    return (f"session folder {folder} is in use by {who}; a session is written by one program at a time: "
            f"stop that one (or open a copy of the folder)")


def _record() -> bytes:
    argv = [Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]]
    rec = {"pid": os.getpid(), "host": socket.gethostname(),
           "since": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "since_unix_s": round(time.time(), 3),
           "command": " ".join(argv)[:300]}
    return (json.dumps(rec) + "\n").encode()


def _open_lock_file(path: Path, folder) -> int:
    """The lock file, opened (created if absent); SessionError when it is not a plain file of its own: the
    lock record is written into it, so a link or a hard link would overwrite a file elsewhere."""
    fd = _open_lock_path(path, folder)
    st = os.fstat(fd)
    if stat.S_ISREG(st.st_mode) and st.st_nlink == 1:
        return fd
    os.close(fd)
    what = "has other hard links (it is also a file elsewhere)" if stat.S_ISREG(st.st_mode) else \
        "is not a regular file"
    raise SessionError(f"{path} {what}: remove it (a session's lock file is a plain file of its own)")


def _open_lock_path(path: Path, folder) -> int:
    flags = os.O_CREAT | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
    try:
        return os.open(path, os.O_RDWR | flags, 0o666)
    except PermissionError:  # someone else's lock file in a folder we may write: flock needs no write access
        try:
            return os.open(path, os.O_RDONLY | flags)
        except OSError as e:
            err = e
    except OSError as e:
        err = e
    if err.errno == errno.ELOOP:
        raise SessionError(f"{path} is a link: remove it (a session's lock file is a plain file)") from None
    raise SessionError(f"cannot write to the session folder {folder} ({err.strerror}): a session is opened for "
                       f"writing only in a folder this user can write") from None


def acquire(folder) -> SessionLock:
    """Lock `folder` for this process; SessionError if another process holds it."""
    folder = Path(folder)
    try:
        st = os.stat(folder)
    except OSError as e:
        raise SessionError(f"session folder {folder} cannot be opened ({e.strerror})") from None
    key = (st.st_dev, st.st_ino)
    path = folder / LOCK_FILE
    with _REGISTRY_LOCK:
        try:
            h = _held.get(key)
            if h is None:
                h = _held[key] = _take(folder, path)
            h.count += 1
            lock = SessionLock(key, h)
        finally:
            _drain()  # releases queued by a collection during this
    _drain_if_free()
    return lock


def _take(folder: Path, path: Path) -> _Held:
    for _ in range(20):
        fd = _open_lock_file(path, folder)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_fd(fd)
            os.close(fd)
            raise SessionError(describe(folder, holder)) from None
        except OSError:  # no flock on this file system: a live process of this host named in the file keeps it
            holder = _read_fd(fd)
            if holder and holder.get("host") == socket.gethostname() and holder.get("pid") != os.getpid() \
                    and _alive(holder.get("pid")):
                os.close(fd)
                raise SessionError(describe(folder, holder)) from None
        if not _same_file(path, fd):  # its holder removed the file between our open and flock: again
            os.close(fd)
            continue
        previous = _read_fd(fd)
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, _record(), 0)
        except OSError:
            pass  # the record is informative; the flock is the lock
        stale = previous if previous and previous.get("pid") != os.getpid() else None
        return _Held(fd, path, stale)
    raise SessionError(f"could not lock the session folder {folder}: its lock file keeps changing")
