"""`--rig sim-uvc`: the simulated world seen through the OpenCV camera driver, over a live MJPEG stream.

    rig = open_sim_uvc_rig("nonoverlap-136", seed=0)
    rig.stream.url       # http://127.0.0.1:PORT/camera.mjpg, what cv2.VideoCapture (FFmpeg) opens
    rig.camera           # SimStreamCamera: drivers.opencv_camera.OpenCVCamera on that URL
    rig.projector, rig.operator, rig.ground_truth()   # the simulated rig's own

`SimCameraStream` serves the simulated camera as multipart/x-mixed-replace JPEG over HTTP on
127.0.0.1, each frame with a strip of cells under the picture carrying the frame's exposure start on
the rig's simulated clock, its exposure and its gain (drivers/frame_stamp.py): the driver reads frame
times from the pixels, so the station's latency gating runs on the rig's own clock however late the
stream delivers (FFmpeg's and the socket's buffering included). The simulated camera renders lazily,
so the server renders a new frame only while a caller waits in get_frame (SimStreamCamera tells it, as
the RealSense emulation's pusher is told); otherwise it repeats the last frame every `idle_resend_s`
(the driver drops it as a duplicate by its stamp) so the stream never times out.

A stream has no exposure or gain: `StreamControls` stands in for the capture's properties and sends
each write to the server's side channel (`POST /controls`, JSON), which applies it to the simulated
camera (`controls="honour"`), or, for a camera that ignores manual exposure, accepts it and changes
nothing (`controls="ignore"`: the driver reads the old value back). `unplug()` closes every
connection and refuses new ones (503) until `replug()`.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import urllib.error
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np

from drivers.errors import DeviceError
from drivers.frame_stamp import FrameStamp, encode_stamp
from drivers.opencv_camera import FrameTiming, OpenCVCamera
from drivers.sim._driver_rig import SimDriverRig
from calib.models.vocab import RenderQuality, RigKind

CONTROL_MODES = ("honour", "ignore")


class SimCameraStream:
    """The simulated camera as an MJPEG stream with frame stamps (module doc)."""

    def __init__(self, sim_camera, host: str = "127.0.0.1", port: int = 0, jpeg_quality: int = 95,
                 controls: str = "honour", idle_resend_s: float = 0.25):
        if controls not in CONTROL_MODES:
            raise DeviceError(f"unknown stream controls mode '{controls}' (one of {', '.join(CONTROL_MODES)})")
        self.sim_camera = sim_camera
        self.jpeg_quality = int(jpeg_quality)
        self.controls_mode = controls
        self.idle_resend_s = float(idle_resend_s)
        self._cond = threading.Condition()
        self._demand = 0
        self._closing = False
        self.unplugged = False
        self._conns: set = set()
        self._sim_lock = threading.Lock()  # one connection renders at a time
        self._last: tuple[int, bytes] | None = None
        timeline = getattr(sim_camera, "settings_timeline", None)
        now = dict(timeline.current) if timeline is not None else {}
        self.state = {"auto_exposure": bool(now.get("auto_exposure", True)),
                      "exposure_us": float(now.get("exposure_us", sim_camera.exposure_limits()["exposure_us"][1])),
                      "gain": float(now.get("gain", sim_camera.exposure_limits()["gain"][0]))}
        self.forwarded: list[tuple[str, object]] = []
        self.rendered = 0
        self.sent = 0
        stream = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # quiet: tests and sessions print their own lines
                pass

            def do_GET(self):
                if self.path.startswith("/controls"):
                    return self._json(200, stream.controls_reply())
                if not self.path.startswith("/camera.mjpg"):
                    return self._json(404, {"error": "not found"})
                if stream.unplugged or stream._closing:
                    return self._json(503, {"error": "unplugged"})
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                stream._serve(self)

            def do_POST(self):
                if not self.path.startswith("/controls") or stream.unplugged:
                    return self._json(404 if not stream.unplugged else 503, {"error": "no such control"})
                try:
                    n = min(int(self.headers.get("Content-Length") or 0), 4096)
                    body = json.loads(self.rfile.read(n).decode("utf-8"))
                    if not isinstance(body, dict):
                        raise ValueError("not an object")
                    reply = stream.apply_controls(body)
                except (ValueError, TypeError, KeyError) as e:
                    return self._json(400, {"error": str(e)})
                return self._json(200, reply)

            def _json(self, code, obj):
                data = json.dumps(obj).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self._server = ThreadingHTTPServer((host, int(port)), Handler)
        self._server.daemon_threads = True
        self.host, self.port = self._server.server_address[:2]
        self._thread = threading.Thread(target=self._server.serve_forever, name="sim-camera-stream", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/camera.mjpg"

    @property
    def controls_url(self) -> str:
        return f"http://{self.host}:{self.port}/controls"

    # ---- demand -------------------------------------------------------------------------------------
    @contextlib.contextmanager
    def hold(self):
        """New frames are rendered while this is held (a caller waits for a frame)."""
        with self._cond:
            self._demand += 1
            self._cond.notify_all()
        try:
            yield
        finally:
            with self._cond:
                self._demand -= 1

    # ---- frames -------------------------------------------------------------------------------------
    def _frame_bytes(self, want_new: bool) -> bytes | None:
        with self._sim_lock:
            last = self._last
            if last is not None and not want_new:
                return last[1]
            sim = self.sim_camera
            if not getattr(sim, "running", True):
                sim.start()
            f = sim.get_frame(2.0) if last is None else sim.get_frame(2.0, newer_than=last[0])
            if last is not None and f.frame_number <= last[0]:
                return None
            meta = f.meta if isinstance(f.meta, dict) else {}
            exposure_us = float(meta.get("exposure_us") or 1e6 / 30.0)
            start_s = f.exposure_start_s if f.exposure_start_s is not None else f.timestamp_ms * 1e-3
            stamp = FrameStamp(int(f.frame_number), int(round(start_s * 1e6)), exposure_us,
                               float(meta.get("gain") or 1.0))
            img = np.asarray(f.image, np.uint8)
            if img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            full = np.vstack([img, encode_stamp(stamp, img.shape[1])])
            ok, buf = cv2.imencode(".jpg", full, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:
                raise DeviceError("the simulated stream could not encode a frame")
            self._last = (int(f.frame_number), buf.tobytes())
            self.rendered += 1
            return self._last[1]

    def _serve(self, handler) -> None:
        conn = handler.connection
        with self._cond:
            self._conns.add(conn)
        try:
            first = True
            while not self._closing and not self.unplugged:
                with self._cond:
                    if not first and self._demand == 0:
                        self._cond.wait(self.idle_resend_s)
                    want_new = self._demand > 0
                data = self._frame_bytes(want_new or (first and self._last is None))
                first = False
                if data is None:
                    continue
                handler.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(data)
                                    + data + b"\r\n")
                handler.wfile.flush()
                self.sent += 1
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass  # the client went away (stop(), a reconnect) or the cable was pulled
        finally:
            with self._cond:
                self._conns.discard(conn)

    # ---- the side channel ---------------------------------------------------------------------------
    def controls_reply(self) -> dict:
        return {"state": dict(self.state), "limits": {k: list(v) for k, v in self.sim_camera.exposure_limits().items()},
                "mode": self.controls_mode}

    def apply_controls(self, body: dict) -> dict:
        """Apply {"auto_exposure": bool, "exposure_us": x, "gain": g} (any of them) to the simulated camera;
        with controls="ignore" nothing changes. Returns the controls' state."""
        want = dict(self.state)
        for key, kind in (("auto_exposure", bool), ("exposure_us", float), ("gain", float)):
            if key in body:
                v = body[key]
                if kind is float and (isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v)):
                    raise ValueError(f"{key} must be a finite number")
                want[key] = kind(v)
        if self.controls_mode == "honour":
            cam = self.sim_camera
            if want["auto_exposure"]:
                if not self.state["auto_exposure"]:
                    cam.set_auto_exposure(True)
                    self.forwarded.append(("auto_exposure", True))
            else:
                got = cam.set_manual_exposure(want["exposure_us"], want["gain"])
                want.update(exposure_us=float(got["exposure_us"]), gain=float(got["gain"]))
                self.forwarded.append(("manual", (want["exposure_us"], want["gain"])))
            self.state = want
        return self.controls_reply()

    # ---- plugging -----------------------------------------------------------------------------------
    def unplug(self) -> None:
        """The camera goes away: open streams end, new ones are refused."""
        self.unplugged = True
        with self._cond:
            conns = list(self._conns)
            self._cond.notify_all()
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)

    def replug(self) -> None:
        self.unplugged = False

    def close(self) -> None:
        self._closing = True
        self.unplug()
        self._server.shutdown()
        self._server.server_close()


