"""Round trips of every file format (session.json, calibration.json, OpenCV YAML), malformed files that
name their culprit, and crash safety of session writes."""

import copy
import json

import cv2
import numpy as np
import pytest

from calib.errors import FormatError, SessionError
from calib.export import opencv
from calib.formats.session import MANIFEST, Capture, RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, VIEW_DIRECT, VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult, MirrorPlane
from calib.synthetic import d455_camera, make_rig, portable_projector

PATTERN = PatternSpec.default_for(1280, 720)
BOARD = CharucoSpec(8, 6, "DICT_5X5_50", 44.3, 22.15, "mm")
MBOARD = CharucoSpec(8, 6, "DICT_4X4_50", 22.2, 13.3, "mm")


def _manifest(**kw) -> SessionManifest:
    caps = (
        Capture("mrv0000", STEP_REAL_VIRTUAL, "images/mrv0000.png", meta={"exposure_us": 8000}),
        Capture("p0000", STEP_PROJECTOR, "images/p0000.png", 3, PATTERN.points_px(1280, 720, 3),
                {"settle_s": 0.12}),
    )
    base = dict(rig=RigInfo((120, 80), (1280, 720), VIEW_MIRROR, {"exposure_us": 8000, "gain": 16}, "sim"),
                projector_board=BOARD, pattern=PATTERN, mirror_board=MBOARD, mirror_method="real-virtual",
                board_thickness=0.0, captures=caps, state={"step": "projector", "position": 4}, blank_area=(250.0, 15.0))
    base.update(kw)
    return SessionManifest(**base)


def _image(seed=0, shape=(80, 120)):
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


# ---- session.json ---------------------------------------------------------------------------------------
def test_manifest_dict_round_trip():
    m = _manifest()
    d = m.to_dict()
    back = SessionManifest.from_dict(json.loads(json.dumps(d)))
    assert back.to_dict() == d
    assert back.rig == m.rig and back.projector_board == BOARD and back.mirror_board == MBOARD
    assert back.pattern == PATTERN and back.state == m.state and back.blank_area == (250.0, 15.0)
    # a session written before the blank area was recorded: not given
    d.pop("projector_blank_area")
    assert SessionManifest.from_dict(json.loads(json.dumps(d))).blank_area is None
    assert np.array_equal(back.captures[1].pattern_points_px, m.captures[1].pattern_points_px)
    assert back.captures[1].pattern_position == 3 and back.captures[0].pattern_points_px is None
    # a direct rig without a mirror board and method
    direct = _manifest(rig=RigInfo((640, 480), (1280, 720), VIEW_DIRECT), mirror_board=None, mirror_method=None,
                       captures=(m.captures[1],))
    d2 = direct.to_dict()
    assert d2["mirror_board"] is None and d2["mirror_method"] is None
    assert SessionManifest.from_dict(json.loads(json.dumps(d2))).to_dict() == d2


def test_session_store_create_open_add_delete(tmp_path):
    folder = tmp_path / "s"
    store = SessionStore.create(folder, _manifest(captures=()))
    imgs = {}
    for k in range(3):
        img = _image(k)
        cap = store.add_capture(STEP_PROJECTOR, img, k, PATTERN.points_px(1280, 720, k), {"k": k})
        imgs[cap.id] = img
    colour = cv2.cvtColor(_image(9), cv2.COLOR_GRAY2BGR)
    colour[..., 2] = 255 - colour[..., 2]
    mcap = store.add_capture(STEP_REAL_MIRROR, colour)
    assert [c.id for c in store.manifest.captures] == ["p0000", "p0001", "p0002", "mrm0000"]

    again = SessionStore.open(folder)
    assert again.manifest.to_dict() == store.manifest.to_dict()
    for cid, img in imgs.items():
        cap = next(c for c in again.manifest.captures if c.id == cid)
        assert np.array_equal(again.load_image(cap, cv2.IMREAD_UNCHANGED), img)  # lossless
    assert np.array_equal(again.load_image(mcap), colour)

    again.delete_capture("p0001")
    assert not (folder / "images" / "p0001.png").exists()
    reopened = SessionStore.open(folder)
    assert [c.id for c in reopened.manifest.captures] == ["p0000", "p0002", "mrm0000"]
    # ids are never reused, even after a delete of the last one
    reopened.delete_capture("p0002")
    assert reopened.add_capture(STEP_PROJECTOR, _image(5), 0, PATTERN.points_px(1280, 720, 0)).id == "p0001"
    with pytest.raises(SessionError, match="no capture 'p9999'"):
        reopened.delete_capture("p9999")
    with pytest.raises(SessionError, match="already holds a session"):
        SessionStore.create(folder, _manifest())
    reopened.update(state={"step": "done"})
    assert SessionStore.open(folder).manifest.state == {"step": "done"}


