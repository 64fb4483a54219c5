"""The station's automatic operator: it asks the rig's operator for each target's board pose and, with
`--auto`, runs the whole session itself.

The rig's operator (`rig.operator`) is the simulated person on the simulated rig (asked for a pose, the
board moves there) and a prompt for a real person otherwise. `AutoOperator` remembers what it asked for
(the target, and which variant: another pose for the same slot), asks for another pose when auto-capture
sees none it may keep (still frames too close to a capture, or unusable, or too many frames), and in
auto mode takes the step the guideline asks for next (start, choose the mirror method, next step,
calibrate, verify, finish).
"""

from __future__ import annotations

from app.station.autocapture import Decision, LiveDetection
from app.station.machine import (
    CALIBRATION,
    CHECK_RIG,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    VERIFICATION,
    ActionRefused,
    Target,
)
from calib.errors import SessionError
from calib.models.vocab import MirrorMethod

VARIANT_STRIDE = 100  # a variant's pose index: the slot's plus this many per variant


class AutoOperator:
    """Leads the operator of one station (`station`: its rig, machine, options and long actions)."""

    def __init__(self, station):
        self.station = station
        self.requested: Target | None = None  # the target whose pose was asked for last
        self.says: str = ""  # what the operator answered (a person's instruction, the simulated one's note)
        self.pose_index = 0  # the pose index asked for (the slot's, or a variant's)
        self.variant = 0  # how many times another pose was asked for the same target
        self._frames_on_target = 0
        self._similar_frames = 0
        self._failing_frames = 0

    @property
    def options(self):
        return self.station.options

    def start_over(self) -> None:
        """The frames seen so far no longer count (a change, a new target)."""
        self._frames_on_target = 0
        self._similar_frames = 0
        self._failing_frames = 0

    def forget(self) -> None:
        """Ask for the current target's pose again at the next frame."""
        self.requested = None

    def wants_pose(self, target: Target | None) -> bool:
        """Whether `target`'s pose is still to be asked for (the station leads the operator)."""
        return target is not None and bool(self.options.follow_operator) and target != self.requested

    def _ask(self, target: Target) -> str:
        index = target.pose_index + VARIANT_STRIDE * self.variant
        m = self.station.machine
        asked = m.asked_pose  # the whole pose (Plan.ask_pose): the operator holds the dashed outline
        self.says = self.station.rig.operator.request_pose(
            target.step, target.pattern_position, index, asked=None if asked is None else asked.T_cam_board,
            on_stand=m.on_stand(target)) or ""
        self.requested = target
        self.pose_index = index
        self.station.frames.changed()
        return self.says

    def request_pose(self, target: Target | None = None) -> str:
        """Ask the operator for the target's board pose (on the simulated rig: the board moves)."""
        target = target or self.station.machine.target
        if target is None:
            raise ActionRefused("move the board", "no capture is asked for now")
        if target != self.requested and self.requested is not None:
            self.variant = 0
        if target != self.requested:
            best = self.station.machine.next_placement
            if best is not None and target.pattern_position == best.position:
                self.station.log(f"next placement: {best.reason()}")
            asked = self.station.machine.asked_pose
            if asked is not None:
                self.station.log(f"asked pose: {asked.reason()}")
        return self._ask(target)

    def retake(self, target: Target) -> str | None:
        """After a retake: a simulated operator is asked for another pose for the same slot (a variant),
        as a person would move; a person is told by the panel."""
        if not self.station.is_sim:
            return None
        self.variant += 1
        return self._ask(target)

    def asked_index(self, target: Target | None) -> int | None:
        """The pose index the operator was asked for, when `target` is what was asked for."""
        return self.pose_index if target is not None and target == self.requested else None

    def judge(self, target: Target, det: LiveDetection, decision: Decision) -> bool:
        """Whether to capture this detected frame: auto-capture's decision; in auto mode, when the board
        stays where no capture may be kept, another pose is asked for (up to `max_variants`), then a pose
        close to another capture is kept, and a frame never usable stops the session (SessionError)."""
        opts = self.options
        self._frames_on_target += 1
        take = decision.capture and opts.auto_capture
        if take or not opts.auto:
            return take
        similar = decision.still and det.ok and not decision.novel
        failing = decision.still and not det.ok  # board still, but the frame is not usable
        self._similar_frames = self._similar_frames + 1 if similar else 0
        self._failing_frames = self._failing_frames + 1 if failing else 0
        stuck = self._similar_frames >= opts.stuck_frames or self._failing_frames >= opts.stuck_frames or \
            self._frames_on_target > opts.max_frames_per_target
        if stuck and self.variant < opts.max_variants:
            self.station.log(f"no capture for this pose ({decision.message}); asking the operator for another pose")
            self.variant += 1
            self.requested = None
            self.request_pose(target)
        elif stuck and similar:
            self.station.log(f"keeping a pose close to {decision.similar_to} (no other pose was found)")
            return True  # the operator cannot do better: keep the pose it was asked for
        elif stuck:
            raise SessionError(
                f"no usable frame for {target.step} (pattern position {target.pattern_position}, pose "
                f"{target.pose_index}) in {self.variant + 1} poses: {decision.message}")
        return False

    # ---- the whole session ------------------------------------------------------------------------
    def mirror_method(self) -> str:
        """The mirror method auto mode chooses: the option's, else the scenario's, else real-virtual."""
        if self.options.mirror_method:
            return self.options.mirror_method
        sc = getattr(self.station.rig, "scenario", None)
        method = getattr(sc, "mirror_method", None)
        return method or MirrorMethod.REAL_VIRTUAL

    def drive(self) -> None:
        """Auto mode: take the step the guideline asks for next."""
        st = self.station
        m = st.machine
        if m.busy or st.long_action_running:
            return
        s = m.state
        if s == CHECK_RIG:
            m.start_session(st.check_rig())  # (its findings are logged)
        elif s == MIRROR_CAPTURE:
            if m.mirror_method is None:
                m.choose_mirror_method(self.mirror_method())
                return
            if m.plan.stop_on_confidence:
                st.wait_for_detections()  # the next pose only once the last capture's confidence is known
            if m.target is None:
                m.proceed()
        elif s == PROJECTOR_CAPTURE:
            if m.plan.stop_on_confidence:
                st.wait_for_detections()
            if m.target is None and m.more_mirror_wanted():
                # the projector step is done, the mirror normal not yet confident: more mirror placements
                st.log("mirror step again: " + "; ".join(m.mirror_confidence_lines()))
                m.go_back()
            elif m.target is None:
                st.run_long("calibrate", st.calibrate)
        elif s == CALIBRATION:
            if m.result is not None and not m.result_stale:
                if m.why_not("verify") is None:
                    st.run_long("verify", st.verify)
                elif m.why_not("finish") is None:
                    m.finish()
            elif m.calibration_error is None and m.why_not("calibrate") is None:
                st.run_long("calibrate", st.calibrate)
        elif s == VERIFICATION:
            if m.why_not("finish") is None:
                m.finish()
            elif m.report is None and m.verification_error is None and m.why_not("verify") is None:
                st.run_long("verify", st.verify)
