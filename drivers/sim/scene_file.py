"""Reader of the simulator's scene.json (written by `procam simulate`): the exact image points of every
capture, for measuring detection against ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from calib.formats import session_files
from calib.formats.fileio import RESULT_MAX_BYTES, read_json
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL
from calib.models.pattern import PatternSpec
from calib.models.result import MirrorPlane
from calib.synthetic import SyntheticRig, projector_points_on_board
from calib.transforms import transform_points


class ExpectedPoints(NamedTuple):
    """Exact camera pixels (lens distortion included) of one capture. `board_px`: ChArUco corners by id
    (the projector board, or the real mirror board); `pattern_px`: images of the pattern's circle
    centres (not the blob centroids: docs/GEOMETRY.md's bias) or None; `virtual_px`: corners of the board's
    reflection (real-virtual captures) or None."""

    board_px: np.ndarray
    pattern_px: np.ndarray | None
    virtual_px: np.ndarray | None


def expected_points(folder) -> dict[str, ExpectedPoints]:
    """{capture id: ExpectedPoints} of a `procam simulate` session folder, from its scene.json."""
    s = read_json(Path(folder) / session_files.SCENE, RESULT_MAX_BYTES, "scene file")
    cam, proj = CameraModel.from_dict(s["camera"]), CameraModel.from_dict(s["projector"])
    mirror = MirrorPlane(s["mirror"]["normal"], s["mirror"]["d"]) if s["mirror"] else None
    rig = SyntheticRig(cam, proj, np.array(s["T_cam_proj"]), mirror, None, np.zeros(3), 0.0, 0.0)
    S = rig.S()
    pboard = CharucoSpec.from_dict(s["projector_board"])
    mboard = CharucoSpec.from_dict(s["mirror_board"]) if s.get("mirror_board") else None
    pattern = PatternSpec.from_dict(s["pattern"])
    out = {}
    for c in s["captures"]:
        T = np.array(c["T_cam_board"])
        if c["step"] == STEP_PROJECTOR:
            q = pattern.points_px(proj.width, proj.height, c["pattern_position"])
            Xb = projector_points_on_board(rig, T, q)
            out[c["id"]] = ExpectedPoints(cam.project(transform_points(S @ T, pboard.corner_points())),
                                          cam.project(transform_points(S @ T, Xb)), None)
        elif mboard is not None:
            X = transform_points(T, mboard.corner_points())
            virt = cam.project(transform_points(S, X)) if c["step"] == STEP_REAL_VIRTUAL else None
            out[c["id"]] = ExpectedPoints(cam.project(X), None, virt)
    return out
