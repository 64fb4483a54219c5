"""The simulator's renderer against analytic projections (docs/GEOMETRY.md), with noise and blur off."""

import numpy as np
import pytest

from _sim_helpers import blob_centroids, imaged_board_disc_centroid, imaged_circle_centroids
from calib.detection.detect import detect_board, detect_pattern, detect_real_mirror, detect_real_virtual
from calib.models.camera import CameraModel
from calib.models.pattern import PatternSpec
from calib.synthetic import BoardLayout, projector_points_on_board
from calib.transforms import make_T, rotation_about, transform_points
from drivers.sim.render import Mark, PlacedBoard, Renderer, RenderSettings, SceneState, layout_for
from drivers.sim.scenarios import get_scenario

EXACT = RenderSettings(supersample=3, quantize=False, projector_falloff=False)


def _renderer(sc, settings=EXACT):
    r = sc.rig
    return Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, settings)


def _nearest(points):
    return min(np.linalg.norm(points[i] - np.delete(points, i, 0), axis=1).min() for i in range(len(points)))


@pytest.fixture(scope="module")
def sc136():
    return get_scenario("nonoverlap-136")


@pytest.fixture(scope="module")
def sc_direct():
    return get_scenario("direct")


# ---- pixel-centre convention -------------------------------------------------------------------------
@pytest.mark.parametrize("supersample", [1, 2, 3, 4])
def test_pixel_centre_convention(supersample):
    """A dot whose centre projects to pixel (100, 80) is imaged centred on (100, 80), whatever the
    supersampling (an off-by-half-a-sample grid would move it), and one at (300.25, 200.5) likewise."""
    cam = CameraModel(640, 480, [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], [])
    sc = get_scenario("direct")
    layout = BoardLayout(sc.projector_board)
    t = np.array([-450.0, -350.0, 1000.0])
    T = make_T(np.eye(3), t)
    # board points at the wanted pixels (frontal board, no distortion: X = (u - c) z / f, board = X - t)
    targets = np.array([[100.0, 80.0], [300.25, 200.5]])
    xy = (targets - [319.5, 239.5]) * 1000.0 / 500.0 - t[:2]
    marks = tuple(Mark(x, y, 3.0, 1.0) for x, y in xy)
    blank = tuple(Mark(x, y, 8.0, 0.0) for x, y in xy)  # a dark surround, so the dot is all that differs
    r = Renderer(cam, sc.rig.projector, sc.rig.T_cam_proj, None, None,
                 RenderSettings(supersample=supersample, quantize=False, background=False))
    on = r.render(SceneState((PlacedBoard(layout, T, blank + marks),)))
    off = r.render(SceneState((PlacedBoard(layout, T, blank),)))
    found = blob_centroids(on - off, targets, 6.0)
    # a convention error would be a quarter or half of a pixel; texture and disc rasterisation leave ~0.01
    assert np.abs(found - targets).max() < 0.02


# ---- mirror geometry: a dot on the board is seen at project(S X) --------------------------------------
def test_reflected_dot_lands_where_geometry_predicts(sc136):
    rig = sc136.rig
    pos, T = sc136.projector_poses[10]
    x0, y0, x1, y1 = sc136.layout.blank_rect
    dots = np.array([[x0 + 60, y0 + 60], [(x0 + x1) / 2, (y0 + y1) / 2], [x1 - 50, y1 - 70]])
    base = tuple(Mark(x, y, 12.0, 0.0) for x, y in dots)
    marks = base + tuple(Mark(x, y, 4.0, 1.0) for x, y in dots)
    r = _renderer(sc136)
    on = r.render(SceneState((PlacedBoard(sc136.layout, T, marks),)))
    off = r.render(SceneState((PlacedBoard(sc136.layout, T, base),)))
    X = transform_points(T, np.column_stack([dots, np.zeros(3)]))
    predicted = rig.camera.project(transform_points(rig.S(), X))  # docs/GEOMETRY.md: u = project(S X)
    assert np.all(rig.camera.in_image(predicted))
    # the board is outside the direct view: only its reflection is imaged
    assert not np.any(rig.camera.in_image(rig.camera.project(X)))
    found = blob_centroids(on - off, predicted, 5.0)
    exact = np.array([imaged_board_disc_centroid(rig, rig.S() @ T, d, 4.0) for d in dots])
    assert np.abs(found - exact).max() < 0.01
    assert np.abs(found - predicted).max() < 0.02
    # with a flat mirror where there is none, the dot would be elsewhere: the test can fail
    assert np.abs(found - rig.camera.flip_points(predicted)).max() > 5


