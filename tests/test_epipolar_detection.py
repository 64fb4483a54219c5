"""Detection of a projected curve in camera images (calib.detection.curves) on synthetic stripe images."""

import numpy as np
import pytest

from calib.detection.curves import detect_projected_curve, distance_to_curve, lit_region, stripe_signal
from calib.epipolar import distance_to_polyline
from _epipolar_helpers import checker_albedo, stripe_frames

SIZE = (640, 400)


def _line(angle_deg, centre=(320.3, 200.7), half=400.0):
    a = np.radians(angle_deg)
    d = np.array([np.cos(a), np.sin(a)])
    c = np.asarray(centre)
    return np.array([c - half * d, c + half * d]), c, np.array([-d[1], d[0]])


@pytest.mark.parametrize("angle", [0, 17, 44, 46, 75, 90, 130])
def test_centre_line_is_subpixel_on_a_checkerboard(angle):
    poly, c, normal = _line(angle)
    on, off, white = stripe_frames(SIZE, poly, albedo=checker_albedo(SIZE), seed=angle)
    det = detect_projected_curve(on, off, white)
    assert det.ok, det.reason
    assert det.scan == ("cols" if abs(np.cos(np.radians(angle))) >= abs(np.sin(np.radians(angle))) else "rows")
    err = distance_to_polyline(det.centre_px, poly).distance
    assert len(err) > 60
    assert err.max() < 0.15 and np.sqrt(np.mean(err**2)) < 0.05
    # a pixel 2.5 px off the line (on either side) measures 2.5 px
    for side in (+1, -1):
        cd = distance_to_curve(det, c + side * 2.5 * normal)
        assert cd.ok, cd.reason
        assert cd.distance_px == pytest.approx(2.5, abs=0.05)
    assert distance_to_curve(det, c).distance_px < 0.05


def test_white_frame_removes_the_albedo_bias():
    """Without normalisation the printed squares skew the stripe's profile by up to pixels."""
    poly, c, normal = _line(30)
    on, off, white = stripe_frames(SIZE, poly, albedo=checker_albedo(SIZE, angle_deg=10), seed=3)
    raw = detect_projected_curve(on, off)
    norm = detect_projected_curve(on, off, white)
    e_raw = distance_to_polyline(raw.centre_px, poly).distance
    e_norm = distance_to_polyline(norm.centre_px, poly).distance
    assert e_raw.max() > 0.5
    assert e_norm.max() < 0.15


def test_curved_stroke_and_its_width():
    x = np.linspace(-20, 660, 200)
    poly = np.column_stack([x, 150 + 0.0004 * (x - 300) ** 2 + 0.05 * x])
    on, off, white = stripe_frames(SIZE, poly, width_px=4.0, blur_px=1.0, seed=5)
    det = detect_projected_curve(on, off, white)
    assert det.ok
    assert distance_to_polyline(det.centre_px, poly).distance.max() < 0.1
    assert 3.0 < det.width_px < 6.0
    p = poly[100] + np.array([0.0, 1.5])
    true = distance_to_polyline(p, poly).distance[0]
    assert distance_to_curve(det, p).distance_px == pytest.approx(true, abs=0.05)


def test_nothing_drawn_is_a_failure_value_not_an_exception():
    on, off, white = stripe_frames(SIZE, None, seed=1)
    det = detect_projected_curve(on, off, white)
    assert not det and det.reason.startswith("no projected curve visible")
    cd = distance_to_curve(det, (10, 10))
    assert not cd.ok and np.isnan(cd.distance_px)
    # a projector that lights nothing the camera sees
    dark = np.zeros((SIZE[1], SIZE[0]), bool)
    on, off, white = stripe_frames(SIZE, _line(10)[0], lit=dark, seed=2)
    det = detect_projected_curve(on, off, white)
    assert not det and "lights" in det.reason


def test_specks_and_a_second_blob_are_ignored():
    poly, c, normal = _line(12)
    on, off, white = stripe_frames(SIZE, poly, seed=7)
    on = on.copy()
    on[40:44, 500:504] = 255  # a speck (e.g. a specular glint) far from the curve
    on[300:303, 100:160] = 255  # a short bright bar
    det = detect_projected_curve(on, off, white)
    assert det.ok
    assert distance_to_polyline(det.centre_px, poly).distance.max() < 0.15


def test_pixel_beyond_the_detected_curve_is_reported():
    poly = np.array([[50.0, 200.2], [300.0, 230.0]])  # the stroke ends at x = 300
    on, off, white = stripe_frames(SIZE, poly, seed=8)
    det = detect_projected_curve(on, off, white)
    assert det.ok
    far = distance_to_curve(det, (560.0, 261.0))
    assert not far.ok and "does not reach" in far.reason
    just_beyond = distance_to_curve(det, (312.0, 231.0))
    assert not just_beyond.ok and "stops before" in just_beyond.reason
    near = distance_to_curve(det, (200.0, 218.1))
    assert near.ok and near.distance_px < 0.1


def test_colour_channel_selects_one_curve():
    p_red, _, _ = _line(5, centre=(320, 120))
    p_blue, _, _ = _line(-5, centre=(320, 280))
    r_on, off, white = stripe_frames(SIZE, p_red, seed=9)
    b_on, _, _ = stripe_frames(SIZE, p_blue, seed=9)
    on = off.copy()
    on[:, :, 2] = r_on[:, :, 2]  # red channel sees only the red curve
    on[:, :, 0] = b_on[:, :, 0]
    det_r = detect_projected_curve(on, off, white, channel=2)
    det_b = detect_projected_curve(on, off, white, channel=0)
    assert distance_to_polyline(det_r.centre_px, p_red).distance.max() < 0.15
    assert distance_to_polyline(det_b.centre_px, p_blue).distance.max() < 0.15


def test_lit_region_and_roi():
    lit = np.zeros((SIZE[1], SIZE[0]), bool)
    lit[100:300, 150:500] = True
    poly, c, _ = _line(20)
    on, off, white = stripe_frames(SIZE, poly, lit=lit, seed=10)
    mask = lit_region(off, white, erode_px=2)
    assert mask[110:290, 160:490].all() and not mask[:95].any() and not mask[:, :145].any()
    s, valid = stripe_signal(on, off, white)
    assert not valid[:90].any()
    roi = np.zeros_like(lit)
    roi[:, 320:] = True
    det = detect_projected_curve(on, off, white, roi=roi)
    assert det.ok and det.centre_px[:, 0].min() >= 319
    assert distance_to_polyline(det.centre_px, poly).distance.max() < 0.15


@pytest.mark.parametrize("angle,width,blur", [(8, 3.0, 0.8), (33, 5.0, 1.2), (70, 2.5, 0.6)])
def test_cross_section_is_the_stroke_width_whatever_the_blur_and_angle(angle, width, blur):
    poly, _, _ = _line(angle)
    on, off, white = stripe_frames(SIZE, poly, width_px=width, blur_px=blur, albedo=checker_albedo(SIZE),
                                   noise_dn=0.5, seed=11)
    det = detect_projected_curve(on, off, white)
    assert det.ok
    assert det.cross_section_px == pytest.approx(width, rel=0.06)
    # without a white frame there is no scale to measure
    assert np.isnan(detect_projected_curve(on, off).cross_section_px)
