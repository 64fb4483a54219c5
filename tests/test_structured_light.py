"""The structured-light projector step: the sequence, its per-pixel decoding against the renderer's exact
projector coordinates, the validity rules, and the local homographies' projector points and uncertainty."""

from dataclasses import replace
from types import MappingProxyType

import cv2
import numpy as np
import pytest

from calib.detection.local_homography import fit_local_homographies
from calib.detection.response import CameraResponse
from calib.detection.structured_light import DecodedMap, Invalid, decode_sequence
from calib.detection.structured_view import BoardPoints, detect_structured_view
from calib.errors import FormatError, SpecError
from calib.models.observations import DetectionFailure
from calib.models.structured_light import Axis, FrameRole, StructuredLightSpec, gray_decode, gray_encode
from calib.transforms import invert_T, rays_to_board_plane
from drivers.projector_images import structured_light_images
from drivers.sim.render import Renderer
from drivers.sim.scenarios import get_scenario
from drivers.sim.structured import render_sequence, true_projector_px

SPEC = StructuredLightSpec()  # 32 px period, 8 phase steps
GRAY_ONLY = StructuredLightSpec(phase_steps=0)
RESPONSE = CameraResponse("bt709", 2.2)  # the simulated camera's tone curve (drivers.sim.scenarios)


# ---- the sequence ------------------------------------------------------------------------------------
def test_gray_code_round_trip_and_one_bit_steps():
    n = np.arange(5000)
    g = gray_encode(n)
    assert np.array_equal(gray_decode(g), n)
    flips = g[1:] ^ g[:-1]
    assert np.all((flips & (flips - 1)) == 0) and np.all(flips > 0)  # neighbours differ in one bit


@pytest.mark.parametrize("spec", [SPEC, GRAY_ONLY, StructuredLightSpec(16, 4)], ids=str)
def test_the_projectors_own_images_decode_to_their_pixels(spec):
    """A camera that sees the projector's image pixel for pixel (no blur, no light but the projector's)
    decodes every pixel to its own column and row: to rounding of the 8-bit sinusoids with phase
    shifting, exactly without."""
    W, H = 640, 360
    frames = spec.frames(W, H)
    assert frames[0].role is FrameRole.WHITE and frames[1].role is FrameRole.BLACK
    assert frames[-1] == type(frames[0])(FrameRole.WHITE, None, 1)  # the closing white (the motion check)
    n_gray = sum(f.role is FrameRole.GRAY for f in frames)
    assert n_gray == spec.n_bits(W) + spec.n_bits(H)
    assert sum(f.role is FrameRole.PHASE for f in frames) == 2 * spec.phase_steps
    # projector levels of 255 are saturated for the decoder: show them at 0.9 of the range
    imgs = [(im.astype(np.float32) * 0.9).round().astype(np.uint8) for im in structured_light_images(spec, (W, H))]
    d = decode_sequence(imgs, spec, (W, H))
    assert not any(a.flags.writeable for a in (d.proj_x, d.proj_y, d.reason, d.lit, d.modulation))
    yy, xx = np.mgrid[0:H, 0:W]
    tol = 0.05 if spec.phase_shifting else 0.0
    if spec.phase_shifting:
        assert d.valid.mean() > 0.999
        assert np.nanmax(np.abs(d.proj_x - xx)) <= tol and np.nanmax(np.abs(d.proj_y - yy)) <= tol
    else:  # 1-px stripes: the stripe's centre is the pixel itself
        assert d.valid.all()
        assert np.array_equal(d.proj_x, xx.astype(np.float32)) and np.array_equal(d.proj_y, yy.astype(np.float32))


def test_spec_refuses_bad_values_and_round_trips():
    for bad in ({"period_px": 31}, {"period_px": 4}, {"phase_steps": 2}, {"phase_steps": 1.5}, {"period_px": True}):
        with pytest.raises(SpecError):
            StructuredLightSpec(**bad)
    assert StructuredLightSpec.from_dict(SPEC.to_dict()) == SPEC
    with pytest.raises(FormatError, match="phase_steps"):
        StructuredLightSpec.from_dict({"period_px": 32})
    with pytest.raises(FormatError):
        StructuredLightSpec.from_dict({"period_px": 32, "phase_steps": 2})