class StreamControls:
    """drivers.opencv_camera.CaptureControls for the simulated stream: each write goes to the server's
    side channel; reads return the state the server reports (module doc)."""

    backend = "STREAM"

    def __init__(self, controls_url: str, timeout_s: float = 2.0):
        self.url = controls_url
        self.timeout_s = float(timeout_s)
        self._state: dict = {}
        self._limits: dict | None = None

    def _call(self, body: dict | None) -> dict:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.url, data=data, method="GET" if body is None else "POST",
                                     headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as r:
                reply = json.loads(r.read().decode())
        except (urllib.error.URLError, OSError, ValueError) as e:
            raise DeviceError(f"the simulated camera's controls did not answer ({e})") from None
        self._state = dict(reply.get("state") or {})
        self._limits = {k: tuple(float(x) for x in v) for k, v in (reply.get("limits") or {}).items()}
        return reply

    def limits(self) -> dict:
        if self._limits is None:
            self._call(None)
        return dict(self._limits)

    def set(self, prop: int, value: float) -> bool:
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE:
            self._call({"auto_exposure": float(value) >= 2.0})  # V4L2's values: 1 manual, 3 auto
        elif prop == cv2.CAP_PROP_EXPOSURE:
            self._call({"auto_exposure": False, "exposure_us": float(value)})
        elif prop == cv2.CAP_PROP_GAIN:
            self._call({"gain": float(value)})
        else:
            return False  # white balance and the rest: the simulated camera has none to set
        return True

    def get(self, prop: int) -> float:
        if not self._state:
            self._call(None)
        if prop == cv2.CAP_PROP_EXPOSURE:
            return float(self._state.get("exposure_us", -1.0))
        if prop == cv2.CAP_PROP_GAIN:
            return float(self._state.get("gain", -1.0))
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE:
            return 3.0 if self._state.get("auto_exposure") else 1.0
        return -1.0


