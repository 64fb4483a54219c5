""""Moved" variants of the simulated rig, for on-site recalibration (issue 15, docs/RECALIBRATION.md).

`bump_scenario(scenario, part, seed)` returns the scenario with its rig disturbed the way a rig is
disturbed on site, and the ground truth of the rig after the bump (`scenario.ground_truth()`):

  projector: turned by 1 deg about a random axis and shifted by 10-20 mm in a random direction
             (about its own centre: the projector as a whole was knocked)
  mirror:    tilted by 0.5 deg about a random in-plane axis through the mirror's centre (re-seated)
  camera:    refocused: fx and fy scaled by 1.005 (0.5 %); principal point and distortion kept
  none:      unchanged (the control: a recalibration must say "unchanged")

Every draw follows from `seed`, so a bump is reproducible. The board poses the scripted operator uses
are derived from the bumped rig (the operator places the board where the moved projector lights).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calib.errors import SpecError
from calib.models.result import MirrorPlane
from calib.synthetic import MirrorRect, SyntheticRig
from calib.transforms import make_T, rotation_about

BUMP_PARTS = ("none", "projector", "mirror", "camera")
PROJECTOR_TURN_DEG = 1.0
PROJECTOR_SHIFT_MM = (10.0, 20.0)
MIRROR_TILT_DEG = 0.5
CAMERA_FOCAL_SCALE = 1.005


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def bump_rig(rig: SyntheticRig, part: str, seed: int = 0) -> SyntheticRig:
    """The rig after `part` was bumped (see the module docstring); a new SyntheticRig."""
    if part not in BUMP_PARTS:
        raise SpecError(f"unknown bump '{part}' (one of: {', '.join(BUMP_PARTS)})")
    rng = np.random.default_rng([int(seed), 1515, BUMP_PARTS.index(part)])
    if part == "none":
        return rig
    if part == "projector":
        T = np.array(rig.T_cam_proj, float)
        R = rotation_about(_unit(rng), PROJECTOR_TURN_DEG) @ T[:3, :3]
        t = T[:3, 3] + _unit(rng) * rng.uniform(*PROJECTOR_SHIFT_MM)
        return replace(rig, T_cam_proj=make_T(R, t))
    if part == "mirror":
        if rig.mirror is None:
            raise SpecError("this scenario has no mirror to bump (a direct rig): bump the projector or the camera")
        n = rig.mirror.normal
        a = rng.uniform(0, 2 * np.pi)
        rect = rig.mirror_rect
        axis = np.cos(a) * rect.axis_u + np.sin(a) * rect.axis_v  # in the mirror's plane
        Rm = rotation_about(axis, MIRROR_TILT_DEG)
        n2 = Rm @ n
        c = rect.centre  # the tilt pivots about the mirror's centre, which stays on the plane
        mirror = MirrorPlane(n2, -float(n2 @ c))
        new_rect = MirrorRect(c, Rm @ rect.axis_u, Rm @ rect.axis_v, rect.size)
        return replace(rig, mirror=mirror, mirror_rect=new_rect)
    # camera: refocused
    cam = rig.camera
    K = np.array(cam.K, float)
    K[0, 0] *= CAMERA_FOCAL_SCALE
    K[1, 1] *= CAMERA_FOCAL_SCALE
    return replace(rig, camera=cam.with_params(K=K))


def bump_scenario(scenario, part: str | None, seed: int | None = None):
    """The scenario with its rig bumped (None or 'none': the scenario itself). seed: default the
    scenario's. The name is kept (a resumed session finds its scenario by name); the description
    says what was bumped."""
    if part is None or part == "none":
        if part is not None and part not in BUMP_PARTS:
            raise SpecError(f"unknown bump '{part}'")
        return scenario
    rig = bump_rig(scenario.rig, part, scenario.seed if seed is None else seed)
    return replace(scenario, rig=rig, description=f"{scenario.description}; {part} bumped (issue 15 recalibration)")