def test_real_virtual_board_seen_twice_and_occludes_the_mirror(sc136):
    """Real-virtual: the board between camera and mirror appears directly and reflected; a dot on it is
    seen at project(X) and at project(S X)."""
    rig = sc136.rig
    layout = layout_for(sc136.mirror_board)
    T = sc136.mirror_poses[0]
    dot = np.array([sc136.mirror_board.size[0] / 2 + 0.0, sc136.mirror_board.size[1] / 2 + 11.0])
    base = (Mark(dot[0], dot[1], 5.0, 0.0),)
    marks = base + (Mark(dot[0], dot[1], 2.0, 1.0),)
    r = _renderer(sc136)
    on = r.render(SceneState((PlacedBoard(layout, T, marks),)))
    off = r.render(SceneState((PlacedBoard(layout, T, base),)))
    X = transform_points(T, np.array([[dot[0], dot[1], 0.0]]))
    direct = rig.camera.project(X)[0]
    mirrored = rig.camera.project(transform_points(rig.S(), X))[0]
    depth = np.array([X[0, 2], transform_points(rig.S(), X)[0, 2]])
    found = np.array([blob_centroids(on - off, u[None], rig.camera.fx * 3.5 / z)[0]
                      for u, z in zip((direct, mirrored), depth)])
    exact = [imaged_board_disc_centroid(rig, TT, dot, 2.0) for TT in (T, rig.S() @ T)]
    assert np.abs(found[0] - exact[0]).max() < 0.02
    assert np.abs(found[1] - exact[1]).max() < 0.02
    assert np.abs(found[1] - mirrored).max() < 0.03
    # where the real board stands in front of the mirror, the camera sees the board, not the mirror
    dark = r.render(SceneState((PlacedBoard(layout, T, (Mark(dot[0], dot[1], 5.0, 0.0),)),)))
    empty = r.render(SceneState(()))
    u = np.round(direct).astype(int)
    assert dark[u[1], u[0]] < 0.2 * empty[u[1], u[0]]


# ---- the projected pattern ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["nonoverlap-136", "direct", "nonoverlap-136-720p"])
def test_pattern_blobs_are_imaged_at_the_exact_circle_centroids(name):
    """The centroid of each imaged projected circle equals the area centroid of the circle's exact
    image (boundary mapped through projector, board, mirror and camera distortion)."""
    sc = get_scenario(name)
    rig = sc.rig
    r = _renderer(sc)
    errs = []
    for pos, T in sc.projector_poses[3::17]:
        img, pts = sc.pattern.render(*rig.projector.size, pos)
        b = PlacedBoard(sc.layout, T)
        lit = r.render(SceneState((b,), img)) - r.render(SceneState((b,), None))
        exact = imaged_circle_centroids(rig, T, pts, sc.pattern.radius_px)
        errs.append(np.linalg.norm(blob_centroids(lit, exact, 0.55 * _nearest(exact)) - exact, axis=1))
    errs = np.concatenate(errs)
    assert errs.mean() < 0.012 and errs.max() < 0.035


