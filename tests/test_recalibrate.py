"""On-site recalibration (issue 15): the bumped simulated rig, the check's verdicts, the re-estimate,
the comparison and the archive (docs/RECALIBRATION.md)."""

from __future__ import annotations

import numpy as np
import pytest

from calib.errors import SpecError
from calib.metrics import compare
from drivers.sim.bump import BUMP_PARTS, bump_scenario
from drivers.sim.scenarios import get_scenario


# ---- the bumped simulated rig --------------------------------------------------------------------
def test_bumps_move_only_their_part_by_the_stated_amounts():
    sc = get_scenario("nonoverlap-136", 0)
    gt = sc.ground_truth()
    m = {p: compare(bump_scenario(sc, p, 0).ground_truth(), gt) for p in BUMP_PARTS}
    assert m["none"].distance == 0 and m["none"].angle_deg == 0 and m["none"].cam_k_px == 0
    assert 10.0 <= m["projector"].distance <= 20.0 and m["projector"].angle_deg == pytest.approx(1.0, abs=1e-9)
    assert m["projector"].cam_k_px == 0 and m["projector"].mirror_angle_deg == 0
    assert m["mirror"].mirror_angle_deg == pytest.approx(0.5, abs=1e-6) and m["mirror"].distance == 0
    cam0, cam1 = gt.camera, bump_scenario(sc, "camera", 0).ground_truth().camera
    assert cam1.fx / cam0.fx == pytest.approx(1.005) and cam1.fy / cam0.fy == pytest.approx(1.005)
    assert cam1.cx == cam0.cx and m["camera"].distance == 0 and m["camera"].mirror_angle_deg == 0


def test_bump_is_seeded_and_unknown_part_refused():
    sc = get_scenario("nonoverlap-136", 0)
    a, b = bump_scenario(sc, "projector", 3), bump_scenario(sc, "projector", 3)
    c = bump_scenario(sc, "projector", 4)
    assert np.array_equal(a.rig.T_cam_proj, b.rig.T_cam_proj)
    assert not np.allclose(a.rig.T_cam_proj, c.rig.T_cam_proj)
    with pytest.raises(SpecError, match="unknown bump"):
        bump_scenario(sc, "tripod", 0)


def test_open_sim_rig_renders_the_bumped_rig_and_says_so():
    from drivers.sim.rig import open_sim_rig

    rig = open_sim_rig("nonoverlap-136", 0, ideal=True, bump="mirror")
    try:
        gt = rig.ground_truth()
        assert compare(gt, get_scenario().ground_truth()).mirror_angle_deg == pytest.approx(0.5, abs=1e-6)
        assert np.allclose(rig.renderer.mirror.normal, gt.mirror.normal)
        assert rig.camera.settings()["bump"] == "mirror"
    finally:
        rig.close()
