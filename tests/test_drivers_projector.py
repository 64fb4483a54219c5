"""The projector window under a real X server (Xvfb): what the screen shows (xwd screenshots) equals
the requested images pixel for pixel, at two resolutions, as soon as wait_presented returns.

pyglet connects to the display when its window module is imported, so every window runs in a fresh
interpreter with DISPLAY set to the test's own Xvfb."""

import json

import numpy as np
import pytest

from _drivers_helpers import run_python, screenshot, xvfb
from calib.models.pattern import PatternSpec
from drivers import projector_images as pi

pytestmark = pytest.mark.display

SHOW_SCRIPT = r"""
import json, os, sys, time
import numpy as np
from _drivers_helpers import screenshot
from drivers.projector_window import ProjectorWindow, run_projector_loop

inp = np.load(sys.argv[1])
names = list(inp.files)
win = ProjectorWindow(0)
assert win.size == tuple(int(v) for v in sys.argv[3].split("x")), win.size
log = []

def worker():
    shots = {}
    for n in names:
        t0 = time.monotonic()
        ticket = win.show(inp[n])
        visible = win.wait_presented(ticket, 5.0)
        shots[n] = screenshot(os.environ["DISPLAY"])   # right after wait_presented returned
        log.append({"name": n, "ticket": ticket, "waited_s": visible - t0})
    return shots

shots = run_projector_loop(win, worker)
np.savez(sys.argv[2], **shots)
print(json.dumps({"log": log, "closed": win.closed, "bits": win.bits_per_channel}))
"""


def expected_images(W, H):
    rng = np.random.default_rng(7)
    circles = PatternSpec.default_for(W, H, "circles")
    chess = PatternSpec.default_for(W, H, "chessboard")
    ramp = np.zeros((H, W, 3), np.uint8)
    ramp[:, :, 0] = (np.arange(W) % 256)[None, :]           # blue ramp along x
    ramp[:, :, 1] = (np.arange(H) % 256)[:, None]           # green ramp along y: orientation
    ramp[:, :, 2] = 255 - (np.arange(W) % 256)[None, :]
    lines = [np.array([[10.3, 5.7], [W - 20.2, H / 2], [W / 3, H - 3.2]]), np.array([[0, H - 1], [W - 1, 0]])]
    return {
        "black": pi.black((W, H)),
        "white": pi.white((W, H)),
        "checker1": pi.checkerboard((W, H), 1),
        "checker1_phase": pi.checkerboard((W, H), 1, phase=1),
        "circles_0": circles.render(W, H, 0)[0],
        "circles_12": circles.render(W, H, 12)[0],
        "chessboard_4": chess.render(W, H, 4)[0],
        "noise_bgr": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        "ramps": ramp,
        "epipolar_aa": pi.draw_polylines((W, H), lines, 3.0, (40, 200, 255), antialias=True,
                                         background=np.full((H, W), 30, np.uint8)),
    }


def as_bgr(img):
    return img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2)


@pytest.mark.parametrize("size", [(1280, 720), (1920, 1080)])
def test_window_shows_images_pixel_exact(size, tmp_path):
    W, H = size
    imgs = expected_images(W, H)
    np.savez(tmp_path / "in.npz", **imgs)
    with xvfb(size) as display:
        r = run_python(SHOW_SCRIPT, display, args=(str(tmp_path / "in.npz"), str(tmp_path / "out.npz"), f"{W}x{H}"))
        assert r.returncode == 0, r.stderr[-3000:]
        report = json.loads(r.stdout.strip().splitlines()[-1])
        # the window was closed at the end of the loop: nothing of it is left on the screen
        assert screenshot(display).max() == 0
    shots = np.load(tmp_path / "out.npz")
    assert report["closed"] and tuple(report["bits"]) == (8, 8, 8)
    assert [e["ticket"] for e in report["log"]] == list(range(1, len(imgs) + 1))
    for name, img in imgs.items():
        shot = shots[name]
        assert shot.shape == (H, W, 3)
        diff = np.abs(shot.astype(int) - as_bgr(img).astype(int))
        assert diff.max() == 0, f"{name}: {np.count_nonzero(diff.max(axis=2))} pixels differ (max {diff.max()})"


