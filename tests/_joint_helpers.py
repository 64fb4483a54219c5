"""Shared fixtures of the joint-refinement tests: synthetic sessions (cached per process), a
deterministic perturbation of the ground truth to start from, and per-parameter errors with their
reported 1-sigma values."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult, MirrorPlane
from calib.synthetic import d455_camera, make_direct_rig, make_rig, make_session, observe, portable_projector
from calib.transforms import rotation_about


@lru_cache(maxsize=16)
def session(rig: str = "136", mirror_method: str = "real-virtual", per_position: int = 4, seed: int = 0,
            camera_dist: tuple | None = None, projector_dist: tuple | None = None,
            pattern: PatternSpec | None = None):
    """rig: '90', '136', '180' (mirrored) or 'direct'; optional distortions replace the defaults."""
    cam = d455_camera() if camera_dist is None else d455_camera().with_params(dist=list(camera_dist))
    proj = portable_projector() if projector_dist is None else portable_projector().with_params(dist=list(projector_dist))
    r = make_direct_rig(cam, proj) if rig == "direct" else make_rig(float(rig), cam, proj)
    return make_session(r, pattern=pattern, mirror_method=None if rig == "direct" else mirror_method,
                        per_position=per_position, seed=seed)


@lru_cache(maxsize=32)
def observations(noise_px: float = 0.0, noise_seed: int = 0, circle_centroids: bool = False, **kw):
    return observe(session(**kw), noise_px, noise_seed, circle_centroids=circle_centroids)


def ground_truth(**kw) -> CalibrationResult:
    return session(**kw).rig.ground_truth()


def perturbed(gt: CalibrationResult) -> CalibrationResult:
    """A start some way off the truth everywhere (a few px, 20-30 % of the distortion, 5 mm, 0.5 deg,
    0.3 deg and 2 mm on the mirror), like a rough sequential calibration."""
    cam = gt.camera.with_params(K=gt.camera.K + [[5, 0, 3], [0, -4, -2], [0, 0, 0]], dist=gt.camera.dist5() * 0.8)
    proj = gt.projector.with_params(K=gt.projector.K + [[30, 0, 10], [0, -25, -8], [0, 0, 0]],
                                    dist=gt.projector.dist5() * 0.7)
    T = np.array(gt.T_cam_proj)
    T[:3, :3] = rotation_about([0.3, 1, 0.2], 0.5) @ T[:3, :3]
    T[:3, 3] += [5, -3, 4]
    mirror = None
    if gt.mirror is not None:
        mirror = MirrorPlane(rotation_about([1, 0.2, 0], 0.3) @ gt.mirror.normal, gt.mirror.d + 2)
    return CalibrationResult(cam, proj, T, mirror, gt.units, method="perturbed")


def parameter_errors(res: CalibrationResult, gt: CalibrationResult) -> list[tuple[str, float, float]]:
    """(name, |error|, reported 1-sigma) of every parameter result.uncertainty reports."""
    u = res.uncertainty
    out = []
    for dev, a, b in (("camera", res.camera, gt.camera), ("projector", res.projector, gt.projector)):
        for k, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            out.append((f"{dev}.{k}", abs(a.K[i, j] - b.K[i, j]), u[dev][k]))
        da, db = a.dist5(), b.dist5()
        for i in range(5):
            out.append((f"{dev}.dist{i}", abs(da[i] - db[i]), u[dev]["dist"][i]))
    t = res.T_cam_proj[:3, 3] - gt.T_cam_proj[:3, 3]
    w = np.degrees(cv2.Rodrigues(np.ascontiguousarray(res.T_cam_proj[:3, :3] @ gt.T_cam_proj[:3, :3].T))[0].ravel())
    for i, ax in enumerate("xyz"):
        out.append((f"t_{ax}", abs(t[i]), u["T_cam_proj"]["t"][i]))
        out.append((f"rot_{ax}", abs(w[i]), u["T_cam_proj"]["rot_deg"][i]))
    if res.mirror is not None:
        ang = np.degrees(np.arccos(np.clip(res.mirror.normal @ gt.mirror.normal, -1, 1)))
        out.append(("mirror.normal", ang, u["mirror"]["normal_deg"]))
        out.append(("mirror.d", abs(res.mirror.d - gt.mirror.d), u["mirror"]["d"]))
    return out
