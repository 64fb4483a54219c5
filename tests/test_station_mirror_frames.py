"""A mirror placement captured as the mean of several frames (Plan.mirror_frames, app/station/mirror_frames.py):
the frames after the one auto-capture chose, averaged into the capture's image, refused when the board
moved too far meanwhile. On the simulated rig with its default hardware model (the operator holds the
board by hand: it sways through the frames), on simulated time."""

from __future__ import annotations

import cv2
import numpy as np

import app.station.mirror_frames as MF
from app.station.machine import Plan
from calib.models.vocab import Step
from _station_helpers import station_on_sim, tick_until

PLAN = Plan(real_virtual_captures=3, min_real_virtual=3, mirror_frames=4)


def _recording_grab(st):
    seen, poses = {}, {}
    real = st.frames.grab

    def grab():
        f = real()
        if f is not None:
            seen[f.frame_number] = np.array(f.image)
            poses[f.frame_number] = np.array(f.meta["T_cam_board"]) if f.meta.get("T_cam_board") else None
        return f

    st.frames.grab = grab
    return seen, poses


def test_each_mirror_placement_is_the_mean_of_its_frames(tmp_path):
    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, auto=True)
    seen, poses = _recording_grab(st)
    tick_until(st, lambda: len(m.captures_of(Step.REAL_VIRTUAL)) == 3, max_ticks=600)
    st.wait_for_detections()
    swayed = []
    for cap in m.captures_of(Step.REAL_VIRTUAL):
        numbers = cap.meta["frame_numbers"]
        assert cap.meta["frames_averaged"] == 4 and len(numbers) == 4 and numbers == sorted(set(numbers))
        assert cap.meta["motion_px"] <= MF.MAX_MEAN_MOTION_PX
        swayed.append(np.linalg.norm(poses[numbers[-1]][:3, 3] - poses[numbers[0]][:3, 3]))
        frames = [seen[n].astype(float) for n in numbers]
        assert not np.array_equal(frames[0], frames[-1])  # each its own noise
        mean = np.clip(np.rint(sum(frames) / 4), 0, 255).astype(np.uint8)
        saved = m.store.load_image(cap, cv2.IMREAD_UNCHANGED)
        if saved.ndim == 2:  # a grey frame is stored as one channel
            assert (mean == mean[..., :1]).all()
            mean = mean[..., 0]
        assert np.array_equal(saved, mean)
    assert max(swayed) > 0.01  # mm: the hand-held board moved through the frames, and was kept
    # a refusal, if the sway went too far, says so
    assert all("the board moved during the 4 frames" in ln for ln in lines if ln.startswith("placement refused"))


def test_a_board_moved_during_its_frames_is_refused_and_the_placement_held_again(tmp_path, monkeypatch):
    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, auto=True)
    real = MF.capture_mean
    moved = {"done": False}

    def slipping(station, first_frame, first_det, count):
        if not moved["done"]:  # the operator's hand slips right after the frame auto-capture chose
            b = rig.board
            T = b.T_cam_board.copy()
            T[:3, 3] += T[:3, 0] * 2.0  # 2 mm along the board
            rig._place(b.layout, T, Step.REAL_VIRTUAL)
            moved["done"] = True
        return real(station, first_frame, first_det, count)

    monkeypatch.setattr(MF, "capture_mean", slipping)
    tick_until(st, lambda: len(m.captures_of(Step.REAL_VIRTUAL)) == 1, max_ticks=600)
    refused = [ln for ln in lines if ln.startswith("placement refused")]
    assert len(refused) >= 1 and "the board moved during the 4 frames of this placement" in refused[0]
    assert "hold it still" in refused[0]
    cap = m.captures_of(Step.REAL_VIRTUAL)[0]  # the placement held again, kept
    assert cap.meta["motion_px"] <= MF.MAX_MEAN_MOTION_PX and cap.meta["frames_averaged"] == 4
    assert len(list((m.store.folder / "images").glob("*.png"))) == 1  # nothing of the refused one on disk