def _write(folder, d):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / MANIFEST).write_text(json.dumps(d))
    return folder


def _broken(tmp_path, edit):
    d = copy.deepcopy(_manifest().to_dict())
    edit(d)
    return _write(tmp_path / "broken", d)


@pytest.mark.parametrize("edit,field,problem", [
    (lambda d: d["rig"].pop("view"), "rig.view", "missing"),
    (lambda d: d["rig"].__setitem__("view", "sideways"), "rig.view", "must be 'mirror' or 'direct'"),
    (lambda d: d["rig"]["camera"].__setitem__("width", "1280"), "rig.camera.width", "wrong type (str)"),
    (lambda d: d["rig"]["projector"].__setitem__("height", 0), "rig.projector.width", "positive"),
    (lambda d: d["captures"][0].__setitem__("step", 3), "captures[0].step", "wrong type (int)"),
    (lambda d: d["captures"][0].__setitem__("step", "calibrate"), "captures[0].step", "must be one of"),
    (lambda d: d["captures"][1].__setitem__("pattern_points_px", d["captures"][1]["pattern_points_px"][:-1]),
     "captures[1].pattern_points_px", "has 35 points, the pattern has 36"),
    (lambda d: d["captures"][1].__setitem__("pattern_points_px", [["a", "b"]]), "captures[1].pattern_points_px",
     "list of [x, y] pairs"),
    (lambda d: d["captures"][1].pop("pattern_points_px"), "captures[1].pattern_points_px", "missing"),
    (lambda d: d["captures"][1].__setitem__("pattern_position", 1.5), "captures[1].pattern_position", "integer"),
    (lambda d: d["captures"][1].__setitem__("id", "mrv0000"), "captures[1].id", "duplicate capture id"),
    (lambda d: d["captures"][0].pop("image"), "captures[0].image", "missing"),
    (lambda d: d["captures"][0].__setitem__("meta", [1]), "captures[0].meta", "must be an object"),
    (lambda d: d["projector_board"].__setitem__("dictionary", "DICT_NOPE"), "projector_board",
     "unknown ArUco dictionary"),
    (lambda d: d["projector_board"].__setitem__("marker_length", 60.0), "projector_board", "marker_length"),
    (lambda d: d["mirror_board"].pop("cols"), "mirror_board.cols", "missing"),
    (lambda d: d["pattern"].__setitem__("kind", "dots"), "pattern", "unknown pattern kind"),
    (lambda d: d["pattern"].__setitem__("rows", "9"), "pattern.rows", "wrong type"),
    (lambda d: d.__setitem__("mirror_method", "mirror-magic"), "mirror_method", "must be one of"),
    (lambda d: d.__setitem__("board_thickness", -1), "board_thickness", ">= 0"),
    (lambda d: d.__setitem__("projector_blank_area", [320, 20]), "projector_blank_area", "must be an object"),
    (lambda d: d.__setitem__("projector_blank_area", {"width": 0, "gap": 20}), "projector_blank_area.width", "> 0"),
    (lambda d: d.__setitem__("projector_blank_area", {"width": 320}), "projector_blank_area.gap", ">= 0"),
    (lambda d: d.__setitem__("projector_blank_area", {"width": 320, "gap": True}), "projector_blank_area.gap", ">= 0"),
    (lambda d: d.__setitem__("format", "something-else"), "format", "procam-session"),
    (lambda d: d.__setitem__("version", 99), "version", "newer"),
    (lambda d: d.pop("captures"), "captures", "missing"),
])
def test_malformed_manifest_names_the_field(tmp_path, edit, field, problem):
    folder = _broken(tmp_path, edit)
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == field and problem in e.value.problem
    assert str(folder / MANIFEST) in str(e.value) and f"field '{field}'" in str(e.value)


def test_manifest_not_json_and_missing_session(tmp_path):
    folder = tmp_path / "s"
    folder.mkdir()
    with pytest.raises(SessionError, match="has no session.json"):
        SessionStore.open(folder)
    with pytest.raises(SessionError, match="does not exist"):
        SessionStore.open(tmp_path / "nowhere")
    (folder / MANIFEST).write_text('{"format": "procam-session", "version": 1,\n "rig": ')
    with pytest.raises(FormatError, match="not valid JSON") as e:
        SessionStore.open(folder)
    assert e.value.field == "<file>"


