"""The session state machine: the paper's guideline as explicit states and transitions.

    check_rig -> mirror_capture -> projector_capture -> calibration -> verification -> done
                 (skipped by direct, overlapping rigs)

Every operator action is a method. An action that is impossible in the current situation raises
`ActionRefused` with a reason a person can act on (the panel shows it); `why_not(action)` gives the
same reason without acting, so the panel can grey out buttons. State changes go through the
`transitions` library; after every change the session manifest's `state` is rewritten (atomically), so
a killed process resumes where it stopped (`SessionMachine.from_store`).

The machine does not talk to devices: captured images are handed to `record_capture`, and the
calibration and verification work is done by the callables given at construction.

Its parts, each in its own module of app.station (their names are importable from here too): the steps
and actions (`session_steps`: STATES, STATE_TITLES, ACTIONS, ActionRefused), the capture plan and the
target (`plan`), when each action is possible (`action_rules`: one Rule per action, its guard) and the
calibration's files (`session_calibration`: calibration.json and its exports, a rejected result kept
apart, the default calibration).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from transitions import Machine, MachineError

from app.station.action_rules import FILE_CHECKED, RULES, Rule
from app.station.operator_files import checked_intrinsics, copy_into_session
from app.station.plan import Plan, Target
from app.station.session_calibration import CALIBRATION_FILE, default_calibrate, keep_rejected, write_calibration
from app.station.targets import free_pose, projector_choice
from app.station.structured_step import STATION_SPEC, is_structured, slot_of
from app.station.session_steps import CAPTURE_STATES  # noqa: F401 (app/recalibration.py imports it from here)
from app.station.session_steps import (
    ACTIONS, CALIBRATION, CHECK_RIG, DONE, MIRROR_CAPTURE, PROJECTOR_CAPTURE, STATE_TITLES, STATES,
    VERIFICATION, ActionRefused, mirror_step,
)
from calib.errors import FormatError, ProcamError
from calib.formats import session_files
from calib.formats.session import Capture, SessionStore
from calib.formats.session_captures import placements
from calib.models.camera import CameraModel
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, VIEW_DIRECT
from calib.models.result import CalibrationResult
from calib.models.vocab import MirrorMethod, Step

_OWN_STATE_KEYS = ("step", "pattern_position", "pose_index", "target", "retake", "mirror_method",
                   "camera_intrinsics", "plan", "calibrated", "result_stale", "verified", "updated_unix_s")


@dataclass(frozen=True)
class RigCheck:
    """One item of the rig check: camera streaming, projector window up, board and pattern specs."""

    name: str
    ok: bool
    detail: str = ""


@dataclass
class Event:
    time_s: float
    text: str


def load_intrinsics(path, camera_size: tuple[int, int] | None = None) -> CameraModel:
    """A camera model from a file (the calibration core's reader: calibration.json or OpenCV YAML);
    FormatError when it does not load or is made for another image size."""
    from calib.pipeline import load_camera_intrinsics

    path = Path(path)
    cam = load_camera_intrinsics(path, camera_size)
    if camera_size is not None and tuple(cam.size) != tuple(camera_size):
        raise FormatError(path, "camera", f"is for a {cam.width}x{cam.height} camera, this camera is "
                                          f"{camera_size[0]}x{camera_size[1]}")
    return cam


CalibrateFn = Callable[[Path, "str | None", "Callable | None"], CalibrationResult]
VerifyFn = Callable[[CalibrationResult], object]


class SessionMachine:
    """One session's progress through the guideline, backed by a SessionStore."""

    def __init__(self, store: SessionStore, plan: Plan | None = None, calibrate_fn: CalibrateFn | None = None,
                 verify_fn: VerifyFn | None = None, initial: str = CHECK_RIG):
        self.store = store
        self.plan = plan or Plan()
        self._calibrate_fn = calibrate_fn or default_calibrate
        self._verify_fn = verify_fn
        self._lock = threading.RLock()
        self.busy: str | None = None
        self.result: CalibrationResult | None = None
        self.result_stale = False
        self.calibration_error: str | None = None
        self.report = None
        self.verification_error: str | None = None
        self.rig_checks: tuple[RigCheck, ...] = ()
        self.retake_target: Target | None = None
        # the projector step's confidence after its latest detected capture (Plan.stop_on_confidence)
        self.projector_confidence = None
        self.mirror_confidence = None  # the mirror normal's, from the same calibrations (mirror rigs)
        # the devices' projection-uncertainty grids from the same calibrations (calibration.json's
        # "projection_uncertainty"): where the next placement helps most (calib.quality.next_pose)
        self.projection_uncertainty: dict | None = None
        # the whole pose asked for next (Plan.ask_pose; app/station/asked.AskedTarget), from the same calibrations
        self.asked = None
        # the projector board's layout, where the asked pose puts the pattern (set by app/station/setup.py)
        self.board_layout = None
        self.last_capture: Capture | None = None
        self.events: list[Event] = []
        self.on_event: Callable[[str], None] | None = None
        st = store.manifest.state or {}
        self.mirror_method: str | None = store.manifest.mirror_method or st.get("mirror_method")
        self.camera_intrinsics: str | None = st.get("camera_intrinsics")
        # keys of the saved state that the machine does not own (the station's rig request...) are kept
        self.extra_state: dict = {k: v for k, v in st.items() if k not in _OWN_STATE_KEYS}
        self.state: str = initial
        self._machine = Machine(model=self, states=list(STATES), initial=initial, auto_transitions=False,
                                model_attribute="state", after_state_change="_state_changed")
        t = self._machine.add_transition
        t("ev_start", CHECK_RIG, PROJECTOR_CAPTURE, conditions="is_direct")
        t("ev_start", CHECK_RIG, MIRROR_CAPTURE)
        t("ev_proceed", MIRROR_CAPTURE, PROJECTOR_CAPTURE)
        t("ev_proceed", PROJECTOR_CAPTURE, CALIBRATION)
        t("ev_back", MIRROR_CAPTURE, CHECK_RIG)
        t("ev_back", PROJECTOR_CAPTURE, CHECK_RIG, conditions="is_direct")
        t("ev_back", PROJECTOR_CAPTURE, MIRROR_CAPTURE)
        t("ev_back", CALIBRATION, PROJECTOR_CAPTURE)
        t("ev_back", VERIFICATION, CALIBRATION)
        t("ev_back", DONE, VERIFICATION, conditions="has_verification")
        t("ev_back", DONE, CALIBRATION)
        t("ev_retake", [MIRROR_CAPTURE, PROJECTOR_CAPTURE, CALIBRATION], MIRROR_CAPTURE,
          conditions="_retaking_mirror")
        t("ev_retake", [MIRROR_CAPTURE, PROJECTOR_CAPTURE, CALIBRATION], PROJECTOR_CAPTURE)
        t("ev_calibrate", [PROJECTOR_CAPTURE, CALIBRATION, VERIFICATION, DONE], CALIBRATION)
        t("ev_verify", [CALIBRATION, VERIFICATION], VERIFICATION)
        t("ev_finish", VERIFICATION, DONE)
        t("ev_finish", CALIBRATION, DONE, unless="has_verification")
        self._retake_step: str | None = None

    # ---- construction / resume ------------------------------------------------------------------
    @classmethod
    def from_store(cls, store: SessionStore, plan: Plan | None = None, **kw) -> "SessionMachine":
        """Resume a session where its manifest's `state` says it stopped."""
        st = store.manifest.state or {}
        step = st.get("step", CHECK_RIG)
        if step not in STATES:
            raise FormatError(store.folder / session_files.MANIFEST, "state.step",
                              f"must be one of {STATES}, got '{step}'")
        if plan is None and "plan" in st:
            plan = Plan.from_dict(st.get("plan"))
        # a session always resumes in a stable state: a calibration that was running is re-run on request
        m = cls(store, plan, initial=step, **kw)
        m.retake_target = Target.from_dict(st.get("retake"))
        cal = store.folder / CALIBRATION_FILE
        if cal.exists() and st.get("calibrated"):
            try:
                m.result = CalibrationResult.load_json(cal)
                m.result_stale = bool(st.get("result_stale", False))
            except FormatError as e:
                m.calibration_error = f"the saved calibration does not load ({e}); re-run the calibration"
        if m.result is None and step in (VERIFICATION, DONE):
            m.state = CALIBRATION  # nothing to verify without a result
        m._log(f"resumed in '{STATE_TITLES[m.state]}' with {len(store.manifest.captures)} captures")
        m.persist()
        return m

    # ---- facts ----------------------------------------------------------------------------------
    @property
    def manifest(self):
        return self.store.manifest

    @property
    def direct(self) -> bool:
        return self.manifest.rig.view == VIEW_DIRECT

    def is_direct(self, *_a, **_k) -> bool:
        return self.direct

    def has_verification(self, *_a, **_k) -> bool:
        return self._verify_fn is not None

    def _retaking_mirror(self, *_a, **_k) -> bool:
        return self._retake_step in (STEP_REAL_VIRTUAL, STEP_REAL_MIRROR)

    @property
    def positions(self) -> int:
        return self.manifest.pattern.positions

    @property
    def projector_total(self) -> int:
        if self.structured:
            return self.plan.structured_placements
        return self.positions * self.plan.poses_per_position

    @property
    def structured(self) -> bool:
        """The projector step shows the structured-light sequence (app.station.structured_step)."""
        return is_structured(self.manifest)

    def on_stand(self, target) -> bool:
        """Whether `target`'s board is to rest on a stand: a structured-light placement, whose sequence
        takes seconds and allows half a pixel of motion, which a board held by hand exceeds (the mean
        of a mirror placement's frames allows a hand's sway: app.station.mirror_frames)."""
        return target is not None and Step(target.step) is Step.PROJECTOR and self.structured

    @property
    def mirror_total(self) -> int:
        return 0 if self.mirror_method is None else self.plan.mirror_captures(self.mirror_method)

    def captures_of(self, step: str) -> list[Capture]:
        return self.manifest.captures_of(step)

    def mirror_captures(self) -> list[Capture]:
        return self.captures_of(STEP_REAL_VIRTUAL) + self.captures_of(STEP_REAL_MIRROR)

    def position_counts(self) -> list[int]:
        counts = [0] * self.positions
        for c in self.captures_of(STEP_PROJECTOR):
            if c.pattern_position is not None and 0 <= c.pattern_position < self.positions:
                counts[c.pattern_position] += 1
        return counts

    def _free_pose(self, caps: list[Capture], n: int) -> int | None:
        return free_pose(caps, n)

    @property
    def target(self) -> Target | None:
        """The capture asked for next in the current capture step, or None (step complete / no step)."""
        if self.state == MIRROR_CAPTURE:
            if self.mirror_method is None:
                return None
            step = mirror_step(self.mirror_method)
            caps = self.captures_of(step)
            if self.retake_target is not None and self.retake_target.step == step:
                return self.retake_target
            return self._mirror_target(step, caps)
        if self.state == PROJECTOR_CAPTURE:
            if self.retake_target is not None and self.retake_target.step == STEP_PROJECTOR:
                return self.retake_target
            return self._projector_target()
        return None

    def _mirror_target(self, step: str, caps: list[Capture]) -> Target | None:
        n = len(caps)
        if n >= self.mirror_total:
            return None
        if self.plan.stop_on_confidence and n >= self.plan.mirror_before_projector(self.mirror_method):
            # the first captures taken: the projector step next, then more only while the normal is unsure
            if self._projector_target() is not None:
                return None
            conf = self.mirror_confidence
            if conf is not None and conf.all_met:
                return None
        return Target(step, None, self._free_pose(caps, self.mirror_total + n))

    def _projector_target(self) -> Target | None:
        return projector_choice(self)[0]

    def more_mirror_wanted(self) -> bool:
        """Stopping on confidence, with the projector step complete: whether the mirror step asks for more
        captures (its normal not confident yet, its maximum not reached)."""
        if self.direct or self.mirror_method is None or not self.plan.stop_on_confidence:
            return False
        step = mirror_step(self.mirror_method)
        return self._projector_target() is None and self._mirror_target(step, self.captures_of(step)) is not None

    def mirror_confidence_lines(self) -> list[str]:
        """The mirror normal's 1-sigma against its target, as the log and the instructions say it."""
        return self.mirror_confidence.lines() if self.mirror_confidence is not None else ["not judged yet"]

    def set_mirror_confidence(self, conf) -> None:
        """The mirror step's confidence after the latest capture (None: not known yet)."""
        with self._lock:
            self.mirror_confidence = conf

    def set_projector_confidence(self, conf) -> None:
        """The projector step's confidence after its latest capture (None: not known yet)."""
        with self._lock:
            self.projector_confidence = conf

    def set_projection_uncertainty(self, pu: dict | None) -> None:
        """The projection-uncertainty grids of the latest calibration (None: none known)."""
        with self._lock:
            self.projection_uncertainty = pu

    def set_asked(self, asked) -> None:
        """The pose to ask for next (app/station/asked.AskedTarget; None: none known)."""
        with self._lock:
            self.asked = asked

    @property
    def asked_pose(self):
        """The asked pose (app/station/asked.AskedTarget) the projector step's target is for now, None when
        the target is not one (no pose computed after the captures there are now, a retake, another step)."""
        a = self.asked
        if a is None or self.state != PROJECTOR_CAPTURE or self.retake_target is not None:
            return None
        tgt = self.target
        if tgt is None or a.for_captures != len(self.captures_of(STEP_PROJECTOR)) or tgt.pattern_position != a.position:
            return None
        return a

    @property
    def next_placement(self):
        """Why the projector step's target stands where it does (calib.quality.next_pose.NextPlacement),
        None when the plan's order chose it."""
        if self.state != PROJECTOR_CAPTURE or self.retake_target is not None:
            return None
        return projector_choice(self)[1]

    def counts(self) -> dict:
        """Checklist numbers: captures taken and asked for, per step."""
        return {
            "mirror": len(self.captures_of(mirror_step(self.mirror_method))) if self.mirror_method else 0,
            "mirror_total": self.mirror_total,
            "mirror_other": len(self.mirror_captures()),
            "projector": len(self.captures_of(STEP_PROJECTOR)),
            "projector_total": self.projector_total,
            "positions_done": sum(c >= self.plan.poses_per_position for c in self.position_counts()),
            "positions": self.positions,
            "placements": placements(self.manifest.captures),
        }

    # ---- refusals -------------------------------------------------------------------------------
    def why_not(self, action: str, arg=None) -> str | None:
        """None when `action` is possible now, else the reason it is not.

        Whether the current state allows an action comes from the transition table (transitions'
        `may_<trigger>`, conditions included) for the actions that move the machine, and from
        `RULES[action].where` (app.station.action_rules) for those that stay in their state; each action's domain checks are one
        small guard."""
        if action not in ACTIONS:
            return f"unknown action '{action}'"
        if self.busy:
            return f"the station is busy ({self.busy}); wait until it finishes"
        rule = RULES[action]
        for check in (rule.before, self._state_refusal(rule), rule.guard):
            reason = check(self, arg) if check is not None else None
            if reason is not None:
                return reason
        return None

    def _state_refusal(self, rule: Rule):
        if isinstance(rule.where, str):
            allowed = getattr(self, f"may_{rule.where}")()
        else:
            allowed = self.state in rule.where
        return None if allowed else (lambda m, _arg: rule.refused(m))

    def available(self) -> dict[str, str | None]:
        """Every action with None (possible) or the reason it is refused."""
        return {a: self.why_not(a) for a in ACTIONS if a not in ("delete", "retake", "skip_camera", "set_board_thickness")}

    def _refuse(self, action: str, arg=None) -> None:
        reason = self.why_not(action, arg)
        if reason is not None:
            raise ActionRefused(action, reason)

    def _fire(self, trigger: str, action: str) -> None:
        try:
            ok = getattr(self, trigger)()
        except MachineError as e:  # a transition the table does not have: refuse with the table's reason
            raise ActionRefused(action, f"not possible during {STATE_TITLES[self.state]} ({e.value})") from None
        if not ok:
            raise ActionRefused(action, f"not possible during {STATE_TITLES[self.state]}")

    # ---- actions --------------------------------------------------------------------------------
    def set_rig_checks(self, checks) -> None:
        with self._lock:
            self.rig_checks = tuple(checks)

    def start_session(self, checks=None) -> str:
        """Leave the rig check (checks all passed). Returns the new state."""
        with self._lock:
            if checks is not None:
                self.rig_checks = tuple(checks)
            self._refuse("start")
            self._fire("ev_start", "start")
            self._log("rig checked; " + ("direct rig: mirror step skipped" if self.direct else "mirror step next"))
            return self.state

    def choose_mirror_method(self, method: str) -> None:
        with self._lock:
            self._refuse("choose_mirror_method", method)
            if method != self.mirror_method:
                self.mirror_method = method
                self.retake_target = None
                self.store.update(mirror_method=method)
                self._mark_stale()
                self._log(f"mirror method: {method}")
            self.persist()

    def set_board_thickness(self, value) -> None:
        """Real-mirror: how far the board's printed face is above the mirror surface (board units)."""
        with self._lock:
            self._refuse("set_board_thickness", value)
            value = float(value)
            if value != self.manifest.board_thickness:
                self.store.update(board_thickness=value)
                if self.mirror_method == MirrorMethod.REAL_MIRROR:
                    self._mark_stale()
                self._log(f"board thickness on the mirror: {value:g} {self.manifest.units}")
            self.persist()

    def record_capture(self, image, meta: dict | None = None, pattern_points_px=None, frames=None) -> Capture:
        """Write the capture for the current target (image first, then the manifest); return it once it
        is on disk. Projector captures store the projector pixels of the pattern at the target position;
        a structured step's capture is the sequence's `frames` (app.station.structured_step)."""
        with self._lock:
            self._refuse("capture")
            tgt = self.target
            meta = dict(meta or {})
            meta["pose_index"] = tgt.pose_index
            if self.retake_target is not None:
                meta["retake"] = True
            pts = None
            if frames is not None and tgt.step != STEP_PROJECTOR:
                raise ActionRefused("capture", "a coded sequence is a projector capture; this step is " + tgt.step)
            caps = self.manifest.captures  # each capture a placement of its own (the operator moves the board)
            placement = max([c.placement for c in caps if c.placement is not None] + [len(caps) - 1]) + 1
            if frames is not None:
                meta["slot_position"] = tgt.pattern_position
                cap = self.store.add_structured_capture(frames, STATION_SPEC, placement=placement, meta=meta)
            elif tgt.step == STEP_PROJECTOR:
                w, h = self.manifest.rig.projector_size
                pts = self.manifest.pattern.points_px(w, h, tgt.pattern_position)
                if pattern_points_px is not None:
                    pts = pattern_points_px
            if frames is None:
                cap = self.store.add_capture(tgt.step, image, tgt.pattern_position, pts, meta, placement)
            self.last_capture = cap
            self.retake_target = None
            self._mark_stale()
            where = "" if tgt.pattern_position is None else f" at pattern position {tgt.pattern_position + 1}"
            self._log(f"captured {cap.id} ({tgt.step}{where}, pose {tgt.pose_index + 1})")
            self.persist()
            return cap

    def delete_capture(self, capture_id: str) -> Capture:
        with self._lock:
            self._refuse("delete", capture_id)
            cap = next(c for c in self.manifest.captures if c.id == capture_id)
            self.store.delete_capture(capture_id)
            if self.last_capture is not None and self.last_capture.id == capture_id:
                self.last_capture = None
            self._mark_stale()
            self._log(f"deleted {capture_id}")
            self.persist()
            return cap

    def retake(self, capture_id: str | None = None) -> Target:
        """Delete a capture (by default the last one) and ask for the same pose again."""
        with self._lock:
            if capture_id is None:
                capture_id = self.last_capture.id if self.last_capture is not None else None
                if capture_id is None and self.manifest.captures:
                    capture_id = self.manifest.captures[-1].id
            self._refuse("retake", capture_id)
            cap = next(c for c in self.manifest.captures if c.id == capture_id)
            self._retake_step = cap.step
            if cap.step != STEP_PROJECTOR:
                method = MirrorMethod.REAL_VIRTUAL if cap.step == STEP_REAL_VIRTUAL else MirrorMethod.REAL_MIRROR
                self.mirror_method = method
            self.store.delete_capture(capture_id)
            tgt = Target(cap.step, *slot_of(cap)) if cap.structured else \
                Target(cap.step, cap.pattern_position, int(cap.meta.get("pose_index", 0)))
            self.retake_target = tgt
            self._mark_stale()
            try:
                self._fire("ev_retake", "retake")
            finally:
                self._retake_step = None
            self._log(f"retake of {capture_id}: deleted, same pose asked again")
            self.persist()
            return tgt

    def proceed(self) -> str:
        with self._lock:
            self._refuse("proceed")
            before = self.state
            self._fire("ev_proceed", "proceed")
            self._log(f"{STATE_TITLES[before]} complete")
            return self.state

    def go_back(self) -> str:
        with self._lock:
            self._refuse("back")
            self.retake_target = None
            self._fire("ev_back", "back")
            self._log(f"back to {STATE_TITLES[self.state]}")
            return self.state

    def skip_camera(self, path) -> None:
        """Use a pre-calibrated camera (intrinsics file) instead of calibrating it from the captures."""
        with self._lock:
            if not path:
                self._refuse("skip_camera", path)
            try:  # read once: what was checked is what the session keeps
                data = checked_intrinsics(path, self.manifest.rig.camera_size)
            except ProcamError as e:
                raise ActionRefused("skip_camera", str(e)) from None
            self._refuse("skip_camera", FILE_CHECKED)
            self.camera_intrinsics = copy_into_session(self.store.folder, path, data)
            self._mark_stale()
            self._log(f"camera intrinsics from {str(path).strip()}, copied into the session as "
                      f"{self.camera_intrinsics}; camera calibration skipped")
            self.persist()

    @property
    def intrinsics_path(self) -> str | None:
        """The given camera's file: its copy in the session (older sessions recorded an absolute path)."""
        return None if self.camera_intrinsics is None else str(Path(self.store.folder) / self.camera_intrinsics)

    def use_camera_calibration(self) -> None:
        with self._lock:
            self._refuse("use_camera_calibration")
            self.camera_intrinsics = None
            self._mark_stale()
            self._log("camera calibrated from the captures")
            self.persist()

    def _run_busy(self, work, error_attr: str, failure_text: str):
        """Run a long step outside the lock; on failure clear `busy`, and for a project error record it
        in `error_attr`, log it and persist the state before re-raising."""
        try:
            return work()
        except ProcamError as e:
            with self._lock:
                self.busy = None
                setattr(self, error_attr, str(e))
                self._log(f"{failure_text}: {e}")
                self.persist()
            raise
        except BaseException:
            with self._lock:
                self.busy = None
            raise

    def calibrate(self, progress=None) -> CalibrationResult:
        """Calibrate (or re-run the calibration) on the captures taken so far; writes calibration.json."""
        with self._lock:
            self._refuse("calibrate")
            self._fire("ev_calibrate", "calibrate")
            self.busy = "calibrating"
            self.calibration_error = None
            self.report = None
            self._log(f"calibrating {len(self.manifest.captures)} captures"
                      + (" with the given camera intrinsics" if self.camera_intrinsics else ""))
        result = self._run_busy(lambda: keep_rejected(self.store.folder, lambda: self._calibrate_fn(
            self.store.folder, self.intrinsics_path, progress)), "calibration_error", "calibration failed")
        with self._lock:
            write_calibration(self.store.folder, result, self._log)
            self.result = result
            self.result_stale = False
            self.busy = None
            rms = ", ".join(f"{k} {v:.3f} px" for k, v in result.rms.items() if isinstance(v, (int, float)))
            self._log(f"calibrated ({rms})" if rms else "calibrated")
            from calib.quality.trust import low_quality_lines  # the quality gate: usable, but say why it is not good

            for line in low_quality_lines(result):
                self._log(line)
            self.persist()
            return result

    def verify(self, **kw):
        """Run the verification of the current result (the verify callable) and keep its report."""
        with self._lock:
            self._refuse("verify")
            self._fire("ev_verify", "verify")
            self.busy = "verifying"
            self.verification_error = None
            result = self.result
        report = self._run_busy(lambda: self._verify_fn(result, **kw), "verification_error",
                                "verification failed to run")
        with self._lock:
            self.report = report
            self.busy = None
            passed = getattr(report, "passed", None)
            mean = getattr(report, "mean_proj_px", None)
            self._log("verification " + ("passed" if passed else "FAILED")
                      + (f" (mean {mean:.2f} projector px)" if isinstance(mean, (int, float)) else ""))
            self.persist()
            return report

    def hold(self, label: str, allowed_states=(CALIBRATION, VERIFICATION, DONE)):
        """Mark the station busy with `label` for the duration of a `with` block (e.g. checking one
        pixel's epipolar curve, which drives the camera and projector); refused when busy already or
        outside `allowed_states`."""
        import contextlib

        @contextlib.contextmanager
        def held():
            with self._lock:
                if self.busy:
                    raise ActionRefused(label, f"the station is busy ({self.busy}); wait until it finishes")
                if self.state not in allowed_states:
                    raise ActionRefused(label, f"not possible during {STATE_TITLES[self.state]}")
                self.busy = label
            try:
                yield
            finally:
                with self._lock:
                    self.busy = None

        return held()

    def finish(self) -> str:
        with self._lock:
            self._refuse("finish")
            self._fire("ev_finish", "finish")
            self._log("session complete")
            return self.state

    # ---- bookkeeping ----------------------------------------------------------------------------
    def _mark_stale(self) -> None:
        if self.result is not None:
            self.result_stale = True
        self.report = None

    def _state_changed(self, *_a, **_k) -> None:
        self.persist()

    def state_dict(self) -> dict:
        tgt = self.target
        return {
            **self.extra_state,
            "step": self.state,
            "pattern_position": None if tgt is None else tgt.pattern_position,
            "pose_index": None if tgt is None else tgt.pose_index,
            "target": None if tgt is None else tgt.to_dict(),
            "retake": None if self.retake_target is None else self.retake_target.to_dict(),
            "mirror_method": self.mirror_method,
            "camera_intrinsics": self.camera_intrinsics,
            "plan": self.plan.to_dict(),
            "calibrated": self.result is not None,
            "result_stale": self.result_stale,
            "verified": None if self.report is None else bool(getattr(self.report, "passed", False)),
            "updated_unix_s": round(time.time(), 3),
        }

    def persist(self) -> None:
        """Write the machine's state (step, plan, mirror method, log) into session.json."""
        self.store.update(state=self.state_dict())

    def log(self, text: str) -> None:
        """Add a line to the session's event log (the panel shows the last ones)."""
        self._log(text)

    def _log(self, text: str) -> None:
        self.events.append(Event(time.time(), text))
        del self.events[:-200]
        if self.on_event is not None:
            self.on_event(text)


