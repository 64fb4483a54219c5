"""The recalibration checklist's words about a round of the re-estimate (app/station/panel_recal.py):
"targets reached" only when every 1-sigma shown is within its target."""

from app.station.panel_recal import progress_lines, round_line
from calib.recalib import Reestimate

TARGETS = {"projector_rot_deg": 0.05, "projector_t": 0.5, "mirror_normal_deg": 0.05, "mirror_d": 0.5,
           "camera_f_px": 1.0}


def _round(rot_deg: float, t_mm: float, reached: bool, floor=()) -> Reestimate:
    return Reestimate(None, ("projector",), {"projector": {"rot_deg": rot_deg, "t_mm": t_mm}}, TARGETS, reached,
                      () if reached else ("projector rotation 1-sigma ...",), "prior", "", tuple(floor))


def test_targets_reached_only_when_every_target_is():
    assert round_line(_round(0.04, 0.3, True), "mm") == "every 1-sigma target reached"
    assert all(line.endswith("✔") for line in progress_lines(_round(0.04, 0.3, True), "mm"))


def test_a_target_only_the_previous_intrinsics_keep_out_of_reach_is_not_called_reached():
    # the flow stops (reached: more captures cannot help) but the position's 1-sigma is over its target
    r = _round(0.04, 0.7, True, floor=("projector position 1-sigma 0.700 mm > 0.500 mm (...)",))
    line = round_line(r, "mm")
    assert "reached" not in line.replace("not reached", "")
    assert line.startswith("1 1-sigma target(s) not reached, limited by the previous calibration's intrinsics")
    assert any(t.startswith("projector t: 1-sigma 0.700 / target 0.500 …") for t in progress_lines(r, "mm"))


def test_a_round_short_of_its_targets_says_it_captures_more():
    assert round_line(_round(0.09, 0.7, False), "mm") == "2 1-sigma target(s) not reached yet: capturing more"