def test_crash_between_image_and_manifest_leaves_an_orphan_that_is_ignored(tmp_path, monkeypatch):
    folder = tmp_path / "s"
    store = SessionStore.create(folder, _manifest(captures=()))
    store.add_capture(STEP_PROJECTOR, _image(1), 0, PATTERN.points_px(1280, 720, 0))
    before = (folder / MANIFEST).read_text()

    def crash(*_args):
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(store, "_write_manifest", crash)
    with pytest.raises(KeyboardInterrupt):
        store.add_capture(STEP_PROJECTOR, _image(2), 1, PATTERN.points_px(1280, 720, 1))
    monkeypatch.undo()
    assert (folder / "images" / "p0001.png").exists()  # the image made it to disk, the manifest did not
    assert (folder / MANIFEST).read_text() == before
    reopened = SessionStore.open(folder)
    assert [c.id for c in reopened.manifest.captures] == ["p0000"]
    assert reopened.next_id(STEP_PROJECTOR) == "p0002"  # the orphan's name is not reused
    cap = reopened.add_capture(STEP_PROJECTOR, _image(3), 1, PATTERN.points_px(1280, 720, 1))
    assert cap.id == "p0002"
    assert np.array_equal(cv2.imread(str(folder / "images" / "p0001.png"), cv2.IMREAD_UNCHANGED), _image(2))


def test_crash_while_replacing_manifest_keeps_the_old_one(tmp_path, monkeypatch):
    import calib.formats.fileio as fileio

    folder = tmp_path / "s"
    store = SessionStore.create(folder, _manifest(captures=()))
    before = (folder / MANIFEST).read_text()

    def failing_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(fileio.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        store.update(state={"step": "mirror"})
    monkeypatch.undo()
    assert (folder / MANIFEST).read_text() == before
    # no temporary file left over (the lock file is there while the store is open)
    assert sorted(p.name for p in folder.iterdir()) == [".procam.lock", "images", MANIFEST]
    assert SessionStore.open(folder).manifest.state == _manifest().state


# ---- calibration.json and the YAML export -----------------------------------------------------------------
def _result() -> CalibrationResult:
    rig = make_rig(136.0)
    return CalibrationResult(
        camera=d455_camera(), projector=portable_projector(), T_cam_proj=rig.T_cam_proj, mirror=rig.mirror,
        units="mm", method="paper",
        rms={"camera": 0.21, "mirror": 0.05, "projector": 0.34, "stereo": None},
        per_view=({"capture_id": "p0000", "rms_px": np.float64(0.3), "n": np.int64(36)},),
        skipped=({"capture_id": "p0003", "image": "images/p0003.png", "reason": "board not found"},),
        uncertainty={"fx_px": 0.8, "t_cam_proj": np.array([0.5, 0.4, 1.1])},
        diagnostics={"mirror": {"inliers": 7, "plane_residual_mm": 0.12, "ok": np.bool_(True)}},
    )


def test_calibration_json_round_trip(tmp_path):
    res = _result()
    path = tmp_path / "calibration.json"
    res.save_json(path)
    raw = json.loads(path.read_text())
    for key in ("camera", "projector", "T_cam_proj", "mirror", "units", "rms", "per_view", "skipped"):
        assert key in raw
    assert raw["camera"]["K"] == res.camera.K.tolist() and len(raw["T_cam_proj"]) == 4
    assert raw["mirror"]["normal"] == pytest.approx(res.mirror.normal.tolist())
    back = CalibrationResult.load_json(path)
    assert back.to_dict() == json.loads(json.dumps(raw))
    assert np.array_equal(back.camera.K, res.camera.K) and np.array_equal(back.camera.dist, res.camera.dist)
    assert np.array_equal(back.projector.K, res.projector.K)
    assert np.array_equal(back.T_cam_proj, res.T_cam_proj)
    assert np.array_equal(back.mirror.normal, res.mirror.normal) and back.mirror.d == res.mirror.d
    assert back.units == "mm" and back.method == "paper" and back.rms["stereo"] is None
    assert back.skipped[0]["reason"] == "board not found" and back.per_view[0]["n"] == 36
    assert back.diagnostics["mirror"]["ok"] is True and back.uncertainty["t_cam_proj"] == [0.5, 0.4, 1.1]
    # saving what was loaded gives the same file
    path2 = tmp_path / "again.json"
    back.save_json(path2)
    assert path2.read_text() == path.read_text()
    # no mirror: null
    direct = res.with_(mirror=None)
    direct.save_json(path)
    assert json.loads(path.read_text())["mirror"] is None and CalibrationResult.load_json(path).mirror is None


@pytest.mark.parametrize("edit,field", [
    (lambda d: d.pop("T_cam_proj"), "T_cam_proj"),
    (lambda d: d.__setitem__("T_cam_proj", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "T_cam_proj"),
    (lambda d: d["T_cam_proj"][0].__setitem__(0, -1.0), "T_cam_proj"),
    (lambda d: d["camera"].pop("K"), "camera.K"),
    (lambda d: d["projector"].__setitem__("K", [[1, 2], [3, 4]]), "projector.K"),
    (lambda d: d["mirror"].__setitem__("normal", [0, 0, 2]), "mirror.normal"),
    (lambda d: d.__setitem__("mirror", {"n": [0, 0, 1]}), "mirror"),
    (lambda d: d.__setitem__("units", 3), "units"),
])
def test_malformed_calibration_json_names_the_field(tmp_path, edit, field):
    path = tmp_path / "calibration.json"
    _result().save_json(path)
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))
    with pytest.raises(FormatError) as e:
        CalibrationResult.load_json(path)
    assert e.value.field == field


