"""procam export and calib.export: each exported model, loaded the way its target software loads it
(mrcal itself, three.js in Chromium; ROS, OpenGL and Unity re-implemented here from their documented
conventions), projects 3D points where the station's own model does."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from app.cli import main
from calib.models.result import CalibrationResult
from calib.synthetic import make_rig
from calib.transforms import invert_T, make_T, transform_points

TOL_PX = 0.01
MM_TO_M = 0.001
SYSTEM_PYTHON = "/usr/bin/python3"
THREE_VERSION = "0.187.0"


def _result(distorted: bool = True, skew: float = 0.0, rational: bool = False) -> CalibrationResult:
    """The simulated rig's ground truth (mm), optionally without distortion, with a skew, or with
    8 distortion coefficients."""
    gt = make_rig(136).ground_truth()
    cam, proj = gt.camera, gt.projector
    if not distorted:
        cam, proj = cam.with_params(dist=np.zeros(0)), proj.with_params(dist=np.zeros(0))
    if rational:
        proj = proj.with_params(dist=[0.021, -0.035, 0.0004, -0.0002, 0.004, 0.01, -0.006, 0.002])
    if skew:
        K = np.array(proj.K)
        K[0, 1] = skew
        proj = proj.with_params(K=K)
    return gt.with_(camera=cam, projector=proj)


def _device(result, name):
    return (result.camera, np.eye(4)) if name == "camera" else (result.projector, np.asarray(result.T_cam_proj))


def _points(result, name, n=(17, 11)):
    """Points in the camera frame (mm) seen all over device `name`'s image at 0.4, 0.9 and 2.5 m, and the
    station's pixels of them."""
    model, T_cam_dev = _device(result, name)
    u, v = np.meshgrid(np.linspace(0, model.width - 1, n[0]), np.linspace(0, model.height - 1, n[1]))
    rays = model.rays(np.column_stack([u.ravel(), v.ravel()]))
    depth = np.resize([400.0, 900.0, 2500.0], len(rays))
    X_cam = transform_points(T_cam_dev, rays / rays[:, 2:] * depth[:, None])
    return X_cam, model.project(transform_points(invert_T(T_cam_dev), X_cam))


def _export(tmp_path, result, fmt, *extra, name="calibration.json"):
    src = tmp_path / name
    result.save_json(src)
    rc = main(["export", str(src), "--format", fmt, "--out", str(tmp_path / "out"), *extra])
    assert rc == 0
    return tmp_path / "out"


def _max_px(a, b) -> float:
    return float(np.max(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1)))


def _gl_pixels(clip, width, height):
    """OpenCV pixels (centres at integers, row 0 at the top) of clip-space points drawn with
    glViewport(0, 0, W, H): window x = (ndc + 1) W / 2, window y counted from the bottom."""
    ndc = clip[:, :3] / clip[:, 3:]
    return np.column_stack([(ndc[:, 0] + 1) * width / 2 - 0.5, height - (ndc[:, 1] + 1) * height / 2 - 0.5])


# ---- ROS camera_info ----------------------------------------------------------------------------------
def _ros_raw_pixels(info, X):
    """image_geometry's raw pixel of points in the device's optical frame: plumb_bob (k1 k2 t1 t2 k3) or
    rational_polynomial (k1 k2 t1 t2 k3 k4 k5 k6) on x/z, y/z, then K."""
    K = np.array(info["camera_matrix"]["data"]).reshape(3, 3)
    D = list(info["distortion_coefficients"]["data"])
    assert {"plumb_bob": 5, "rational_polynomial": 8}[info["distortion_model"]] == len(D)
    k1, k2, t1, t2, k3, k4, k5, k6 = D + [0.0] * (8 - len(D))
    x, y = X[:, 0] / X[:, 2], X[:, 1] / X[:, 2]
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * t1 * x * y + t2 * (r2 + 2 * x * x)
    yd = y * radial + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
    return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def _ros_tf(text) -> np.ndarray:
    """T_camera_projector (metres) from the static_transform_publisher line the projector's file states."""
    m = re.search(r"static_transform_publisher ((?:\S+ ){7})camera projector", text)
    x, y, z, qx, qy, qz, qw = (float(v) for v in m.group(1).split())
    return make_T(Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), [x, y, z])


