"""`procam session`'s summary when the projector step stops on confidence: the captures the step used,
the plan's count as a maximum, and whether the step ended because it was confident."""

from pathlib import Path
from types import SimpleNamespace

from app.commands.session import summary
from app.station.plan import Plan
from calib.models.vocab import Step
from calib.quality.confidence import Confidence, Quantity


def _machine(plan, conf):
    counts = {"mirror": 3, "mirror_total": 3, "mirror_other": 0, "projector": 9, "projector_total": 13,
              "positions_done": 0, "positions": 13, "placements": 12}
    return SimpleNamespace(plan=plan, projector_confidence=conf, counts=lambda: counts, mirror_method="real-virtual",
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
