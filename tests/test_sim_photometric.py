"""Photometric realism of the simulator's renderer (issue 18, docs/SIMULATOR.md "Photometric realism"):
each effect changes the image as the physics says, and its neutral value switches it off."""

from dataclasses import replace

import numpy as np
import pytest

from calib.synthetic import projector_points_on_board
from calib.transforms import invert_T, transform_points
from drivers.sim.render import (
    PlacedBoard,
    Renderer,
    RenderSettings,
    SceneState,
    decode_gamma,
    defocus_sigma_px,
    encode_gamma,
)
from drivers.sim.scenarios import DEFAULT_SCENARIO, get_scenario

# linear, noise-free, float output: levels are exactly albedo x light x 255
CLEAN = RenderSettings(supersample=1, quantize=False, projector_falloff=False, ambient=0.0)


@pytest.fixture(scope="module")
def sc_direct():
    return get_scenario("direct")


def _renderer(sc, settings):
    r = sc.rig
    return Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, settings)


def _blank_pixels(sc, T, n=200):
    """Camera pixels (rounded) well inside the blank region of the board at T, seen directly."""
    x0, y0, x1, y1 = sc.layout.blank_rect
    g = np.stack(np.meshgrid(np.linspace(x0 + 40, x1 - 40, 20), np.linspace(y0 + 40, y1 - 40, 10)), -1).reshape(-1, 2)
    uv = sc.rig.camera.project(transform_points(T, np.column_stack([g, np.zeros(len(g))])))
    return np.round(uv).astype(int)[:n]


def _uniform(sc, level: float) -> np.ndarray:
    W, H = sc.rig.projector.size
    return np.full((H, W), level, np.float32)


def test_projector_gamma_gives_the_power_law_fraction_of_light(sc_direct):
    """A uniform projector image at level 0.5 sends 0.5^2.2 = 21.8% of full white's light."""
    T = sc_direct.verification_pose
    u = _blank_pixels(sc_direct, T)
    board = (PlacedBoard(sc_direct.layout, T),)
    for gamma in (1.0, 2.2):
        r = _renderer(sc_direct, replace(CLEAN, projector_gamma=gamma))
        half = r.render(SceneState(board, _uniform(sc_direct, 0.5)))[u[:, 1], u[:, 0]]
        full = r.render(SceneState(board, _uniform(sc_direct, 1.0)))[u[:, 1], u[:, 0]]
        assert full.min() > 50
        np.testing.assert_allclose(half / full, 0.5 ** gamma, rtol=1e-4)


def test_projector_black_level_lights_the_board_when_showing_black(sc_direct):
    T = sc_direct.verification_pose
    u = _blank_pixels(sc_direct, T)
    board = (PlacedBoard(sc_direct.layout, T),)
    r = _renderer(sc_direct, replace(CLEAN, ambient=0.3, projector_black_level=0.01))
    off = r.render(SceneState(board, None))[u[:, 1], u[:, 0]]  # projector switched off
    black = r.render(SceneState(board, _uniform(sc_direct, 0.0)))[u[:, 1], u[:, 0]]
    white = r.render(SceneState(board, _uniform(sc_direct, 1.0)))[u[:, 1], u[:, 0]]
    # black adds 1% of the full-white light on top of the ambient light
    np.testing.assert_allclose((black - off) / (white - off), 0.01, rtol=1e-4)
    r0 = _renderer(sc_direct, replace(CLEAN, ambient=0.3))
    assert np.array_equal(r0.render(SceneState(board, _uniform(sc_direct, 0.0))), r0.render(SceneState(board, None)))


