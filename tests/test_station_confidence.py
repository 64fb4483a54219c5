"""The station's projector step stopping when the calibration is confident (Plan.stop_on_confidence,
app/station/confidence_watch.py): poses asked one at every pattern position before the next, the
confidence judged after each detected capture, the step ended at the first confident one, the plan's
count a maximum."""

import pytest

import calib.quality.confidence as C
from app.station.machine import CALIBRATION, PROJECTOR_CAPTURE, Plan
from calib.formats.session_files import CALIBRATION as CALIBRATION_FILE, GROUND_TRUTH
from calib.models.observations import STEP_PROJECTOR
from _station_helpers import assert_within_its_uncertainty, station_on_sim, tick_until

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

PLAN = Plan(poses_per_position=4, real_virtual_captures=5, min_real_virtual=3, min_projector_captures=6,
            stop_on_confidence=True)


def _station(tmp_path, plan=PLAN):
    return station_on_sim(tmp_path / "s", plan, auto=True)


def test_the_projector_step_ends_at_its_first_confident_capture(tmp_path, monkeypatch):
    # targets a short session reaches: the test is about when the step ends, not about the default share
    monkeypatch.setattr(C, "TARGET_FRACTION", 0.3)
    rig, m, st, lines = _station(tmp_path)
    seen = []
    real = m.set_projector_confidence

    def recording(conf):
        seen.append((len(m.captures_of(STEP_PROJECTOR)), conf.all_met))
        real(conf)

    monkeypatch.setattr(m, "set_projector_confidence", recording)
    tick_until(st, lambda: m.state == CALIBRATION and m.result is not None, max_ticks=900)
    caps = m.captures_of(STEP_PROJECTOR)
    n = len(caps)
    assert PLAN.min_projector_captures <= n < m.projector_total  # stopped before the plan's 52
    # judged after every capture; the step ended at the first confident one (never before the minimum)
    assert [k for k, _ in seen] == list(range(1, n + 1))
    assert seen[-1][1] and not any(ok for k, ok in seen[:-1] if k >= PLAN.min_projector_captures)
    assert any("projector step confident after" in ln for ln in lines)
    # one pose at every pattern position before the next pose
    positions = [c.pattern_position for c in caps]
    assert positions[:min(n, 13)] == list(range(min(n, 13)))
    # a stopped session still calibrates within its own uncertainty of the truth
    if not (m.store.folder / GROUND_TRUTH).exists():
        rig.ground_truth().save_json(m.store.folder / GROUND_TRUTH)
    assert (m.store.folder / CALIBRATION_FILE).exists()
    assert_within_its_uncertainty(m.store.folder)


def test_without_confidence_the_step_takes_every_capture_it_plans(tmp_path, monkeypatch):
    """Targets no session meets: the step asks for all its captures, in the pose-major order."""
    monkeypatch.setattr(C, "TARGET_FRACTION", 1e-9)
    plan = Plan(poses_per_position=1, real_virtual_captures=3, min_real_virtual=3, min_projector_captures=6,
                stop_on_confidence=True)
    rig, m, st, lines = _station(tmp_path, plan)
    tick_until(st, lambda: m.state == PROJECTOR_CAPTURE, max_ticks=300)
    tick_until(st, lambda: m.state == CALIBRATION, max_ticks=600)
    assert len(m.captures_of(STEP_PROJECTOR)) == m.projector_total == 13
    assert m.projector_confidence is not None and not m.projector_confidence.all_met
    assert any("not yet" in ln for ln in lines if ln.startswith("projector step after"))


def test_the_plan_keeps_the_switch_across_a_resume():
    d = PLAN.to_dict()
    assert d["stop_on_confidence"] is True
    assert Plan.from_dict(d) == PLAN and Plan.from_dict({}).stop_on_confidence is False
    nb = Plan(stop_on_confidence=True, next_best=True)
    assert Plan.from_dict(nb.to_dict()).next_best is True and Plan.from_dict({}).next_best is False


def test_next_best_without_stopping_on_confidence_is_refused_with_the_reason():
    from argparse import Namespace

    from app.commands.session import plan_from_args
    from calib.errors import OptionError

    with pytest.raises(OptionError, match="--next-best .* only --stop-on-confidence computes: give both"):
        plan_from_args(Namespace(next_best=True, stop_on_confidence=None))
    assert plan_from_args(Namespace(next_best=True, stop_on_confidence=True)).next_best


