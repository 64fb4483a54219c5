"""When a capture step is confident (calib.quality.confidence): its 1-sigmas against targets derived from
the quality gate's references; a thin session is not, a full one is; nothing is met without a
calibration; and `procam bench placements` emulates the station's stopping on it."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from _joint_helpers import observations
from calib.models.vocab import Step
from calib.pipeline import calibrate_observations
from calib.quality._trust_gate import QualityThresholds
from calib.quality.confidence import TARGET_FRACTION, confidence_of, sigmas, targets, unconfident

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

NOISE_PX = 0.03  # about the noise of the rendered sessions' detections (their joint 1-sigmas match at this noise)
# a share of the references a full session at this noise meets and a thin one does not (the default,
# TARGET_FRACTION, sits at the full sessions' own level: docs/BENCHMARKS.md "Placements")
FRACTION = 0.15


@pytest.fixture(scope="module")
def full():
    return calibrate_observations(observations(NOISE_PX, 1))


def test_targets_are_a_share_of_the_quality_gates_references():
    th = QualityThresholds()
    goal = targets(Step.PROJECTOR)
    assert goal["t_mm"] == pytest.approx(TARGET_FRACTION * th.reference_t_mm)
    assert goal["projector_intrinsics_px"] == pytest.approx(TARGET_FRACTION * th.reference_projector_intrinsics_px)
    assert targets(Step.REAL_MIRROR, 0.5) == {"mirror_normal_deg": 0.5 * th.reference_mirror_normal_deg}


def test_a_full_session_is_confident_in_every_step(full):
    got = sigmas(full)
    assert all(math.isfinite(v) and v > 0 for v in got.values()), got
    for step in (Step.PROJECTOR, Step.REAL_VIRTUAL):
        conf = confidence_of(full, step, FRACTION)
        assert conf.all_met, conf.lines()
        assert all(q.sigma <= q.target for q in conf.quantities)


def test_a_thin_projector_step_is_not_confident_and_says_which_quantities(full):
    obs = observations(NOISE_PX, 1)
    thin = calibrate_observations(replace(obs, projector_views=obs.projector_views[:6]), trust=None)
    conf = confidence_of(thin, Step.PROJECTOR, FRACTION)
    assert not conf.all_met
    unmet = [q for q in conf.quantities if not q.met]
    assert unmet and all("not yet" in q.line() for q in unmet)
    # fewer placements, larger 1-sigmas: each quantity of the thin session above the full one's
    full_sigmas, thin_sigmas = sigmas(full), sigmas(thin)
    assert all(thin_sigmas[q.key] > full_sigmas[q.key] for q in conf.quantities)


def test_an_unconfident_mirror_step_says_what_limits_it_and_what_more_would_give(full):
    obs = observations(NOISE_PX, 1)
    thin = calibrate_observations(replace(obs, mirror_views=obs.mirror_views[:3]), trust=None)
    conf = confidence_of(thin, Step.REAL_VIRTUAL, 0.01)
    assert not conf.all_met
    m = thin.uncertainty["mirror"]
    line = conf.lines()[-1]
    assert line.startswith("mirror normal outlook: ")
    assert f"{m['normal_deg_given_camera']:.3g} deg" in line
    assert f"4 more mirror placements: about {m['normal_deg_with_more_mirror'][3]:.3g} deg" in line
    assert f"4 more projector placements: about {m['normal_deg_with_more_projector'][3]:.3g} deg" in line
    # a confident step, and the projector step, carry no outlook line
    assert not any("outlook" in x for x in confidence_of(full, Step.REAL_VIRTUAL, FRACTION).lines())
    assert not any("outlook" in x for x in confidence_of(thin, Step.PROJECTOR, 0.01).lines())


def test_a_step_whose_captures_do_not_calibrate_meets_nothing():
    conf = unconfident(Step.PROJECTOR, "too few projector views")
    assert not conf.all_met and conf.reason == "too few projector views"
    assert conf.lines()[0] == "not yet: too few projector views"
    assert all(not q.met and q.sigma == math.inf for q in conf.quantities)


def test_a_given_camera_has_nothing_left_to_constrain(full):
    obs = observations(NOISE_PX, 1)
    res = calibrate_observations(obs, camera=full.camera)
    assert sigmas(res)["camera_intrinsics_px"] == 0.0
    assert sigmas(res)["projection_camera_max_px"] == 0.0


def test_bench_placements_stops_each_step_when_confident(tmp_path, monkeypatch):
    """The emulated station on a rendered session: the projector step ends as soon as its targets are
    met (so not before, and not after), and with targets no session meets it takes every capture."""
    from app.commands import _bench_placements as B
    from app.commands.simulate import simulate_session
    from calib.detection.detect import detect_session
    from drivers.sim.scenarios import get_scenario

    sc = get_scenario("nonoverlap-136", 0)
    store = simulate_session(sc, tmp_path / "s", quality="live", workers=1, progress=False, structured_placements=5)
    obs = detect_session(store, 1, cache="refresh")
    calls = []
    real = B._calibrate

    def counting(o, mirror, projector):
        out = real(o, mirror, projector)
        calls.append((len(mirror), len(projector), out[0] is not None))
        return out

    monkeypatch.setattr(B, "_calibrate", counting)
    result, m, p, lines = B.stop_on_confidence(store, obs, mirror_first=4, fraction=10.0)
    # loose targets: met at the first placement count that calibrates at all (3 or more)
    assert result is not None and m == 4 and p >= 3 and all("not yet" not in line for line in lines)
    assert calls[-1] == (4, p, True) and all(not ok for _, _, ok in calls[:-1])
    assert [c[1] for c in calls] == list(range(3, p + 1))
    calls.clear()
    result, m, p, lines = B.stop_on_confidence(store, obs, mirror_first=4, fraction=1e-6)
    assert (m, p) == (len(obs.mirror_views), len(obs.projector_views))  # never confident: every capture
    assert any("not yet" in line for line in lines)
    assert [c[1] for c in calls[:3]] == [3, 4, 5]  # one more placement at a time
    assert calls[-1][:2] == (m, p)