def test_vignetting_darkens_the_farthest_corner_by_the_set_factor(sc_direct):
    """A flat, uniformly lit scene (no board, flat background): the farthest corner receives
    `vignetting_corner` of the light on the optical axis, the others a little more."""
    st = replace(CLEAN, background=False, vignetting_corner=0.6)
    img = _renderer(sc_direct, st).render(SceneState())
    flat = _renderer(sc_direct, replace(st, vignetting_corner=1.0)).render(SceneState())
    cam = sc_direct.rig.camera
    W, H = cam.size
    corners = np.array([img[0, 0], img[0, W - 1], img[H - 1, 0], img[H - 1, W - 1]]) / flat[0, 0]
    assert corners.min() == pytest.approx(0.6, abs=1e-4)
    assert np.all(corners < 0.75)
    cx, cy = int(round(cam.K[0, 2])), int(round(cam.K[1, 2]))
    assert img[cy, cx] / flat[cy, cx] == pytest.approx(1.0, abs=1e-3)
    # monotone from the axis outwards along the middle row
    row = img[cy, cx:] / flat[cy, cx:]
    assert np.all(np.diff(row) <= 1e-6)


def _edge_width(row: np.ndarray) -> float:
    """10-90% rise distance (px) of a monotone-ish edge profile, by linear interpolation."""
    lo, hi = np.percentile(row, 2), np.percentile(row, 98)
    f = (row - lo) / (hi - lo)
    if f[0] > f[-1]:
        f = f[::-1]

    def cross(level):
        i = int(np.argmax(f >= level))
        return i - 1 + (level - f[i - 1]) / (f[i] - f[i - 1])

    return cross(0.9) - cross(0.1)


