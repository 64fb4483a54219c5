"""Detection on rendered images with exact ground truth (tests/_detect_helpers.py)."""

import cv2
import numpy as np
import pytest

from _detect_helpers import (
    blank_region_proj_homography,
    board_homography,
    flip_H,
    pinhole_rig,
    render_board_scene,
    synthetic_homographies,
)
from calib.models.boards import CharucoSpec
from calib.detection.detect import (
    DetectionFailure,
    detect_board,
    detect_pattern,
    detect_real_mirror,
    detect_real_virtual,
)
from calib.models.observations import STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, BoardObservation
from calib.models.pattern import PatternSpec
from calib.synthetic import make_session, observe

SPEC = CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0)
W, H = 1280, 800
PROJ = (1920, 1080)


def _rms(e):
    return float(np.sqrt(np.mean(np.square(e))))


def _scene(mirrored=False, kind="circles", angle=8.0, tilt=(0.3, 0.1), position=4, noise=0.0, **kw):
    pattern = PatternSpec.default_for(*PROJ, kind=kind)
    Hb = board_homography(W, H, SPEC, angle_deg=angle, tilt=tilt, mirrored=mirrored)
    Hbp = blank_region_proj_homography(SPEC, pattern, PROJ, position, angle_deg=5, tilt=(0.2, 0.1))
    return pattern, render_board_scene(W, H, SPEC, Hb, pattern, Hbp, PROJ, position, noise_px=noise, **kw)


@pytest.fixture(scope="module")
def direct_circles():
    return _scene(False, "circles")


@pytest.fixture(scope="module")
def mirrored_circles():
    return _scene(True, "circles")


# ---- the board ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("angle,tilt,scale", [(0.0, (0, 0), None), (20.0, (0.5, -0.3), 1.0), (-15, (0.1, 0.4), 1.6)])
def test_board_corners_subpixel_accurate(angle, tilt, scale):
    Hb = board_homography(W, H, SPEC, angle_deg=angle, tilt=tilt, scale_px=scale)
    sc = render_board_scene(W, H, SPEC, Hb)
    obs = detect_board(sc.image, SPEC, mirrored=False)
    assert isinstance(obs, BoardObservation) and not obs.mirrored
    assert len(obs.ids) >= 20 and np.all(np.diff(obs.ids) > 0)
    err = obs.corners_px - sc.corners_px[obs.ids]
    assert _rms(err) < 0.02 and np.abs(err).max() < 0.05


def test_board_accepts_bgr_and_gray(direct_circles):
    _, sc = direct_circles
    gray = detect_board(sc.image, SPEC, False)
    bgr = detect_board(cv2.cvtColor(sc.image, cv2.COLOR_GRAY2BGR), SPEC, False)
    assert np.array_equal(gray.ids, bgr.ids) and np.allclose(gray.corners_px, bgr.corners_px, atol=1e-6)


def test_mirrored_board_maps_back_with_w_minus_1(mirrored_circles):
    _, sc = mirrored_circles
    obs = detect_board(sc.image, SPEC, mirrored=True)
    assert isinstance(obs, BoardObservation) and obs.mirrored and len(obs.ids) == SPEC.n_corners
    err = obs.corners_px - sc.corners_px[obs.ids]
    assert _rms(err) < 0.02 and np.abs(err).max() < 0.05
    # the published reference code maps back with W - x: every x would be one pixel too far right
    in_flipped = (W - 1) - obs.corners_px[:, 0]
    wrong = W - in_flipped
    assert np.allclose(wrong - sc.corners_px[obs.ids, 0], 1.0, atol=0.05)
    # ArUco markers cannot be read in a mirror image without the flip
    assert isinstance(detect_board(sc.image, SPEC, mirrored=False), DetectionFailure)


def test_legacy_board_layout_is_recognised():
    # a board printed by OpenCV < 4.6 (even number of rows): same corner positions, markers shifted
    Hb = board_homography(W, H, SPEC, angle_deg=-7, tilt=(0.2, 0.2))
    legacy = render_board_scene(W, H, SPEC, Hb, legacy=True)
    modern = render_board_scene(W, H, SPEC, Hb)
    assert not np.array_equal(legacy.image, modern.image)
    for sc in (legacy, modern):
        obs = detect_board(sc.image, SPEC, False)
        assert isinstance(obs, BoardObservation) and len(obs.ids) == SPEC.n_corners
        assert np.abs(obs.corners_px - sc.corners_px[obs.ids]).max() < 0.06


