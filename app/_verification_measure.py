"""The verification's measurement (behind app/verification.py): a pixel's stroke found in the captured
frames and its distance to the pixel, and several strokes in one projector image (where the camera
sees each, so their pixels can be told apart)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from app._verification_capture import ReferenceFrames, grey
from app._verification_report import PixelCheck
from calib.detection.curves import (
    CurveDetection,
    detect_projected_curve,
    distance_to_curve,
    stripe_signal,
)
from calib.epipolar import predicted_camera_curve
from calib.models.result import CalibrationResult


def measure_pixel(result: CalibrationResult, pixel, curve: np.ndarray, frame_on: np.ndarray, refs: ReferenceFrames,
                  stroke_px: float, board_pose=None, roi: np.ndarray | None = None, signal=None) -> PixelCheck:
    """The measurement of verify_pixel on captured frames (pure: no devices). `frame_on` and `refs` as
    the camera delivered them, read as light through `refs.response` (see capture_references). `roi`:
    where in the camera image this pixel's stroke is looked for (when other strokes share the frame);
    `signal`: calib.detection.curves.stripe_signal of the frames' light, computed once for all strokes
    of the frame (frame_on is then not read)."""
    pixel = (float(pixel[0]), float(pixel[1]))
    predicted = None
    if board_pose is not None:
        predicted = predicted_camera_curve(result, pixel, board_pose)
    if signal is None:
        signal = stripe_signal(grey(frame_on, refs.response), *refs.light())
    if roi is not None and roi.any():
        det = _detect_in_box(signal, roi, refs.white)
    else:
        det: CurveDetection = detect_projected_curve(None, None, refs.white, roi=roi, signal=signal)
    if not det.ok:
        return PixelCheck(pixel, curve, np.zeros((0, 2)), predicted, None, None, None, None, stroke_px, None,
                          det.reason)
    cd = distance_to_curve(det, pixel)
    scale = det.cross_section_px / stroke_px if np.isfinite(det.cross_section_px) and det.cross_section_px > 0 else None
    if not cd.ok:
        return PixelCheck(pixel, curve, det.centre_px, predicted, None, None, None, scale, stroke_px, None, cd.reason)
    d_proj = cd.distance_px / scale if scale else None
    return PixelCheck(pixel, curve, det.centre_px, predicted, cd.distance_px, cd.signed_px, d_proj, scale,
                      stroke_px, cd.fit_rms_px, None)


# ---- several curves per projected image --------------------------------------------------------------
#: Strokes drawn in one projector image: at most this many ...
MAX_CURVES_PER_IMAGE = 4
#: ... and each picked pixel at least this far (camera px) from every other stroke's line in the image.
MIN_SEPARATION_PX = 60.0


def stroke_line(result: CalibrationResult, pixel, curve: np.ndarray) -> np.ndarray:
    """Where the camera sees the stroke of `pixel`'s epipolar curve, whatever the board's pose: the
    camera-side epipolar curve of the epipolar plane through the pixel (the camera curve of a
    projector pixel on its curve). (K, 2) camera pixels, empty when it cannot be traced."""
    from calib.epipolar import camera_curve_for_projector_pixel

    if len(curve) < 2:
        return np.zeros((0, 2))
    mid = np.asarray(curve, float)[len(curve) // 2]
    line = np.asarray(camera_curve_for_projector_pixel(result, mid).px, float).reshape(-1, 2)
    return line if len(line) >= 2 else np.zeros((0, 2))


def group_pixels(pixels: np.ndarray, lines: list[np.ndarray], per_image: int = MAX_CURVES_PER_IMAGE,
                 min_separation_px: float = MIN_SEPARATION_PX) -> list[list[int]]:
    """Indices of `pixels` grouped so the strokes of a group can be drawn in one projector image and
    told apart in the camera: each pixel at least `min_separation_px` from the other strokes' lines.
    A pixel without a line gets a group of its own."""
    from calib.epipolar import distance_to_polyline

    def far(i, j) -> bool:
        if len(lines[i]) < 2 or len(lines[j]) < 2:
            return False
        return (float(distance_to_polyline(pixels[i], lines[j]).distance[0]) >= min_separation_px and
                float(distance_to_polyline(pixels[j], lines[i]).distance[0]) >= min_separation_px)

    groups: list[list[int]] = []
    for i in range(len(pixels)):
        for g in groups:
            if len(g) < per_image and all(far(i, j) for j in g):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def _detect_in_box(signal, roi: np.ndarray, white: np.ndarray) -> CurveDetection:
    """detect_projected_curve on the bounding box of `roi` only (the same result, far less work)."""
    s, valid = signal
    ys, xs = np.nonzero(roi)
    pad = 3
    y0, y1 = max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, roi.shape[0])
    x0, x1 = max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, roi.shape[1])
    box = (slice(y0, y1), slice(x0, x1))
    det = detect_projected_curve(None, None, white[box], roi=roi[box], signal=(s[box], valid[box]))
    return replace(det, centre_px=det.centre_px + np.array([x0, y0], float)) if det.ok else det


def stroke_rois(shape, lines: list[np.ndarray], half_width_px: float) -> list[np.ndarray]:
    """Per line, the camera pixels nearer to it than to the other lines and within `half_width_px`."""
    H, W = shape
    dists = []
    for ln in lines:
        m = np.full((H, W), 255, np.uint8)
        cv2.polylines(m, [np.round(ln).astype(np.int32).reshape(-1, 1, 2)], False, 0, 1)
        dists.append(cv2.distanceTransform(m, cv2.DIST_L2, 3))
    out = []
    for i, d in enumerate(dists):
        roi = d <= half_width_px
        for j, o in enumerate(dists):
            if j != i:
                roi &= d < o
        out.append(roi)
    return out