class SimStreamCamera(OpenCVCamera):
    """The OpenCV driver, unchanged, on the simulated stream, plus what the emulation needs: new frames
    are rendered while a caller waits in start() or get_frame (the simulated camera renders on demand)."""

    def __init__(self, stream: SimCameraStream, clock, **kw):
        super().__init__(stream.url, timing=FrameTiming.STAMP, clock=clock,
                         controls=StreamControls(stream.controls_url), **kw)
        self.stream = stream
        #: driver frame number -> the simulated camera's frame number, for every frame handed out (so a
        #: test can look up what the simulator showed during that frame's exposure)
        self.device_numbers: dict[int, int] = {}

    def start(self) -> None:
        with self.stream.hold():
            super().start()

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None, not_before_s: float | None = None):
        with self.stream.hold():
            f = super().get_frame(timeout_s, newer_than=newer_than, not_before_s=not_before_s)
        self.device_numbers[f.frame_number] = int(f.meta["device_frame_number"])
        return f


class SimUvcRig(SimDriverRig):
    """A simulated rig whose camera is the OpenCV driver on the simulated camera's live stream."""

    kind = RigKind.SIM_UVC

    def __init__(self, sim_rig, controls: str = "honour", jpeg_quality: int = 95):
        self.sim = sim_rig
        self.stream = SimCameraStream(sim_rig.camera, controls=controls, jpeg_quality=jpeg_quality)
        self.camera = SimStreamCamera(self.stream, sim_rig.clock)

    def _close_feed(self) -> None:
        self.stream.close()


def open_sim_uvc_rig(scenario: str | None = None, seed: int = 0, quality: str = RenderQuality.LIVE, faults=(),
                     controls: str = "honour", jpeg_quality: int = 95, **settings) -> SimUvcRig:
    """The simulated rig of `scenario` (drivers.sim.rig.open_sim_rig options, its own simulated clock)
    with its camera served as a stream and read through drivers/opencv_camera.py; the fault
    "ignores-exposure" (drivers.sim.faults) is controls="ignore"."""
    from drivers.sim.rig import open_sim_rig

    args = () if scenario is None else (scenario,)
    sim = open_sim_rig(*args, seed=seed, quality=quality, faults=faults, **settings)
    sim.camera.start()
    if "ignores-exposure" in (faults or ()):
        controls = "ignore"
    return SimUvcRig(sim, controls, jpeg_quality)
