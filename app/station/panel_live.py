"""The live camera image as the panel draws it: detections, the verified pixels with their predicted
curve, detected stroke, distance and verdict, where to hold the board next, and a banner that wraps
instead of being cut. Also the geometry of clicking a pixel on the camera image shown in the 3D view.

Colours (BGR here; the legend under the image names them): board corners green, the board seen in the
mirror yellow, the projected pattern violet; verification: predicted curve cyan, detected stroke
orange, the pixel green when it passes and red when it fails.
"""

from __future__ import annotations

import cv2
import numpy as np

from app.station.panel_guidance import dashed_polygon, dashed_rect
from app.station.panel_results import check_passes

GREEN = (60, 220, 60)
YELLOW = (40, 220, 240)
VIOLET = (220, 80, 240)
CYAN = (240, 220, 40)
ORANGE = (30, 140, 255)
RED = (50, 50, 235)
PASS = (60, 210, 60)
NOT_MEASURED = (170, 170, 170)  # grey: no verdict, not a failure

LEGEND = ("Green: board corners; yellow: the board in the mirror; violet: projected pattern; dashed box: where "
          "to hold the board next; dashed outline: the board pose asked for. Verification: cyan predicted curve, orange detected stroke, pixel green "
          "(pass) or red (fail) with its distance and unit beside it; a grey circle: not measured (no verdict).")

FONT = cv2.FONT_HERSHEY_SIMPLEX


def wrap(text: str, width_px: int, scale: float = 0.45, max_lines: int = 3) -> list[str]:
    """Words of `text` in lines no wider than `width_px` at `scale` (the last line ends with ... when cut)."""
    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cv2.getTextSize(trial, FONT, scale, 1)[0][0] <= width_px or not cur:
            cur = trial
        else:
            lines.append(cur)
            cur = word
    if cur:
        lines.append(cur)
    if len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] = lines[-1] + " ..."
    return lines


def draw_banner(img: np.ndarray, text: str, colour, top: bool = True, scale: float = 0.45) -> None:
    """A dark band with `text` wrapped over up to three lines, at the top (or bottom) of `img`."""
    if not text:
        return
    w = img.shape[1]
    lines = wrap(text, w - 12, scale)
    line_h = 17
    band = 6 + line_h * len(lines)
    y0 = 0 if top else img.shape[0] - band
    cv2.rectangle(img, (0, y0), (w, y0 + band), (0, 0, 0), -1)
    for i, ln in enumerate(lines):
        cv2.putText(img, ln, (6, y0 + 15 + i * line_h), FONT, scale, colour, 1, cv2.LINE_AA)


def draw_detection(img: np.ndarray, det, s: float) -> None:
    if det is None:
        return
    if det.board is not None:
        for x, y in det.board.corners_px * s:
            cv2.circle(img, (int(round(x)), int(round(y))), 2, GREEN, -1, cv2.LINE_AA)
    if det.virtual is not None:
        for x, y in det.virtual.corners_px * s:
            cv2.circle(img, (int(round(x)), int(round(y))), 2, YELLOW, -1, cv2.LINE_AA)
    if det.pattern_px is not None:
        pts = np.round(det.pattern_px * s).astype(np.int32)
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, VIOLET, 1, cv2.LINE_AA)
        for x, y in pts:
            cv2.circle(img, (int(x), int(y)), 3, VIOLET, 1, cv2.LINE_AA)


def _poly(img, pts, s, colour, thickness) -> None:
    if pts is None:
        return
    a = np.asarray(pts, float).reshape(-1, 2)
    a = a[np.all(np.isfinite(a), axis=1)]
    if len(a) > 1:
        cv2.polylines(img, [np.round(a * s).astype(np.int32).reshape(-1, 1, 2)], False, colour, thickness, cv2.LINE_AA)


