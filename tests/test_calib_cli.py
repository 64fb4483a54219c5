"""`procam calibrate` and `procam evaluate` end to end: a rendered session folder (ray-cast images of
a synthetic rig, tests/_calib_helpers.py) through detection, the paper pipeline and the files."""

import json

import cv2
import numpy as np
import pytest

from _calib_helpers import write_session
from app.cli import main
from calib.errors import FormatError
from calib.export import opencv
from calib.formats.session import RigInfo, SessionManifest, SessionStore
from calib.models.result import CalibrationResult
from calib.pipeline import load_camera_intrinsics
from calib.quality.metrics import compare
from calib.synthetic import make_rig, make_session


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """136-degree rig, one board pose per pattern position (13) and 5 real-virtual images."""
    rig = make_rig(136)
    ss = make_session(rig, per_position=1, mirror_count=5, seed=2)
    folder = tmp_path_factory.mktemp("calib_cli") / "session"
    write_session(folder, ss)
    truth = folder.parent / "truth.json"
    rig.ground_truth().save_json(truth)
    return folder, truth, rig


@pytest.mark.slow
def test_calibrate_and_evaluate_a_rendered_session(rendered, tmp_path, capsys):
    folder, truth, rig = rendered
    rc = main(["calibrate", str(folder), "--method", "paper", "--workers", "2"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "detect" in err and "calibrate" in err  # tqdm bars on stderr
    for text in ("method: paper", "T_cam_proj", "mirror: normal", "RMS: camera", "skipped"):
        assert text in out
    result = CalibrationResult.load_json(folder / "calibration.json")
    assert result.method == "paper" and result.units == "mm"
    m = compare(result, rig.ground_truth())
    # rendered images, real detection: better than the paper's synthetic headline (3.2 mm, 0.18 deg), the
    # angle within 0.22 deg: this session has 13 projector poses, a quarter of the protocol's 52, and the
    # paper method's angle moves with the data (0.166 deg before the ChArUco search on a linearised copy,
    # 0.197 after it: 6-9 more virtual corners in 4 of the 5 mirror views, all within 0.12 px of the
    # truth, camera K 0.84 -> 0.78 px; issue 18)
    assert m.distance < 3.2 and m.angle_deg < 0.22
    assert m.proj_k_px < 7.6 and m.mirror_angle_deg < 0.09 and m.mirror_offset < 0.6
    assert m.cam_rms_px < 0.3 and m.stereo_rms_px < 0.3
    fs = cv2.FileStorage(str(folder / "calibration.yaml"), cv2.FILE_STORAGE_READ)
    assert np.allclose(fs.getNode("camera_matrix").mat(), result.camera.K)
    assert np.allclose(fs.getNode("T_cam_proj").mat(), result.T_cam_proj)
    fs.release()
    # procam export of the session writes the same YAML as procam calibrate did (one registry), byte for byte
    assert main(["export", str(folder), "--format", "opencv,mrcal", "--out", str(tmp_path / "x")]) == 0
    capsys.readouterr()
    assert (tmp_path / "x" / "calibration.yaml").read_bytes() == (folder / "calibration.yaml").read_bytes()

    rc = main(["evaluate", str(folder / "calibration.json"), str(truth)])
    out, _ = capsys.readouterr()
    assert rc == 0
    line = next(ln for ln in out.splitlines() if ln.startswith("Distance"))
    assert float(line.split()[1]) == pytest.approx(m.distance, abs=1e-3)
    rc = main(["evaluate", str(folder / "calibration.json"), str(truth), "--json"])
    data = json.loads(capsys.readouterr().out)
    assert data["angle_deg"] == pytest.approx(m.angle_deg, abs=1e-9)


@pytest.mark.slow
def test_calibrate_with_given_camera_intrinsics(rendered, tmp_path, capsys):
    folder, truth, rig = rendered
    yml = tmp_path / "cam.yaml"
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", rig.camera.width)
    fs.write("image_height", rig.camera.height)
    fs.write("camera_matrix", np.array(rig.camera.K))
    fs.write("distortion_coefficients", np.array(rig.camera.dist).reshape(1, -1))
    fs.release()
    out_json = tmp_path / "out" / "cal.json"
    rc = main(["calibrate", str(folder), "--method", "paper", "--camera-intrinsics", str(yml), "--out", str(out_json),
               "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    result = CalibrationResult.load_json(out_json)
    assert np.allclose(result.camera.K, rig.camera.K) and np.allclose(result.camera.dist, rig.camera.dist)
    assert result.diagnostics["camera"]["precalibrated"] is True
    assert (tmp_path / "out" / "cal.yaml").exists()
    assert compare(result, rig.ground_truth()).distance < 3.2


def _empty_session(folder, view="mirror", n_projector=5, mirror=True):
    rig = make_rig(136)
    ss = make_session(rig, per_position=1, mirror_count=1, seed=1)
    manifest = SessionManifest(RigInfo(rig.camera.size, rig.projector.size, view), ss.layout.charuco, ss.pattern,
                               ss.mirror_board, "real-virtual" if mirror else None)
    store = SessionStore.create(folder, manifest)
    blank = np.full((rig.camera.height, rig.camera.width), 90, np.uint8)
    for i in range(n_projector):
        store.add_capture("projector", blank, i, ss.pattern.points_px(rig.projector.width, rig.projector.height, i))
    return store


def test_session_without_usable_views_exits_2_with_a_reason(tmp_path, capsys):
    _empty_session(tmp_path / "s")
    rc = main(["calibrate", str(tmp_path / "s"), "--method", "paper", "--no-progress", "--workers", "1"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("procam calibrate: error: only 0 usable projector image(s)")
    assert "board not found" in err or "not found" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "s" / "calibration.json").exists()


def test_missing_session_exits_2(tmp_path, capsys):
    rc = main(["calibrate", str(tmp_path / "nope"), "--method", "paper"])
    assert rc == 2 and "does not exist" in capsys.readouterr().err


def test_unknown_method_exits_2(tmp_path, capsys):
    _empty_session(tmp_path / "s", n_projector=0)
    rc = main(["calibrate", str(tmp_path / "s"), "--method", "nonsense", "--no-progress", "--workers", "1"])
    assert rc == 2 and "unknown calibration method 'nonsense'" in capsys.readouterr().err


def test_camera_intrinsics_files(tmp_path):
    rig = make_rig(90)
    gt = rig.ground_truth()
    gt.save_json(tmp_path / "c.json")
    cam = load_camera_intrinsics(tmp_path / "c.json")
    assert np.allclose(cam.K, rig.camera.K) and cam.size == rig.camera.size
    opencv.write(gt, [tmp_path / "c.yaml"])  # our own export: camera_distortion, camera_width
    cam = load_camera_intrinsics(tmp_path / "c.yaml")
    assert np.allclose(cam.dist, rig.camera.dist) and cam.size == rig.camera.size
    # a minimal OpenCV file without a size takes the session's
    fs = cv2.FileStorage(str(tmp_path / "m.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array(rig.camera.K))
    fs.write("distortion_coefficients", np.array(rig.camera.dist).reshape(-1, 1))
    fs.release()
    cam = load_camera_intrinsics(tmp_path / "m.yml", (1280, 800))
    assert cam.size == (1280, 800) and np.allclose(cam.dist, rig.camera.dist)
    fs = cv2.FileStorage(str(tmp_path / "bad.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    with pytest.raises(FormatError, match="camera_matrix"):
        load_camera_intrinsics(tmp_path / "bad.yml", (1280, 800))
    (tmp_path / "junk.json").write_text("{")
    with pytest.raises(FormatError, match="not valid JSON"):
        load_camera_intrinsics(tmp_path / "junk.json")
    with pytest.raises(FormatError, match="does not exist"):
        load_camera_intrinsics(tmp_path / "missing.yaml")


def test_evaluate_prints_the_paper_metrics(tmp_path, capsys):
    rig = make_rig(136)
    gt = rig.ground_truth()
    gt.save_json(tmp_path / "gt.json")
    T = np.array(gt.T_cam_proj)
    T[:3, 3] += [3.0, 0.0, 4.0]
    K = np.array(gt.projector.K)
    K[0, 0] += 6.0
    est = gt.with_(T_cam_proj=T, projector=gt.projector.with_params(K=K), method="paper",
                   rms={"camera": 0.1, "projector": 0.2, "stereo": 0.15, "mirror_plane": 0.05})
    est.save_json(tmp_path / "est.json")
    assert main(["evaluate", str(tmp_path / "est.json"), str(tmp_path / "gt.json")]) == 0
    out = capsys.readouterr().out
    rows = {ln.split()[0]: ln.split()[1] for ln in out.splitlines()[1:] if ln.strip()}
    assert float(rows["Distance"]) == pytest.approx(5.0, abs=1e-3)
    assert float(rows["ProjK"]) == pytest.approx(6.0, abs=1e-3)
    assert float(rows["Angle"]) == pytest.approx(0.0, abs=1e-6)
    assert float(rows["StereoRMS"]) == pytest.approx(0.15)
    # units must agree
    gt.with_(units="cm").save_json(tmp_path / "gt_cm.json")
    assert main(["evaluate", str(tmp_path / "est.json"), str(tmp_path / "gt_cm.json")]) == 2
    assert "units" in capsys.readouterr().err