PROTOCOL_SCRIPT = r"""
import json, os, threading, time
import numpy as np
from _drivers_helpers import screenshot
from drivers.base import ProjectorDriver
from drivers.errors import DeviceError, DeviceTimeout
from drivers.projector_window import ProjectorWindow, list_screens, run_projector_loop
from drivers import projector_images as pi

out = {"screens": list_screens()}
disp = os.environ["DISPLAY"]

def error_of(fn):
    try:
        fn()
    except DeviceError as e:
        return f"{type(e).__name__}: {e}"
    return None

out["bad_screen"] = error_of(lambda: ProjectorWindow(3))
out["bad_fullscreen_size"] = error_of(lambda: ProjectorWindow(0, size=(800, 600)))

# a borderless window smaller than the screen, at the screen's top-left corner
small = ProjectorWindow(0, size=(800, 600), fullscreen=False)
img = pi.checkerboard((800, 600), 1)
small.wait_presented(small.show(img), 5.0)   # single-threaded use: wait_presented pumps by itself
shot = screenshot(disp)
out["small_exact"] = bool(np.array_equal(shot[:600, :800], np.repeat(img[:, :, None], 3, 2)))
out["small_outside_black"] = int(shot[600:, :].max()) + int(shot[:, 800:].max())
small.close()

win = ProjectorWindow(0, settle_s=0.25)
out["is_projector_driver"] = isinstance(win, ProjectorDriver)
W, H = win.size
out["wrong_size"] = error_of(lambda: win.show(np.zeros((H, W + 1), np.uint8)))
out["wrong_type"] = error_of(lambda: win.show(np.zeros((H, W), np.float32)))
out["unknown_ticket"] = error_of(lambda: win.wait_presented(99))

def worker():
    res = {}
    # three requests at once from this thread: presented in order, each for at least one refresh
    imgs = [pi.solid((W, H), v) for v in (60, 120, 180)]
    t_show = time.monotonic()
    tickets = [win.show(im) for im in imgs]
    times = [win.wait_presented(t, 5.0) for t in tickets]
    res["tickets"] = tickets
    res["in_order"] = all(b >= a for a, b in zip(times, times[1:]))
    res["settle_respected"] = time.monotonic() - t_show >= 0.25 and times[0] - t_show >= 0.25
    res["last_on_screen"] = int(np.unique(screenshot(disp)).tolist() == [180])
    # another thread waits for an image this thread shows
    got = {}
    t = win.show(pi.white((W, H)))
    th = threading.Thread(target=lambda: got.setdefault("t", win.wait_presented(t, 5.0)))
    th.start(); th.join(10)
    res["other_thread_waited"] = "t" in got and int(screenshot(disp).min()) == 255
    win.close()                        # from the worker: the loop closes the window and ends
    time.sleep(0.3)
    res["show_after_close"] = error_of(lambda: win.show(pi.black((W, H))))
    return res

out["worker"] = run_projector_loop(win, worker)
out["closed"] = win.closed

# a worker's exception reaches the main thread
w2 = ProjectorWindow(0)
def failing():
    raise RuntimeError("worker failed")
try:
    run_projector_loop(w2, failing)
    out["worker_error"] = None
except RuntimeError as e:
    out["worker_error"] = str(e)
out["closed_after_error"] = w2.closed

# Esc / q typed on the window end the loop; other keys do not; the worker's next show() fails
from _drivers_helpers import send_key
for key in ("Escape", "q"):
    w3 = ProjectorWindow(0)
    def quitting_worker():
        w3.wait_presented(w3.show(pi.white(w3.size)), 5.0)
        send_key_requests.append(key)
        while not w3.closed:
            time.sleep(0.01)
        return error_of(lambda: w3.show(pi.black(w3.size)))
    send_key_requests = []
    # the key is sent from the main thread between pumps (Xlib calls stay on the window's thread)
    import threading as _t
    th = _t.Thread(target=lambda: out.setdefault("quit_" + key, quitting_worker()))
    th.start()
    sent_other = False
    t_end = time.monotonic() + 10
    while th.is_alive() and time.monotonic() < t_end:
        if send_key_requests and not sent_other:
            send_key(w3, "a")          # not a quit key
            for _ in range(10):
                w3.pump(0.01)
            out["alive_after_other_key_" + key] = not w3.closed
            send_key(w3, key)
            sent_other = True
        w3.pump(0.01)
    th.join(5)
    out["quit_requested_" + key] = w3.quit_requested

# nobody runs the loop: waiting from another thread times out with a clear message
w4 = ProjectorWindow(0)
res = {}
t = w4.show(pi.white(w4.size))
th = threading.Thread(target=lambda: res.setdefault("e", error_of(lambda: w4.wait_presented(t, 0.3))))
th.start(); th.join(5)
out["no_loop"] = res.get("e")
w4.close()
print(json.dumps(out))
"""


