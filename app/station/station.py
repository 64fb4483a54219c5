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
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from app.station import wording
from app.station.activity import CHECK_RIG_NAME, Activities, activity_name, outcome_text, rig_findings
from app.station.auto_operator import AutoOperator
from app.station.autocapture import (
    AutoCapture, AutoCaptureSettings, Decision, LiveDetection, PoseFeatures, approximate_camera, detect_for_step,
)
from app.station.capture_writer import CaptureWriter
from app.station.frame_source import FrameSource
from app.station.machine import (
    ACTIONS, CAPTURE_STATES, MIRROR_CAPTURE, PROJECTOR_CAPTURE, ActionRefused, RigCheck, SessionMachine, Target,
)
from app.station.projector_light import BACK_MESSAGE as LIGHT_BACK, LOST_MESSAGE as LIGHT_LOST, ProjectorLightWatch
from app.station.rig_check import RigChecker
from app.station.structured_step import SequenceCapture
from calib.errors import ProcamError
from calib.models.observations import STEP_PROJECTOR
from calib.models.vocab import RigKind, Step
from drivers.base import Frame
from drivers.clock import clock_of
from drivers.errors import DeviceError

_log = logging.getLogger("procam.station")


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
    """Wires its collaborators, each with one job (the modules are app.station's):

    - `machine` (machine.SessionMachine): the session's steps, targets and refusals; it writes the captures
      and runs calibration and verification. The station never decides what is allowed.
    - `frames` (frame_source.FrameSource): the camera's frames (a preview thread keeps the newest), the
      timing rule saying which count after a change, the camera's problems, the frame rates, and the
      supervised capture loop of `procam station`.
    - `operator` (auto_operator.AutoOperator): asks the rig's operator for each target's pose (the simulated
      one moves the board), for another pose when auto-capture keeps none, and with `--auto` takes the
      guideline's next step itself.
    - `autocap` (autocapture.AutoCapture): per frame, whether the board is still and in a new pose.
    - `captures` (capture_writer.CaptureWriter): writes a kept frame with its record, then detects it in the
      background as calibration will.
    - `activities` (activity.Activities): what runs now and what the last actions came to; `light_watch`
      (projector_light.ProjectorLightWatch): whether the pattern still reaches the camera; the rig check
      (rig_check.RigChecker) and the operator's words (wording) are run and asked by the station.

    What stays here: the projector's image (pattern or black, and from when it is visible), one frame's
    work (`tick`), the capture button, and the long actions (calibrate, verify, check a pixel: inline when
    headless, in a worker thread under the panel).
    """

    def __init__(self, rig, machine: SessionMachine, options: StationOptions | None = None,
                 log: Callable[[str], None] | None = None):
        self.rig = rig
        self.clock = clock_of(rig.camera)  # frame and presentation times (simulated time on the simulated rig)
        self.machine = machine
        self.options = options or StationOptions()
        self.kind = getattr(rig, "kind", RigKind.SIM)
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
        self.frames = FrameSource(cam, self.clock, self.options, machine, self.log, on_change=self._start_over)
        self.operator = AutoOperator(self)
        self.captures = CaptureWriter(machine, self.log)
        self.live: LiveView | None = None
        self._shown = None
        self.shown_ticket = 0  # the projector ticket of the image the station shows now
        self._autocap_target = object()
        self._pattern_cache: dict[int, np.ndarray] = {}
        self._worker: threading.Thread | None = None
        self._worker_error: str | None = None
        self.started_s = time.monotonic()
        self.last_capture_s = -1e9
        self.pixel_check = None  # the last live epipolar check (app.verification.PixelCheck)
        self._change_timing = None  # how the camera confirms a changed setting (drivers.exposure.ChangeTiming)
        self.progress: tuple[int, int, str] | None = None  # (done, total, label) of the running calibration
        self.on_progress: Callable | None = None
        self.light_watch = ProjectorLightWatch()  # the projector's image still reaching the camera
        self.sequence = SequenceCapture(self)  # a structured projector step's coded sequence

    @property
    def device_problem(self) -> str | None:
        """What is wrong with the camera or the projector now (None: nothing)."""
        return self.frames.device_problem

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

    def _start_over(self) -> None:
        """The frames before now no longer count (FrameSource.changed): judge the next ones afresh."""
        self.autocap.reset()
        self.operator.start_over()

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
        if state == PROJECTOR_CAPTURE and target is not None and self.machine.structured:
            want = ("white",)  # the sequence's opening image while the operator places the board
        elif state == PROJECTOR_CAPTURE and target is not None:
            want = ("pattern", target.pattern_position)
        elif state == MIRROR_CAPTURE:
            want = ("black",)
        if want is None or want == self._shown:
            return
        image = {"pattern": lambda: self.pattern_image(want[1]), "white": self.sequence.white}.get(want[0], self._black)()
        visible = self._show(image)
        self._shown = want
        self.frames.changed(visible)

    def request_pose(self, target: Target | None = None) -> str:
        """Ask the operator for the target's board pose (on the simulated rig: the board moves)."""
        return self.operator.request_pose(target)

    def retake_pose(self, target: Target, avoid: PoseFeatures | None, label: str) -> str | None:
        """After a retake: auto-capture must see a pose other than the deleted one (`avoid`); a simulated
        operator is asked for another pose for the same slot (a variant), as a person would move."""
        self.autocap.avoid(label, avoid)
        return self.operator.retake(target)

    def tick(self) -> LiveView | None:
        view = self._tick()
        if view is not None:
            self.frames.went_well()
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
            if self.operator.wants_pose(target):
                self.request_pose(target)
        except DeviceError as e:
            self.frames.device_problem = f"projector: {e}"
            time.sleep(0.2)
            return None
        if target != self._autocap_target:
            self.autocap.reset(self.captures.taken_for(target))
            self._autocap_target = target
            self.operator.start_over()
        if m.busy:
            time.sleep(0.2)  # leave the processor to the calibration; the live view slows down
        frame = self.frames.grab()
        if frame is None:
            return None
        now = self.clock.now()
        det, decision = None, None
        accepted = self.frames.accepts(frame)
        if target is not None and accepted:  # a frame exposed before the last change is not even detected
            det = detect_for_step(frame.image, target.step, m.manifest, self.camera_model, frame.frame_number)
            self.frames.detected()
            decision = self.autocap.update(det)
        if target is None or target.step != STEP_PROJECTOR or m.structured:  # (no pattern to watch in white)
            self.light_watch.reset()  # no pattern shown: no evidence (the hint clears with the step)
        elif det is not None:
            self._watch_light(self.light_watch.update(det, target))
        self.live = LiveView(frame.image, frame.frame_number, now, det, decision, target, self.frames.detection_fps,
                             accepted, frame.exposure_start_s)
        if decision is not None and target is not None and self.operator.judge(target, det, decision):
            try:
                self._capture(frame, det, decision, "auto")
            except ActionRefused:
                pass  # the target changed under us (a button action); the next tick follows it
        if self.options.auto:
            self._drive()
        return self.live

    def _capture(self, frame, det: LiveDetection, decision: Decision | None, how: str):
        sequence = mean = None
        target = self.machine.target
        if self.machine.structured and target is not None and target.step == STEP_PROJECTOR:
            # the whole coded sequence while the board stands still
            sequence = self.sequence.run(frame, det.board)
            self._refuse_placement(sequence.refused)
        elif target is not None and Step(target.step).is_mirror and self.machine.plan.mirror_frames > 1:
            from app.station.mirror_frames import capture_mean

            mean = capture_mean(self, frame, det, self.machine.plan.mirror_frames)
            self._refuse_placement(mean.refused)
            frame = mean.frame
        cap = self.captures.write(frame, det, decision, how, self.shown_ticket,
                                  self.operator.asked_index(self.machine.target), sequence, mean)
        self.last_capture_s = time.monotonic()
        self.frames.changed()
        return cap

    def _refuse_placement(self, reason: str | None) -> None:
        """A placement whose frames cannot be kept (the board moved, a frame missing): say why, forget its
        frames and ask for it again (ActionRefused); nothing when `reason` is None."""
        if reason is None:
            return
        self.log(f"placement refused: {reason}")
        self.machine.log(f"placement refused: {reason}")
        self.frames.changed()
        self.operator.start_over()
        self.autocap.reset(self.captures.taken_for(self.machine.target))
        raise ActionRefused("capture", reason)

    def wait_for_detections(self, timeout_s: float | None = None) -> None:
        """Block until every capture taken so far has been detected in the background."""
        self.captures.wait(timeout_s)

    def capture_now(self):
        """The operator's capture button: the newest frame, if what the step needs is detected in it."""
        live = self.live
        m = self.machine
        if self.frames.loop_stopped:
            raise ActionRefused("capture", "the capture loop stopped after repeated errors; restart the station")
        reason = m.why_not("capture")
        if reason:
            raise ActionRefused("capture", reason)
        if live is None or live.detection is None or live.target != m.target:
            raise ActionRefused("capture", "no camera frame for the current step yet; wait a moment")
        frame = Frame(live.image, live.frame_number, live.timestamp_s * 1000.0,
                      exposure_start_s=live.exposure_start_s)  # the frame detected on
        if not self.frames.accepts(frame):
            raise ActionRefused("capture", "the projector or the board just changed; wait for a new frame")
        if not live.detection.ok:
            raise ActionRefused("capture", f"the current frame is not usable: {live.detection.failure}")
        return self._capture(frame, live.detection, live.decision, "button")

    def _drive(self) -> None:
        """Auto mode: take the step the guideline asks for next (app.recalibration narrows it)."""
        self.operator.drive()

    # ---- long actions -----------------------------------------------------------------------------
    background_long_actions = False

    @property
    def long_action_running(self) -> bool:
        """A long action runs in its worker thread now."""
        return self._worker is not None and self._worker.is_alive()

    def run_long(self, name: str, fn: Callable[[], object], action: str | None = None):
        """Calibration and verification: inline (headless) or in a worker thread (panel). A refused
        action (`action`, default `name` when it is one of the machine's) is refused here, before any
        thread starts, so the caller shows the reason."""
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
        if self.long_action_running:
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
                self.rig.operator.request_pose(Step.VERIFICATION, None, 0)
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
        self.frames.start_preview(preview_fps)

    def start_loop(self, preview_fps: float = 20.0) -> None:
        """Run the station in background threads: a preview thread keeping the newest frame and a
        station thread detecting and capturing on it (the panel only draws)."""
        self.background_long_actions = True
        self.frames.start_preview(preview_fps)
        self.frames.start_loop(self.tick)

    def stop_loop(self, timeout_s: float = 5.0) -> None:
        self.frames.stop(timeout_s)
        if self._worker is not None:
            self._worker.join(timeout_s)
        self.captures.close()

    # ---- what to do next ----------------------------------------------------------------------------
    def instruction(self) -> str:
        """What the person at the rig should do next, in plain words (app.station.wording)."""
        return wording.instruction(self.machine, self.frames.device_problem, self.frames.problem,
                                   self.live_hint(self.live))

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