def test_projector_defocus_is_sharp_at_the_focus_distance_and_grows_away_from_it(sc_direct):
    """A projected vertical edge (left half white) on a board at the focus distance is the pinhole's
    edge; at 0.7 x that distance it is wider by the thin-lens circle of confusion."""
    rig = sc_direct.rig
    T0 = sc_direct.verification_pose
    P = rig.T_cam_proj[:3, 3]
    W, H = rig.projector.size
    img = np.zeros((H, W), np.float32)
    img[:, : W // 2] = 1.0
    centre = np.array([[(W - 1) / 2, (H - 1) / 2]])
    T_pc = invert_T(rig.T_cam_proj)

    def at_scale(k):
        T = T0.copy()
        T[:3, 3] = P + k * (T0[:3, 3] - P)  # the board moved along rays from the projector
        Xc = transform_points(T, projector_points_on_board(rig, T, centre))
        return T, float(transform_points(T_pc, Xc)[0, 2])  # depth of the image centre along the axis

    _, focus = at_scale(1.0)
    aperture = 10.0
    st = replace(CLEAN, supersample=3, projector_aperture_mm=aperture, projector_focus_mm=focus)
    pin = replace(st, projector_aperture_mm=0.0)
    for k in (1.0, 0.7):
        T, depth = at_scale(k)
        state = SceneState((PlacedBoard(sc_direct.layout, T),), img)
        a = _renderer(sc_direct, st).render(state)
        b = _renderer(sc_direct, pin).render(state)
        # the edge in the camera: where the projector's centre pixel lands, along the row
        c = rig.camera.project(transform_points(T, projector_points_on_board(rig, T, centre)))[0]
        side = rig.camera.project(transform_points(T, projector_points_on_board(rig, T, centre + [10.0, 0.0])))[0]
        cam_per_proj = np.linalg.norm(side - c) / 10.0
        x, y = int(round(c[0])), int(round(c[1]))
        wa, wb = _edge_width(a[y, x - 25 : x + 26]), _edge_width(b[y, x - 25 : x + 26])
        if k == 1.0:  # the edge is at the focus distance (the tilted board's far parts are not)
            assert wa == pytest.approx(wb, abs=0.02)
            assert np.abs(a[y, x - 25 : x + 26] - b[y, x - 25 : x + 26]).max() < 0.01 * a[y].max()
            continue
        sigma_cam = float(defocus_sigma_px(depth, aperture, focus, rig.projector.fx)) * cam_per_proj
        assert sigma_cam > 0.5  # a visible defocus at this distance
        expected = np.sqrt(wb ** 2 + (2.563 * sigma_cam) ** 2)  # 10-90% of a Gaussian: 2.563 sigma
        assert wa == pytest.approx(expected, rel=0.2)
        assert wa > wb + 0.4


def test_camera_gamma_is_the_bt709_curve_and_invertible():
    """gamma 1/0.45 is BT.709's curve (linear 0.018 -> 0.081, 0.5 -> 0.7055, 1 -> 1); decode inverts."""
    L = np.array([0.0, 0.01, 0.018, 0.18, 0.5, 1.0], np.float32)
    V = encode_gamma(L, 1 / 0.45)
    # (BT.709's published 0.018 and 4.5 are rounded values of the joint this curve solves for exactly)
    np.testing.assert_allclose(V[[2, 4, 5]], [0.081, 1.099 * 0.5 ** 0.45 - 0.099, 1.0], atol=5e-4)
    assert V[1] == pytest.approx(0.045, abs=2e-4)  # the linear toe, slope 4.5
    np.testing.assert_allclose(decode_gamma(V, 1 / 0.45), L, atol=1e-6)
    assert np.all(np.diff(encode_gamma(np.linspace(0, 1, 1001, dtype=np.float32), 2.2)) > 0)


def test_camera_gamma_encodes_after_the_noise(sc_direct):
    """finish(): mid-grey linear light 0.18 -> level 255 x encode(0.18); noise is added before the
    curve, so it is amplified in the shadows (the curve is steeper there) and compressed in the lights."""
    st = replace(CLEAN, camera_gamma=2.2)
    r = _renderer(sc_direct, st)
    grey = np.full((200, 200), 0.18 * 255, np.float32)
    assert r.finish(grey, st)[0, 0] == pytest.approx(255 * float(encode_gamma(np.float32(0.18), 2.2)), abs=1e-3)
    noisy = replace(st, read_noise_dn=1.0)
    dark = r.finish(np.full((200, 200), 8.0, np.float32), noisy, np.random.default_rng(0))
    light = r.finish(np.full((200, 200), 200.0, np.float32), noisy, np.random.default_rng(0))
    slope = lambda L: (encode_gamma(np.float32((L + 0.5) / 255), 2.2) - encode_gamma(np.float32((L - 0.5) / 255), 2.2)) * 255  # noqa: E731
    assert dark.std() == pytest.approx(float(slope(8.0)), rel=0.05)
    assert light.std() == pytest.approx(float(slope(200.0)), rel=0.05)
    assert light.std() < 1.0 < dark.std()


def test_neutral_settings_switch_every_effect_off():
    """The default scenario's settings made neutral are the settings before issue 18, and render the
    same bytes (an effect left on would change them)."""
    sc = get_scenario(DEFAULT_SCENARIO)
    before = RenderSettings(blur_sigma_px=0.5, read_noise_dn=0.8, electrons_per_dn=40.0)
    assert sc.render.photometrically_neutral() == before
    pos, T = sc.projector_poses[3]
    img, _ = sc.pattern.render(*sc.rig.projector.size, pos)
    state = SceneState((PlacedBoard(sc.layout, T),), img)
    live = dict(supersample=1)
    a = _renderer(sc, replace(before, **live)).render(state, np.random.default_rng(5))
    b = _renderer(sc, replace(sc.render.photometrically_neutral(), **live)).render(state, np.random.default_rng(5))
    c = _renderer(sc, replace(sc.render, **live)).render(state, np.random.default_rng(5))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("name", ["nonoverlap-136", "direct", "wideangle-realmirror"])
def test_scenarios_render_with_realistic_photometry(name):
    """Gamma, black level, defocus (focused in the middle of the board distances) and vignetting on."""
    sc = get_scenario(name)
    st = sc.render
    assert st.projector_gamma == 2.2 and st.camera_gamma == 2.2
    assert 0 < st.projector_black_level < 0.01 and 0 < st.vignetting_corner < 1 and st.projector_aperture_mm > 0
    rig = sc.rig
    T_pc = invert_T(rig.T_cam_proj)
    depths = []
    for pos, T in sc.projector_poses:
        pts = sc.pattern.points_px(*rig.projector.size, pos)
        depths.append(transform_points(T_pc, transform_points(T, projector_points_on_board(rig, T, pts)))[:, 2])
    depths = np.concatenate(depths)
    assert depths.min() < st.projector_focus_mm < depths.max()
    assert st.projector_focus_mm == pytest.approx(np.median(depths), rel=0.1)
