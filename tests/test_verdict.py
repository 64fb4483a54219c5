"""The overall verdict (calib.quality.verdict) on results a file could hold: each absurd one is NOT
TRUSTED with its reason, a good one TRUSTED; and the report says it at the top (issue 29's files)."""

import json
import shutil

import numpy as np
import pytest

from calib.models.camera import CameraModel
from calib.quality.verdict import Level, overall_verdict
from calib.synthetic import make_rig


def _with_camera(result, **changes):
    return result.with_(camera=CameraModel.from_dict(dict(result.camera.to_dict(), **changes)))


def test_absurd_results_are_not_trusted_and_say_why():
    gt = make_rig(136).ground_truth()
    assert overall_verdict(gt, mirror_rig=True).level is Level.TRUSTED
    cam = gt.camera
    far = gt.T_cam_proj.copy()
    far[0, 3] = 1e300
    cases = {
        "focal length is not positive": _with_camera(gt, K=[[-642.0, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]]),
        "radial distortion moves the image corners' rays": _with_camera(gt, dist=[1e10, 0, 0, 0, 0]),
        "has no mirror plane": gt.with_(mirror=None),
        "projector is inf": gt.with_(T_cam_proj=far),
    }
    for words, bad in cases.items():
        v = overall_verdict(bad, mirror_rig=True)
        assert v.level is Level.UNTRUSTED and v.headline.startswith("NOT TRUSTED"), words
        assert any(words in r for r in v.reasons), (words, v.reasons)
    # a direct-view rig has no mirror: none is asked for
    assert not any("mirror plane" in r for r in overall_verdict(gt.with_(mirror=None), mirror_rig=False).reasons)


@pytest.mark.slow
def test_the_report_puts_the_verdict_on_top(calibrated, tmp_path):
    from app.report import write_report

    html = write_report(calibrated, tmp_path / "good.html").read_text()
    top = html[html.index("<h1"):html.index('id="summary"')]
    assert 'id="overall-verdict" data-level="trusted"' in top and "TRUSTED: passes the trust check" in top
    # coverage: one definition, named as the panel names it
    assert "Coverage is the share of an image's 16-column grid cells that hold a point" in html
    folder = tmp_path / "s"
    shutil.copytree(calibrated, folder)
    cal = json.loads((folder / "calibration.json").read_text())
    cal["camera"]["K"][0][0] = -642.0
    cal["projector"]["dist"] = [1e10] + [0.0] * (len(cal["projector"]["dist"]) - 1)
    cal["mirror"] = None
    cal["T_cam_proj"][0][3] = 1e9  # absurd but a number the file reader accepts (1e300 is refused as a file error)
    (folder / "calibration.json").write_text(json.dumps(cal))
    html = write_report(folder, tmp_path / "bad.html").read_text()
    top = html[html.index("<h1"):html.index('id="summary"')]
    assert 'data-level="not trusted"' in top and "NOT TRUSTED: fails the trust check" in top
    for words in ("focal length is not positive", "has no mirror plane", "radial distortion moves the image corners"):
        assert words in top, words


from test_report import calibrated  # noqa: E402,F401  (the module's simulated, calibrated session)
