"""Guidance towards a good calibration, for the panel: where the board corners of the captures landed in
the camera image (a coverage map), where the pattern points landed in the projector image, which
diversity targets are not met yet, and where to hold the board next (the region of the camera image
that would fill the coverage map best, with a suggested tilt).

Pure computation on the session's captures (their `board_px` and `pose` metadata, written by the
station when it takes a capture); the drawing returns RGB images.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from app.station.autocapture import Bar
from calib.quality.coverage import cell_counts
from calib.models.vocab import PatternKind

MAP_WIDTH = 300  # pixels of each of the two coverage maps


@dataclass(frozen=True)
class Suggestion:
    """Where to hold the board next: a rectangle in fractions of the camera image, and words."""

    rect: tuple[float, float, float, float]  # x0, y0, x1, y1 (0..1)
    tilt_deg: float | None  # a tilt to aim for, None when the tilt target is met
    text: str


def capture_corners_px(captures) -> list[np.ndarray]:
    """The board corners (camera pixels) each capture recorded, (N, 2) arrays."""
    out = []
    for c in captures:
        px = c.meta.get("board_px") if isinstance(c.meta, dict) else None
        if px is None:
            continue
        try:
            a = np.asarray(px, float).reshape(-1, 2)
        except (TypeError, ValueError):
            continue
        a = a[np.all(np.isfinite(a), axis=1)]
        if len(a):
            out.append(a)
    return out


def coverage_grid(corner_sets, camera_size) -> np.ndarray:
    """Corners per cell of the coverage grid (calib.quality.coverage), (rows, cols) counts."""
    pts = np.concatenate(corner_sets) if corner_sets else np.zeros((0, 2))
    return cell_counts(pts, *camera_size)


def coverage_summary(counts: np.ndarray) -> str:
    """Fraction of the camera image covered and how many of its four corner regions have corners."""
    covered = float((counts > 0).mean())
    gy, gx = counts.shape
    qy, qx = max(1, gy // 4), max(1, gx // 4)
    corners = [counts[:qy, :qx], counts[:qy, -qx:], counts[-qy:, :qx], counts[-qy:, -qx:]]
    n = sum(int(c.sum() > 0) for c in corners)
    return (f"coverage **{covered * 100:.0f}%** (board corners); **{n} of 4** image corners "
            "reached (they alone constrain the higher distortion terms)")


def suggest_next(counts: np.ndarray, features, bars: list[Bar]) -> Suggestion:
    """The board-sized window of the coverage grid with the fewest corners so far (ties: nearer the
    image's edges, which constrain distortion most), and a tilt beyond the ones captured when the tilt
    target is not met."""
    gy, gx = counts.shape
    sizes = [f.size for f in features] if features else []
    size = float(np.median(sizes)) if sizes else 0.35  # sqrt of the image fraction the board covers
    ww = int(np.clip(round(size * gx * 1.1), 3, gx))
    wh = int(np.clip(round(size * gy * 1.1), 2, gy))
    occupied = (counts > 0).astype(float)
    best, best_score = (0, 0), None
    for y in range(0, gy - wh + 1):
        for x in range(0, gx - ww + 1):
            filled = occupied[y:y + wh, x:x + ww].mean()
            cxn = (x + ww / 2) / gx - 0.5
            cyn = (y + wh / 2) / gy - 0.5
            score = filled - 0.15 * (abs(cxn) + abs(cyn))  # prefer the edges when equally empty
            if best_score is None or score < best_score:
                best, best_score = (x, y), score
    x, y = best
    rect = (x / gx, y / gy, (x + ww) / gx, (y + wh) / gy)
    horiz = "left" if rect[0] + rect[2] < 0.9 else ("right" if rect[0] + rect[2] > 1.1 else "middle")
    vert = "top" if rect[1] + rect[3] < 0.9 else ("bottom" if rect[1] + rect[3] > 1.1 else "middle")
    where = "the middle" if horiz == vert == "middle" else (
        f"the {vert} {horiz}" if "middle" not in (horiz, vert) else f"the {vert if horiz == 'middle' else horiz}")
    tilt_bar = next((b for b in bars if b.name == "tilt"), None)
    tilt = None
    if tilt_bar is not None and not tilt_bar.met:
        tilts = [f.tilt_deg for f in features] if features else []
        lo, hi = (min(tilts), max(tilts)) if tilts else (0.0, 0.0)
        # widen the range on the side with more room (0 to 60 deg from facing the camera)
        tilt = float(min(60.0, max(hi + 15.0, 30.0))) if 60.0 - hi >= lo else float(max(0.0, lo - 15.0))
    text = f"Hold the board next towards {where} of the camera image (dashed box)"
    text += f", tilted about {tilt:.0f} deg from facing the camera" if tilt is not None else ""
    return Suggestion(rect, tilt, text + ".")


def unmet_targets(bars: list[Bar]) -> list[str]:
    """The diversity targets not met yet, in words (for the note under the Calibrate button)."""
    return [f"{b.name} spans {b.detail}, the target is a range of {b.target} ({b.fraction * 100:.0f}% there)"
            for b in bars if not b.met]


def _map_canvas(size, width=MAP_WIDTH) -> tuple[np.ndarray, float]:
    W, H = size
    s = width / W
    return np.full((int(round(H * s)), width, 3), 38, np.uint8), s


def camera_coverage_image(corner_sets, camera_size, counts: np.ndarray, suggestion: Suggestion | None) -> np.ndarray:
    """The camera image's coverage map (BGR): cells with corners shaded green by count, every corner a
    dot, the suggested region dashed in white."""
    img, s = _map_canvas(camera_size)
    h, w = img.shape[:2]
    gy, gx = counts.shape
    peak = max(1, int(counts.max()))
    for y in range(gy):
        for x in range(gx):
            if counts[y, x] > 0:
                a = 0.25 + 0.6 * counts[y, x] / peak
                p0 = (int(x * w / gx), int(y * h / gy))
                p1 = (int((x + 1) * w / gx) - 1, int((y + 1) * h / gy) - 1)
                cv2.rectangle(img, p0, p1, (int(38 + a * 40), int(38 + a * 150), int(38 + a * 40)), -1)
    for a in corner_sets:
        for x, y in np.round(a * s).astype(int):
            if 0 <= x < w and 0 <= y < h:
                img[y, x] = (120, 255, 120)
    if suggestion is not None:
        dashed_rect(img, suggestion.rect, (255, 255, 255))
    cv2.putText(img, "camera: board corners", (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (230, 230, 230), 1, cv2.LINE_AA)
    return img


def projector_coverage_image(pattern, projector_size, counts_per_position, poses_per_position: int,
                             current: int | None, chosen_area=None) -> np.ndarray:
    """The projector image's coverage map (BGR): the pattern points of every captured position as dots,
    each position's area green when complete, orange when started; the position shown now outlined; the
    area a next-best placement was chosen for (x0, y0, x1, y1 projector pixels) dashed in white."""
    img, s = _map_canvas(projector_size)
    W, H = projector_size
    pad = pattern.radius_px if pattern.kind == PatternKind.CIRCLES else pattern.spacing_px
    for p in range(pattern.positions):
        pts = pattern.points_px(W, H, p)
        p0 = tuple(int(v) for v in (pts.min(axis=0) - pad) * s)
        p1 = tuple(int(v) for v in (pts.max(axis=0) + pad) * s)
        n = counts_per_position[p] if p < len(counts_per_position) else 0
        if n > 0:
            over = img.copy()
            cv2.rectangle(over, p0, p1, (90, 190, 60) if n >= poses_per_position else (40, 150, 240), -1)
            img = cv2.addWeighted(over, 0.45, img, 0.55, 0)
            for x, y in np.round(pts * s).astype(int):
                cv2.circle(img, (int(x), int(y)), 1, (240, 240, 240), -1)
        cv2.rectangle(img, p0, p1, (120, 120, 120), 1)
        cv2.putText(img, str(p + 1), (p0[0] + 2, p0[1] + 10), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (220, 220, 220), 1,
                    cv2.LINE_AA)
        if current == p:
            cv2.rectangle(img, p0, p1, (255, 255, 255), 2)
    if chosen_area is not None:
        x0, y0, x1, y1 = chosen_area
        dashed_rect(img, ((x0 + 0.5) / W, (y0 + 0.5) / H, (x1 + 0.5) / W, (y1 + 0.5) / H), (255, 255, 255))
    cv2.putText(img, "projector: pattern points", (4, img.shape[0] - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                (230, 230, 230), 1, cv2.LINE_AA)
    return img


def side_by_side(a: np.ndarray, b: np.ndarray, gap: int = 8) -> np.ndarray:
    """Two BGR maps next to each other, top-aligned (RGB out, for the panel)."""
    h = max(a.shape[0], b.shape[0])
    out = np.full((h, a.shape[1] + gap + b.shape[1], 3), 255, np.uint8)
    out[:a.shape[0], :a.shape[1]] = a
    out[:b.shape[0], a.shape[1] + gap:] = b
    return out[:, :, ::-1].copy()


def dashed_rect(img: np.ndarray, rect, colour, dash: int = 8, thickness: int = 2) -> None:
    """A dashed rectangle over `img` at `rect` (fractions of the image)."""
    h, w = img.shape[:2]
    x0, y0, x1, y1 = int(rect[0] * (w - 1)), int(rect[1] * (h - 1)), int(rect[2] * (w - 1)), int(rect[3] * (h - 1))
    dashed_polygon(img, [(x0, y0), (x1, y0), (x1, y1), (x0, y1)], colour, dash, thickness)


def dashed_polygon(img: np.ndarray, points, colour, dash: int = 8, thickness: int = 2) -> None:
    """A closed dashed polygon over `img` through `points` (pixels of `img`)."""
    pts = [(float(x), float(y)) for x, y in points]
    for (ax, ay), (bx, by) in zip(pts, pts[1:] + pts[:1]):
        n = max(1, int(np.hypot(bx - ax, by - ay) // dash))
        for i in range(0, n, 2):
            p = (int(ax + (bx - ax) * i / n), int(ay + (by - ay) * i / n))
            q = (int(ax + (bx - ax) * min(i + 1, n) / n), int(ay + (by - ay) * min(i + 1, n) / n))
            cv2.line(img, p, q, colour, thickness, cv2.LINE_AA)