@pytest.mark.parametrize("rational", [False, True])
def test_ros_camera_info_projects_like_the_station(tmp_path, rational):
    result = _result(rational=rational)
    out = _export(tmp_path, result, "ros")
    tf = None
    for name in ("camera", "projector"):
        text = (out / f"calibration-{name}.ros.yaml").read_text()
        info = yaml.safe_load(text)
        model, _ = _device(result, name)
        assert (info["image_width"], info["image_height"], info["camera_name"]) == (model.width, model.height, name)
        assert info["distortion_model"] == ("rational_polynomial" if rational and name == "projector" else "plumb_bob")
        X_cam, station = _points(result, name)
        if name == "projector":
            tf = _ros_tf(text)
        T_dev_cam = np.eye(4) if tf is None else invert_T(tf)
        X_dev = transform_points(T_dev_cam, X_cam * MM_TO_M)
        assert _max_px(_ros_raw_pixels(info, X_dev), station) <= TOL_PX
        # the rectified image (R = I, P = [K | 0]) is the same device without distortion
        P = np.array(info["projection_matrix"]["data"]).reshape(3, 4)
        R = np.array(info["rectification_matrix"]["data"]).reshape(3, 3)
        h = np.hstack([X_dev @ R.T, np.ones((len(X_dev), 1))]) @ P.T
        ideal = model.with_params(dist=np.zeros(0)).project(X_dev)
        assert _max_px(h[:, :2] / h[:, 2:], ideal) <= TOL_PX


# ---- mrcal ---------------------------------------------------------------------------------------------
MRCAL_SCRIPT = """
import json, sys
import numpy as np
import mrcal
out = {}
for name, spec in json.load(sys.stdin).items():
    m = mrcal.cameramodel(spec["file"])
    p = mrcal.transform_point_rt(m.extrinsics_rt_fromref(), np.array(spec["points"]))
    out[name] = mrcal.project(p, *m.intrinsics()).tolist()
print(json.dumps(out))
"""


def _mrcal_project(files_points: dict) -> dict:
    """mrcal's own projection (Debian's python3-mrcal, in the system Python) of points in the reference frame."""
    probe = subprocess.run([SYSTEM_PYTHON, "-c", "import mrcal"], capture_output=True, env={"PATH": os.environ["PATH"]})
    if probe.returncode != 0:
        pytest.fail("Debian's python3-mrcal is not installed (apt-get install python3-mrcal; .ci/run installs it)")
    done = subprocess.run([SYSTEM_PYTHON, "-c", MRCAL_SCRIPT], input=json.dumps(files_points), capture_output=True,
                          text=True, env={"PATH": os.environ["PATH"]}, check=True)
    return json.loads(done.stdout)


@pytest.mark.parametrize("rational", [False, True])
def test_mrcal_cameramodel_projects_like_the_station(tmp_path, rational):
    result = _result(rational=rational)
    out = _export(tmp_path, result, "mrcal")
    request, station = {}, {}
    for name in ("camera", "projector"):
        X_cam, station[name] = _points(result, name)
        request[name] = {"file": str(out / f"calibration-{name}.cameramodel"), "points": X_cam.tolist()}
    got = _mrcal_project(request)
    for name in ("camera", "projector"):
        assert _max_px(got[name], station[name]) <= TOL_PX, name
    assert "LENSMODEL_OPENCV8" in (out / "calibration-projector.cameramodel").read_text() or not rational


def test_mrcal_states_the_skew_it_cannot_hold_and_its_residual(tmp_path, capsys):
    result = _result(skew=3.0)
    out = _export(tmp_path, result, "mrcal")
    text = (out / "calibration-projector.cameramodel").read_text()
    stated = float(re.search(r"mrcal cannot represent the skew; written without it, up to ([0-9.]+) px", text).group(1))
    assert "cannot represent" not in (out / "calibration-camera.cameramodel").read_text()
    assert f"up to {stated:.2f} px" in capsys.readouterr().err
    X_cam, station = _points(result, "projector", n=(65, 41))
    got = _mrcal_project({"projector": {"file": str(out / "calibration-projector.cameramodel"),
                                        "points": X_cam.tolist()}})
    measured = _max_px(got["projector"], station)
    assert stated > 1.0 and abs(measured - stated) <= 0.01  # rounded to 0.01 px in the file


