"""Hostile inputs that used to give a wrong calibration with exit 0, grouped by input."""

import json

import pytest

from calib.errors import FormatError
from calib.formats.session import SessionManifest
from tests._calib_helpers import session, write_session


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