def test_decoding_refuses_a_sequence_of_the_wrong_length():
    imgs = SPEC.images(320, 200)
    with pytest.raises(SpecError, match="frames"):
        decode_sequence(imgs[:-1], SPEC, (320, 200))
    with pytest.raises(SpecError, match="8-bit"):
        decode_sequence([im.astype(np.float32) for im in imgs], SPEC, (320, 200))


# ---- rendered sequences ------------------------------------------------------------------------------
def _renderer(sc, **overrides):
    r = sc.rig
    st = replace(sc.render, supersample=1, **overrides)
    return Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, st)


class _Capture:
    def __init__(self, name, pose_index, spec=SPEC, **overrides):
        self.sc = get_scenario(name)
        self.R = _renderer(self.sc, **overrides)
        self.T = self.sc.projector_poses[pose_index][1]
        self.spec = spec
        self.images = render_sequence(self.R, self.sc.layout, self.T, spec, np.random.default_rng(7))
        P = self.sc.rig.projector
        self.proj_size = (P.width, P.height)
        self.mirrored = self.sc.rig.mirror is not None

    def decode(self, **kw):
        return decode_sequence(self.images, self.spec, self.proj_size, response=RESPONSE, **kw)

    def board_xy(self, uv):
        """Board coordinates of the points seen at camera pixels uv."""
        T_view = self.T if self.R.mirror is None else self.R.mirror.reflection() @ self.T
        return rays_to_board_plane(invert_T(T_view), self.R.camera.rays(uv))[0][:, :2]


@pytest.fixture(scope="module")
def mirrored():
    return _Capture("nonoverlap-136", 0)


@pytest.fixture(scope="module")
def direct():
    return _Capture("direct", 5)


def _decode_errors(cap, d):
    ys, xs = np.nonzero(d.valid)
    q = true_projector_px(cap.R, cap.sc.layout, cap.T, np.column_stack([xs, ys]).astype(float))
    return np.hypot(d.proj_x[ys, xs] - q[:, 0], d.proj_y[ys, xs] - q[:, 1])


@pytest.mark.parametrize("which", ["mirrored", "direct"])
def test_decoded_coordinates_match_the_renderers_projector_pixels(which, request):
    cap = request.getfixturevalue(which)
    d = cap.decode()
    e = _decode_errors(cap, d)
    assert len(e) > 20000  # the board's white areas decode
    assert np.all(np.isfinite(e))
    print(f"{which}: {len(e)} pixels, error median {np.median(e):.3f} p99 {np.percentile(e, 99):.3f} px")
    assert np.median(e) < 0.3 and np.percentile(e, 99) < 1.0


def test_phase_shifting_is_finer_than_the_gray_code_alone(mirrored):
    gray = _Capture("nonoverlap-136", 0, GRAY_ONLY)
    e_phase = np.median(_decode_errors(mirrored, mirrored.decode()))
    e_gray = np.median(_decode_errors(gray, gray.decode()))
    assert e_phase < 0.3 * e_gray


def _printed_black(cap, uv, margin):
    """Which camera pixels see the ChArUco print's black, at least `margin` (board units) from white."""
    spec = cap.sc.projector_board
    s = 4.0  # texels per unit
    img = spec.render(s)
    k = int(2 * margin * s) + 1
    deep_black = cv2.dilate(img, np.ones((k, k), np.uint8)) == 0
    xy = cap.board_xy(uv)
    j = np.floor(xy[:, 0] * s).astype(int)
    i = np.floor(xy[:, 1] * s).astype(int)
    inside = (i >= 0) & (j >= 0) & (i < img.shape[0]) & (j < img.shape[1])
    out = np.zeros(len(uv), bool)
    out[inside] = deep_black[i[inside], j[inside]]
    return out