# ---- OpenGL --------------------------------------------------------------------------------------------
def _gl_matrix(values) -> np.ndarray:
    return np.array(values, float).reshape(4, 4, order="F")  # column-major, as glUniformMatrix4fv takes it


def _opengl_pixels(dev, X_cam_mm):
    """OpenCV pixels of camera-frame points through the file's view and projection (world: the camera's
    frame in OpenGL axes, x right, y up, z back, metres)."""
    world = np.column_stack([X_cam_mm * MM_TO_M * [1, -1, -1], np.ones(len(X_cam_mm))])
    clip = world @ (_gl_matrix(dev["projection"]) @ _gl_matrix(dev["view"])).T
    return _gl_pixels(clip, dev["width"], dev["height"]), clip


def test_opengl_matrices_project_like_the_station(tmp_path):
    result = _result(distorted=False, skew=0.0)
    data = json.loads((_export(tmp_path, result, "opengl", "--near", "0.2", "--far", "7") / "calibration-opengl.json")
                      .read_text())
    for name in ("camera", "projector"):
        X_cam, station = _points(result, name)
        px, clip = _opengl_pixels(data[name], X_cam)
        assert _max_px(px, station) <= TOL_PX
        assert data[name]["distortion_residual_px"] == 0.0 and data[name]["warning"] is None
        depth = clip[:, 2] / clip[:, 3]
        assert np.all((depth > -1) & (depth < 1))  # 0.4 to 2.5 m lies between near and far
    # near and far map to the ends of the depth range
    _, T = _device(result, "projector")
    ends = transform_points(T, [[0, 0, 200.0], [0, 0, 7000.0]])
    _, clip = _opengl_pixels(data["projector"], ends)
    assert np.allclose(clip[:, 2] / clip[:, 3], [-1, 1])


def test_opengl_states_the_distortion_it_leaves_out(tmp_path, capsys):
    result = _result()
    data = json.loads((_export(tmp_path, result, "opengl") / "calibration-opengl.json").read_text())
    err = capsys.readouterr().err
    for name in ("camera", "projector"):
        stated = data[name]["distortion_residual_px"]
        assert f"warning: {name}: OpenGL cannot represent the lens distortion" in err
        assert f"up to {stated:.2f} px" in err and data[name]["warning"]
        X_cam, station = _points(result, name, n=(65, 41))
        measured = _max_px(_opengl_pixels(data[name], X_cam)[0], station)
        assert stated > 1.0 and measured <= stated + TOL_PX and measured >= 0.98 * stated


# ---- Unity ---------------------------------------------------------------------------------------------
def _unity_pixels(dev, X_cam_mm):
    """Unity's physical camera with gateFit None: projection from focal length, sensor size and lens shift
    (m00 = 2f/sx, m11 = 2f/sy, m02 = 2 shift x, m12 = 2 shift y); the transform's position and rotation in
    Unity's left-handed world (x right, y up, z forward); view space is the camera's local frame with z
    negated."""
    lens = dev["lens"]
    f, (sx, sy), (hx, hy) = lens["focalLength"], lens["sensorSize"], lens["lensShift"]
    n, fa = lens["nearClipPlane"], lens["farClipPlane"]
    P = np.array([[2 * f / sx, 0, 2 * hx, 0], [0, 2 * f / sy, 2 * hy, 0],
                  [0, 0, -(fa + n) / (fa - n), -2 * fa * n / (fa - n)], [0, 0, -1, 0]])
    world = X_cam_mm * MM_TO_M * [1, -1, 1]
    local = (world - dev["position"]) @ Rotation.from_quat(dev["quaternion"]).as_matrix()
    view = np.column_stack([local * [1, 1, -1], np.ones(len(local))])
    return _gl_pixels(view @ P.T, *lens["resolution"])


