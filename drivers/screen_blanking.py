"""Keep the X server from blanking the screens while a session runs (its screen saver and DPMS power
saving would turn the projector's image off mid-session), and put back what was set before.

    inhibit = ScreenBlankingInhibitor.start()   # screen saver timeout 0, DPMS off (if the server has it)
    ...
    inhibit.restore()                           # the timeout, interval and DPMS state as they were

X11 only (libX11 and libXext through ctypes, on the display pyglet uses: $DISPLAY); elsewhere, or
when the libraries are missing, `start()` returns an inhibitor that did nothing and says why
(`reason`). A desktop's own lock screen (a session manager's idle timer) is not an X server setting
and is not covered.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from dataclasses import dataclass

_log = logging.getLogger(__name__)


def _lib(name: str):
    path = ctypes.util.find_library(name)
    return ctypes.CDLL(path) if path else None


@dataclass
class ScreenBlankingInhibitor:
    """What start() changed and how to put it back; `active` False (with `reason`) when nothing was."""

    active: bool
    reason: str = ""
    _x11: object = None
    _xext: object = None
    _display: int = 0
    _saver: tuple[int, int, int, int] | None = None  # timeout, interval, prefer_blanking, allow_exposures
    _dpms_was_on: bool | None = None

    @classmethod
    def start(cls) -> "ScreenBlankingInhibitor":
        if not os.environ.get("DISPLAY"):
            return cls(False, "no X display (DISPLAY unset): screen blanking is not prevented")
        x11 = _lib("X11")
        if x11 is None:
            return cls(False, "libX11 not found: screen blanking is not prevented")
        x11.XOpenDisplay.restype = ctypes.c_void_p
        x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
        display = x11.XOpenDisplay(None)
        if not display:
            return cls(False, f"cannot open display {os.environ.get('DISPLAY')}: screen blanking is not prevented")
        vals = [ctypes.c_int() for _ in range(4)]
        x11.XGetScreenSaver.argtypes = [ctypes.c_void_p] + [ctypes.POINTER(ctypes.c_int)] * 4
        x11.XSetScreenSaver.argtypes = [ctypes.c_void_p] + [ctypes.c_int] * 4
        x11.XFlush.argtypes = [ctypes.c_void_p]
        x11.XGetScreenSaver(display, *[ctypes.byref(v) for v in vals])
        saver = tuple(int(v.value) for v in vals)
        x11.XSetScreenSaver(display, 0, saver[1], saver[2], saver[3])  # timeout 0: never
        out = cls(True, "", x11, None, display, saver)
        xext = _lib("Xext")
        if xext is not None:
            try:
                xext.DPMSQueryExtension.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int),
                                                    ctypes.POINTER(ctypes.c_int)]
                xext.DPMSInfo.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_ushort),
                                          ctypes.POINTER(ctypes.c_ubyte)]
                xext.DPMSDisable.argtypes = [ctypes.c_void_p]
                a, b = ctypes.c_int(), ctypes.c_int()
                if xext.DPMSQueryExtension(display, ctypes.byref(a), ctypes.byref(b)):
                    level, state = ctypes.c_ushort(), ctypes.c_ubyte()
                    xext.DPMSInfo(display, ctypes.byref(level), ctypes.byref(state))
                    out._xext, out._dpms_was_on = xext, bool(state.value)
                    if state.value:
                        xext.DPMSDisable(display)
            except AttributeError:  # a libXext without DPMS
                pass
        x11.XFlush(display)
        return out

    def saver_timeout_s(self) -> int | None:
        """The X server's screen saver timeout now (seconds; 0: never)."""
        if not self.active:
            return None
        vals = [ctypes.c_int() for _ in range(4)]
        self._x11.XGetScreenSaver(self._display, *[ctypes.byref(v) for v in vals])
        return int(vals[0].value)

    def restore(self) -> None:
        """Put the screen saver and DPMS back as they were (safe to call twice)."""
        if not self.active:
            return
        self.active = False
        try:
            self._x11.XSetScreenSaver(self._display, *self._saver)
            if self._xext is not None and self._dpms_was_on:
                self._xext.DPMSEnable.argtypes = [ctypes.c_void_p]
                self._xext.DPMSEnable(self._display)
            self._x11.XFlush(self._display)
            self._x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
            self._x11.XCloseDisplay(self._display)
        except Exception as e:  # noqa: BLE001 - the display may be gone at exit; nothing else to undo
            _log.warning("could not restore the screen saver settings: %s", e)
