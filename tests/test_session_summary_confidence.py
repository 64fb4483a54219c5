"""`procam session`'s summary when the projector step stops on confidence: the captures the step used,
the plan's count as a maximum, and whether the step ended because it was confident."""

from pathlib import Path
from types import SimpleNamespace

from app.commands.session import summary
from app.station.plan import Plan
from calib.models.vocab import Step
from calib.quality.confidence import Confidence, Quantity


def _machine(plan, conf, mirror_conf=None):
    counts = {"mirror": 5, "mirror_total": 14, "mirror_other": 0, "projector": 9, "projector_total": 13,
              "positions_done": 0, "positions": 13, "placements": 12}
    return SimpleNamespace(plan=plan, projector_confidence=conf, mirror_confidence=mirror_conf, direct=False, counts=lambda: counts, mirror_method="real-virtual",
                           result=None, report=None, state="calibration", busy=None, structured=False,
                           mirror_captures=lambda: [], captures_of=lambda step: [])


def _conf(sigma):
    return Confidence(Step.PROJECTOR, (Quantity("t_mm", "projector position", "mm", sigma, 0.48),))


def test_a_step_stopped_on_confidence_says_so(tmp_path, monkeypatch):
    import app.commands.session as S

    monkeypatch.setattr(S, "STATE", lambda m: "calibration")
    text = summary(_machine(Plan(poses_per_position=1, stop_on_confidence=True), _conf(0.2)), tmp_path, 1.0)
    assert "projector 9 of at most 13 (stopped when confident) at 0/13 pattern positions" in text
    text = summary(_machine(Plan(poses_per_position=1, stop_on_confidence=True), _conf(0.9)), tmp_path, 1.0)
    assert "projector 9 of at most 13 (not confident) at" in text


def test_a_fixed_plan_prints_the_captures_only(tmp_path, monkeypatch):
    import app.commands.session as S

    monkeypatch.setattr(S, "STATE", lambda m: "calibration")
    text = summary(_machine(Plan(poses_per_position=1), _conf(0.2)), tmp_path, 1.0)
    assert "projector 9 at 0/13 pattern positions" in text and "at most" not in text
    assert "placements: 12 (the board's positions: mirror 0, projector 0)" in text  # counts() and the steps' own


def test_a_mirror_step_stopped_on_confidence_says_so(tmp_path, monkeypatch):
    import app.commands.session as S

    monkeypatch.setattr(S, "STATE", lambda m: "calibration")
    plan = Plan(poses_per_position=1, stop_on_confidence=True)
    normal = lambda s: Confidence(Step.REAL_VIRTUAL, (Quantity("mirror_normal_deg", "mirror normal", "deg", s, 0.01),))
    text = summary(_machine(plan, _conf(0.2), normal(0.005)), tmp_path, 1.0)
    assert "captures: mirror 5 of at most 14 (stopped when confident) (real-virtual)" in text
    text = summary(_machine(plan, _conf(0.2), normal(0.05)), tmp_path, 1.0)
    assert "captures: mirror 5 of at most 14 (not confident) (real-virtual)" in text
    # an unconfident mirror step says why, with the outlook of what more placements would give
    outlook = "mirror normal outlook: the mirror views' own share 0.01 deg; 4 more mirror placements: about 0.04 deg"
    unmet = Confidence(Step.REAL_VIRTUAL, (Quantity("mirror_normal_deg", "mirror normal", "deg", 0.05, 0.01),),
                       outlook=outlook)
    text = summary(_machine(plan, _conf(0.2), unmet), tmp_path, 1.0)
    assert f"mirror step not confident: mirror normal: 0.05 deg (target 0.01) not yet; {outlook}" in text
    assert "mirror step not confident" not in summary(_machine(plan, _conf(0.2), normal(0.005)), tmp_path, 1.0)
    assert "captures: mirror 5 (real-virtual)" in summary(_machine(Plan(), _conf(0.2)), tmp_path, 1.0)