def test_circle_centroid_bias_is_rendered(sc_direct):
    """Big circles on a tilted board: the imaged blob's centroid follows the exact imaged circle, not
    the projection of the circle's centre (docs/GEOMETRY.md: conic centres are not preserved)."""
    sc, rig = sc_direct, sc_direct.rig
    pattern = PatternSpec("circles", 3, 3, 90.0, 36.0, 13)
    r = _renderer(sc)
    T0 = sc.verification_pose
    c = transform_points(T0, sc.layout.blank_centre[None])[0]
    R = rotation_about(T0[:3, 1], 40.0) @ T0[:3, :3]
    T = make_T(R, c - R @ sc.layout.blank_centre)
    img, pts = pattern.render(*rig.projector.size, 4)
    b = PlacedBoard(sc.layout, T)
    lit = r.render(SceneState((b,), img)) - r.render(SceneState((b,), None))
    exact = imaged_circle_centroids(rig, T, pts, pattern.radius_px)
    centre_proj = rig.camera.project(transform_points(T, projector_points_on_board(rig, T, pts)))
    found = blob_centroids(lit, exact, 0.55 * _nearest(exact))
    err = np.linalg.norm(found - exact, axis=1)
    bias = np.linalg.norm(centre_proj - found, axis=1)
    assert err.max() < 0.01
    assert bias.mean() > 0.03 and bias.mean() > 5 * err.mean()


def test_pattern_detection_matches_ground_truth(sc136):
    """calib.detection.detect finds the projected circles (in a mirrored view) where the exact geometry puts them."""
    rig = sc136.rig
    r = _renderer(sc136, RenderSettings(supersample=3))
    errs = []
    for pos, T in sc136.projector_poses[1::13]:
        img, pts = sc136.pattern.render(*rig.projector.size, pos)
        frame = r.render(SceneState((PlacedBoard(sc136.layout, T),), img))
        board = detect_board(frame, sc136.projector_board, True)
        found = detect_pattern(frame, sc136.pattern, True, board, sc136.projector_board)
        assert isinstance(found, np.ndarray), found
        errs.append(np.linalg.norm(found - imaged_circle_centroids(rig, T, pts, sc136.pattern.radius_px), axis=1))
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.05 and errs.max() < 0.2


def test_projected_chessboard_corners():
    sc = get_scenario("nonoverlap-136-chessboard")
    rig = sc.rig
    r = _renderer(sc, RenderSettings(supersample=3, blur_sigma_px=0.5))
    errs = []
    for pos, T in sc.projector_poses[0::17]:
        img, pts = sc.pattern.render(*rig.projector.size, pos)
        frame = r.render(SceneState((PlacedBoard(sc.layout, T),), img))
        board = detect_board(frame, sc.projector_board, True)
        found = detect_pattern(frame, sc.pattern, True, board, sc.projector_board)
        assert isinstance(found, np.ndarray), found
        Xb = projector_points_on_board(rig, T, pts)
        errs.append(np.linalg.norm(found - rig.camera.project(transform_points(rig.S() @ T, Xb)), axis=1))
    errs = np.concatenate(errs)
    # (a rare detector outlier of ~2 px at one inner corner is the grid finder's, not the image's)
    assert np.median(errs) < 0.07 and np.percentile(errs, 90) < 0.15


# ---- ChArUco corners -----------------------------------------------------------------------------------
@pytest.mark.parametrize("name,quality", [("direct", 3), ("nonoverlap-136", 3), ("nonoverlap-136", 1)])
def test_charuco_corners_detected_at_ground_truth(name, quality):
    sc = get_scenario(name)
    rig = sc.rig
    r = _renderer(sc, RenderSettings(supersample=quality))
    errs = []
    for pos, T in sc.projector_poses[2::13]:
        frame = r.render(SceneState((PlacedBoard(sc.layout, T),)))
        obs = detect_board(frame, sc.projector_board, rig.mirror is not None)
        assert obs, obs
        assert len(obs.ids) >= 30
        expected = rig.camera.project(transform_points(rig.S() @ T, sc.projector_board.corner_points()))[obs.ids]
        errs.append(np.linalg.norm(obs.corners_px - expected, axis=1))
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.06 and errs.mean() < 0.07 and np.percentile(errs, 95) < 0.15


