"""The trust check on a family of random, physically valid rigs (calib.synthetic.random_session): it
accepts every correct calibration and rejects every corrupted one. A check that refuses a correct
result is as much a bug as one that passes a wrong one."""

import dataclasses

import numpy as np
import pytest

from calib.models.result import MirrorPlane
from calib.pipeline import calibrate_observations
from calib.quality.trust import check_calibration
from calib.synthetic import random_session, observe
from calib.transforms import make_T, rotation_about

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

RIGS = 200
CHUNK = 20


def _corruptions(result, ss):
    """(name, corrupted result) for a correct result: a wrong pose, a swapped mirror normal, absurd
    intrinsics. Each keeps the correct result's recorded residuals and uncertainty (as a forged or
    mixed-up file would)."""
    T = np.array(result.T_cam_proj, float)
    dist = float(np.linalg.norm(T[:3, 3]))
    moved = T.copy()
    moved[:3, 3] += T[:3, :3] @ np.array([0.12 * dist + 40.0, 0.0, 0.0])
    yield "pose shifted", result.with_(T_cam_proj=moved)
    turned = make_T(rotation_about([0.0, 1.0, 0.0], 4.0) @ T[:3, :3], T[:3, 3])
    yield "pose turned 4 deg", result.with_(T_cam_proj=turned)
    if result.mirror is not None:
        yield "mirror normal swapped", result.with_(mirror=MirrorPlane(-np.asarray(result.mirror.normal), result.mirror.d))
    pj = result.projector
    K = np.array(pj.K, float)
    K[0, 0] *= 40.0
    K[1, 1] *= 40.0
    yield "projector focal x40", result.with_(projector=pj.with_params(K=K))
    Kc = np.array(result.camera.K, float)
    Kc[1, 1] = -Kc[1, 1]
    yield "camera fy negative", result.with_(camera=result.camera.with_params(K=Kc))


@pytest.mark.parametrize("first", range(0, RIGS, CHUNK))
def test_valid_rigs_are_trusted_and_corrupted_results_are_not(first):
    false_rejections, missed = [], []
    for seed in range(first, first + CHUNK):
        ss = random_session(seed)
        obs = observe(ss, 0.2, seed, circle_centroids=True)
        result = calibrate_observations(obs, "joint", trust=None)
        rep = check_calibration(result, observations=obs)
        if not rep.passed:
            false_rejections.append((seed, ss.extras, [r.message for r in rep.reasons]))
        for name, bad in _corruptions(result, ss):
            if check_calibration(bad, observations=obs).passed:
                missed.append((seed, name, ss.extras))
    assert not false_rejections, false_rejections
    assert not missed, missed


def test_the_family_spans_the_rigs_it_claims():
    """The generator draws what the property test claims to cover (over the test's seeds)."""
    ex = [random_session(s).extras for s in range(0, RIGS, 4)]
    angles = [e["angle_deg"] for e in ex]
    base = [e["baseline_mm"] for e in ex]
    throws = [e["throw"] for e in ex]
    fovs = [e["hfov_deg"] for e in ex]
    assert min(angles) < 20 and max(angles) > 165
    assert min(base) < 300 and max(base) > 1500
    assert min(throws) < 0.5 and max(throws) > 1.8
    assert min(fovs) < 45 and max(fovs) > 100
    mirrored = [random_session(s).rig.mirror is not None for s in range(0, 40, 4)]
    assert any(mirrored) and not all(mirrored)


def test_without_observations_the_check_still_runs():
    ss = random_session(3)
    obs = observe(ss, 0.2, 3)
    result = calibrate_observations(obs, "joint")  # the pipeline hands the observations to the check
    assert "observations.pattern_rms_px" in result.diagnostics["trust"]["metrics"]
    assert check_calibration(result).passed
    assert not check_calibration(dataclasses.replace(result), observations=obs).codes