def test_unity_camera_projects_like_the_station(tmp_path):
    result = _result(distorted=False)
    data = json.loads((_export(tmp_path, result, "unity") / "calibration-unity.json").read_text())
    assert data["units"] == "m" and data["camera"]["position"] == [0, 0, 0]
    for name in ("camera", "projector"):
        X_cam, station = _points(result, name)
        assert _max_px(_unity_pixels(data[name], X_cam), station) <= TOL_PX
        assert data[name]["lens"]["gateFit"] == "None"


# ---- three.js in Chromium --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def three_build():
    """three.js's build folder, fetched from the npm registry once into a cache folder."""
    npm = shutil.which("npm")
    if npm is None:
        pytest.fail("npm is not installed (apt-get install npm; .ci/run installs it)")
    cache = Path(os.environ.get("PROCAM_TEST_CACHE", Path.home() / ".cache" / "procam-station-tests")) / "npm"
    build = cache / "node_modules" / "three" / "build"
    if not (build / "three.module.js").is_file():
        cache.mkdir(parents=True, exist_ok=True)
        done = subprocess.run([npm, "install", "--no-save", "--no-audit", "--no-fund", "--prefix", str(cache),
                               f"three@{THREE_VERSION}"], capture_output=True, text=True)
        if done.returncode != 0:
            pytest.fail(f"npm could not fetch three@{THREE_VERSION}: {done.stderr.strip()[-300:]}")
    return build


THREE_PROJECT = """(data) => {
  const out = {};
  for (const [name, dev] of Object.entries(data.devices)) {
    const L = dev.lens;
    const byFov = new THREE.PerspectiveCamera(L.fov, L.aspect, L.near, L.far);
    const byFocal = new THREE.PerspectiveCamera(50, L.aspect, L.near, L.far);
    byFocal.filmGauge = L.filmGauge;
    byFocal.setFocalLength(L.focalLength);
    for (const cam of [byFov, byFocal]) {
      cam.setViewOffset(L.view.fullWidth, L.view.fullHeight, L.view.offsetX, L.view.offsetY, L.view.width, L.view.height);
      cam.position.fromArray(dev.position);
      cam.quaternion.fromArray(dev.quaternion);
      cam.updateMatrixWorld(true);
    }
    out[name] = [byFov, byFocal].map(cam => data.points[name].map(p => new THREE.Vector3(...p).project(cam).toArray()));
  }
  return out;
}"""


@pytest.mark.browser
def test_threejs_camera_projects_like_the_station_in_chromium(tmp_path, three_build):
    from playwright.sync_api import sync_playwright

    from _station_helpers import launch_chromium

    result = _result(distorted=False)
    data = json.loads((_export(tmp_path, result, "threejs") / "calibration-threejs.json").read_text())
    points, station = {}, {}
    for name in ("camera", "projector"):
        X_cam, station[name] = _points(result, name)
        points[name] = (X_cam * MM_TO_M * [1, -1, -1]).tolist()  # three.js world: x right, y up, z back
    page_html = '<script type="module">import * as THREE from "./three.module.js"; window.THREE = THREE;</script>'

    def serve(route):
        name = route.request.url.rsplit("/", 1)[-1]
        if name == "index.html":
            return route.fulfill(body=page_html, content_type="text/html")
        return route.fulfill(path=str(three_build / name), content_type="text/javascript")

    with sync_playwright() as p:
        browser = launch_chromium(p)
        page = browser.new_page()
        page.route("http://three.test/**", serve)
        page.goto("http://three.test/index.html")
        page.wait_for_function("window.THREE !== undefined")
        got = page.evaluate(THREE_PROJECT, {"devices": {n: data[n] for n in points}, "points": points})
        browser.close()
    for name in ("camera", "projector"):
        model, _ = _device(result, name)
        for ndc in got[name]:
            ndc = np.array(ndc)
            px = np.column_stack([(ndc[:, 0] + 1) * model.width / 2 - 0.5, (1 - ndc[:, 1]) * model.height / 2 - 0.5])
            assert _max_px(px, station[name]) <= TOL_PX, name