def test_the_checklist_shows_each_1_sigma_against_its_target():
    from types import SimpleNamespace

    from app.station.panel_status import checklist
    from calib.quality.confidence import Quantity

    conf = C.Confidence(STEP_PROJECTOR, (Quantity("t_mm", "projector position", "mm", 0.21, 0.48),
                                         Quantity("rot_deg", "projector orientation", "deg", 0.05, 0.0385)))
    class M(SimpleNamespace):
        def counts(self):
            return {"mirror": 5, "mirror_total": 5, "projector": 9, "projector_total": 52, "positions_done": 0,
                    "positions": 13, "placements": 14}

        def why_not(self, _action):
            return None

    m = M(state=PROJECTOR_CAPTURE, rig_checks=(), direct=False, mirror_method="real-virtual", result=None,
          result_stale=False, camera_intrinsics=None, busy=None, report=None, plan=PLAN, projector_confidence=conf,
          structured=False)
    text = checklist(m)
    assert "9 / 52" in text and "ends when confident" in text
    assert "projector position: 0.21 mm (target 0.48)" in text
    assert "projector orientation: 0.05 deg (target 0.0385) not yet" in text


def _conf(step, met: bool):
    from calib.quality.confidence import Quantity

    key, label = ("mirror_normal_deg", "mirror normal") if step != STEP_PROJECTOR else ("t_mm", "projector position")
    return C.Confidence(step, (Quantity(key, label, "deg", 0.001 if met else 1.0, 0.01),))


def test_the_mirror_step_takes_its_first_captures_then_more_after_the_projector_step_until_confident(tmp_path):
    """The machine alone (fake confidences): the mirror step's first `mirror_first` captures, then the
    projector step, then mirror captures while the normal is not confident, at most the plan's count."""
    from app.station.machine import MIRROR_CAPTURE, SessionMachine
    from app.station.wording import instruction
    from calib.models.observations import STEP_REAL_VIRTUAL
    from _station_helpers import TINY, make_store
    from test_station_machine import OK

    plan = Plan(poses_per_position=1, real_virtual_captures=8, min_real_virtual=3, min_projector_captures=3,
                stop_on_confidence=True, mirror_first=4)
    m = SessionMachine(make_store(tmp_path / "s", "mirror", 5), plan, calibrate_fn=lambda *a: None)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    for _ in range(4):
        assert m.target is not None and m.target.step == STEP_REAL_VIRTUAL
        assert "of at most 8" in instruction(m, None, None, "")
        m.record_capture(TINY)
    # four taken: the projector step next, whatever the (unknown) confidence
    assert m.target is None and not m.more_mirror_wanted()
    assert "projector" in instruction(m, None, None, "")
    m.proceed()
    for _ in range(3):
        m.record_capture(TINY)
    m.set_projector_confidence(_conf(STEP_PROJECTOR, True))
    m.set_mirror_confidence(_conf(STEP_REAL_VIRTUAL, False))
    # the projector step is confident; the mirror normal is not: more mirror captures are asked for
    assert m.target is None and m.more_mirror_wanted()
    assert "Press 'Back' for more mirror captures" in instruction(m, None, None, "")
    m.go_back()
    assert m.state == MIRROR_CAPTURE and m.target is not None and m.target.pose_index == 4
    m.record_capture(TINY)
    m.set_mirror_confidence(_conf(STEP_REAL_VIRTUAL, True))
    assert m.target is None and not m.more_mirror_wanted()
    assert "confident after 5 mirror captures" in instruction(m, None, None, "")
    m.proceed()
    assert m.state == PROJECTOR_CAPTURE and m.target is None
    # never confident: the plan's count is the maximum
    m.go_back()
    m.set_mirror_confidence(_conf(STEP_REAL_VIRTUAL, False))
    while m.target is not None:
        m.record_capture(TINY)
    assert len(m.captures_of(STEP_REAL_VIRTUAL)) == 8
    m.proceed()
    assert m.target is None and not m.more_mirror_wanted()
    # without stopping on confidence the mirror step takes all its captures before the projector step
    assert Plan(real_virtual_captures=8, mirror_first=4).mirror_before_projector("real-virtual") == 8


