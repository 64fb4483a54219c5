"""The station's frame source: which camera frames the station sees, and which of them count.

`FrameSource` reads the camera (from a preview thread that keeps the newest frame, or directly when no
thread runs), applies the timing rule (a frame counts only if it was exposed after the last change of
the projector's image or of the board's pose, docs/STATION.md "Timing: which frames count"), says what
is wrong with the camera while it is (`device_problem`, reopening a disconnected one), and runs the
supervised capture loop of `procam station` (an unexpected error is logged with its traceback and the
loop restarts after a back-off; too many in a row stop it with a message saying what to do).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

from calib.errors import ProcamError
from drivers.base import Frame
from drivers.errors import DeviceDisconnected, DeviceError, StreamReset

_log = logging.getLogger("procam.station")


@dataclass(frozen=True)
class LoopError:
    """An unexpected error of the capture loop (it was restarted)."""

    time_s: float  # time.monotonic()
    summary: str
    traceback: str


def rate_of(times, window_s: float = 2.0, longest_s: float = 10.0) -> float:
    """Events per second of a list of time.monotonic() stamps, over the last `window_s` seconds or, when
    events come slower (a starved machine), over the span of the last three (up to `longest_s`): a slow
    but live source reads as slow, not as 0."""
    stamps = list(times)
    now = time.monotonic()
    if len(stamps) >= 3:
        window_s = min(longest_s, max(window_s, now - stamps[-3]))
    return sum(1 for t in stamps if now - t <= window_s) / window_s


class FrameSource:
    """The camera's frames for one station.

    `camera` is the rig's camera, `clock` its clock (simulated time on the simulated rig), `options`
    the station's options (`settle_frames`, `frame_timeout_s`, read when used), `machine` the session
    machine (while it is busy the camera is left alone; its log gets the camera's events), `log` the
    station's own log line, and `on_change` is called whenever the frames before now stop counting (so
    whoever judges frames starts over)."""

    # the capture loop's supervision: the first wait after an unexpected error and the longest (it
    # doubles with each failure), and this many unexpected errors in this many seconds stop it for good
    loop_backoff_s: tuple[float, float] = (0.5, 8.0)
    loop_give_up: tuple[int, float] = (5, 60.0)

    def __init__(self, camera, clock, options, machine, log: Callable[[str], None],
                 on_change: Callable[[], None] = lambda: None):
        self.camera = camera
        self.clock = clock
        self.options = options
        self.machine = machine
        self.log = log
        self.on_change = on_change
        self.last_frame = -1  # the newest frame number handed on (or seen by the rig check)
        self._min_frame = -1
        self._min_start_s = -1e18  # frames exposed before this host time show an old projector image or pose
        self.preview: Frame | None = None  # newest camera frame (preview thread)
        self._preview_times: list[float] = []
        self._detection_times: list[float] = []
        self.device_problem: str | None = None  # what is wrong with a device now (the panel says it)
        self.problem: str | None = None  # the last error of the capture loop (not a device's)
        self.loop_errors: list[LoopError] = []  # unexpected errors of the capture loop (supervised)
        self.loop_stopped: str | None = None  # why the capture loop stopped for good (None: running)
        self._stop = threading.Event()
        self._frame_cond = threading.Condition()
        self._grab_thread: threading.Thread | None = None
        self.loop_thread: threading.Thread | None = None

    # ---- which frames count -----------------------------------------------------------------------
    def changed(self, visible_s: float | None = None) -> None:
        """The projector image (visible from `visible_s`) or the board (now) changed: frames exposed
        before no longer count."""
        self._min_frame = self.last_frame + self.options.settle_frames
        self._min_start_s = max(self._min_start_s, self.clock.now() if visible_s is None else float(visible_s))
        self.on_change()

    def accepts(self, frame: Frame) -> bool:
        """The timing rule: a frame counts only if its exposure started at or after the moment the
        projector's image (and the board's pose) became what the station asked for; a camera that cannot
        time its frames skips `settle_frames` frames instead."""
        if frame.exposure_start_s is not None:
            return frame.exposure_start_s >= self._min_start_s
        return frame.frame_number > self._min_frame

    def seen(self, frame_number: int) -> None:
        """A frame read by someone else (the rig check): the next frame handed on is a newer one."""
        self.last_frame = max(self.last_frame, int(frame_number))

    # ---- reading the camera -----------------------------------------------------------------------
    def _camera_lost(self, e: DeviceError) -> None:
        """A camera error: say so in the panel; a disconnected device is reopened when it comes back."""
        self.device_problem = f"camera: {e}; waiting for it to come back"
        reconnect = getattr(self.camera, "reconnect", None)
        if isinstance(e, StreamReset):  # the driver reset a stalled stream: frames come again
            self.machine.log(f"camera: {e}")
            self.device_problem = None
            self.changed()
        elif isinstance(e, DeviceDisconnected) and callable(reconnect):
            try:
                reconnect(timeout_s=2.0)
                self.device_problem = None
                self.machine.log("camera reconnected")
                self.changed()
            except DeviceError:
                pass
        else:
            time.sleep(0.2)

    def grab(self) -> Frame | None:
        """The next frame for detection: from the preview thread when it runs, else from the camera."""
        if self._grab_thread is not None:
            with self._frame_cond:
                self._frame_cond.wait_for(lambda: (self.preview is not None and self.preview.frame_number >
                                                   self.last_frame) or self._stop.is_set(), timeout=1.0)
                frame = self.preview
            if frame is None or frame.frame_number <= self.last_frame:
                return None
            self.last_frame = frame.frame_number
            return frame
        try:
            frame = self.camera.get_frame(timeout_s=self.options.frame_timeout_s,
                                          newer_than=self.last_frame if self.last_frame >= 0 else None)
        except DeviceError as e:
            self._camera_lost(e)
            return None
        self.device_problem = None
        self.last_frame = frame.frame_number
        return frame

    def _grab_loop(self, max_fps: float) -> None:
        """Preview thread: keep the newest camera frame (for the live image and for detection)."""
        period = 1.0 / max_fps
        last_n = -1
        while not self._stop.is_set():
            t0 = time.monotonic()
            if self.machine.busy == "verifying":  # the verification owns the camera meanwhile
                time.sleep(0.1)
                continue
            if self.machine.busy == "calibrating":  # leave the processor to the calibration
                time.sleep(0.5)
            try:
                frame = self.camera.get_frame(timeout_s=self.options.frame_timeout_s,
                                              newer_than=last_n if last_n >= 0 else None)
            except DeviceError as e:
                self._camera_lost(e)
                continue
            if self.device_problem and self.device_problem.startswith("camera"):
                self.device_problem = None
            last_n = frame.frame_number
            with self._frame_cond:
                self.preview = frame
                self._preview_times.append(time.monotonic())
                del self._preview_times[:-60]
                self._frame_cond.notify_all()
            time.sleep(max(0.0, period - (time.monotonic() - t0)))

    # ---- rates ------------------------------------------------------------------------------------
    def detected(self) -> None:
        """A frame was detected on (the detection rate)."""
        self._detection_times.append(time.monotonic())
        del self._detection_times[:-60]

    @property
    def preview_fps(self) -> float:
        """Camera frames per second over the last two seconds."""
        return rate_of(self._preview_times)

    @property
    def detection_fps(self) -> float:
        """Frames detected per second over the last two seconds."""
        return rate_of(self._detection_times)

    def went_well(self) -> None:
        """A tick gave a live view: the loop's last problem is over, and a device's once frames flow."""
        self.problem = None
        if self.device_problem and self._grab_thread is not None and self.preview_fps > 0:
            self.device_problem = None

    # ---- threads ----------------------------------------------------------------------------------
    def start_preview(self, preview_fps: float = 20.0) -> None:
        """Keep the newest camera frame in a thread (the live image, its frame rate, and the frames
        the station detects on)."""
        self._grab_thread = threading.Thread(target=self._grab_loop, args=(preview_fps,), name="station-preview",
                                             daemon=True)
        self._grab_thread.start()

    def start_loop(self, tick: Callable[[], object]) -> None:
        """Call `tick` again and again in a supervised thread (the station's capture loop)."""
        self.loop_thread = threading.Thread(target=self._supervised_loop, args=(tick,), name="station-loop",
                                            daemon=True)
        self.loop_thread.start()

    def _supervised_loop(self, tick: Callable[[], object]) -> None:
        """An unexpected error is logged with its traceback (the panel's log tab and the process log),
        shown, and the loop restarts after a back-off; `loop_give_up` failures within its window stop
        it for good with a clear message."""
        failures: list[float] = []
        wait_s = self.loop_backoff_s[0]
        while not self._stop.is_set():
            try:
                tick()
                wait_s = self.loop_backoff_s[0]
            except DeviceError as e:
                self.device_problem = str(e)
                self.log(str(e))
                time.sleep(0.5)
            except ProcamError as e:  # e.g. auto mode could not go on: shown until the next good tick
                self.problem = str(e)
                self.log(str(e))
                time.sleep(0.5)
            except Exception as e:  # a bug: say so, with the traceback, and go on
                now = time.monotonic()
                failures = [t for t in failures if now - t <= self.loop_give_up[1]] + [now]
                err = LoopError(now, f"{type(e).__name__}: {e}", traceback.format_exc())
                self.loop_errors.append(err)
                del self.loop_errors[:-50]
                _log.error("procam station: the capture loop failed (%s)", err.summary, exc_info=True)
                self.machine.log(f"capture loop failed: {err.summary}\n{err.traceback}")
                if len(failures) >= self.loop_give_up[0]:
                    self.loop_stopped = (
                        f"It failed {len(failures)} times in {self.loop_give_up[1]:.0f} s (last: {err.summary}); "
                        "no more captures are taken. Stop the station and restart it with --resume on the session "
                        "folder (every acknowledged capture is in it), and report the traceback in the Log tab.")
                    self.problem = "the capture loop stopped after repeated errors; restart the station with --resume"
                    self.machine.log("capture loop stopped: " + self.loop_stopped)
                    _log.error("procam station: the capture loop stopped: %s", self.loop_stopped)
                    return
                self.problem = f"the capture loop failed ({err.summary}); restarting it in {wait_s:g} s"
                self._stop.wait(wait_s)
                wait_s = min(self.loop_backoff_s[1], wait_s * 2.0)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the capture loop and the preview thread (each given `timeout_s` to end)."""
        self._stop.set()
        with self._frame_cond:
            self._frame_cond.notify_all()
        for t in (self.loop_thread, self._grab_thread):
            if t is not None:
                t.join(timeout_s)
