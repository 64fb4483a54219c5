"""The rig check's exposure (app/station/rig_check.py): metered under the brightest light the projector
step puts on the board, so that no capture of the step saturates. Metering the circle grid at its middle
position alone left the other positions overexposed on a rig with a brighter part of the board
(nonoverlap-90, seed 1: its first projector pose was never detected and the session stopped)."""

import cv2
import numpy as np
import pytest

from app.station.machine import Plan
from app.station.rig_check import RigChecker
from calib.models.observations import STEP_PROJECTOR
from _station_helpers import station_on_sim, tick_until

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

PLAN = Plan(poses_per_position=1, real_virtual_captures=3, min_real_virtual=3, structured_placements=3,
            min_structured_placements=1)


@pytest.mark.parametrize("pattern", [None, "structured"])
def test_the_exposure_is_metered_under_every_light_the_step_shows(tmp_path, pattern):
    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, projector_pattern=pattern, auto=True)
    image = RigChecker(st)._metering_image()
    if pattern is None:  # every position's dots, each where that position puts it
        for p in range(m.positions):
            assert np.all(image >= st.pattern_image(p))
        assert np.array_equal(image > 0, np.any([st.pattern_image(p) > 0 for p in range(m.positions)], axis=0))
    else:  # the structured sequence's white frame
        assert np.array_equal(image, st.sequence.white())


@pytest.mark.parametrize("pattern", [None, "structured"])
def test_no_capture_of_the_projector_step_saturates_the_board(tmp_path, pattern):
    """nonoverlap-90 seed 1: the projector step's captures are taken (the session went on) and the lit
    board in them stays below saturation."""
    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, projector_pattern=pattern, scenario="nonoverlap-90",
                                       seed=1, auto=True)
    tick_until(st, lambda: len(m.captures_of(STEP_PROJECTOR)) >= 2, max_ticks=600)
    for cap in m.captures_of(STEP_PROJECTOR)[:2]:
        rel = cap.frames[0] if cap.structured else cap.image
        img = cv2.imread(str(m.store.folder / rel), cv2.IMREAD_UNCHANGED)
        assert np.mean(img >= 254) < 1e-4, (cap.id, float(np.mean(img >= 254)))


@pytest.mark.parametrize("error, ok", [("reset", True), ("timeout", False)])
def test_a_stream_the_driver_reset_is_asked_again_a_dead_one_fails(tmp_path, monkeypatch, error, ok):
    """The first frame meets a stalled stream: reset by the driver (StreamReset: it streams again), the
    check asks once more and the camera passes; no frame at all (DeviceTimeout) fails the camera."""
    from drivers.errors import DeviceTimeout, StreamReset

    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, auto=True)
    real = rig.camera.get_frame
    calls = []

    def stalling(*a, **kw):
        calls.append(1)
        if len(calls) == 1 or error == "timeout":
            raise (StreamReset if error == "reset" else DeviceTimeout)("no frame for 3.0 s with the camera connected")
        return real(*a, **kw)

    monkeypatch.setattr(rig.camera, "get_frame", stalling)
    camera = next(c for c in RigChecker(st).run() if c.name == "camera")
    assert camera.ok is ok, camera
    if not ok:
        assert "no frame" in camera.detail


def test_the_rig_check_passes_a_realsense_stream_that_stalled_and_was_reset(tmp_path):
    """Through the real RealSense driver on librealsense's software device: the stream stalls before the
    rig check's first frame, the driver resets it (hardware_reset, StreamReset), and the check asks
    again: the camera passes and the stream line reports the reset."""
    from drivers.sim.faults import parse_faults

    rig, m, st, lines = station_on_sim(tmp_path / "s", PLAN, kind="sim-realsense",
                                       rig_options={"faults": parse_faults("stall")}, auto=True)
    try:
        rig.device.stall_after_frames = 0
        checks = RigChecker(st).run()
        camera = next(c for c in checks if c.name == "camera")
        assert camera.ok, camera
        assert rig.device.resets == 1
        assert any("stalled and was reset (1x)" in c.detail for c in checks), [c.detail for c in checks]
    finally:
        rig.close()