def test_board_noise_robust():
    Hb = board_homography(W, H, SPEC, angle_deg=12, tilt=(0.2, 0.2))
    sc = render_board_scene(W, H, SPEC, Hb, noise_px=3.0, seed=3)
    obs = detect_board(sc.image, SPEC, False)
    err = obs.corners_px - sc.corners_px[obs.ids]
    assert len(obs.ids) == SPEC.n_corners and _rms(err) < 0.06


def test_board_failures_have_reasons():
    blank = np.full((H, W), 90, np.uint8)
    r = detect_board(blank, SPEC, False)
    assert isinstance(r, DetectionFailure) and r.reason == "board not found" and not r
    # only a corner of the board in view: a few markers, fewer than 6 ChArUco corners
    Hb = board_homography(W, H, SPEC, centre=(W + 230.0, H + 110.0), scale_px=1.2)
    sc = render_board_scene(W, H, SPEC, Hb)
    r = detect_board(sc.image, SPEC, False)
    assert isinstance(r, DetectionFailure)
    assert r.reason.startswith("only ") and r.reason.endswith("ChArUco corners (need 6)")
    n = int(r.reason.split()[1])
    assert 0 <= n < 6
    ok = detect_board(sc.image, SPEC, False, min_corners=max(n, 1))
    assert n == 0 or isinstance(ok, BoardObservation)


# ---- the projected pattern ----------------------------------------------------------------------------------
def test_circle_grid_direct_is_accurate_and_ordered(direct_circles):
    pattern, sc = direct_circles
    board = detect_board(sc.image, SPEC, False)
    pts = detect_pattern(sc.image, pattern, False, board, SPEC)
    assert pts.shape == (pattern.n_points, 2)
    # blob centroid = centre of the imaged conic (not the image of the circle's centre)
    assert np.abs(pts - sc.pattern_px).max() < 0.04
    # without the board hint as well
    assert np.abs(detect_pattern(sc.image, pattern, False) - sc.pattern_px).max() < 0.04