def check_label(check, passed: bool) -> str:
    """Short, with its unit: the distance in projector px (camera px when the scale is unknown), and a
    FAIL; "not measured" when the stroke was not found. The colour of the marker says pass too."""
    if not check.ok:
        return "not measured"
    d = (f"{check.distance_proj_px:.2f} proj px" if check.distance_proj_px is not None
         else f"{check.distance_px:.2f} cam px")
    return d if passed else f"{d} FAIL"


def _label_spot(mask: np.ndarray, px: int, py: int, tw: int, th: int) -> tuple[int, int]:
    """Where a label of tw x th px next to the pixel (px, py) covers the fewest stroke pixels of `mask`
    (beside the strokes, not under them); inside the image."""
    H, W = mask.shape
    best, spot = None, (px + 8, py - 6)
    for dx, dy in ((8, -6), (8, th + 10), (-tw - 8, -6), (-tw - 8, th + 10), (-tw // 2, -14), (-tw // 2, th + 18)):
        x = min(max(px + dx, 2), W - tw - 2)
        y = min(max(py + dy, th + 3), H - 3)
        covered = int(mask[max(y - th - 3, 0):y + 3, max(x - 2, 0):x + tw + 2].sum())
        if best is None or covered < best:
            best, spot = covered, (x, y)
    return spot


def draw_checks(img: np.ndarray, checks, s: float, threshold_px: float, worst_factor: float,
                predicted: dict | None = None) -> None:
    """Every verified pixel: predicted curve (from the check, else `predicted[i]`), detected stroke, the
    pixel coloured by its verdict (a grey circle: not measured, no verdict) and its distance with its unit
    written beside the strokes."""
    mask = np.zeros(img.shape[:2], np.uint8)
    for i, c in enumerate(checks):
        pred = c.predicted_curve if c.predicted_curve is not None and len(c.predicted_curve) > 1 else (
            (predicted or {}).get(i))
        for pts, colour, thick in ((pred, CYAN, 1), (c.detected_curve, ORANGE, 2)):
            _poly(img, pts, s, colour, thick)
            _poly(mask, pts, s, 1, thick + 6)
    for c in checks:
        ok = check_passes(c, threshold_px, worst_factor)
        px, py = (int(round(v * s)) for v in c.pixel)
        colour = NOT_MEASURED if not c.ok else PASS if ok else RED
        if c.ok:
            cv2.drawMarker(img, (px, py), colour, cv2.MARKER_CROSS, 14, 2)
        else:
            cv2.circle(img, (px, py), 6, colour, 2, cv2.LINE_AA)
        label = check_label(c, ok)
        (tw, th), _ = cv2.getTextSize(label, FONT, 0.35, 1)
        x, y = _label_spot(mask, px, py, tw, th)
        cv2.rectangle(img, (x - 2, y - th - 3), (x + tw + 2, y + 3), (0, 0, 0), -1)
        cv2.putText(img, label, (x, y), FONT, 0.35, colour, 1, cv2.LINE_AA)
        cv2.rectangle(mask, (x - 2, y - th - 3), (x + tw + 2, y + 3), 1, -1)  # the next label avoids this one


def draw_suggestion(img: np.ndarray, suggestion) -> None:
    """The dashed box where to hold the board next, labelled on a dark band just below it (above it when
    the box reaches the bottom of the image)."""
    if suggestion is None:
        return
    dashed_rect(img, suggestion.rect, (255, 255, 255))
    h, w = img.shape[:2]
    label = "hold the board here next" + (f", tilted {suggestion.tilt_deg:.0f} deg" if suggestion.tilt_deg else "")
    (tw, th), _ = cv2.getTextSize(label, FONT, 0.4, 1)
    x = min(max(int(suggestion.rect[0] * (w - 1)), 0), w - tw - 6)
    y = int(suggestion.rect[3] * (h - 1)) + th + 8
    if y > h - 4:
        y = int(suggestion.rect[1] * (h - 1)) - 8
    cv2.rectangle(img, (x, y - th - 4), (x + tw + 6, y + 4), (0, 0, 0), -1)
    cv2.putText(img, label, (x + 3, y), FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


def draw_asked_outline(img: np.ndarray, asked) -> None:
    """The asked pose's board outline (app/station/asked.AskedTarget.outline, fractions of the camera
    image), dashed in white, labelled on a dark band beside its top-left corner."""
    if asked is None:
        return
    h, w = img.shape[:2]
    pts = np.asarray(asked.outline, float) * np.array([w, h]) - 0.5  # pixel centres of the drawn image
    if not np.isfinite(pts).all():
        return
    dashed_polygon(img, pts, (255, 255, 255))
    label = "hold the board on this outline"
    (tw, th), _ = cv2.getTextSize(label, FONT, 0.4, 1)
    x = int(min(max(pts[:, 0].min(), 0), w - tw - 6))
    y = int(pts[:, 1].min()) - 8
    if y < th + 4:
        y = int(min(pts[:, 1].max() + th + 8, h - 4))
    cv2.rectangle(img, (x, y - th - 4), (x + tw + 6, y + 4), (0, 0, 0), -1)
    cv2.putText(img, label, (x + 3, y), FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


def flash(img: np.ndarray) -> None:
    cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), GREEN, 4)


# ---- clicking on the camera image in the 3D view ---------------------------------------------------------
def image_plane(camera, depth_m: float):
    """Where the camera image is laid in the 3D view (camera frame, metres): a plane at `depth_m` in front
    of the camera that its pixels map onto. Returns (centre (3,), width_m, height_m, wxyz)."""
    W, H = camera.size
    cx, cy, fx, fy = camera.cx, camera.cy, camera.fx, camera.fy
    centre = np.array([((W - 1) / 2 - cx) / fx * depth_m, ((H - 1) / 2 - cy) / fy * depth_m, depth_m])
    # a scene image lies in its local x-y plane, its first row towards local -y and first column towards
    # -x: unrotated in the camera frame (y down) it reads as the camera sees it (checked in Chromium)
    return centre, W / fx * depth_m, H / fy * depth_m, (1.0, 0.0, 0.0, 0.0)


def pixel_of_click(camera, depth_m: float, ray_origin, ray_direction) -> tuple[float, float] | None:
    """The camera pixel a click on the image plane points at (None when the ray misses the plane or the
    pixel is outside the image)."""
    o = np.asarray(ray_origin, float)
    d = np.asarray(ray_direction, float)
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))) or abs(d[2]) < 1e-9:
        return None
    t = (depth_m - o[2]) / d[2]
    if t <= 0:
        return None
    p = o + t * d
    u = camera.fx * p[0] / depth_m + camera.cx
    v = camera.fy * p[1] / depth_m + camera.cy
    W, H = camera.size
    if not (-0.5 <= u <= W - 0.5 and -0.5 <= v <= H - 0.5):
        return None
    return float(u), float(v)


def predicted_curves(result, checks, image, board) -> dict:
    """Predicted camera curves of checks that carry none, from the calibration and the board's pose in
    `image` (found with the session's board): {check index: (M, 2) camera px}. Empty when the board is not
    found in the image."""
    missing = [i for i, c in enumerate(checks) if c.predicted_curve is None or len(c.predicted_curve) < 2]
    if not missing or image is None or board is None:
        return {}
    from app.verification import estimate_board_pose
    from calib.epipolar import predicted_camera_curve

    try:
        T = estimate_board_pose(image, board, result)
    except Exception:  # a frame the board detection cannot use: no predicted curves, the rest is drawn
        return {}
    if T is None:
        return {}
    out = {}
    for i in missing:
        try:
            curve = predicted_camera_curve(result, checks[i].pixel, T)
        except Exception:
            continue
        if len(curve) > 1:
            out[i] = curve
    return out
