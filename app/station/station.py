"""The station controller: drives a rig (camera, projector, operator) through a session.

One `tick()` is one camera frame: keep the projector showing what the current target needs, ask the
operator for the target's pose when the station leads the operator, detect what the step needs, feed
auto-capture, and write a capture when it says so. `procam session --auto` calls `tick()` in a loop;
`procam station` calls it from a background thread while the panel shows `live` and calls the
operator's actions (which go through the SessionMachine, so refusals carry their reasons).
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from app.station import wording
from app.station.activity import CHECK_RIG_NAME, Activities, activity_name, outcome_text, rig_findings
from app.station.autocapture import (
    AutoCapture,
    AutoCaptureSettings,
    Decision,
    LiveDetection,
    PoseFeatures,
    approximate_camera,
    detect_for_step,
)
from app.station.machine import (
    CALIBRATION,
    CAPTURE_STATES,
    CHECK_RIG,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    VERIFICATION,
    ActionRefused,
    RigCheck,
    SessionMachine,
    Target,
)
from app.station.projector_light import BACK_MESSAGE as LIGHT_BACK, LOST_MESSAGE as LIGHT_LOST, ProjectorLightWatch
from app.station.rig_check import RigChecker
from calib.detection.detect import DetectionFailure, detect_capture
from calib.errors import ProcamError, SessionError
from calib.models.observations import STEP_PROJECTOR
from drivers.base import Frame
from drivers.clock import clock_of
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


@dataclass
class StationOptions:
    auto: bool = False  # the station runs the whole session itself (the simulated operator moves the board)
    auto_capture: bool = True  # capture when the board is detected, still and in a new pose
    follow_operator: bool | None = None  # ask the operator for each new pose (None: real rigs, or auto)
    mirror_method: str | None = None  # auto: the method to choose (None: the scenario's, else real-virtual)
    settle_frames: int = 2  # frames to skip after a change, for a camera that cannot time its frames
    frame_timeout_s: float = 3.0
    max_frames_per_target: int = 12  # auto: frames without a capture before asking for another pose
    max_variants: int = 3  # auto: other poses asked for one target before giving up
    stuck_frames: int = 3  # auto: still frames that are unusable or too similar before asking for another pose
    autocapture: AutoCaptureSettings = field(default_factory=AutoCaptureSettings)


@dataclass(frozen=True, eq=False)
class LiveView:
    """The newest frame with what was detected in it, for the panel."""

    image: np.ndarray
    frame_number: int
    timestamp_s: float
    detection: LiveDetection | None
    decision: Decision | None
    target: Target | None
    fps: float
    accepted: bool = True  # exposed after the last projector or board change (may be captured)
    exposure_start_s: float | None = None  # Frame.exposure_start_s


class Station:
    def __init__(self, rig, machine: SessionMachine, options: StationOptions | None = None,
                 log: Callable[[str], None] | None = None):
        self.rig = rig
        self.clock = clock_of(rig.camera)  # frame and presentation times (simulated time on the simulated rig)
        self.machine = machine
        self.options = options or StationOptions()
        self.kind = getattr(rig, "kind", "sim")
        from drivers.factory import is_simulated

        self.is_sim = is_simulated(self.kind)
        self.log = log or (lambda text: None)
        self.activities = Activities(log=machine.log)  # what runs and what the last actions came to (the panel)
        if self.options.follow_operator is None:
            self.options.follow_operator = self.options.auto or not self.is_sim
        cam = self.rig.camera
        factory = None
        try:
            factory = cam.factory_intrinsics()
        except Exception:  # a device that cannot report intrinsics is judged with an approximate model
            factory = None
        self.camera_model = approximate_camera(tuple(cam.size), factory)
        self.autocap = AutoCapture(self.options.autocapture)
        self.live: LiveView | None = None
        self.operator_says: str = ""
        self.device_problem: str | None = None
        self._shown = None
        self.shown_ticket = 0  # the projector ticket of the image the station shows now
        self._requested: Target | None = None
        self._autocap_target = object()
        self._last_frame = -1
        self._min_frame = -1
        self._min_start_s = -1e18  # frames exposed before this host time show an old projector image or pose
        self._frames_on_target = 0
        self._similar_frames = 0
        self._failing_frames = 0
        self._tick_times: list[float] = []
        self._pattern_cache: dict[int, np.ndarray] = {}
        self._worker: threading.Thread | None = None
        self._worker_error: str | None = None
        self._stop = threading.Event()
        self._loop_thread: threading.Thread | None = None
        self.loop_errors: list[LoopError] = []  # unexpected errors of the capture loop (supervised)
        self.loop_stopped: str | None = None  # why the capture loop stopped for good (None: running)
        self._grab_thread: threading.Thread | None = None
        self._frame_cond = threading.Condition()
        self.preview = None  # newest camera frame (preview thread)
        self._preview_times: list[float] = []
        self._operator_index = 0
        self._variant = 0  # auto mode: how many times the operator was asked for another pose
        self.started_s = time.monotonic()
        self.last_capture_s = -1e9
        self.problem: str | None = None  # the last error of the background loop (not a device's)
        # every capture is detected once, in the background, as calibration will (detections.json)
        self._detector = ThreadPoolExecutor(max_workers=1, thread_name_prefix="station-detect")
        self._detecting: list[Future] = []
        self.pixel_check = None  # the last live epipolar check (app.verification.PixelCheck)
        self._change_timing = None  # how the camera confirms a changed setting (drivers.exposure.ChangeTiming)
        self.progress: tuple[int, int, str] | None = None  # (done, total, label) of the running calibration
        self.on_progress: Callable | None = None
        self.light_watch = ProjectorLightWatch()  # the projector's image still reaching the camera

    # ---- devices --------------------------------------------------------------------------------
    @property
    def projector_size(self) -> tuple[int, int]:
        return tuple(self.machine.manifest.rig.projector_size)

    def _black(self) -> np.ndarray:
        w, h = self.projector_size
        return np.zeros((h, w), np.uint8)

    def pattern_image(self, position: int) -> np.ndarray:
        if position not in self._pattern_cache:
            w, h = self.projector_size
            self._pattern_cache[position] = self.machine.manifest.pattern.render(w, h, position)[0]
        return self._pattern_cache[position]

    def _show(self, image: np.ndarray) -> float:
        """Show `image`; returns the host time from which it is visible (presentation + the projector's
        measured latency, ProjectorDriver.wait_presented)."""
        ticket = self.rig.projector.show(image)
        self.shown_ticket = ticket
        return self.rig.projector.wait_presented(ticket, timeout_s=self.options.frame_timeout_s)

    def _changed(self, visible_s: float | None = None) -> None:
        """The projector image (visible from `visible_s`) or the board (now) changed: frames exposed
        before no longer count."""
        self._min_frame = self._last_frame + self.options.settle_frames
        self._min_start_s = max(self._min_start_s, self.clock.now() if visible_s is None else float(visible_s))
        self.autocap.reset()
        self._frames_on_target = 0
        self._similar_frames = 0
        self._failing_frames = 0

    def check_rig(self) -> list[RigCheck]:
        """Camera streaming, projector window presenting, board and pattern specs usable; an activity
        ("Check rig") with a line per stage while it runs, and its findings logged and kept as its outcome."""
        with self.activities.running(CHECK_RIG_NAME, "camera: waiting for a frame") as act:
            checks = RigChecker(self).run()
            for c in checks:
                self.machine.log(f"rig check: {c.name} {'ok' if c.ok else 'FAILED'}: {c.detail}")
            act.outcome, act.failed = rig_findings(checks), not all(c.ok for c in checks)
        return checks

    # ---- one frame ------------------------------------------------------------------------------
    def _sync_projector(self, state: str, target: Target | None) -> None:
        want = None
        if state == PROJECTOR_CAPTURE and target is not None:
            want = ("pattern", target.pattern_position)
        elif state == MIRROR_CAPTURE:
            want = ("black",)
        if want is None or want == self._shown:
            return
        visible = self._show(self.pattern_image(want[1]) if want[0] == "pattern" else self._black())
        self._shown = want
        self._changed(visible)

    def request_pose(self, target: Target | None = None) -> str:
        """Ask the operator for the target's board pose (on the simulated rig: the board moves)."""
        target = target or self.machine.target
        if target is None:
            raise ActionRefused("move the board", "no capture is asked for now")
        if target != self._requested and self._requested is not None:
            self._variant = 0
        index = target.pose_index + 100 * self._variant  # a variant: another pose for the same slot
        text = self.rig.operator.request_pose(target.step, target.pattern_position, index)
        self.operator_says = text or ""
        self._requested = target
        self._operator_index = index
        self._changed()
        return self.operator_says

    def retake_pose(self, target: Target, avoid: PoseFeatures | None, label: str) -> str | None:
        """After a retake: auto-capture must see a pose other than the deleted one (`avoid`); a simulated
        operator is asked for another pose for the same slot (a variant), as a person would move."""
        self.autocap.avoid(label, avoid)
        if not self.is_sim:
            return None
        self._requested = target
        self._variant += 1
        index = target.pose_index + 100 * self._variant
        self.operator_says = self.rig.operator.request_pose(target.step, target.pattern_position, index) or ""
        self._operator_index = index
        self._changed()
        return self.operator_says

    def _camera_lost(self, e: DeviceError) -> None:
        """A camera error: say so in the panel; a disconnected device is reopened when it comes back."""
        self.device_problem = f"camera: {e}; waiting for it to come back"
        reconnect = getattr(self.rig.camera, "reconnect", None)
        if isinstance(e, StreamReset):  # the driver reset a stalled stream: frames come again
            self.machine.log(f"camera: {e}")
            self.device_problem = None
            self._changed()
        elif isinstance(e, DeviceDisconnected) and callable(reconnect):
            try:
                reconnect(timeout_s=2.0)
                self.device_problem = None
                self.machine.log("camera reconnected")
                self._changed()
            except DeviceError:
                pass
        else:
            time.sleep(0.2)

    def accepts(self, frame: Frame) -> bool:
        """The timing rule: a frame counts only if its exposure started at or after the moment the
        projector's image (and the board's pose) became what the station asked for; a camera that cannot
        time its frames skips `settle_frames` frames instead."""
        if frame.exposure_start_s is not None:
            return frame.exposure_start_s >= self._min_start_s
        return frame.frame_number > self._min_frame

    def _grab(self):
        """The next frame for detection: from the preview thread when it runs, else from the camera."""
        if self._grab_thread is not None:
            with self._frame_cond:
                self._frame_cond.wait_for(lambda: (self.preview is not None and self.preview.frame_number >
                                                   self._last_frame) or self._stop.is_set(), timeout=1.0)
                frame = self.preview
            if frame is None or frame.frame_number <= self._last_frame:
                return None
            self._last_frame = frame.frame_number
            return frame
        try:
            frame = self.rig.camera.get_frame(timeout_s=self.options.frame_timeout_s,
                                              newer_than=self._last_frame if self._last_frame >= 0 else None)
        except DeviceError as e:
            self._camera_lost(e)
            return None
        self.device_problem = None
        self._last_frame = frame.frame_number
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
                frame = self.rig.camera.get_frame(timeout_s=self.options.frame_timeout_s,
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

    @property
    def preview_fps(self) -> float:
        """Camera frames per second over the last two seconds."""
        return rate_of(self._preview_times)

    @property
    def detection_fps(self) -> float:
        """Frames detected per second over the last two seconds."""
        return rate_of(self._tick_times)

    def taken_for(self, target: Target | None) -> list[tuple[str, PoseFeatures]]:
        """Features of the captured poses a new capture for `target` must differ from."""
        if target is None:
            return []
        out = []
        for c in self.machine.manifest.captures_of(target.step):
            if target.step == STEP_PROJECTOR and c.pattern_position != target.pattern_position:
                continue
            f = PoseFeatures.from_dict(c.meta.get("pose")) if isinstance(c.meta.get("pose"), dict) else None
            if f is not None:
                out.append((c.id, f))
        return out

    def tick(self) -> LiveView | None:
        view = self._tick()
        if view is not None:
            self.problem = None
            if self.device_problem and self._grab_thread is not None and self.preview_fps > 0:
                self.device_problem = None  # frames flow again
        return view

    def _tick(self) -> LiveView | None:
        m = self.machine
        if m.busy == "verifying":  # the verification drives camera and projector itself
            time.sleep(0.05)
            return None
        state = m.state
        target = m.target if state in CAPTURE_STATES and not m.busy else None
        try:
            self._sync_projector(state, target)
            if target is not None and self.options.follow_operator and target != self._requested:
                self.request_pose(target)
        except DeviceError as e:
            self.device_problem = f"projector: {e}"
            time.sleep(0.2)
            return None
        if target != self._autocap_target:
            self.autocap.reset(self.taken_for(target))
            self._autocap_target = target
            self._frames_on_target = 0
            self._similar_frames = 0
            self._failing_frames = 0
        if m.busy:
            time.sleep(0.2)  # leave the processor to the calibration; the live view slows down
        frame = self._grab()
        if frame is None:
            return None
        now = self.clock.now()
        det, decision = None, None
        accepted = self.accepts(frame)
        if target is not None and accepted:  # a frame exposed before the last change is not even detected
            det = detect_for_step(frame.image, target.step, m.manifest, self.camera_model, frame.frame_number)
            self._tick_times.append(time.monotonic())
            del self._tick_times[:-60]
            decision = self.autocap.update(det)
            self._frames_on_target += 1
        if target is None or target.step != STEP_PROJECTOR:
            self.light_watch.reset()  # no pattern shown: no evidence (the hint clears with the step)
        elif det is not None:
            self._watch_light(self.light_watch.update(det, target))
        self.live = LiveView(frame.image, frame.frame_number, now, det, decision, target, self.detection_fps,
                             accepted, frame.exposure_start_s)
        if decision is not None and target is not None:
            take = decision.capture and self.options.auto_capture
            if not take and self.options.auto:
                similar = decision.still and det.ok and not decision.novel
                failing = decision.still and not det.ok  # board still, but the frame is not usable
                self._similar_frames = self._similar_frames + 1 if similar else 0
                self._failing_frames = self._failing_frames + 1 if failing else 0
                stuck = self._similar_frames >= self.options.stuck_frames or \
                    self._failing_frames >= self.options.stuck_frames or \
                    self._frames_on_target > self.options.max_frames_per_target
                if stuck and self._variant < self.options.max_variants:
                    self.log(f"no capture for this pose ({decision.message}); asking the operator for another pose")
                    self._variant += 1
                    self._requested = None
                    self.request_pose(target)
                elif stuck and similar:
                    take = True  # the operator cannot do better: keep the pose it was asked for
                    self.log(f"keeping a pose close to {decision.similar_to} (no other pose was found)")
                elif stuck:
                    raise SessionError(
                        f"no usable frame for {target.step} (pattern position {target.pattern_position}, pose "
                        f"{target.pose_index}) in {self._variant + 1} poses: {decision.message}")
            if take:
                try:
                    self._capture(frame, det, decision, "auto")
                except ActionRefused:
                    pass  # the target changed under us (a button action); the next tick follows it
        if self.options.auto:
            self._drive()
        return self.live

    def _capture(self, frame, det: LiveDetection, decision: Decision | None, how: str):
        meta = {"how": how, "frame_number": int(frame.frame_number), "timestamp_ms": float(frame.timestamp_ms),
                "projector_ticket": int(self.shown_ticket)}
        if frame.exposure_start_s is not None:
            meta["exposure_start_s"] = float(frame.exposure_start_s)
        if det.features is not None:
            meta["pose"] = det.features.to_dict()
        if det.board is not None:
            meta["corners"] = int(len(det.board.ids))
            # the corners as detected live: the panel redraws the board poses with the calibrated camera
            meta["board_ids"] = [int(i) for i in det.board.ids]
            meta["board_px"] = np.round(np.asarray(det.board.corners_px, float), 3).tolist()
        if det.virtual is not None:
            meta["virtual_corners"] = int(len(det.virtual.ids))
        if decision is not None and decision.motion_px is not None:
            meta["motion_px"] = round(float(decision.motion_px), 4)
        if decision is not None and decision.similar_to:
            meta["similar_to"] = decision.similar_to
        if self._requested == self.machine.target and self._requested is not None:
            meta["operator_pose_index"] = int(self._operator_index)
        cap = self.machine.record_capture(frame.image, meta)
        self.last_capture_s = time.monotonic()
        self.log(f"captured {cap.id}: {self._describe(cap)}")
        self._detect_in_background(cap.id)
        self._changed()
        return cap

    def _detect_in_background(self, capture_id: str) -> None:
        """Detect a new capture from its file exactly as calibration will (calib.detection.detect.detect_capture) in
        a background thread, keeping the result in the session's detections.json. Calibrate then finds
        every image already detected, and a capture that calibration would leave out is reported now,
        while the operator can still retake it."""
        store = self.machine.store

        def work():
            try:
                result = detect_capture(store, capture_id)
            except ProcamError:
                return  # deleted before its turn
            if isinstance(result, DetectionFailure) and any(c.id == capture_id for c in store.manifest.captures):
                self.log(f"{capture_id}: {result.reason}; calibration will leave it out (retake it to replace it)")

        self._detecting = [f for f in self._detecting if not f.done()] + [self._detector.submit(work)]

    def wait_for_detections(self, timeout_s: float | None = None) -> None:
        """Block until every capture taken so far has been detected in the background."""
        for f in list(self._detecting):
            f.result(timeout_s)

    def _describe(self, cap) -> str:
        m = self.machine
        k = cap.meta.get("pose_index", 0) + 1
        if cap.step == STEP_PROJECTOR:
            c = m.counts()
            return (f"pattern position {cap.pattern_position + 1}/{m.positions}, pose {k}/"
                    f"{m.plan.poses_per_position} ({c['projector']}/{c['projector_total']})")
        c = m.counts()
        return f"{cap.step}, pose {k} ({c['mirror']}/{c['mirror_total']})"

    def capture_now(self):
        """The operator's capture button: the newest frame, if what the step needs is detected in it."""
        live = self.live
        m = self.machine
        if self.loop_stopped:
            raise ActionRefused("capture", "the capture loop stopped after repeated errors; restart the station")
        reason = m.why_not("capture")
        if reason:
            raise ActionRefused("capture", reason)
        if live is None or live.detection is None or live.target != m.target:
            raise ActionRefused("capture", "no camera frame for the current step yet; wait a moment")
        frame = Frame(live.image, live.frame_number, live.timestamp_s * 1000.0,
                      exposure_start_s=live.exposure_start_s)  # the frame detected on
        if not self.accepts(frame):
            raise ActionRefused("capture", "the projector or the board just changed; wait for a new frame")
        if not live.detection.ok:
            raise ActionRefused("capture", f"the current frame is not usable: {live.detection.failure}")
        return self._capture(frame, live.detection, live.decision, "button")

    # ---- the station leads a whole session --------------------------------------------------------
    def _default_mirror_method(self) -> str:
        if self.options.mirror_method:
            return self.options.mirror_method
        sc = getattr(self.rig, "scenario", None)
        method = getattr(sc, "mirror_method", None)
        return method or "real-virtual"

    def _drive(self) -> None:
        """Auto mode: take the step the guideline asks for next."""
        m = self.machine
        if m.busy or (self._worker is not None and self._worker.is_alive()):
            return
        s = m.state
        if s == CHECK_RIG:
            m.start_session(self.check_rig())  # (its findings are logged)
        elif s == MIRROR_CAPTURE:
            if m.mirror_method is None:
                m.choose_mirror_method(self._default_mirror_method())
            elif m.target is None:
                m.proceed()
        elif s == PROJECTOR_CAPTURE:
            if m.target is None:
                self.run_long("calibrate", self.calibrate)
        elif s == CALIBRATION:
            if m.result is not None and not m.result_stale:
                if m.why_not("verify") is None:
                    self.run_long("verify", self.verify)
                elif m.why_not("finish") is None:
                    m.finish()
            elif m.calibration_error is None and m.why_not("calibrate") is None:
                self.run_long("calibrate", self.calibrate)
        elif s == VERIFICATION:
            if m.why_not("finish") is None:
                m.finish()
            elif m.report is None and m.verification_error is None and m.why_not("verify") is None:
                self.run_long("verify", self.verify)

    # ---- long actions -----------------------------------------------------------------------------
    background_long_actions = False

    def run_long(self, name: str, fn: Callable[[], object], action: str | None = None):
        """Calibration and verification: inline (headless) or in a worker thread (panel). A refused
        action (`action`, default `name` when it is one of the machine's) is refused here, before any
        thread starts, so the caller shows the reason."""
        from app.station.machine import ACTIONS

        action = action or (name if name in ACTIONS else None)
        reason = self.machine.why_not(action) if action else (
            f"the station is busy ({self.machine.busy}); wait until it finishes" if self.machine.busy else None)
        if reason is not None:
            raise ActionRefused(name, reason)
        label = activity_name(name)
        if not self.background_long_actions:
            with self.activities.running(label) as act:
                out = fn()
                act.outcome = outcome_text(name, out)
            return out
        if self._worker is not None and self._worker.is_alive():
            raise ActionRefused(name, "another long action is running")
        self._worker_error = None
        self.activities.start(label)  # before the thread: whoever pressed the button sees it running

        def work():
            try:
                self.activities.conclude(label, fn, lambda out: outcome_text(name, out))
            except ProcamError as e:
                self._worker_error = str(e)
                self.log(f"{name} failed: {e}")

        self._worker = threading.Thread(target=work, name=f"station-{name}", daemon=True)
        self._worker.start()
        return None

    def calibrate(self):
        self._shown = None  # the projector is free again after the captures
        self.progress = None

        def progress(done, total, label=""):
            self.progress = (int(done), int(total), str(label))
            self.activities.progress(activity_name("calibrate"), f"{label or 'step'} {done} of {total}", log=False)
            if self.on_progress is not None:
                self.on_progress(done, total, label)

        self.wait_for_detections()  # the last capture's, at most a fraction of a second
        return self.machine.calibrate(progress=progress)

    def verify(self):
        self._shown = None
        return self.machine.verify()

    def check_pixel(self, x: float, y: float):
        """The live epipolar check of one camera pixel with the current calibration: the projector draws
        the pixel's epipolar curve, the camera sees it, the distance is measured (app.verification)."""
        m = self.machine
        if m.result is None:
            raise ActionRefused("check a pixel", "calibrate first")
        from app.verification import verify_pixel
        from calib.detection.response import recorded_response

        with m.hold("verifying"):
            if self.is_sim:  # the simulated person holds the board where the projector lights it
                self.rig.operator.request_pose("verification", None, 0)
            self._shown = None
            check = verify_pixel(self.rig.camera, self.rig.projector, m.result, (float(x), float(y)),
                                 response=recorded_response(m.manifest.rig.camera_settings))
        self.pixel_check = check
        m.log("pixel check " + check.label())
        return check

    # ---- background loop (panel) ------------------------------------------------------------------
    def start_preview(self, preview_fps: float = 20.0) -> None:
        """Keep the newest camera frame in a thread (the live image, its frame rate, and the frames
        `tick` detects on), whoever ticks the station."""
        self._grab_thread = threading.Thread(target=self._grab_loop, args=(preview_fps,), name="station-preview",
                                             daemon=True)
        self._grab_thread.start()

    def start_loop(self, preview_fps: float = 20.0) -> None:
        """Run the station in background threads: a preview thread keeping the newest frame and a
        station thread detecting and capturing on it (the panel only draws)."""
        self.background_long_actions = True
        self.start_preview(preview_fps)

        self._loop_thread = threading.Thread(target=self._supervised_loop, name="station-loop", daemon=True)
        self._loop_thread.start()

    # the capture loop's supervision: an unexpected error is logged with its traceback (the panel's log
    # tab and the process log), shown, and the loop restarts after a back-off that doubles with each
    # failure; `loop_give_up` failures within the window stop it for good with a clear message
    loop_backoff_s: tuple[float, float] = (0.5, 8.0)  # first wait after an unexpected error, longest
    loop_give_up: tuple[int, float] = (5, 60.0)  # this many unexpected errors in this many seconds: stop

    def _supervised_loop(self) -> None:
        failures: list[float] = []
        wait_s = self.loop_backoff_s[0]
        while not self._stop.is_set():
            try:
                self.tick()
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

    def stop_loop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        with self._frame_cond:
            self._frame_cond.notify_all()
        for t in (self._loop_thread, self._grab_thread, self._worker):
            if t is not None:
                t.join(timeout_s)
        self._detector.shutdown(wait=True, cancel_futures=True)

    # ---- what to do next ----------------------------------------------------------------------------
    def instruction(self) -> str:
        """What the person at the rig should do next, in plain words (app.station.wording)."""
        return wording.instruction(self.machine, self.device_problem, self.problem, self.live_hint(self.live))

    def _watch_light(self, event: str | None) -> None:
        """Log an episode of a projector image that no longer reaches the camera, once when it begins and
        once when it ends (app.station.projector_light)."""
        if event == "lost":
            self.log(LIGHT_LOST)
            _log.warning(LIGHT_LOST)
        elif event == "back":
            self.log(LIGHT_BACK)

    def live_hint(self, live: LiveView | None) -> str:
        return wording.live_hint(self.light_watch.lost, live)

    def status_line(self) -> str:
        return wording.status_line(self.machine)
