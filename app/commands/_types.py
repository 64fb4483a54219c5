"""Argparse `type=` validators shared by every `procam` command (a private module: not a sub-command).

Each one turns the option's text into a value or raises argparse.ArgumentTypeError saying what is
allowed; argparse puts the option's name in front ("argument --port: ...") and app/cli.py turns that
into one line, exit code 2. So a value out of range is refused before any folder, device or file is
touched, and NaN, infinities and negative counts never reach a manifest.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import stat
from pathlib import Path

#: seeds the simulator and numpy accept (numpy's legacy generators take 32 bits)
SEED_MAX = 2**32 - 1
_HOST_LABEL = re.compile(r"(?!-)[a-z0-9-]{1,63}(?<!-)", re.IGNORECASE)


def _bad(text: str, allowed: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(f"must be {allowed}, got {text!r}")


def camera_source(text: str):
    """A camera for cv2.VideoCapture: an index (0..99) or a URL / path (no control characters)."""
    t = str(text).strip()
    if t.isdigit():
        v = int(t)
        if v > 99:
            raise _bad(text, "a camera index from 0 to 99, or a URL")
        return v
    if not t or len(t) > 2000 or any(ord(c) < 32 for c in t):
        raise _bad(text, "a camera index from 0 to 99, or a URL")
    return t


def int_range(lo: int, hi: int | None = None):
    """A whole number in [lo, hi] (no upper bound when hi is None)."""
    allowed = f"a whole number from {lo} to {hi}" if hi is not None else f"a whole number >= {lo}"

    def parse(text: str) -> int:
        try:
            v = int(text, 10)
        except ValueError:
            raise _bad(text, allowed) from None
        if v < lo or (hi is not None and v > hi):
            raise _bad(text, allowed)
        return v

    parse.__name__ = "whole number"
    return parse


_MODE = re.compile(r"(\d{1,5})x(\d{1,5})@(\d{1,3})")


def camera_mode(text: str) -> tuple[int, int, int]:
    """A colour stream mode WxH@FPS (16-8192 pixels, 1-300 fps): (width, height, fps)."""
    allowed = "WIDTHxHEIGHT@FPS, e.g. 1280x800@30 (16-8192 pixels, 1-300 fps)"
    m = _MODE.fullmatch(str(text).strip())
    if not m:
        raise _bad(text, allowed)
    w, h, fps = (int(g) for g in m.groups())
    if not (16 <= w <= 8192 and 16 <= h <= 8192 and 1 <= fps <= 300):
        raise _bad(text, allowed)
    return w, h, fps


camera_mode.__name__ = "camera mode"


def float_range(lo: float, hi: float, *, lo_open: bool = False):
    """A finite number in [lo, hi] ((lo, hi] with lo_open): never NaN or an infinity."""
    allowed = f"a number above {lo:g}, at most {hi:g}" if lo_open else f"a number between {lo:g} and {hi:g}"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise _bad(text, allowed) from None
        if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
            raise _bad(text, allowed)
        return v

    parse.__name__ = "number"
    return parse


#: a TCP port a server can listen on (0: any free one)
port = int_range(0, 65535)
#: a seed of the simulated rig or of a scenario
seed = int_range(0, SEED_MAX)
#: threads or processes of a command
workers = int_range(1, 64)
#: a screen's index as `procam devices` lists it
screen = int_range(0, 63)
#: a delay in seconds (a projector's latency, a wait before measuring)
seconds = float_range(0.0, 60.0)
#: the simulated camera's read noise (sigma, 8-bit levels), shot noise (electrons per level), optical blur
#: (sigma, pixels): beyond these the images hold no board to detect, or rendering never ends
noise_dn = float_range(0.0, 64.0)
shot_e_per_dn = float_range(0.0, 1e6)
blur_px = float_range(0.0, 20.0)


def host(text: str) -> str:
    """A host name or an IP address (syntax only; whether it is this machine's is checked by binding)."""
    import ipaddress

    t = text.strip()
    try:
        ipaddress.ip_address(t.strip("[]"))
        return t
    except ValueError:
        pass
    labels = t.rstrip(".").split(".")
    if t and len(t) <= 253 and all(_HOST_LABEL.fullmatch(x) for x in labels):
        return t
    raise _bad(text, "a host name or an IP address of this machine (e.g. 127.0.0.1, or 0.0.0.0 for every "
                     "network interface)")


def regular_file(text: str) -> str:
    """An existing regular file (a link to one is followed): never a folder, device, FIFO or socket, which
    reading could hang on or never finish."""
    try:
        mode = os.stat(text).st_mode
    except FileNotFoundError:
        raise argparse.ArgumentTypeError(f"{text} does not exist") from None
    except OSError as e:
        raise argparse.ArgumentTypeError(f"cannot read {text}: {e.strerror or e}") from None
    if stat.S_ISDIR(mode):
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    if not stat.S_ISREG(mode):
        kind = ("a FIFO (named pipe)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a special file")
        raise argparse.ArgumentTypeError(f"{text} is {kind}, not a regular file")
    return str(Path(text))