def test_black_squares_are_masked_and_the_blank_area_decodes(mirrored):
    d = mirrored.decode()
    H, W = d.shape
    yy, xx = np.mgrid[0:H, 0:W]
    uv = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    lit = np.isfinite(true_projector_px(mirrored.R, mirrored.sc.layout, mirrored.T, uv)).all(axis=1)
    lit &= (mirrored.R.projector.in_image(true_projector_px(mirrored.R, mirrored.sc.layout, mirrored.T, uv),
                                          margin_px=20))
    black = _printed_black(mirrored, uv, 4.0) & lit
    reason = d.reason.ravel()
    assert black.sum() > 2000
    assert np.mean(reason[black] != Invalid.VALID) > 0.999
    # mostly named as the print's black (the darkest black squares of a dim corner stay below the
    # projector's contrast: UNLIT; their rims: EDGE)
    assert np.mean(reason[black] == Invalid.DARK_PRINT) > 0.4
    assert np.all(np.isin(reason[black], [Invalid.DARK_PRINT, Invalid.UNLIT, Invalid.EDGE, Invalid.VALID]))
    x0, y0, x1, y1 = mirrored.sc.layout.blank_rect
    xy = mirrored.board_xy(uv)
    blank = lit & (xy[:, 0] > x0 + 10) & (xy[:, 0] < x1 - 10) & (xy[:, 1] > y0 + 10) & (xy[:, 1] < y1 - 10)
    assert blank.sum() > 5000
    assert np.mean(reason[blank] == Invalid.VALID) > 0.99
    # away from the board nothing is lit: the background is UNLIT, never decoded
    off = ~np.isfinite(true_projector_px(mirrored.R, mirrored.sc.layout, mirrored.T, uv)).all(axis=1)
    assert np.mean(reason[off] == Invalid.VALID) < 1e-3


def test_a_dim_projector_is_unlit_and_a_bright_one_saturates():
    dim = _Capture("nonoverlap-136", 0, projector_gain=0.01)
    d = dim.decode()
    assert d.counts["valid"] == 0 and d.counts["unlit"] > 0.99 * d.reason.size
    sv = detect_structured_view(dim.images, SPEC, dim.sc.projector_board, dim.proj_size, dim.mirrored)
    assert isinstance(sv, DetectionFailure) and "exposure" in sv.reason
    bright = _Capture("nonoverlap-136", 0, projector_gain=3.0)
    d = bright.decode()
    assert d.counts["saturated"] > 10000
    assert np.all(np.asarray(bright.images[0])[:, :, 0][d.reason == Invalid.SATURATED] >= 250)


def test_a_corrupted_code_disagrees_with_its_neighbours(mirrored):
    d0 = mirrored.decode()
    ys, xs = np.nonzero(d0.valid)
    pick = np.random.default_rng(3).choice(len(ys), 40, replace=False)
    py, px = ys[pick], xs[pick]
    imgs = [im.copy() for im in mirrored.images]
    frames = SPEC.frames(*mirrored.proj_size)
    # swap the most significant column bit with its inverse at those pixels: a code 1024 px away
    i = next(k for k, f in enumerate(frames) if f.role is FrameRole.GRAY and f.axis is Axis.COLUMNS and f.index == 0)
    a, b = imgs[i][py, px].copy(), imgs[i + 1][py, px].copy()
    imgs[i][py, px], imgs[i + 1][py, px] = b, a
    d = decode_sequence(imgs, SPEC, mirrored.proj_size, response=RESPONSE)
    assert np.mean(d.reason[py, px] == Invalid.INCONSISTENT) > 0.9
    # their neighbours still decode
    assert np.mean(d.valid[py, np.clip(px + 2, 0, d.shape[1] - 1)] == d0.valid[py, np.clip(px + 2, 0, d.shape[1] - 1)]) > 0.9


