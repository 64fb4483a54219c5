"""Hostile values in a session's manifest (session.json), grouped by value: board lengths, the pattern,
capture ids; and nothing read from a file drives the terminal when printed."""

import json
import shutil

import pytest

from calib.errors import FormatError
from calib.formats.session import SessionManifest
from _calib_helpers import session, write_session


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("manifest") / "s"
    write_session(folder, session("136", per_position=1), projector_indices=[0], mirror_indices=[0])
    return folder


@pytest.fixture
def manifest(session_dir):
    return json.loads((session_dir / "session.json").read_text())


def _refused(d, *words):
    with pytest.raises(FormatError) as e:
        SessionManifest.from_dict(d)
    for w in words:
        assert w in str(e.value), str(e.value)
    return str(e.value)


# ---- board lengths --------------------------------------------------------------------------------
@pytest.mark.parametrize("board", ["projector_board", "mirror_board"])
@pytest.mark.parametrize("square", [1e308, 1e-300])
def test_absurd_board_square_is_refused_naming_the_board_and_length(manifest, board, square):
    manifest[board].update(square_length=square, marker_length=square * 0.6)
    _refused(manifest, board, "square_length")


def test_a_board_length_is_judged_in_its_own_unit(manifest):
    """3 (cm) is a board; 3 m squares and 0.003 mm squares are not."""
    mb = manifest["mirror_board"]
    mb.update(square_length=3.0, marker_length=2.0, units="cm")
    assert SessionManifest.from_dict(manifest).mirror_board.square_length == pytest.approx(30.0)
    for length, units in ((3000.0, "cm"), (0.003, "mm")):
        mb.update(square_length=length, marker_length=length * 0.6, units=units)
        _refused(manifest, "mirror_board", "square_length")


def test_a_marker_too_small_to_read_is_refused(manifest):
    manifest["projector_board"]["marker_length"] = 1e-300
    _refused(manifest, "projector_board", "marker_length")


def test_calibrate_with_an_absurd_board_square_is_one_line_never_opencv(session_dir, tmp_path, capsys):
    from app.cli import main

    s = tmp_path / "s"
    shutil.copytree(session_dir, s)
    d = json.loads((s / "session.json").read_text())
    d["projector_board"].update(square_length=1e308, marker_length=6e307)
    (s / "session.json").write_text(json.dumps(d))
    assert main(["calibrate", str(s), "--no-progress", "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "projector_board" in err[0] and "square_length" in err[0], err
    assert "unexpected" not in err[0] and not (s / "calibration.json").exists()


# ---- the pattern ----------------------------------------------------------------------------------
@pytest.mark.parametrize("change, words", [
    ({"spacing_px": 1e308}, ("pattern", "spacing_px")),
    ({"spacing_px": 1e-300, "radius_px": 1e-301}, ("pattern", "spacing_px")),
    ({"spacing_px": 400.0, "radius_px": 100.0}, ("pattern.spacing_px", "projector image")),
    ({"cols": 1_000_000}, ("pattern", "points a side")),
    ({"positions": 10 ** 9}, ("pattern", "positions")),
    ({"margin_px": 1e308}, ("pattern", "margin_px")),
])
def test_a_pattern_that_would_hang_detection_is_refused_naming_the_field(manifest, change, words):
    manifest["pattern"].update(change)
    _refused(manifest, *words)


# ---- capture ids ----------------------------------------------------------------------------------
@pytest.mark.parametrize("cid", ["p0000\n", "\x1b[2Jp0000", "../p0000", "a b", "", "-p", "x" * 65, "p/0"])
def test_a_capture_id_outside_the_safe_characters_is_refused(manifest, cid):
    manifest["captures"][0]["id"] = "proj_01.b-2"  # letters, digits, '_', '.', '-'
    assert SessionManifest.from_dict(manifest).captures[0].id == "proj_01.b-2"
    manifest["captures"][0]["id"] = cid
    msg = _refused(manifest, "captures[0].id")
    assert "\x1b" not in msg and "\n" not in msg


# ---- printing what a file says --------------------------------------------------------------------
def test_the_calibration_summary_never_prints_control_characters_from_files():
    """A skipped image's reason comes from the detection cache or calibration.json: ESC[2J would clear
    the operator's screen."""
    from app.commands.calibrate import format_summary
    from drivers.sim.scenarios import get_scenario

    res = get_scenario().ground_truth().with_(skipped=({"capture_id": "p0000", "stage": "detect",
                                                        "reason": "\x1b[2J\x1b[31mno board\r\x07"},))
    text = format_summary(res)
    assert "no board" in text and not any(ch in text for ch in "\x1b\r\x07")
