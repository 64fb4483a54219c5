"""Hostile inputs that used to give a wrong calibration with exit 0, grouped by input."""

import json

import pytest

from calib.errors import FormatError
from calib.formats.session import SessionManifest
from _calib_helpers import session, write_session


# ---- a mirror board declared in other units than the projector board --------------------------------
@pytest.fixture(scope="module")
def manifest_dict(tmp_path_factory):
    store = write_session(tmp_path_factory.mktemp("s"), session("136", per_position=1), projector_indices=[0],
                          mirror_indices=[0])
    return json.loads((store.folder / "session.json").read_text()) if hasattr(store, "folder") else \
        store.manifest.to_dict()


def test_mirror_board_in_cm_is_the_same_board_in_mm(manifest_dict):
    d = json.loads(json.dumps(manifest_dict))
    mb = d["mirror_board"]
    mb.update(square_length=mb["square_length"] / 10, marker_length=mb["marker_length"] / 10, units="cm")
    m = SessionManifest.from_dict(d)
    ref = SessionManifest.from_dict(manifest_dict)
    assert m.mirror_board.units == ref.units
    assert m.mirror_board.square_length == pytest.approx(ref.mirror_board.square_length)
    assert m.mirror_board.marker_length == pytest.approx(ref.mirror_board.marker_length)


def test_unknown_board_unit_is_refused_naming_the_field(manifest_dict):
    d = json.loads(json.dumps(manifest_dict))
    d["mirror_board"]["units"] = "furlong"
    with pytest.raises(FormatError, match="mirror_board.units"):
        SessionManifest.from_dict(d)


def test_a_camera_from_a_file_holds_numbers_only():
    """CameraModel.from_dict reads untrusted files: numpy would turn "600", true and null into numbers;
    a file that says so is refused naming the field. Absurd but numeric values load (the trust check
    judges them)."""
    from calib.errors import FormatError
    from calib.models.camera import CameraModel

    good = {"width": 1280, "height": 800, "K": [[600, 0, 640], [0, 600, 400], [0, 0, 1]], "dist": [0.1, 0, 0, 0, 0]}
    assert CameraModel.from_dict(good).fx == 600
    assert CameraModel.from_dict(dict(good, K=[[-642, 0, 640], [0, 600, 400], [0, 0, 1]])).fx == -642
    cases = {"K": dict(good, K=[["600", 0, 640], [0, 600, 400], [0, 0, 1]]),
             "dist": dict(good, dist=[True, 0, 0, 0, 0]),
             "width": dict(good, width=True),
             "height": dict(good, height=10 ** 9)}
    for field, bad in cases.items():
        with pytest.raises(FormatError, match=f"camera.{field}"):
            CameraModel.from_dict(bad)
    with pytest.raises(FormatError, match="last row"):
        CameraModel.from_dict(dict(good, K=[[600, 0, 640], [0, 600, 400], [0, 0, 2]]))
    with pytest.raises(FormatError, match="must be an object"):
        CameraModel.from_dict(["not", "a", "camera"])


# ---- calibration files (calibration.json and every file given as one) -------------------------------
def _calibration_dict() -> dict:
    from drivers.sim.scenarios import get_scenario

    return json.loads(json.dumps(get_scenario().ground_truth().to_dict()))


def _set(path: str, value):
    """A change of a calibration dict: `path` is dotted keys and list indices (camera.K.0.0)."""
    def change(d):
        *parents, last = path.split(".")
        for k in parents:
            d = d[int(k)] if isinstance(d, list) else d[k]
        d[int(last) if isinstance(d, list) else last] = value
    return change


#: case -> (change of a good calibration.json's bytes or dict, the field the error must name)
BAD_CALIBRATIONS = {
    "fx_nan": (_set("camera.K.0.0", float("nan")), r"camera\.K\[0\]\[0\]"),
    "fx_zero": (_set("camera.K.0.0", 0), r"camera\.K\[0\]\[0\]"),
    "fx_1e300": (_set("camera.K.0.0", 1e300), r"camera\.K\[0\]\[0\]"),
    "projector_fy_inf": (_set("projector.K.1.1", float("inf")), r"projector\.K\[1\]\[1\]"),
    "t_nan": (_set("T_cam_proj.0.3", float("nan")), r"T_cam_proj\[0\]\[3\]"),
    "mirror_d_nan": (_set("mirror.d", float("nan")), r"mirror\.d"),
    "mirror_normal_string": (_set("mirror.normal", ["0", 0, 1]), r"mirror\.normal"),
    "units_unknown": (_set("units", "parsec"), r"'units'"),
    "rms_list": (_set("rms", [1, 2]), r"'rms'"),
    "rms_value_string": (_set("rms", {"camera": "low"}), r"rms\.camera"),
    "diagnostics_string": (_set("diagnostics", "x"), r"'diagnostics'"),
    "per_view_5": (_set("per_view", 5), r"'per_view'"),
    "per_view_entry_number": (_set("per_view", [5]), r"per_view\[0\]"),
    "skipped_string": (_set("skipped", "all"), r"'skipped'"),
    "not_utf8": (lambda raw: raw.replace(b'"mm"', b'"\xff\xfe"'), r"not UTF-8"),
    "nested_100000_deep": (lambda raw: b"[" * 100_000 + b"]" * 100_000, r"nests more than"),
    "nested_200_deep": (lambda raw: raw[:-1] + b', "extra": ' + b"[" * 200 + b"]" * 200 + b"}", r"nests more than"),
}