def test_window_protocol_threads_and_errors():
    with xvfb((1280, 720)) as display:
        r = run_python(PROTOCOL_SCRIPT, display)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    (screen,) = out["screens"]  # Xvfb: one RandR output named "screen", no refresh rate
    assert {k: screen[k] for k in ("index", "x", "y", "width", "height")} == \
        {"index": 0, "x": 0, "y": 0, "width": 1280, "height": 720}
    assert screen["name"] == "screen" and screen["refresh_hz"] is None
    assert "no screen 3" in out["bad_screen"] and "0: screen 1280x720 at (0, 0)" in out["bad_screen"]
    assert "1280x720 but 800x600" in out["bad_fullscreen_size"]
    assert out["small_exact"] and out["small_outside_black"] == 0
    assert out["is_projector_driver"]
    assert "must be 1280x720" in out["wrong_size"] and "uint8" in out["wrong_type"]
    assert "unknown projector ticket" in out["unknown_ticket"]
    w = out["worker"]
    assert w["tickets"] == [1, 2, 3] and w["in_order"] and w["settle_respected"] and w["last_on_screen"]
    assert w["other_thread_waited"]
    assert "closed" in w["show_after_close"] and out["closed"]
    assert out["worker_error"] == "worker failed" and out["closed_after_error"]
    for key in ("Escape", "q"):
        assert out["alive_after_other_key_" + key] and out["quit_requested_" + key]
        assert "closed" in out["quit_" + key]
    assert out["no_loop"].startswith("DeviceTimeout") and "event loop" in out["no_loop"]


SETTLE_SCRIPT = r"""
import json, os
from _drivers_helpers import ScreenCamera
from drivers.projector_window import ProjectorWindow, measure_settle, run_projector_loop

win = ProjectorWindow(0, settle_s=0.123)
cam = ScreenCamera(os.environ["DISPLAY"])
cam.start()
m = run_projector_loop(win, lambda: measure_settle(win, cam, trials=3, observe_s=0.6, rest_s=0.2))
cam.stop()
print(json.dumps({"m": m.to_dict(), "restored": win.settle_s, "grab_max_s": max(cam.grab_durations_s)}))
"""


def test_settle_time_measured_with_a_camera_filming_the_screen():
    """A real window and a 'camera' that films the X screen (xwd): the change is never seen before
    the presentation, and is seen within about one grab (the camera's frame time) after it."""
    with xvfb((1280, 720)) as display:
        r = run_python(SETTLE_SCRIPT, display)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    m = out["m"]
    assert len(m["samples_s"]) == 3 and out["restored"] == pytest.approx(0.123)
    assert m["changed_fraction"] > 0.99  # the whole screen turned white
    for s in m["samples_s"]:
        assert 0.0 < s <= 2 * out["grab_max_s"] + 0.15  # + scheduling slack on a busy machine
    # each sample bounds the latency from above, so the tightest is the smallest; the recommended
    # settle time is that bound plus at least the 10 ms jitter margin (drivers/settle.py)
    assert m["settle_s"] >= min(m["samples_s"]) + 0.010 - 1e-9
    assert m["settle_s"] <= min(m["samples_s"]) + max(0.010, max(m["samples_s"]) - min(m["samples_s"])) + 1e-9


BLANKING_SCRIPT = r"""
import ctypes, ctypes.util, json
from drivers.projector_window import ProjectorWindow

x11 = ctypes.CDLL(ctypes.util.find_library("X11"))
x11.XOpenDisplay.restype = ctypes.c_void_p
x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
x11.XGetScreenSaver.argtypes = [ctypes.c_void_p] + [ctypes.POINTER(ctypes.c_int)] * 4
x11.XSetScreenSaver.argtypes = [ctypes.c_void_p] + [ctypes.c_int] * 4
x11.XFlush.argtypes = [ctypes.c_void_p]
d = x11.XOpenDisplay(None)

def timeout():  # as another X client sees it
    v = [ctypes.c_int() for _ in range(4)]
    x11.XGetScreenSaver(d, *[ctypes.byref(x) for x in v])
    return v[0].value

x11.XSetScreenSaver(d, 600, 60, 1, 1)  # a desktop's screen saver: blank after 10 minutes
x11.XFlush(d)
out = {"before": timeout()}
win = ProjectorWindow(0)
out["open"] = timeout()
out["active"] = win.blanking.active
win.close()
out["after"] = timeout()
print(json.dumps(out))
"""


def test_the_window_keeps_the_screen_saver_off_while_open_and_restores_it():
    """A screen saver (or DPMS) would blank the projector mid-session: the window sets the X server's
    screen saver timeout to 0 while it is open and puts the old one back when it closes."""
    with xvfb((1280, 720)) as display:
        r = run_python(BLANKING_SCRIPT, display)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"before": 600, "open": 0, "active": True, "after": 600}, out
