"""The projector as a fullscreen pyglet window, behind drivers.base.ProjectorDriver.

Pixel-exact: the window covers one display (screen) with a borderless fullscreen window whose
framebuffer is exactly the screen's size; an image is uploaded unchanged into a texture (8 bits per
channel, nearest-neighbour sampling) and drawn 1:1 at the window's origin, rows top-down (the numpy
array is handed to pyglet with a negative pitch). No scaling, no filtering, no blending, no dithering,
no sRGB conversion; the mouse cursor is hidden. A window whose framebuffer cannot hold 8 bits per
channel, or does not match the screen's size (desktop scaling), is refused with a DeviceError.

Threads: pyglet (and OpenGL) belong to the thread that created the window, normally the main thread.
`show()` and `wait_presented()` may be called from any thread: show() converts the image and queues
it; the window's thread presents queued images in order (each for at least one refresh) in `pump()`,
which `run_projector_loop(window, worker)` calls in a loop while `worker` runs in a thread.
wait_presented() called on the window's own thread pumps by itself, so simple single-threaded use
works too.

Presented means: the image was drawn into the back buffer, the buffers were swapped (vsync on),
glFinish() returned and the X server processed every request (XSync), so a screenshot taken now shows
it. The projector itself needs longer (its own processing and the panel's response): `settle_s` is
added to the presentation time; measure it with drivers.settle.measure_settle_time.

Which screen: `list_screens()` describes every display output pyglet sees (name, primary flag,
position, resolution, refresh rate; pyglet lists X outputs through RandR, ordered by output, not by
the OS settings, pyglet #1246). Without an explicit index the projector goes to the one non-primary
screen; with a single screen, to that screen; with more than two screens (or no way to tell the
primary one) an explicit index is required (`choose_projector_screen`).

Checks, because fullscreen on a second monitor has known problems (pyglet #763, #1330) and two
screens of the same resolution would otherwise pass every size check: after going fullscreen the
window's position (read back from the X server) must equal its screen's origin and its size the
screen's size, else DeviceError. Every presentation checks again that the window is still mapped,
in place and that its output is still listed (re-listed at most every `output_check_s`); a hidden,
moved or closed window or a vanished output makes show() / wait_presented() raise DeviceError with
the reason, which the station shows.

Vsync: the window asks for it (pyglet's `vsync=True` sets the GLX swap interval); `self.vsync` is
what pyglet reports back. Whether the driver honours the swap interval cannot be read back through
pyglet, so it is not confirmed: an X server without a real display (Xvfb) presents at once.
`refresh_hz` is the output's mode rate (None when the X server does not report one, as Xvfb; the
ProjectorDriver property then falls back to 60 Hz and `refresh_hz_known` is False).

pyglet opens the X display when `pyglet.window` is first imported, so this module imports pyglet
only when a window is created or the screens are listed.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
import time
from collections import deque
from typing import Any, Callable

import numpy as np

from drivers.errors import DeviceError, DeviceTimeout
from drivers.settle import SettleMeasurement, measure_settle, measure_settle_time  # noqa: F401 (re-exported)

_log = logging.getLogger(__name__)

QUIT_KEYS = ("escape", "q")


def display_available() -> bool:
    """Whether an X display is configured (DISPLAY set); on other platforms assume one."""
    if sys.platform.startswith("linux"):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def _display_error(e: Exception) -> DeviceError:
    """pyglet's 'Cannot connect to None' and friends, said so a person can act on it."""
    shown = os.environ.get("DISPLAY")
    if shown:
        why = "" if "cannot connect" in str(e).lower() else f" ({e})"  # pyglet says 'Cannot connect to "None"'
        return DeviceError(f"DISPLAY={shown} cannot be reached{why}: no X server answers there; start the X session, fix DISPLAY "
                           "(e.g. DISPLAY=:0 for the local screen; over ssh use ssh -X or run on the rig's own "
                           "desktop), or check that this user may use it (xhost / XAUTHORITY)")
    return DeviceError(f"cannot open the display ({e}): run on the rig's desktop session or set DISPLAY")