def _write_bad(folder, case: str):
    change, field = BAD_CALIBRATIONS[case]
    raw = json.dumps(_calibration_dict()).encode()
    if change.__name__ == "change":
        d = _calibration_dict()
        change(d)
        raw = json.dumps(d).encode()
    else:
        raw = change(raw)
    path = folder / f"{case}.json"
    path.write_bytes(raw)
    return path, field


@pytest.mark.parametrize("case", sorted(BAD_CALIBRATIONS))
def test_a_calibration_file_that_is_not_one_is_refused_naming_the_field(tmp_path, case):
    """The one reader of calibration files (CalibrationResult.load_json): types, finiteness, sizes, shapes,
    nesting and encoding, each a FormatError naming the field (never LinAlgError, TypeError, RecursionError...)."""
    from calib.models.result import CalibrationResult

    path, field = _write_bad(tmp_path, case)
    with pytest.raises(FormatError, match=field):
        CalibrationResult.load_json(path)


def test_absurd_but_well_formed_calibrations_load_and_the_trust_check_refuses_them(tmp_path):
    from calib.models.result import CalibrationResult
    from calib.quality.trust import check_calibration

    for change, code in ((_set("camera.K.0.0", -642), "focal_nonpositive"),
                         (_set("camera.dist", [1e10, 0, 0, 0, 0]), "distortion_scale")):
        d = _calibration_dict()
        change(d)
        (tmp_path / "c.json").write_text(json.dumps(d))
        assert code in check_calibration(CalibrationResult.load_json(tmp_path / "c.json")).codes
    assert check_calibration(CalibrationResult.from_dict(_calibration_dict())).passed


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    """A session folder (one projector and one mirror capture): enough for a command to read a calibration."""
    folder = tmp_path_factory.mktemp("hostile") / "s"
    write_session(folder, session("136", per_position=1), projector_indices=[0], mirror_indices=[0])
    return folder


def _command(kind: str, session_dir, cal, tmp_path) -> list[str]:
    return {"calibrate": ["calibrate", str(session_dir), "--camera-intrinsics", str(cal), "--no-progress",
                          "--workers", "1", "--out", str(tmp_path / "out.json")],
            "report": ["report", str(session_dir), "--calibration", str(cal), "--out", str(tmp_path / "r.html")],
            "verify": ["verify", str(session_dir), "--rig", "sim", "--calibration", str(cal),
                       "--out", str(tmp_path / "v.json")],
            "recalibrate": ["recalibrate", str(cal), "--rig", "sim", "--auto", "--out", str(tmp_path / "recal")],
            }[kind]


@pytest.fixture
def nothing_runs(monkeypatch):
    """Detection and opening a rig fail loudly: a command refusing its calibration file never gets there."""
    import app.station.setup
    import calib.detection.detect
    from calib.errors import ProcamError

    def never(*a, **kw):
        raise ProcamError("REACHED: the file was not refused first")

    monkeypatch.setattr(calib.detection.detect, "detect_session", never)
    monkeypatch.setattr(app.station.setup, "open_requested_rig", never)


COMMANDS = ("calibrate", "report", "verify", "recalibrate")


@pytest.mark.parametrize("kind", COMMANDS)
def test_every_command_refuses_a_broken_calibration_file_in_one_line_naming_the_field(
        session_dir, tmp_path, capsys, kind, nothing_runs):
    import re

    from app.cli import main

    for case in ("fx_nan", "fx_zero", "t_nan", "mirror_d_nan", "rms_list", "diagnostics_string", "per_view_5",
                 "not_utf8", "nested_100000_deep"):
        path, field = _write_bad(tmp_path, case)
        assert main(_command(kind, session_dir, path, tmp_path)) == 2, case
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"procam {kind}: error: "), (case, err)
        assert re.search(field, err[0]) and "unexpected" not in err[0] and "REACHED" not in err[0], (case, err)
    assert not (tmp_path / "recal").exists() and not (tmp_path / "r.html").exists()


@pytest.mark.parametrize("kind", ("calibrate", "recalibrate"))
def test_absurd_intrinsics_or_previous_are_refused_by_the_trust_check_before_any_work(
        session_dir, tmp_path, capsys, kind, nothing_runs):
    """fx -642 / dist 1e10: the trust check's reason (never the images blamed, never a capture taken, never
    the absurd previous written back as the recalibrated calibration)."""
    from app.cli import main

    for change, code in ((_set("camera.K.0.0", -642), "focal_nonpositive"),
                         (_set("camera.dist", [1e10, 0, 0, 0, 0]), "distortion_scale")):
        d = _calibration_dict()
        change(d)
        (tmp_path / "c.json").write_text(json.dumps(d))
        assert main(_command(kind, session_dir, tmp_path / "c.json", tmp_path)) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"[{code}]" in err[0] and "REACHED" not in err[0], err
        assert not (tmp_path / "recal").exists() and not (tmp_path / "out.json").exists()


def test_a_sessions_own_calibration_json_nested_100000_deep_is_no_unexpected_error(session_dir, tmp_path, capsys):
    """`procam calibrate` looks at the calibration.json already in the session (whose method is it?): a
    broken one counts as none, never a RecursionError."""
    import shutil

    from app.cli import main

    s = tmp_path / "s"
    shutil.copytree(session_dir, s)
    (s / "calibration.json").write_bytes(b"[" * 100_000 + b"]" * 100_000)
    main(["calibrate", str(s), "--no-progress", "--workers", "1"])
    err = capsys.readouterr().err
    assert "unexpected" not in err and "Recursion" not in err, err
