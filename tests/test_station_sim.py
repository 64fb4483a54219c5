"""The station on the simulated rig: auto-capture waits for the board to settle, the projector follows
the targets, the operator's buttons (move board, capture, retake) and refusals, a small session
calibrated for real."""

import numpy as np
import pytest

from app.station.machine import CALIBRATION, ActionRefused, Plan
from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
from app.station.station import Station, StationOptions
from calib.formats.session import SessionStore
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL

SMALL = Plan(poses_per_position=1, real_virtual_captures=3, min_real_virtual=3, min_projector_captures=6)


class RecordingCamera:
    """The sim camera, remembering each frame's meta (the sim marks frames of a moving board)."""

    def __init__(self, cam, projector):
        self._cam = cam
        self._projector = projector
        self.meta = {}

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def get_frame(self, *a, **k):
        f = self._cam.get_frame(*a, **k)
        self.meta[f.frame_number] = f.meta
        return f


def images_seen(rig, frame_number) -> set:
    """Hashes of the projector images that lit the scene during the frame's exposure (the sim's truth)."""
    return {hash(rig.projector.timeline.image_of(t).tobytes()) for t, frac in rig.frame_truth[frame_number]
            if frac > 0}


def session(tmp_path, scenario="nonoverlap-136", plan=SMALL, **rig_opts):
    req = RigRequest("sim", scenario, 0)
    rig = open_requested_rig(req, **rig_opts)
    rig.camera = RecordingCamera(rig.camera, rig.projector)
    store = create_session(tmp_path / "s", rig, req, plan)
    return rig, make_machine(store, rig, plan)


def tick_until(station, cond, max_ticks=200):
    for _ in range(max_ticks):
        if cond():
            return
        station.tick()
    raise AssertionError(f"condition not met in {max_ticks} ticks; state {station.machine.state}, "
                         f"last decision {station.live and station.live.decision}")


def test_auto_capture_waits_for_the_settled_board_and_follows_the_targets(tmp_path):
    rig, m = session(tmp_path, settling_frames=3)
    st = Station(rig, m, StationOptions(auto=False, follow_operator=True, auto_capture=True))
    assert st.options.follow_operator is True
    st.check_rig()
    m.start_session()
    m.choose_mirror_method("real-virtual")
    tick_until(st, lambda: m.target is None)
    caps = m.captures_of(STEP_REAL_VIRTUAL)
    assert len(caps) == 3
    for c in caps:
        assert rig.camera.meta[c.meta["frame_number"]]["moving"] is False
        assert c.meta["motion_px"] < 1.0 and c.meta["how"] == "auto"
    # the operator was asked for each pose in turn
    assert [c.meta["pose_index"] for c in caps] == [0, 1, 2]
    m.proceed()
    tick_until(st, lambda: len(m.captures_of(STEP_PROJECTOR)) == 2)
    # the projector showed each capture's pattern position when it was taken
    for c in m.captures_of(STEP_PROJECTOR):
        assert rig.camera.meta[c.meta["frame_number"]]["moving"] is False
        assert images_seen(rig, c.meta["frame_number"]) == {hash(st.pattern_image(c.pattern_position).tobytes())}
    st.tick()
    assert np.array_equal(rig.projector.image, st.pattern_image(m.target.pattern_position))
    # the manifest on disk names every acknowledged capture, each with its image
    disk = SessionStore.open(m.store.folder).manifest
    assert [c.id for c in disk.captures] == [c.id for c in m.manifest.captures]
    assert all((m.store.folder / c.image).exists() for c in disk.captures)


def test_operator_buttons_and_refusals(tmp_path):
    rig, m = session(tmp_path)
    st = Station(rig, m, StationOptions(auto=False, auto_capture=False))  # sim + panel: the person clicks
    assert st.options.follow_operator is False
    st.check_rig()
    m.start_session()
    with pytest.raises(ActionRefused, match="choose the mirror method"):
        st.capture_now()
    m.choose_mirror_method("real-virtual")
    st.tick()
    # the board is not in view until someone moves it there
    with pytest.raises(ActionRefused) as e:
        st.capture_now()
    assert "not usable" in e.value.reason or "no camera frame" in e.value.reason
    text = st.request_pose()
    assert "mirror" in text.lower()
    tick_until(st, lambda: st.live is not None and st.live.detection is not None and st.live.detection.ok
               and st.live.accepted)
    cap = st.capture_now()
    assert cap.meta["how"] == "button" and m.counts()["mirror"] == 1
    # move the board out: capture refused with the detection's reason
    rig.operator.move_out()
    st.tick()
    tick_until(st, lambda: st.live.accepted and st.live.detection is not None)
    with pytest.raises(ActionRefused) as e:
        st.capture_now()
    assert "board not found" in e.value.reason
    # retake: the same pose is asked again and captured again
    tgt = m.retake(cap.id)
    assert tgt.pose_index == 0 and m.counts()["mirror"] == 0
    st.request_pose()
    tick_until(st, lambda: st.live.detection is not None and st.live.detection.ok
               and st.live.accepted)
    again = st.capture_now()
    assert again.meta["pose_index"] == 0 and again.meta["retake"] is True
    a, b = cap.meta["pose"], again.meta["pose"]
    assert np.allclose(a["centre"], b["centre"], atol=0.01)
    # instructions in plain words for the current step
    assert "Mirror capture 2 of 3" in st.instruction()


@pytest.mark.slow
def test_small_session_calibrates_near_ground_truth(tmp_path, monkeypatch):
    """A short session (1 pose per pattern position, 3 mirror captures) run by the station itself. Each
    capture is decoded and detected once, in the background while the next one is taken; calibrating
    detects nothing again."""
    import threading
    from collections import Counter

    import calib.detection.session_jobs as D
    from calib.quality.metrics import compare

    detected = Counter()
    real = D._detect_job

    def counting(job, data):
        if job.image_path.startswith(str(tmp_path)):  # not a capture of an earlier test's station
            detected[(job.capture_id, threading.current_thread().name.split("_")[0])] += 1
        return real(job, data)

    monkeypatch.setattr(D, "_detect_job", counting)
    rig, m = session(tmp_path)
    lines = []
    st = Station(rig, m, StationOptions(auto=True), log=lines.append)
    tick_until(st, lambda: m.state == CALIBRATION and m.result is not None, max_ticks=400)
    # the projector's light reached the camera throughout (app.station.projector_light: no false alarm)
    assert not any("no longer reaches the camera" in ln for ln in lines), lines
    c = m.counts()
    assert c["mirror"] == 3 and c["projector"] == 13 and c["positions_done"] == 13
    # (a capture the station deleted, to take its pose again, may or may not have been detected first)
    assert {who for _, who in detected} == {"station-detect"}, detected
    assert all(detected[(cap.id, "station-detect")] == 1 for cap in m.manifest.captures), (detected, m.manifest.captures)
    mt = compare(m.result, rig.ground_truth())
    # a quarter of the paper's protocol; still well within the paper's synthetic accuracy
    assert mt.distance < 3.2 and mt.angle_deg < 0.18
    assert (m.store.folder / "calibration.json").exists()