def _screen_rate(screen) -> float | None:
    try:
        mode = screen.get_mode()
    except Exception:  # noqa: BLE001 - not every backend has modes
        return None
    rate = float(getattr(mode, "rate", 0) or 0) if mode is not None else 0.0
    return rate if rate > 0 else None


def _pyglet_screens() -> list:
    if not display_available():
        raise DeviceError("DISPLAY is not set, so there is no screen to show patterns on: run on the rig's "
                          "desktop session (or set DISPLAY=:0), with the projector connected as a screen")
    try:
        import pyglet

        return list(pyglet.display.get_display().get_screens())
    except DeviceError:
        raise
    except Exception as e:  # noqa: BLE001 - pyglet raises its own types per platform
        raise _display_error(e) from None


def describe_screen(index: int, screen) -> dict:
    """{index, name, primary, x, y, width, height, refresh_hz} of a pyglet screen (primary and
    refresh_hz are None when the platform does not say)."""
    name = getattr(screen, "name", None)
    if name is None and hasattr(screen, "get_monitor_name"):
        try:
            name = screen.get_monitor_name()
        except Exception:  # noqa: BLE001
            name = None
    primary = getattr(screen, "is_primary", None)
    return {"index": index, "name": str(name) if name else f"screen {index}",
            "primary": None if primary is None else bool(primary), "x": int(screen.x), "y": int(screen.y),
            "width": int(screen.width), "height": int(screen.height), "refresh_hz": _screen_rate(screen)}


def list_screens() -> list[dict]:
    """The display outputs pyglet sees: [{index, name, primary, x, y, width, height, refresh_hz}], index
    as `screen_index` uses it. Raises DeviceError when there is no display to talk to."""
    return [describe_screen(i, s) for i, s in enumerate(_pyglet_screens())]


def screen_line(s: dict) -> str:
    """One screen in words: '1: HDMI-1 1920x1080 at (1920, 0), 60 Hz'."""
    rate = f"{s['refresh_hz']:.2f} Hz".replace(".00 Hz", " Hz") if s.get("refresh_hz") else "refresh rate unknown"
    prim = ", primary" if s.get("primary") else ""
    return f"{s['index']}: {s.get('name') or '?'} {s['width']}x{s['height']} at ({s['x']}, {s['y']}), {rate}{prim}"


def choose_projector_screen(screens: list[dict], requested: int | None = None) -> int:
    """The index of the projector's screen: `requested` when given (checked); else the only screen,
    or with two screens the non-primary one. With more than two screens, or two where the primary
    cannot be told, the operator has to choose (DeviceError listing them)."""
    if not screens:
        raise DeviceError("the display has no screens: connect the projector and turn it on")
    listed = "; ".join(screen_line(s) for s in screens)
    if requested is not None:
        idx = int(requested)
        if not 0 <= idx < len(screens):
            raise DeviceError(f"there is no screen {requested}; the screens are {listed}")
        return idx
    if len(screens) == 1:
        return 0
    if len(screens) == 2:
        others = [s for s in screens if s.get("primary") is False]
        prim = [s for s in screens if s.get("primary")]
        if len(prim) == 1 and len(others) == 1:
            return int(others[0]["index"])
        raise DeviceError(f"cannot tell which of the two screens is the projector (no primary screen is set): "
                          f"choose it with --projector-screen N (screens: {listed})")
    raise DeviceError(f"{len(screens)} screens are connected: choose the projector's with --projector-screen N "
                      f"(screens: {listed}; `procam devices` lists them)")


