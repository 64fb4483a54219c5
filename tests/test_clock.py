"""The simulated rig keeps its own time (drivers.clock): what it does depends on what was asked of it,
never on how fast the machine renders."""

import threading
import time

import pytest

from drivers.clock import MONOTONIC, SimClock, clock_of
from drivers.settle import apply_timing
from drivers.sim.rig import open_sim_rig


def test_simulated_time_moves_only_when_someone_waits_and_never_goes_back():
    c = SimClock(start_s=10.0, realtime=False)
    assert c.now() == 10.0
    time.sleep(0.05)  # the wall clock moves; the simulated one does not
    assert c.now() == 10.0
    c.sleep(2.5)
    assert c.now() == 12.5
    c.sleep_until(11.0)  # already past: no going back
    assert c.now() == 12.5
    c.sleep(-1.0)
    assert c.now() == 12.5
    c.advance(0.5)
    assert c.now() == 13.0


def test_concurrent_sleepers_share_one_time():
    c = SimClock(start_s=0.0, realtime=False)
    seen = []

    def sleeper(k):
        for _ in range(200):
            c.sleep(0.001 * k)
            seen.append(c.now())

    threads = [threading.Thread(target=sleeper, args=(k,)) for k in (1, 2, 3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert c.now() >= 0.6 - 1e-9  # the slowest sleeper's 200 x 3 ms at least
    assert c.now() <= 0.2 + 0.4 + 0.6 + 1e-9  # never more than all sleeps end to end


def test_devices_report_their_clock():
    rig = open_sim_rig("nonoverlap-136", seed=0, realtime=False)
    assert clock_of(rig.camera) is rig.clock is clock_of(rig.projector) and rig.clock.simulated
    assert clock_of(object()) is MONOTONIC


def _timing_run(slow_render_s: float):
    rig = open_sim_rig("nonoverlap-136", seed=3, latency_ms=95.0)  # realtime: paced like a rig in use
    if slow_render_s:
        render = rig._render_frame

        def starved(*a, **k):  # a starved CPU: every frame takes long to render
            time.sleep(slow_render_s)
            return render(*a, **k)

        rig._render_frame = starved
    rig.camera.start()
    rig.operator.request_pose("verification", None, 0)
    applied = apply_timing(rig.camera, rig.projector)
    return applied, sorted(rig.frame_truth.items()), rig.clock.now()


def test_a_starved_machine_changes_nothing_the_simulated_rig_does():
    """The exposure search and the latency measurement, once at full speed and once with every frame
    taking 60 ms of wall time to render (two frame periods at 30 fps): the same settings, the same
    latency, the same frames seeing the same projector images, the same simulated time."""
    fast = _timing_run(0.0)
    slow = _timing_run(0.06)
    assert fast[0] == slow[0]
    assert fast[1] == slow[1]
    assert fast[2] == pytest.approx(slow[2], abs=1e-9)
    truth_ms = 95.0
    assert truth_ms <= fast[0]["projector"]["latency_ms"] <= truth_ms + 50