def test_circle_grid_in_mirrored_view_comes_back_in_order(mirrored_circles):
    pattern, sc = mirrored_circles
    board = detect_board(sc.image, SPEC, True)
    pts = detect_pattern(sc.image, pattern, True, board, SPEC)
    assert pts.shape == (pattern.n_points, 2)
    assert np.abs(pts - sc.pattern_px).max() < 0.04
    # the trap: OpenCV finds the asymmetric grid in the mirror image too, but not in the drawn order
    ok, naive = cv2.findCirclesGrid(255 - sc.image, pattern.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
    assert ok
    naive = naive.reshape(-1, 2)
    assert np.linalg.norm(naive - sc.pattern_px, axis=1).max() > pattern.spacing_px * 0.2


@pytest.mark.parametrize("mirrored", [False, True])
def test_chessboard_pattern(mirrored):
    pattern, sc = _scene(mirrored, "chessboard", position=6)
    board = detect_board(sc.image, SPEC, mirrored)
    pts = detect_pattern(sc.image, pattern, mirrored, board, SPEC)
    assert pts.shape == (pattern.n_points, 2)
    assert np.abs(pts - sc.pattern_px).max() < 0.06
    # the board's observation alone (no spec) also masks the printed area
    assert np.abs(detect_pattern(sc.image, pattern, mirrored, board) - sc.pattern_px).max() < 0.06


def test_chessboard_pattern_rotated_half_turn_keeps_drawn_order():
    # the camera sees the projection upside down: the detector must still return PatternSpec order
    pattern = PatternSpec.default_for(*PROJ, kind="chessboard")
    Hb = board_homography(W, H, SPEC, angle_deg=5)
    Hbp = blank_region_proj_homography(SPEC, pattern, PROJ, 3, angle_deg=180)
    sc = render_board_scene(W, H, SPEC, Hb, pattern, Hbp, PROJ, 3)
    pts = detect_pattern(sc.image, pattern, False, detect_board(sc.image, SPEC, False), SPEC)
    assert np.abs(pts - sc.pattern_px).max() < 0.06


def test_pattern_noise_robust():
    pattern, sc = _scene(False, "circles", noise=3.0, seed=5)
    pts = detect_pattern(sc.image, pattern, False, detect_board(sc.image, SPEC, False), SPEC)
    assert np.abs(pts - sc.pattern_px).max() < 0.25 and _rms(pts - sc.pattern_px) < 0.1


def test_pattern_failures_have_reasons(direct_circles):
    pattern, sc = direct_circles
    board = detect_board(sc.image, SPEC, False)
    # no projection at all
    Hb = board_homography(W, H, SPEC, angle_deg=8, tilt=(0.3, 0.1))
    dark = render_board_scene(W, H, SPEC, Hb).image
    r = detect_pattern(dark, pattern, False, board, SPEC)
    assert isinstance(r, DetectionFailure) and r.reason.startswith("pattern")
    # the pattern cut off by the image border: some circles are missing
    cut = sc.image.copy()
    xs = sc.pattern_px[:, 0]
    x_cut = int(np.percentile(xs, 85))
    cut[:, x_cut:] = 30
    r = detect_pattern(cut, pattern, False, board, SPEC)
    assert isinstance(r, DetectionFailure)
    assert r.reason.startswith("pattern partial: ") and r.reason.endswith(f"of {pattern.n_points} points")
    found = int(r.reason.split()[2])
    assert found == int(np.sum(sc.pattern_px[:, 0] < x_cut - 3)) or 20 <= found < pattern.n_points
    # a chessboard that is not there
    r = detect_pattern(dark, PatternSpec.default_for(*PROJ, kind="chessboard"), False, board, SPEC)
    assert isinstance(r, DetectionFailure) and r.reason == "pattern not found"


# ---- synthetic rig poses (calib.synthetic) ----------------------------------------------------------------
def test_detection_matches_synthetic_observations():
    rig = pinhole_rig(136.0)
    ss = make_session(rig, per_position=1, mirror_method=None)
    truth = observe(ss)
    cam = rig.camera
    for i in (0, 8):
        Hib, Hbp, pos = synthetic_homographies(ss, i)
        sc = render_board_scene(cam.width, cam.height, ss.layout.charuco, Hib, ss.pattern, Hbp, rig.projector.size,
                                pos, blank_width=ss.layout.blank_width)
        tv = truth.projector_views[i]
        board = detect_board(sc.image, ss.layout.charuco, mirrored=True)
        assert isinstance(board, BoardObservation) and len(board.ids) >= 30
        assert _rms(board.corners_px - tv.board.corners_px[board.ids]) < 0.05
        pts = detect_pattern(sc.image, ss.pattern, True, board, ss.layout.charuco)
        assert np.abs(pts - tv.pattern_cam_px).max() < 0.08


# ---- mirror-calibration images --------------------------------------------------------------------------
MSPEC = CharucoSpec(6, 5, "DICT_4X4_50", 30.0, 18.0)


def _mirror_scene():
    Hr = board_homography(W, H, MSPEC, centre=(330.0, 400.0), scale_px=2.4, angle_deg=10, tilt=(0.2, 0.1),
                          blank_width=0.0)
    Hv = board_homography(W, H, MSPEC, centre=(W - 1 - 900.0, 380.0), scale_px=2.0, angle_deg=-6, tilt=(0.1, 0.3),
                          blank_width=0.0, mirrored=True)
    real = render_board_scene(W, H, MSPEC, Hr, blank_width=0.0, background=0.0)
    virt = render_board_scene(W, H, MSPEC, Hv, blank_width=0.0, background=0.0)
    img = np.maximum(real.image, virt.image)
    return img, real.corners_px, virt.corners_px


def test_real_virtual_and_real_mirror():
    img, real_gt, virt_gt = _mirror_scene()
    mv = detect_real_virtual(img, MSPEC, "mrv0000")
    assert mv.method == STEP_REAL_VIRTUAL and mv.capture_id == "mrv0000"
    assert not mv.real.mirrored and mv.virtual.mirrored
    assert len(mv.real.ids) == MSPEC.n_corners and len(mv.virtual.ids) == MSPEC.n_corners
    assert _rms(mv.real.corners_px - real_gt[mv.real.ids]) < 0.03
    assert _rms(mv.virtual.corners_px - virt_gt[mv.virtual.ids]) < 0.03
    rm = detect_real_mirror(img, MSPEC, "mrm0000")
    assert rm.method == STEP_REAL_MIRROR and rm.virtual is None
    assert np.allclose(rm.real.corners_px, mv.real.corners_px)
    # only the real board: the virtual one is missing, which real-virtual reports
    only_real = img.copy()
    only_real[:, 560:] = 0
    r = detect_real_virtual(only_real, MSPEC)
    assert isinstance(r, DetectionFailure) and r.reason.startswith("virtual board")
    r = detect_real_mirror(np.zeros_like(img), MSPEC)
    assert isinstance(r, DetectionFailure) and r.reason == "board not found"


def test_flip_homography_is_pixel_centre_exact():
    # the renderer's mirror: pixel x of the flipped image is pixel (W - 1) - x of the original
    img = np.random.default_rng(0).integers(0, 255, (7, 11), dtype=np.uint8)
    warped = cv2.warpPerspective(img, flip_H(11), (11, 7), flags=cv2.INTER_NEAREST)
    assert np.array_equal(warped, cv2.flip(img, 1))


def _board_corners_px(scale, offset):
    """Every corner of SPEC at `scale` px per unit, shifted by `offset` px (a fronto-parallel view)."""
    return SPEC.corner_points()[:, :2] * scale + np.asarray(offset, float)


def test_the_linearised_retry_is_searched_around_the_board_or_not_at_all():
    import calib.detection.charuco as D

    shape = (H, W)
    ids = np.arange(SPEC.n_corners)
    # half the corners found, the others predicted in view: a box around the whole board (2.5 squares more)
    allpx = _board_corners_px(1.0, (300, 200))
    found = ids[ids % 7 < 4]
    box = D._board_box(allpx[found], found, (0, 0), SPEC, shape)
    side = 1.0 * SPEC.square_length
    assert box[0] <= allpx[:, 0].min() - 2 * side and box[2] >= allpx[:, 0].max() + 2 * side
    assert box[1] <= allpx[:, 1].min() - 2 * side and box[3] >= allpx[:, 1].max() + 2 * side
    assert (box[2] - box[0]) * (box[3] - box[1]) < 0.5 * W * H
    # corners found in a region's coordinates are offset into the image's
    shifted = D._board_box(allpx[found] - [40, 30], found, (40, 30), SPEC, shape)
    assert shifted == box
    # the missing corners all lie beyond the image's right edge: no retry can find them
    cut = _board_corners_px(1.0, (W - 0.5 - 3.5 * side, 200))
    inside = ids[cut[:, 0] < W - 0.5]
    assert 0 < len(inside) < SPEC.n_corners
    assert D._board_box(cut[inside], inside, (0, 0), SPEC, shape) == ()
    # too few corners to predict the board: not known (the caller searches as before)
    assert D._board_box(allpx[:3], ids[:3], (0, 0), SPEC, shape) is None


def test_a_board_incomplete_in_its_roi_is_searched_again_only_if_corners_may_lie_beyond_it():
    import calib.detection.charuco as D

    shape = (H, W)
    ids = np.arange(SPEC.n_corners)
    allpx = _board_corners_px(1.0, (300, 200))
    found = ids[ids % 7 < 4]
    side = 1.0 * SPEC.square_length
    lo, hi = allpx.min(axis=0), allpx.max(axis=0)
    wide = (int(lo[0] - 3 * side), int(lo[1] - 3 * side), int(hi[0] + 3 * side), int(hi[1] + 3 * side))
    assert not D._missing_beyond(allpx[found], found, (0, 0), SPEC, wide, shape)
    tight = (int(lo[0] - 3 * side), int(lo[1] - 3 * side), int(hi[0] - 2 * side), int(hi[1] + 3 * side))
    assert D._missing_beyond(allpx[found], found, (0, 0), SPEC, tight, shape)
    # an ROI edge on the image's border needs no margin: nothing lies beyond it
    at_edge = _board_corners_px(1.0, (W - 0.5 - 3.5 * side, 200))
    inside = ids[at_edge[:, 0] < W - 0.5 - side]
    roi = (int(at_edge[:, 0].min() - 3 * side), 0, W, H)
    assert not D._missing_beyond(at_edge[inside], inside, (0, 0), SPEC, roi, shape)
    assert D._missing_beyond(None, None, (0, 0), SPEC, roi, shape)