def to_rgba(image: np.ndarray, size: tuple[int, int]) -> bytes:
    """(H, W) grey or (H, W, 3) BGR uint8 -> RGBA bytes, rows top-down. Refuses any other size or type."""
    a = np.asarray(image)
    w, h = size
    if a.dtype != np.uint8:
        raise DeviceError(f"projector images must be uint8, got {a.dtype}")
    if a.shape[:2] != (h, w) or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise DeviceError(f"projector image must be {w}x{h} ((H, W) grey or (H, W, 3) BGR) to be shown "
                          f"pixel for pixel, got shape {a.shape}")
    rgba = np.empty((h, w, 4), np.uint8)
    if a.ndim == 2:
        rgba[:, :, :3] = a[:, :, None]
    else:
        rgba[:, :, :3] = a[:, :, ::-1]
    rgba[:, :, 3] = 255
    return rgba.tobytes()


class ProjectorWindow:
    """A fullscreen, pixel-exact pattern window (see the module doc).

    screen_index: which screen (list_screens); None = choose_projector_screen's choice (the
    non-primary one of two). size: the image size; None = the screen's size;
    with fullscreen=True it must equal the screen's size (set the projector's resolution in the OS);
    with fullscreen=False a borderless window of `size` is put at the screen's top-left corner.
    settle_s: the projector's own latency, added to every presentation time.
    output_check_s: how often a presentation re-lists the outputs to notice a vanished one.
    quit_keys: keys that close the window (Esc, q); () to ignore the keyboard.
    """

    def __init__(self, screen_index: int | None = None, size: tuple[int, int] | None = None,
                 fullscreen: bool = True, settle_s: float = 0.0, vsync: bool = True,
                 quit_keys: tuple[str, ...] = QUIT_KEYS, caption: str = "procam projector",
                 output_check_s: float = 1.0):
        screens = list_screens()
        idx = choose_projector_screen(screens, screen_index)
        info = screens[idx]
        sw, sh = info["width"], info["height"]
        if size is None:
            size = (sw, sh)
        size = (int(size[0]), int(size[1]))
        if fullscreen and size != (sw, sh):
            raise DeviceError(
                f"screen {idx} is {sw}x{sh} but {size[0]}x{size[1]} was asked for: set the projector's "
                "resolution in the operating system, or use a borderless window (fullscreen=False)")
        if size[0] > sw or size[1] > sh:
            raise DeviceError(f"a {size[0]}x{size[1]} window does not fit screen {idx} ({sw}x{sh})")

        import pyglet
        from pyglet import gl

        self._pyglet, self._gl = pyglet, gl
        self.screen_index, self.screen = idx, info
        self.fullscreen = bool(fullscreen)
        self.output_check_s = float(output_check_s)
        self._next_output_check = 0.0
        self._fault: str | None = None
        self.settle_s = float(settle_s)
        self._size = size
        screen = pyglet.display.get_display().get_screens()[idx]
        style = pyglet.window.Window.WINDOW_STYLE_BORDERLESS
        window = None
        errors = []
        for cfg in (dict(double_buffer=True, red_size=8, green_size=8, blue_size=8, alpha_size=0, depth_size=0),
                    dict(double_buffer=True, red_size=8, green_size=8, blue_size=8), None):
            try:
                kw = dict(screen=screen, vsync=vsync, caption=caption)
                if cfg is not None:
                    kw["config"] = gl.Config(**cfg)
                if fullscreen:
                    window = pyglet.window.Window(fullscreen=True, **kw)
                else:
                    window = pyglet.window.Window(size[0], size[1], style=style, visible=False, **kw)
                    window.set_location(info["x"], info["y"])
                    window.set_visible(True)
                break
            except Exception as e:  # noqa: BLE001 - pyglet.window.NoSuchConfigException and friends
                errors.append(str(e))
        if window is None:
            raise DeviceError(f"cannot open the projector window on screen {idx}: {'; '.join(errors)}")
        self._window = window
        from drivers.screen_blanking import ScreenBlankingInhibitor

        # a screen saver or DPMS would turn the projector's image off mid-session: off while the window is open
        self.blanking = ScreenBlankingInhibitor.start()
        if not self.blanking.active:
            _log.warning("%s", self.blanking.reason)
        self._owner = threading.current_thread()
        self._cond = threading.Condition()
        self._pending: deque[tuple[int, bytes]] = deque()
        self._next_ticket = 1
        self._last_presented = 0
        self._presented_at: dict[int, float] = {}
        self._current: int | None = None
        self._closed = False
        self._close_requested = False
        self._redraw = False
        self._exposed = False
        self.quit_requested = False
        quit_syms = {getattr(pyglet.window.key, k.upper()) for k in quit_keys}

        def on_key_press(symbol, modifiers):
            if symbol in quit_syms:
                self.quit_requested = True
                self._close_requested = True
            return pyglet.event.EVENT_HANDLED  # no default Esc-closes-window behaviour

        def on_close():
            self.quit_requested = True
            self._close_requested = True
            return pyglet.event.EVENT_HANDLED

        def on_expose():
            self._redraw = True
            self._exposed = True

        def on_hide():
            if not self._closed:
                self._fault = self._fault or ("the projector window is not visible any more (hidden, minimised "
                                              "or unmapped): bring it back, or restart the station")

        window.push_handlers(on_key_press=on_key_press, on_close=on_close, on_expose=on_expose, on_hide=on_hide)
        self._window_x11 = getattr(window, "_x_display", None)
        bits = [getattr(window.context.config, k, 0) or 0 for k in ("red_size", "green_size", "blue_size")]
        if min(bits) < 8:
            window.close()
            raise DeviceError(f"the display gives only {bits} bits per colour channel; 8 are needed to show "
                              "images pixel for pixel")
        self.bits_per_channel = tuple(bits)
        window.set_mouse_visible(False)
        window.switch_to()
        # wait until the window is on the screen (mapped and exposed; pyglet sets viewport and projection
        # on the way): drawing before that is lost, and the first image would count as presented while
        # the screen still showed something else
        deadline = time.monotonic() + 3.0
        while True:
            window.dispatch_events()
            if self._exposed or time.monotonic() > deadline:
                break
            time.sleep(0.005)
        fb = tuple(window.get_framebuffer_size())
        if fb != size:
            window.close()
            raise DeviceError(f"the window's framebuffer is {fb[0]}x{fb[1]} instead of {size[0]}x{size[1]} "
                              "(desktop scaling?): turn display scaling off for the projector screen")
        self.vsync = bool(getattr(window, "vsync", vsync))
        problem = self._placement_problem()
        if problem is not None:
            window.close()
            raise DeviceError(problem)
        gl.glDisable(gl.GL_DITHER)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_FRAMEBUFFER_SRGB)
        self._texture = pyglet.image.Texture.create(size[0], size[1], min_filter=gl.GL_NEAREST,
                                                    mag_filter=gl.GL_NEAREST)
        self._draw()  # a defined start: black

    # ---- ProjectorDriver ------------------------------------------------------------------------------
    @property
    def size(self) -> tuple[int, int]:
        return self._size

    @property
    def closed(self) -> bool:
        return self._closed or self._close_requested

    @property
    def refresh_hz(self) -> float:
        """The output's refresh rate; 60 when the X server does not report one (refresh_hz_known)."""
        return float(self.screen.get("refresh_hz") or 60.0)

    @property
    def refresh_hz_known(self) -> bool:
        return bool(self.screen.get("refresh_hz"))

    @property
    def fault(self) -> str | None:
        """Why the window can no longer be trusted to show images (hidden, moved, output gone), or None."""
        return self._fault

    def describe(self) -> dict:
        """The screen and window as recorded in the session manifest (rig.camera_settings.projector.screen)."""
        return {**self.screen, "window_size": list(self._size), "fullscreen": self.fullscreen, "vsync": self.vsync,
                "refresh_hz_known": self.refresh_hz_known}

    def _placement_problem(self) -> str | None:
        """Why the window is not exactly on its screen (position, size, mapped), or None."""
        w = self._window
        sx, sy, sw, sh = (self.screen[k] for k in ("x", "y", "width", "height"))
        name = self.screen.get("name") or f"screen {self.screen_index}"
        want_size = (sw, sh) if self.fullscreen else self._size
        if self._window_x11 is not None:
            from pyglet.libs.x11 import xlib

            attrs = xlib.XWindowAttributes()
            xlib.XGetWindowAttributes(self._window_x11, w._window, ctypes.byref(attrs))
            if attrs.map_state != xlib.IsViewable:
                return (f"the projector window on {name} is not visible (hidden, minimised or on another "
                        "workspace): bring it back, or restart the station")
        x, y = (int(v) for v in w.get_location())
        size = tuple(int(v) for v in w.get_size())
        if (x, y) != (sx, sy):
            return (f"the projector window is at ({x}, {y}) but its screen {name} starts at ({sx}, {sy}): the "
                    "window manager placed it elsewhere (it may be showing on another screen); check the screen "
                    "arrangement, choose the screen with --projector-screen (see `procam devices`)")
        if size != tuple(want_size):
            return (f"the projector window is {size[0]}x{size[1]} but screen {name} is {want_size[0]}x{want_size[1]}: "
                    "fullscreen did not cover the screen; turn off display scaling and check the projector's "
                    "resolution in the operating system")
        return None

    def _output_problem(self) -> str | None:
        """Why the window's output is no longer there, or None (re-lists the screens)."""
        try:
            screens = list_screens()
        except DeviceError as e:
            return f"the display went away: {e}"
        mine = self.screen
        for s in screens:
            if s.get("name") == mine.get("name") and all(s[k] == mine[k] for k in ("x", "y", "width", "height")):
                return None
        now = "; ".join(screen_line(s) for s in screens) or "none"
        return (f"the projector's output {mine.get('name')} ({mine['width']}x{mine['height']} at ({mine['x']}, "
                f"{mine['y']})) is gone or changed (screens now: {now}): reconnect the projector, then restart")

    def check(self, outputs: bool = True) -> None:
        """Raise DeviceError when the window cannot be trusted to show images (see `fault`)."""
        if self._fault is None and not self._closed:
            self._fault = self._placement_problem() or (self._output_problem() if outputs else None)
        if self._fault is not None:
            raise DeviceError(self._fault)

    def show(self, image: np.ndarray) -> int:
        """Queue `image` for presentation; returns its ticket (tickets increase by one per image)."""
        data = to_rgba(image, self._size)
        with self._cond:
            if self._fault is not None:
                raise DeviceError(self._fault)
            if self.closed:
                raise DeviceError("the projector window was closed")
            ticket = self._next_ticket
            self._next_ticket += 1
            self._pending.append((ticket, data))
            self._cond.notify_all()
        return ticket

    def wait_presented(self, ticket: int, timeout_s: float = 2.0) -> float:
        """Block until the image of `ticket` was presented and `settle_s` has passed since; returns the
        host time (time.monotonic()) from which it counts as visible."""
        if not 1 <= ticket < self._next_ticket:
            raise DeviceError(f"unknown projector ticket {ticket}")
        deadline = time.monotonic() + timeout_s
        on_owner = threading.current_thread() is self._owner
        while True:
            with self._cond:
                t = self._presented_at.get(ticket)
                if self._fault is not None:
                    raise DeviceError(self._fault)
                if t is None:
                    if self.closed:
                        raise DeviceError("the projector window was closed before the image was shown")
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise DeviceTimeout(
                            f"the projector did not present image #{ticket} within {timeout_s:.2f} s (is the "
                            "window's event loop running? see run_projector_loop)")
                    if not on_owner:
                        self._cond.wait(min(left, 0.1))
                        continue
            if t is not None:
                visible = t + self.settle_s
                delay = visible - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                return visible
            self.pump(min(left, 0.01))

    def close(self) -> None:
        """Close the window (from its own thread at once, from another thread at the next pump)."""
        if threading.current_thread() is self._owner:
            self._close_now()
        else:
            with self._cond:
                self._close_requested = True
                self._cond.notify_all()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- the window's thread ----------------------------------------------------------------------------
    def pump(self, wait_s: float = 0.0) -> bool:
        """One turn of the event loop on the window's thread: handle window events, present the next
        queued image (or redraw after an expose), else wait up to `wait_s` for a request. Returns
        False once the window is closed."""
        if threading.current_thread() is not self._owner:
            raise DeviceError("pump() must run on the thread that created the projector window")
        if self._closed:
            return False
        self._window.dispatch_events()
        if self._close_requested:
            self._close_now()
            return False
        with self._cond:
            item = self._pending.popleft() if self._pending else None
            if item is None and not self._redraw and wait_s > 0:
                self._cond.wait(wait_s)
                item = self._pending.popleft() if self._pending else None
        if item is not None:
            ticket, data = item
            image = self._pyglet.image.ImageData(self._size[0], self._size[1], "RGBA", data,
                                                 pitch=-self._size[0] * 4)
            self._window.switch_to()
            self._texture.blit_into(image, 0, 0, 0)
            self._current = ticket
            self._draw()
            t = time.monotonic()
            # the image only counts if the window is still where it must be
            now = time.monotonic()
            check_outputs = now >= self._next_output_check
            if check_outputs:
                self._next_output_check = now + self.output_check_s
            try:
                self.check(outputs=check_outputs)
            except DeviceError:
                with self._cond:
                    self._cond.notify_all()
                return not self._closed
            with self._cond:
                self._last_presented = ticket
                self._presented_at[ticket] = t
                self._cond.notify_all()
        elif self._redraw:
            self._draw()
        return not self._closed

    def _draw(self) -> None:
        gl = self._gl
        self._redraw = False
        w = self._window
        w.switch_to()
        gl.glClearColor(0.0, 0.0, 0.0, 1.0)
        w.clear()
        if self._current is not None:
            self._texture.blit(0, 0)
        w.flip()
        gl.glFinish()
        if self._window_x11 is not None:
            from pyglet.libs.x11 import xlib

            xlib.XSync(self._window_x11, False)

    def _close_now(self) -> None:
        if self._closed:
            return
        with self._cond:
            self._closed = True
            self._close_requested = True
            self._pending.clear()
            self._cond.notify_all()
        try:
            self._window.close()
        except Exception:  # noqa: BLE001 - closing twice or after the display went away
            pass
        self.blanking.restore()


def run_projector_loop(window: ProjectorWindow, worker: Callable[[], Any], close: bool = True,
                       join_timeout_s: float = 5.0) -> Any:
    """Run `worker()` in a thread while this (main) thread runs the window's event loop; returns what
    the worker returns, or raises what it raised. The loop ends when the worker ends or the window is
    closed (Esc / q, or window.close() from the worker); the worker then gets DeviceError from
    show() / wait_presented(). Closes the window at the end unless close=False."""
    result: dict[str, Any] = {}
    done = threading.Event()

    def target():
        try:
            result["value"] = worker()
        except BaseException as e:  # noqa: BLE001 - re-raised on the main thread
            result["error"] = e
        finally:
            done.set()
            with window._cond:
                window._cond.notify_all()

    thread = threading.Thread(target=target, name="procam-worker", daemon=True)
    thread.start()
    try:
        while not done.is_set():
            if not window.pump(0.005):
                break
    finally:
        if close:
            window.close()
    thread.join(join_timeout_s)
    if "error" in result:
        raise result["error"]
    return result.get("value")