def test_mirror_calibration_scenes_detect_at_ground_truth(sc136):
    rig = sc136.rig
    spec = sc136.mirror_board
    r = _renderer(sc136, RenderSettings(supersample=3))
    real, virt = [], []
    for T in sc136.mirror_poses[:4]:
        mv = detect_real_virtual(r.render(SceneState((PlacedBoard(layout_for(spec), T),))), spec)
        assert mv, mv
        X = transform_points(T, spec.corner_points())
        real.append(np.linalg.norm(mv.real.corners_px - rig.camera.project(X)[mv.real.ids], axis=1))
        virt.append(np.linalg.norm(mv.virtual.corners_px - rig.camera.project(transform_points(rig.S(), X))[mv.virtual.ids], axis=1))
    real, virt = np.concatenate(real), np.concatenate(virt)
    assert np.median(real) < 0.05 and np.median(virt) < 0.06
    assert np.percentile(real, 90) < 0.15 and np.percentile(virt, 90) < 0.15
    # real-mirror: the board lies on the mirror, printed face `thickness` above it
    sc = get_scenario("nonoverlap-136-realmirror")
    T = sc.mirror_poses[0]
    assert sc.rig.mirror.signed_distance(transform_points(T, spec.corner_points())) == pytest.approx(3.0)
    mv = detect_real_mirror(_renderer(sc, RenderSettings(supersample=3)).render(
        SceneState((PlacedBoard(layout_for(spec), T),))), spec)
    assert mv and len(mv.real.ids) == spec.n_corners
    err = np.linalg.norm(mv.real.corners_px - sc.rig.camera.project(transform_points(T, spec.corner_points())), axis=1)
    assert np.median(err) < 0.05


# ---- image formation switches ----------------------------------------------------------------------------
def test_noise_blur_quantisation_are_configurable(sc136):
    rig = sc136.rig
    pos, T = sc136.projector_poses[0]
    img, _ = sc136.pattern.render(*rig.projector.size, pos)
    state = SceneState((PlacedBoard(sc136.layout, T),), img)
    clean = _renderer(sc136, RenderSettings(supersample=1, quantize=False))
    a = clean.render(state, np.random.default_rng(1))
    b = clean.render(state, np.random.default_rng(2))
    assert a.dtype == np.float32 and a.ndim == 2 and np.array_equal(a, b)  # no noise: deterministic
    noisy = _renderer(sc136, RenderSettings(supersample=1, quantize=False, read_noise_dn=2.0))
    d = noisy.render(state, np.random.default_rng(1)) - a
    assert d.std() == pytest.approx(2.0, rel=0.05)
    shot = _renderer(sc136, RenderSettings(supersample=1, quantize=False, electrons_per_dn=10.0))
    d = shot.render(state, np.random.default_rng(1)) - a
    bright = a > 150
    assert d[bright].std() == pytest.approx(np.sqrt(a[bright] / 10.0).mean(), rel=0.1)
    assert d[a < 60].std() < 0.8 * d[bright].std()
    blurred = _renderer(sc136, RenderSettings(supersample=1, quantize=False, blur_sigma_px=1.5)).render(state)
    assert np.abs(np.diff(blurred, axis=1)).max() < 0.6 * np.abs(np.diff(a, axis=1)).max()
    q = _renderer(sc136, RenderSettings(supersample=1)).render(state)
    assert q.dtype == np.uint8 and q.shape == (800, 1280, 3)
    assert np.abs(q[:, :, 0].astype(float) - a).max() <= 0.5 + 1e-3


def test_projector_lights_only_where_its_image_is_bright(sc136):
    rig = sc136.rig
    pos, T = sc136.projector_poses[5]
    img, pts = sc136.pattern.render(*rig.projector.size, pos)
    r = _renderer(sc136, RenderSettings(supersample=1, quantize=False, projector_falloff=False))
    b = PlacedBoard(sc136.layout, T)
    lit = r.render(SceneState((b,), img)) - r.render(SceneState((b,), None))
    st = r.settings
    centres = rig.camera.project(transform_points(rig.S() @ T, projector_points_on_board(rig, T, pts)))
    u = np.round(centres).astype(int)
    peak = lit[u[:, 1], u[:, 0]]
    full = 255 * st.white_albedo * st.projector_gain * st.mirror_reflectance
    assert np.all(peak > 0.6 * full) and np.all(peak < 1.001 * full)
    assert lit.sum() == pytest.approx(np.sort(lit.ravel())[-len(pts) * 200:].sum(), rel=0.05)