def test_calibration_json_unreadable(tmp_path):
    with pytest.raises(FormatError, match="cannot be read"):
        CalibrationResult.load_json(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{ nope")
    with pytest.raises(FormatError, match="not valid JSON"):
        CalibrationResult.load_json(tmp_path / "bad.json")


def test_opencv_yaml_export_reads_back(tmp_path):
    res = _result()
    path = tmp_path / "calibration.yaml"
    opencv.write(res, [path])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    try:
        assert np.allclose(fs.getNode("camera_matrix").mat(), res.camera.K)
        assert np.allclose(fs.getNode("camera_distortion").mat().ravel(), res.camera.dist)
        assert np.allclose(fs.getNode("projector_matrix").mat(), res.projector.K)
        assert np.allclose(fs.getNode("projector_distortion").mat().ravel(), res.projector.dist)
        assert np.allclose(fs.getNode("T_cam_proj").mat(), res.T_cam_proj)
        assert np.allclose(fs.getNode("R_cam_proj").mat(), res.T_cam_proj[:3, :3])
        assert np.allclose(fs.getNode("t_cam_proj").mat().ravel(), res.T_cam_proj[:3, 3])
        assert np.allclose(fs.getNode("mirror_normal").mat().ravel(), res.mirror.normal)
        assert fs.getNode("mirror_d").real() == pytest.approx(res.mirror.d)
        assert int(fs.getNode("camera_width").real()) == res.camera.width
        assert int(fs.getNode("projector_height").real()) == res.projector.height
        assert fs.getNode("units").string() == "mm" and fs.getNode("method").string() == "paper"
        assert fs.getNode("rms_camera").real() == pytest.approx(0.21)
        assert fs.getNode("rms_stereo").empty()  # None is not written
    finally:
        fs.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.yaml"]  # written via a temporary file
    # without a mirror there are no mirror keys
    opencv.write(res.with_(mirror=None), [path])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.getNode("mirror_normal").empty() and fs.getNode("mirror_d").empty()
    fs.release()


def test_camera_model_dict_round_trip():
    for cam in (d455_camera(), CameraModel(640, 480, np.diag([500.0, 501.0, 1.0]) + [[0, 0, 319.5], [0, 0, 239.5],
                                                                                    [0, 0, 0]], np.zeros(8))):
        d = json.loads(json.dumps(cam.to_dict()))
        back = CameraModel.from_dict(d)
        assert back.size == cam.size and np.array_equal(back.K, cam.K) and np.array_equal(back.dist, cam.dist)
    with pytest.raises(FormatError) as e:
        CameraModel.from_dict({"width": 10, "height": 10, "K": np.eye(3).tolist(), "dist": [0.1, 0.2, 0.3]},
                              "camera")
    assert e.value.field.startswith("camera.dist")
    assert MirrorPlane([0, 0, -2.0], -100.0).to_dict() == {"normal": [0.0, 0.0, 1.0], "d": 50.0}


def test_capture_images_round_trip_losslessly(tmp_path):
    """Colour, gray-as-colour (stored with one channel), gray and 16-bit captures read back exactly."""
    store = SessionStore.create(tmp_path / "s", _manifest(captures=()))
    gray = _image(3)
    colour = np.dstack([_image(4), _image(5), _image(6)])
    gray_as_bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    deep = np.random.default_rng(7).integers(0, 65536, (80, 120), dtype=np.uint16)
    caps = [store.add_capture(STEP_REAL_VIRTUAL, im) for im in (colour, gray_as_bgr, gray, deep)]
    again = SessionStore.open(tmp_path / "s")
    assert np.array_equal(again.load_image(caps[0]), colour)
    assert np.array_equal(again.load_image(caps[1]), gray_as_bgr)
    assert np.array_equal(again.load_image(caps[1], cv2.IMREAD_GRAYSCALE), gray)
    assert np.array_equal(again.load_image(caps[2], cv2.IMREAD_UNCHANGED), gray)
    assert np.array_equal(again.load_image(caps[3], cv2.IMREAD_UNCHANGED), deep)
    # equal channels are stored once: the file holds one channel
    assert cv2.imread(str(again.image_path(caps[1])), cv2.IMREAD_UNCHANGED).ndim == 2
    assert cv2.imread(str(again.image_path(caps[0])), cv2.IMREAD_UNCHANGED).shape == colour.shape
