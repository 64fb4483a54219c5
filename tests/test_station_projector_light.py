"""A projector image that no longer reaches the camera mid-session: the station on the
simulated rig, its projector blanked (SimProjector.blank) while it shows the pattern."""

from app.station.machine import Plan
from app.station.projector_light import BACK_MESSAGE, LOST_MESSAGE, ProjectorLightWatch
from calib.models.observations import STEP_PROJECTOR
from _station_helpers import station_on_sim, tick_until_projector_captures

SMALL = Plan(poses_per_position=1, real_virtual_captures=3, min_real_virtual=3, min_projector_captures=6)


def _station(tmp_path, **opts):
    return station_on_sim(tmp_path / "s", SMALL, **opts)


def _ticks(st, n):
    for _ in range(n):
        st.tick()


def test_a_blanked_projector_is_reported_once_and_clears_when_its_light_returns(tmp_path):
    rig, m, st, lines = _station(tmp_path, auto=False, follow_operator=True, auto_capture=True)
    st.check_rig()
    tick_until_projector_captures(st, m, 1)
    assert m.captures_of(STEP_PROJECTOR) and m.target is not None and m.target.step == STEP_PROJECTOR
    st.options.auto_capture = False  # the board stays on this target's pattern from here on
    for _ in range(200):  # the simulated operator brings the board to the next target's pattern
        st.tick()
        if st.live is not None and st.live.detection is not None and st.live.detection.pattern_px is not None:
            break
    assert st.live.detection.pattern_px is not None
    _ticks(st, 3)
    assert LOST_MESSAGE not in st.instruction()

    rig.projector.blank(True)
    _ticks(st, 60)  # more than the watch's 45 frames
    assert st.live.detection.board is not None  # the board is still seen, its pattern is not
    assert st.light_watch.lost
    assert LOST_MESSAGE in st.instruction()
    assert lines.count(LOST_MESSAGE) == 1  # once per episode
    _ticks(st, 5)
    assert lines.count(LOST_MESSAGE) == 1

    rig.projector.blank(False)
    _ticks(st, 4)
    assert not st.light_watch.lost
    assert LOST_MESSAGE not in st.instruction()
    assert lines.count(BACK_MESSAGE) == 1 and lines.count(LOST_MESSAGE) == 1


class _Det:
    def __init__(self, board=True, pattern=True):
        self.board = object() if board else None
        self.pattern_px = [(0, 0)] if pattern else None
        self.failure = None if pattern else "pattern: pattern not found"


def test_the_watch_needs_a_pattern_seen_first_and_a_board_in_view():
    w = ProjectorLightWatch(lost_frames=3)
    assert [w.update(_Det(pattern=False)) for _ in range(5)] == [None] * 5  # never seen: no evidence
    assert w.update(_Det()) is None
    assert [w.update(_Det(board=False)) for _ in range(5)] == [None] * 5  # no board: no evidence
    assert [w.update(_Det(pattern=False)) for _ in range(4)] == [None, None, "lost", None]
    assert w.lost and w.update(_Det()) == "back" and not w.lost
    for _ in range(3):
        w.update(_Det(pattern=False))
    assert w.lost and w.reset() == "back" and not w.lost
    w.update(_Det(), target="p1")
    w.update(_Det(pattern=False), target="p1")
    # a new target's pattern (the operator moves the board to it) is no evidence until it was seen
    assert [w.update(_Det(pattern=False), target="p2") for _ in range(6)] == [None] * 6 and not w.lost