# ---- bad input -------------------------------------------------------------------------------------------
def _run_export(tmp_path, source, fmt="all", capsys=None):
    rc = main(["export", str(source), "--format", fmt, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err if capsys else ""
    return rc, err


def test_a_rejected_calibration_is_not_exported(tmp_path, capsys):
    result = _result()
    bad = result.projector.with_params(K=np.diag([-50.0, 2300.0, 1.0]) + [[0, 0, 960], [0, 0, 540], [0, 0, 0]])
    result.with_(projector=bad).save_json(tmp_path / "calibration.json")
    rc, err = _run_export(tmp_path, tmp_path / "calibration.json", capsys=capsys)
    assert rc == 2 and "the trust check rejects this calibration ([focal_nonpositive]" in err
    assert "nothing was written" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_a_calibration_written_with_accept_untrusted_is_not_exported(tmp_path, capsys):
    trust = {"passed": False, "reasons": [{"code": "rms_high", "message": "residuals of 9 px"}]}
    _result().with_(diagnostics={"trust": trust}).save_json(tmp_path / "calibration.json")
    rc, err = _run_export(tmp_path, tmp_path / "calibration.json", "ros", capsys)
    assert rc == 2 and "[rms_high] residuals of 9 px" in err and not (tmp_path / "out").exists()


def test_a_missing_calibration_is_named(tmp_path, capsys):
    (tmp_path / "session").mkdir()
    rc, err = _run_export(tmp_path, tmp_path / "session", capsys=capsys)
    assert rc == 2 and "no calibration.json in" in err and "procam calibrate" in err
    rc, err = _run_export(tmp_path, tmp_path / "nothing.json", capsys=capsys)
    assert rc == 2 and "nothing.json does not exist" in err
    (tmp_path / "broken.json").write_text('{"camera": 1')
    rc, err = _run_export(tmp_path, tmp_path / "broken.json", capsys=capsys)
    assert rc == 2 and "broken.json: field '<file>': is not valid JSON" in err
    assert not (tmp_path / "out").exists()


def test_an_unknown_format_lists_the_formats(tmp_path, capsys):
    _result().save_json(tmp_path / "calibration.json")
    rc, err = _run_export(tmp_path, tmp_path / "calibration.json", "ros,collada", capsys)
    assert rc == 2 and "unknown export format 'collada'" in err
    assert "opencv, ros, mrcal, opengl, unity, threejs" in err and not (tmp_path / "out").exists()


def test_a_session_folder_exports_its_calibration_with_every_format(tmp_path, capsys):
    session = tmp_path / "session"
    session.mkdir()
    _result().save_json(session / "calibration-paper.json")
    _result().save_json(session / "calibration.json")
    rc, err = _run_export(tmp_path, session, capsys=capsys)
    assert rc == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted([
        "calibration.yaml", "calibration-camera.ros.yaml", "calibration-projector.ros.yaml",
        "calibration-camera.cameramodel", "calibration-projector.cameramodel", "calibration-opengl.json",
        "calibration-unity.json", "calibration-threejs.json"])


@pytest.mark.parametrize("extra, message", [
    (["--near", "5", "--far", "1"], "--far (1 m) must be beyond --near (5 m)"),
    (["--near", "nan"], "--near must be a positive number of metres, got nan"),
    (["--far", "-3"], "--far must be a positive number of metres, got -3.0"),
])
def test_bad_clipping_planes_are_named(tmp_path, capsys, extra, message):
    _result().save_json(tmp_path / "calibration.json")
    rc = main(["export", str(tmp_path / "calibration.json"), "--format", "opengl", "--out", str(tmp_path / "out"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_an_out_that_is_a_file_is_refused(tmp_path, capsys):
    _result().save_json(tmp_path / "calibration.json")
    rc = main(["export", str(tmp_path / "calibration.json"), "--format", "ros", "--out", str(tmp_path / "calibration.json")])
    assert rc == 2 and "is a file; give a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]
