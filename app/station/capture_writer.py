"""The station's captures: a frame the station keeps, written into the session with what it knew of it,
then detected once in the background exactly as calibration will detect it.

`CaptureWriter.write` hands the image and its record (how it was taken, frame number and exposure time,
the projector image shown, the live detection's corners and pose) to the session machine, which writes
it; the capture is then detected from its file (calib.detection.detect.detect_capture) in a background
thread, keeping the result in the session's detections.json, so calibration finds every image detected
already and a capture it would leave out is reported while the operator can still retake it.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from app.station.autocapture import Decision, LiveDetection, PoseFeatures
from app.station.confidence_watch import update_after
from app.station.machine import SessionMachine, Target
from calib.detection.detect import DetectionFailure, detect_capture
from calib.errors import ProcamError
from calib.models.observations import STEP_PROJECTOR


def capture_meta(frame, det: LiveDetection, decision: Decision | None, how: str, projector_ticket: int,
                 operator_pose_index: int | None) -> dict:
    """What a capture records of the frame it was taken from (session.json, docs/FORMATS.md)."""
    meta = {"how": how, "frame_number": int(frame.frame_number), "timestamp_ms": float(frame.timestamp_ms),
            "projector_ticket": int(projector_ticket)}
    if frame.exposure_start_s is not None:
        meta["exposure_start_s"] = float(frame.exposure_start_s)
    if det.features is not None:
        meta["pose"] = det.features.to_dict()
    if det.board is not None:
        meta["corners"] = len(det.board.ids)
        # the corners as detected live: the panel redraws the board poses with the calibrated camera
        meta["board_ids"] = [int(i) for i in det.board.ids]
        meta["board_px"] = np.round(np.asarray(det.board.corners_px, float), 3).tolist()
    if det.virtual is not None:
        meta["virtual_corners"] = len(det.virtual.ids)
    if decision is not None and decision.motion_px is not None:
        meta["motion_px"] = round(float(decision.motion_px), 4)
    if decision is not None and decision.similar_to:
        meta["similar_to"] = decision.similar_to
    if operator_pose_index is not None:
        meta["operator_pose_index"] = int(operator_pose_index)
    return meta


class CaptureWriter:
    """Writes one station's captures (through `machine`) and detects them in the background."""

    def __init__(self, machine: SessionMachine, log: Callable[[str], None]):
        self.machine = machine
        self.log = log
        self._detector = ThreadPoolExecutor(max_workers=1, thread_name_prefix="station-detect")
        self._detecting: list[Future] = []

    def write(self, frame, det: LiveDetection, decision: Decision | None, how: str, projector_ticket: int,
              operator_pose_index: int | None = None, sequence=None, mean=None):
        """Write the capture of the current target from `frame` (ActionRefused when the target changed);
        a structured step's from its captured `sequence` (structured_step.SequenceResult), `frame` its
        opening frame; a mirror placement of several frames (mirror_frames.MeanFrame) from their mean."""
        meta = capture_meta(frame, det, decision, how, projector_ticket, operator_pose_index)
        if mean is not None:
            meta.update({"frames_averaged": len(mean.frame_numbers), "frame_numbers": list(mean.frame_numbers),
                         "motion_px": round(float(mean.motion_px), 4)})
        asked = self.machine.asked_pose
        if asked is not None:  # the pose the station asked for (--ask-pose): what the operator was to hold
            meta["asked_T_cam_board"] = np.round(np.asarray(asked.T_cam_board, float), 6).tolist()
        if sequence is not None:
            meta.update({"frame_numbers": list(sequence.frame_numbers), "sequence_s": round(sequence.duration_s, 3),
                         "sequence_scheduled": int(sequence.scheduled),
                         "motion_px": round(float(sequence.motion_px), 4)})
        cap = self.machine.record_capture(frame.image, meta, frames=None if sequence is None else sequence.frames)
        self.log(f"captured {cap.id}: {self.describe(cap)}")
        self._detect_in_background(cap.id)
        return cap

    def _detect_in_background(self, capture_id: str) -> None:
        store = self.machine.store

        def work():
            try:
                result = detect_capture(store, capture_id)
            except ProcamError:
                return  # deleted before its turn
            if isinstance(result, DetectionFailure) and any(c.id == capture_id for c in store.manifest.captures):
                self.log(f"{capture_id}: {result.reason}; calibration will leave it out (retake it to replace it)")
            update_after(self.machine, capture_id, self.log)

        self._detecting = [f for f in self._detecting if not f.done()] + [self._detector.submit(work)]

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until every capture taken so far has been detected in the background."""
        for f in list(self._detecting):
            f.result(timeout_s)

    def close(self) -> None:
        """Detect the captures still waiting, then stop the background thread."""
        self._detector.shutdown(wait=True, cancel_futures=True)

    def describe(self, cap) -> str:
        """A capture in the log's words: its slot and the step's progress."""
        m = self.machine
        k = cap.meta.get("pose_index", 0) + 1
        c = m.counts()
        if cap.structured:
            return f"placement {c['projector']} of at most {c['projector_total']} (structured light, {len(cap.frames)} frames)"
        if cap.step == STEP_PROJECTOR:
            return (f"pattern position {cap.pattern_position + 1}/{m.positions}, pose {k}/"
                    f"{m.plan.poses_per_position} ({c['projector']}/{c['projector_total']})")
        return f"{cap.step}, pose {k} ({c['mirror']}/{c['mirror_total']})"

    def taken_for(self, target: Target | None) -> list[tuple[str, PoseFeatures]]:
        """Features of the captured poses a new capture for `target` must differ from."""
        if target is None:
            return []
        out = []
        for c in self.machine.manifest.captures_of(target.step):
            if target.step == STEP_PROJECTOR and not c.structured and c.pattern_position != target.pattern_position:
                continue  # a circle pose differs from the others at its position; a placement from every other
            f = PoseFeatures.from_dict(c.meta.get("pose")) if isinstance(c.meta.get("pose"), dict) else None
            if f is not None:
                out.append((c.id, f))
        return out
