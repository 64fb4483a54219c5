"""Projector images as pure numpy: solid frames, patterns, checkerboards and exact polylines."""

import numpy as np
import pytest

from calib.errors import SpecError
from calib.models.pattern import PatternSpec
from drivers import projector_images as pi


def test_solid_frames_and_checkerboard():
    assert pi.black((8, 4)).shape == (4, 8) and pi.black((8, 4)).max() == 0
    assert pi.white((8, 4)).min() == 255 and pi.white((8, 4)).dtype == np.uint8
    bgr = pi.solid((5, 3), (10, 20, 30))
    assert bgr.shape == (3, 5, 3) and (bgr[1, 2] == [10, 20, 30]).all()
    c = pi.checkerboard((6, 4), 1)
    assert c[0, 0] == 255 and c[0, 1] == 0 and c[1, 0] == 0 and c[1, 1] == 255
    assert np.array_equal(pi.checkerboard((6, 4), 1, phase=1), 255 - c)
    c2 = pi.checkerboard((8, 8), 2)
    assert c2[0:2, 0:2].min() == 255 and c2[0:2, 2:4].max() == 0
    with pytest.raises(SpecError):
        pi.solid((0, 4))
    with pytest.raises(SpecError):
        pi.solid((4, 4), 300)


def test_pattern_image_is_the_spec_rendering():
    spec = PatternSpec.default_for(1280, 720)
    img, pts = pi.pattern_image(spec, (1280, 720), 12)
    ref_img, ref_pts = spec.render(1280, 720, 12)
    assert np.array_equal(img, ref_img) and np.array_equal(pts, ref_pts)
    imgs = pi.pattern_images(spec, (1280, 720))
    assert len(imgs) == 13 and np.array_equal(imgs[12], ref_img)


def reference_stroke(size, polylines, thickness):
    """Pixel-by-pixel: is the pixel centre within thickness/2 of a segment (direct definition)?"""
    w, h = size
    out = np.zeros((h, w), bool)
    for line in polylines:
        p = np.asarray(line, float)
        for a, b in zip(p[:-1], p[1:]):
            if not (np.isfinite(a).all() and np.isfinite(b).all()):
                continue
            for y in range(h):
                for x in range(w):
                    q = np.array([x, y], float)
                    d = b - a
                    t = 0.0 if d @ d == 0 else min(1.0, max(0.0, (q - a) @ d / (d @ d)))
                    if np.linalg.norm(q - (a + t * d)) <= thickness / 2:
                        out[y, x] = True
    return out


def test_polylines_without_antialiasing_cover_exactly_the_pixel_centres_in_the_stroke():
    size = (40, 30)
    lines = [np.array([[3.2, 4.7], [30.9, 12.1], [12.5, 27.3]]), np.array([[0, 29], [39, 0]])]
    for thickness in (1.0, 2.5, 4.0):
        img = pi.draw_polylines(size, lines, thickness, 200)
        assert set(np.unique(img)) <= {0, 200}
        assert np.array_equal(img == 200, reference_stroke(size, lines, thickness)), thickness


def test_a_horizontal_line_has_round_caps():
    img = pi.draw_polylines((30, 20), [np.array([[5, 10], [20, 10]])], 3.0, 255)
    assert img[9:12, 5:21].min() == 255
    assert img[10, 4] == 255 and img[9, 4] == 255 and img[10, 3] == 0  # cap: radius 1.5 around (5, 10)
    assert img[8].max() == 0 and img[12].max() == 0


def test_antialiased_coverage_is_exact_for_a_band():
    # a band y in [9, 11] (thickness 2 around y = 10) covers row 10 fully, rows 9 and 11 half
    img = pi.draw_polylines((40, 20), [np.array([[-10, 10], [60, 10]])], 2.0, 200, antialias=True)
    assert (img[10] == 200).all() and (img[9] == 100).all() and (img[11] == 100).all()
    assert img[:9].max() == 0 and img[12:].max() == 0


def test_nan_splits_a_polyline_and_colour_on_grey_background():
    line = np.array([[2, 5], [10, 5], [np.nan, np.nan], [20, 5], [28, 5]])
    bg = np.full((10, 30), 40, np.uint8)
    img = pi.draw_polylines((30, 10), [line], 1.0, (0, 0, 255), background=bg)
    assert img.shape == (10, 30, 3)
    assert (img[5, 2:11] == [0, 0, 255]).all() and (img[5, 20:29] == [0, 0, 255]).all()
    assert (img[5, 12:19] == 40).all()  # no segment across the gap
    assert (img[0] == 40).all()


def test_lines_are_clipped_to_the_image():
    W, H = 64, 48
    v = pi.line_polyline([1.0, 0.0, -20.3], (W, H))  # x = 20.3
    assert np.allclose(v, [[20.3, -0.5], [20.3, H - 0.5]]) or np.allclose(v, [[20.3, H - 0.5], [20.3, -0.5]])
    d = pi.line_polyline([1.0, -1.0, 0.0], (W, H))  # y = x
    assert np.allclose(sorted(d.tolist()), [[-0.5, -0.5], [H - 0.5, H - 0.5]])
    assert pi.line_polyline([0.0, 1.0, 500.0], (W, H)).shape == (0, 2)  # y = -500: misses
    img = pi.draw_lines((W, H), [[0.0, 1.0, -7.0]], 1.0, 255)  # y = 7
    assert (img[7] == 255).all() and img.sum() == 255 * W