def test_a_station_goes_back_to_the_mirror_step_while_the_mirror_normal_is_not_confident(tmp_path, monkeypatch):
    """The simulated station, stopping on confidence: the mirror step's first captures, the projector step
    until it is confident, then mirror captures again because the normal's target (made unreachable here)
    is not met, up to the plan's count; then the session calibrates."""
    from calib.models.observations import STEP_REAL_VIRTUAL

    monkeypatch.setattr(C, "TARGET_FRACTION", 0.3)
    real_targets = C.targets

    def mirror_unreachable(step, fraction=None, thresholds=None):
        goal = real_targets(step, fraction, thresholds)
        return {k: (1e-9 if k == "mirror_normal_deg" else v) for k, v in goal.items()}

    monkeypatch.setattr(C, "targets", mirror_unreachable)
    plan = Plan(poses_per_position=2, real_virtual_captures=6, min_real_virtual=3, min_projector_captures=6,
                stop_on_confidence=True, mirror_first=3)
    rig, m, st, lines = _station(tmp_path, plan)
    tick_until(st, lambda: m.state == CALIBRATION and m.result is not None, max_ticks=1500)
    steps = [c.step for c in m.manifest.captures]
    n_proj = steps.count(STEP_PROJECTOR)
    assert plan.min_projector_captures <= n_proj < m.projector_total  # the projector step stopped when confident
    assert steps == [STEP_REAL_VIRTUAL] * 3 + [STEP_PROJECTOR] * n_proj + [STEP_REAL_VIRTUAL] * 3
    assert any(ln.startswith("mirror step again: mirror normal") for ln in lines)
    assert m.mirror_confidence is not None and not m.mirror_confidence.all_met
    # each mirror capture after the projector step was judged, and the projector step stayed confident
    assert sum(ln.startswith("mirror step after mrv") for ln in lines) == 3
    assert m.projector_confidence.all_met
    assert_within_its_uncertainty(m.store.folder) if (m.store.folder / GROUND_TRUTH).exists() else None


def test_a_resumed_session_judges_its_captures_once(tmp_path, monkeypatch):
    """The judgements are not saved: a session resumed in a capture step judges its captures again, so a
    step that was confident before the stop is not asked for more."""
    import app.station.confidence_watch as W
    from app.station.machine import MIRROR_CAPTURE, SessionMachine
    from app.station.setup import make_machine
    from calib.models.observations import STEP_REAL_VIRTUAL
    from _station_helpers import TINY, make_store
    from test_station_machine import OK

    plan = Plan(poses_per_position=1, real_virtual_captures=8, min_real_virtual=3, min_projector_captures=3,
                stop_on_confidence=True, mirror_first=4)
    store = make_store(tmp_path / "s", "mirror", 5)
    m = SessionMachine(store, plan, calibrate_fn=lambda *a: None)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    for _ in range(4):
        m.record_capture(TINY)
    m.proceed()
    for _ in range(3):
        m.record_capture(TINY)
    judged = []

    def fake(machine):
        judged.append(len(machine.manifest.captures))
        return _conf(STEP_PROJECTOR, True), _conf(STEP_REAL_VIRTUAL, True), None, None

    monkeypatch.setattr(W, "step_confidences", fake)

    class Rig:  # make_machine asks the rig only for its verifier
        pass

    monkeypatch.setattr("app.station.setup.make_verify_fn", lambda rig, folder: None)
    resumed = make_machine(store, Rig(), resume=True)
    assert judged == [7]
    assert resumed.state == PROJECTOR_CAPTURE and resumed.target is None and not resumed.more_mirror_wanted()
    assert any("projector step on resume confident" in e.text for e in resumed.events)
    # in the mirror step before the projector step's minimum: nothing to judge
    judged.clear()
    store2 = make_store(tmp_path / "t", "mirror", 5)
    m2 = SessionMachine(store2, plan, calibrate_fn=lambda *a: None)
    m2.start_session(OK)
    m2.choose_mirror_method("real-virtual")
    m2.record_capture(TINY)
    assert make_machine(store2, Rig(), resume=True).state == MIRROR_CAPTURE and judged == []
