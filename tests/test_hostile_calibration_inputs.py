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