# ---- local homographies -----------------------------------------------------------------------------
def _synthetic_map(Hm, noise_px, rng, shape=(120, 160), outliers=0.0):
    """A decoded map of a plane seen under homography Hm (camera -> projector) with Gaussian decoding noise."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    p = np.stack([xx, yy, np.ones_like(xx)], -1) @ Hm.T
    qx, qy = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    qx = qx + rng.normal(0, noise_px, qx.shape)
    qy = qy + rng.normal(0, noise_px, qy.shape)
    reason = np.zeros(shape, np.uint8)
    if outliers:
        bad = rng.random(shape) < outliers
        qx[bad] += rng.uniform(-30, 30, bad.sum())
    reason[:, :30] = Invalid.DARK_PRINT  # a masked strip
    qx[reason > 0] = np.nan
    qy[reason > 0] = np.nan
    z = np.zeros(shape, np.float32)
    return DecodedMap(qx.astype(np.float32), qy.astype(np.float32), reason, z, z, (1920, 1080), MappingProxyType({}))


HM = np.array([[3.9, 0.4, 400.0], [-0.3, 4.2, 300.0], [1e-4, -2e-4, 1.0]])


def test_local_homography_is_within_its_own_uncertainty():
    """Over many noisy maps, each point's error against the exact homography is distributed as its
    covariance says (mean of e^T C^-1 e near 2, the chi-square's degrees of freedom)."""
    rng = np.random.default_rng(11)
    pts = np.array([[60.0, 60.0], [100.5, 40.25], [140.0, 100.0], [34.0, 20.0]])  # the last: its window cut by the masked strip
    exact = np.column_stack([pts, np.ones(len(pts))]) @ HM.T
    exact = exact[:, :2] / exact[:, 2:]
    chi2 = []
    for _ in range(60):
        fit = fit_local_homographies(_synthetic_map(HM, 0.5, rng), pts)
        assert fit.ok.all()
        e = fit.proj_px - exact
        chi2 += [float(ei @ np.linalg.solve(c, ei)) for ei, c in zip(e, fit.cov_px2)]
    assert 1.5 < np.mean(chi2) < 2.6
    # 0.5 px per pixel over ~400 pixels: a few hundredths of a pixel
    assert np.all(fit.sigma_px < 0.1)


def test_local_homography_rejects_outliers_and_refuses_one_sided_windows():
    rng = np.random.default_rng(5)
    pts = np.array([[80.0, 60.0], [25.0, 60.0], [2.0, 60.0]])
    fit = fit_local_homographies(_synthetic_map(HM, 0.2, rng, outliers=0.05), pts, half_window_px=10)
    exact = np.column_stack([pts[:1], [1.0]]) @ HM.T
    assert fit.n_rejected[0] >= 10
    assert np.linalg.norm(fit.proj_px[0] - exact[0, :2] / exact[0, 2]) < 5 * fit.sigma_px[0]
    assert not fit.ok[1] and "one side" in fit.reasons[1]  # at the masked strip's edge: pixels on its right only
    assert not fit.ok[2] and "0 decoded pixels" in fit.reasons[2]  # inside the strip


def test_a_board_that_moves_during_the_sequence_is_refused(mirrored):
    """The closing white frame rendered with the board 3 mm further along its x axis (about 2 camera px):
    the capture is refused with a reason naming the motion; 0.1 mm (a fraction of the corner noise's
    reach, 0.06 px) is still."""
    from drivers.sim.render import PlacedBoard, SceneState

    P = mirrored.sc.rig.projector
    white = np.full((P.height, P.width), 255, np.uint8)
    for shift_mm, refused in ((3.0, True), (0.1, False)):
        T = mirrored.T.copy()
        T[:3, 3] += shift_mm * T[:3, 0]
        last = mirrored.R.render(SceneState((PlacedBoard(mirrored.sc.layout, T),), white), np.random.default_rng(9))
        imgs = mirrored.images[:-1] + [last]
        sv = detect_structured_view(imgs, SPEC, mirrored.sc.projector_board, mirrored.proj_size, True,
                                    response=RESPONSE)
        assert isinstance(sv, DetectionFailure) == refused, sv
        if refused:
            assert "moved" in sv.reason and "hold it still" in sv.reason
    # the board gone by the closing frame: refused too
    empty = mirrored.R.render(SceneState((), white), np.random.default_rng(9))
    sv = detect_structured_view(mirrored.images[:-1] + [empty], SPEC, mirrored.sc.projector_board, mirrored.proj_size,
                                True, response=RESPONSE)
    assert isinstance(sv, DetectionFailure) and "out of view" in sv.reason


def _truly_lit_share(cap, corners):
    hull = cv2.convexHull(np.asarray(corners, np.float32)).reshape(-1, 2)
    mask = np.zeros(cap.images[0].shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    ys, xs = np.nonzero(mask)
    q = true_projector_px(cap.R, cap.sc.layout, cap.T, np.column_stack([xs, ys]).astype(float))
    return float(np.mean(cap.R.projector.in_image(q)))


def test_the_share_of_the_board_the_projector_lights(mirrored):
    """Pose 16 holds the board with part of its print outside the projector's light (the renderer's exact
    projector pixels say how much); pose 0's print is lit whole."""
    partial = _Capture("nonoverlap-136", 16)
    for cap, whole in ((partial, False), (mirrored, True)):
        sv = detect_structured_view(cap.images, SPEC, cap.sc.projector_board, cap.proj_size, True, response=RESPONSE)
        truth = _truly_lit_share(cap, sv.view.board.corners_px)
        assert (truth > 0.99) == whole  # the premise
        print(f"lit share {sv.lit_share:.3f}, truth {truth:.3f}")
        assert abs(sv.lit_share - truth) < 0.03


@pytest.mark.parametrize("which", ["mirrored", "direct"])
def test_board_points_get_their_projector_pixels(which, request):
    cap = request.getfixturevalue(which)
    for points in (BoardPoints.BLANK_GRID, BoardPoints.CORNERS):
        sv = detect_structured_view(cap.images, SPEC, cap.sc.projector_board, cap.proj_size, cap.mirrored, "c1",
                                    points, response=RESPONSE)
        assert not isinstance(sv, DetectionFailure), sv
        v = sv.view
        assert len(v.pattern_cam_px) >= 10 and v.board.mirrored == cap.mirrored
        q = true_projector_px(cap.R, cap.sc.layout, cap.T, v.pattern_cam_px)
        e = np.hypot(*(np.asarray(v.pattern_proj_px) - q).T)
        print(f"{which} {points.value}: {len(e)} points, error rms {np.sqrt(np.mean(e ** 2)):.3f} max {e.max():.3f} px, "
              f"sigma median {np.median(sv.points.sigma_px):.3f} px")
        # the decoded pixels' errors are correlated over a window (blur), so the fit's sigma is optimistic
        # by up to about 2x: bound each point by 6 of its sigmas plus the corner detector's share
        slack = 0.0 if points is BoardPoints.BLANK_GRID else 0.1 * 4.0  # ~0.1 cam px x ~4 proj px per cam px
        assert np.all(e < 6 * sv.points.sigma_px + 0.02 + slack)
        assert np.sqrt(np.mean(e ** 2)) < (0.1 if points is BoardPoints.BLANK_GRID else 0.3)


# ---- into the calibration methods ------------------------------------------------------------------
def test_structured_views_calibrate_the_projector_with_both_methods():
    """Five placements of the structured-light step (the projector image's corners and centre) with the
    scenario's mirror views: both methods calibrate, and the joint one lands near the truth (a loose
    sanity bound; the accuracy itself is measured in benchmarks/structured_light.py)."""
    from calib.joint.method import calibrate_joint
    from calib.models.observations import SessionObservations
    from calib.paper.method import calibrate_paper
    from calib.quality.metrics import compare
    from calib.synthetic import SyntheticSession, observe

    sc = get_scenario("nonoverlap-136")
    R = _renderer(sc)
    P = sc.rig.projector
    views = []
    for i, pos in enumerate((0, 2, 4, 6, 8)):
        T = sc.projector_poses[pos * sc.per_position][1]
        imgs = render_sequence(R, sc.layout, T, SPEC, np.random.default_rng([i, 23]))
        sv = detect_structured_view(imgs, SPEC, sc.projector_board, (P.width, P.height), True, f"p{i}",
                                    response=RESPONSE)
        assert not isinstance(sv, DetectionFailure), sv
        views.append(sv.view)
    ss = SyntheticSession(sc.rig, sc.layout, sc.mirror_board, sc.pattern, [], sc.mirror_poses, sc.mirror_method)
    mirror_views = observe(ss, 0.1, 5).mirror_views
    obs = SessionObservations(sc.rig.camera.size, P.size, sc.rig.view, sc.projector_board, sc.pattern,
                              tuple(views), sc.mirror_board, tuple(mirror_views))
    truth = sc.ground_truth()
    paper = compare(calibrate_paper(obs), truth)
    joint = compare(calibrate_joint(obs, pattern_model="point"), truth)
    print(f"paper: {paper.distance:.3f} mm, ProjK {paper.proj_k_px:.2f} px; "
          f"joint: {joint.distance:.3f} mm {joint.angle_deg:.4f} deg, ProjK {joint.proj_k_px:.2f} px")
    assert paper.proj_k_px < 40 and paper.distance < 10
    assert joint.proj_k_px < 3 and joint.distance < 1.0 and joint.angle_deg < 0.15
