"""The joint adjustment's 1-sigmas predicted for more observations without solving
(calib.joint.predict): what the station's asked pose would be ranked by."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import pytest

from calib.errors import CalibrationError
from calib.joint.predict import predict_uncertainty
from calib.pipeline import calibrate_observations
from calib.quality.confidence import sigmas
from _calib_helpers import placements_observations


def _session():
    """nonoverlap-136's 14 mirror views with the structured step's first 4, and first 6, projector placements
    (0.05 px of noise): the 4-placement observations are the 6's first views."""
    six = placements_observations("nonoverlap-136", 0, 6, 0.05)
    return replace(six, projector_views=six.projector_views[:4]), six


@lru_cache(maxsize=None)
def _calibrated(n: int):
    four, six = _session()
    return calibrate_observations(four if n == 4 else six, "joint")


def test_predicting_the_observations_a_result_was_calibrated_from_gives_its_own_sigmas():
    four, _ = _session()
    est = _calibrated(4)
    got, want = sigmas(predict_uncertainty(four, est)), sigmas(est)
    for key, value in want.items():
        assert got[key] == pytest.approx(value, rel=1e-6), key


def test_two_more_placements_predicted_from_four_match_their_calibration():
    """The 1-sigmas of 6 placements predicted at the 4-placement calibration agree with calibrating the
    6 (the same distortion models chosen) within 5%, and each is smaller than the 4's."""
    _, six = _session()
    est, full = _calibrated(4), _calibrated(6)
    for key in ("camera_model", "projector_model"):
        assert est.diagnostics[key] == full.diagnostics[key], "the data changed: the models differ"
    before, pred, calibrated = sigmas(est), sigmas(predict_uncertainty(six, est)), sigmas(full)
    for key, value in calibrated.items():
        assert pred[key] == pytest.approx(value, rel=0.05), key
        assert pred[key] < before[key], key


def test_a_result_without_its_joint_uncertainty_is_refused_with_the_reason():
    four, _ = _session()
    paper = calibrate_observations(four, "paper")
    with pytest.raises(CalibrationError, match="needs a joint calibration"):
        predict_uncertainty(four, paper)
    with pytest.raises(CalibrationError, match="needs a joint calibration"):
        predict_uncertainty(four, _calibrated(4).with_(uncertainty=None))
