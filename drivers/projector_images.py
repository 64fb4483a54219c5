"""Images the projector shows, as pure numpy functions (no display needed).

The projector window, the simulated rig and the station all build their projector images here, so a
simulated session shows exactly what the real projector would.

Conventions (docs/CONVENTIONS.md): images are (H, W) uint8 grey or (H, W, 3) uint8 BGR, row 0 at the
top; projector pixel (0, 0) is the centre of the top-left pixel, so a W-wide image spans x in
[-0.5, W - 0.5].
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from calib.errors import SpecError
from calib.models.pattern import PatternSpec
from calib.models.structured_light import StructuredLightSpec

Size = tuple[int, int]  # (width, height)


def _check_size(size: Size) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        raise SpecError(f"image size must be (width, height), got {size!r}") from None
    if w <= 0 or h <= 0:
        raise SpecError(f"image size must be positive, got {w}x{h}")
    return w, h


def _fill_value(value) -> tuple[int, ...]:
    v = np.atleast_1d(np.asarray(value))
    if v.size not in (1, 3) or np.any(v < 0) or np.any(v > 255):
        raise SpecError(f"a pixel value is one grey level or three BGR levels in 0..255, got {value!r}")
    return tuple(int(round(float(x))) for x in v)


def solid(size: Size, value=0) -> np.ndarray:
    """A uniform image: grey (H, W) for a scalar value, BGR (H, W, 3) for a 3-tuple."""
    w, h = _check_size(size)
    v = _fill_value(value)
    if len(v) == 1:
        return np.full((h, w), v[0], np.uint8)
    img = np.empty((h, w, 3), np.uint8)
    img[...] = v
    return img


def black(size: Size) -> np.ndarray:
    return solid(size, 0)


def white(size: Size) -> np.ndarray:
    return solid(size, 255)


def pattern_image(spec: PatternSpec, size: Size, position: int) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W) uint8, points (N, 2)) of `spec` at pattern position `position` (0-based):
    calib.models.pattern.PatternSpec.render, so detection and display agree on every point."""
    w, h = _check_size(size)
    return spec.render(w, h, position)


def pattern_images(spec: PatternSpec, size: Size) -> list[np.ndarray]:
    """The images of all `spec.positions` positions, in order."""
    return [pattern_image(spec, size, k)[0] for k in range(spec.positions)]


def structured_light_images(spec: StructuredLightSpec, size: Size) -> list[np.ndarray]:
    """The frames of a structured-light sequence (calib.models.structured_light), in display order."""
    w, h = _check_size(size)
    return spec.images(w, h)


def checkerboard(size: Size, cell_px: int = 1, phase: int = 0) -> np.ndarray:
    """A black/white checkerboard of `cell_px` square cells (cell_px=1: alternate pixels), the top-left
    cell white when `phase` is 0. Fine structure for checking that nothing scales or filters."""
    w, h = _check_size(size)
    if cell_px < 1:
        raise SpecError(f"cell_px must be >= 1, got {cell_px}")
    yy, xx = np.mgrid[0:h, 0:w]
    return np.where(((yy // cell_px + xx // cell_px + phase) % 2) == 0, 255, 0).astype(np.uint8)


# ---- polylines ----------------------------------------------------------------------------------

def _split_at_nan(points: np.ndarray) -> list[np.ndarray]:
    """Pieces of a polyline between NaN rows (a curve leaving the image is given as NaN points)."""
    ok = np.isfinite(points).all(axis=1)
    pieces, start = [], None
    for i, good in enumerate(ok):
        if good and start is None:
            start = i
        elif not good and start is not None:
            pieces.append(points[start:i])
            start = None
    if start is not None:
        pieces.append(points[start:])
    return pieces


def _segment_distance(px: np.ndarray, py: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance of points (px, py) to the closed segment a-b (a point when a == b)."""
    d = b - a
    L2 = float(d @ d)
    if L2 == 0.0:
        return np.hypot(px - a[0], py - a[1])
    t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / L2, 0.0, 1.0)
    return np.hypot(px - (a[0] + t * d[0]), py - (a[1] + t * d[1]))


def polyline_coverage(size: Size, polylines: Iterable[np.ndarray], thickness_px: float,
                      antialias: bool = False, supersample: int = 4) -> np.ndarray:
    """(H, W) float coverage in [0, 1] of the stroke of `polylines`.

    The stroke of a polyline is the set of points within `thickness_px / 2` of any of its segments
    (round caps and joins). Without anti-aliasing a pixel is covered (1.0) exactly when its centre
    lies in the stroke (distance <= thickness_px / 2); with anti-aliasing its coverage is the fraction
    of `supersample` x `supersample` sample points, placed symmetrically about the pixel centre, that
    lie in the stroke. Polylines are (N, 2) arrays of pixel coordinates; NaN rows split them."""
    w, h = _check_size(size)
    if not thickness_px > 0:
        raise SpecError(f"line thickness must be > 0 px, got {thickness_px}")
    n = int(supersample) if antialias else 1
    if n < 1:
        raise SpecError(f"supersample must be >= 1, got {supersample}")
    sub = (np.arange(n) + 0.5) / n - 0.5  # sample offsets from the pixel centre
    half = thickness_px / 2.0
    cover = np.zeros((h, w), np.float64)
    for line in polylines:
        pts = np.asarray(line, float).reshape(-1, 2)
        for piece in _split_at_nan(pts):
            segs = [(piece[0], piece[0])] if len(piece) == 1 else list(zip(piece[:-1], piece[1:]))
            for a, b in segs:
                x0 = max(int(np.floor(min(a[0], b[0]) - half)) - 1, 0)
                x1 = min(int(np.ceil(max(a[0], b[0]) + half)) + 2, w)
                y0 = max(int(np.floor(min(a[1], b[1]) - half)) - 1, 0)
                y1 = min(int(np.ceil(max(a[1], b[1]) + half)) + 2, h)
                if x0 >= x1 or y0 >= y1:
                    continue
                xs = (np.arange(x0, x1)[:, None] + sub[None, :]).ravel()
                ys = (np.arange(y0, y1)[:, None] + sub[None, :]).ravel()
                inside = _segment_distance(xs[None, :], ys[:, None], a, b) <= half
                c = inside.reshape(y1 - y0, n, x1 - x0, n).mean(axis=(1, 3))
                np.maximum(cover[y0:y1, x0:x1], c, out=cover[y0:y1, x0:x1])
    return cover


def draw_polylines(size: Size, polylines: Sequence[np.ndarray], thickness_px: float = 3.0, value=255,
                   antialias: bool = False, background: np.ndarray | None = None,
                   supersample: int = 4) -> np.ndarray:
    """Draw `polylines` (e.g. epipolar lines or curves) onto a black image (or a copy of `background`).

    Each pixel becomes `round(coverage * value + (1 - coverage) * background)` with the coverage of
    `polyline_coverage`: without anti-aliasing exactly the pixels whose centres lie within
    thickness_px / 2 of a polyline get `value` and all others keep the background. `value` is a grey
    level, or a BGR triple (the result is then BGR)."""
    w, h = _check_size(size)
    v = np.array(_fill_value(value), float)
    if background is None:
        base = np.zeros((h, w) if v.size == 1 else (h, w, 3), np.uint8)
    else:
        base = np.asarray(background)
        if base.dtype != np.uint8 or base.shape[:2] != (h, w):
            raise SpecError(f"background must be a uint8 image of {w}x{h}, got {base.dtype} {base.shape}")
        if v.size == 3 and base.ndim == 2:
            base = np.repeat(base[:, :, None], 3, axis=2)
    cover = polyline_coverage((w, h), polylines, thickness_px, antialias, supersample)
    if base.ndim == 3:
        cover = cover[:, :, None]
        if v.size == 1:
            v = np.repeat(v, 3)
    else:
        v = v[0]
    out = np.round(cover * v + (1.0 - cover) * base.astype(float))
    return np.clip(out, 0, 255).astype(np.uint8)


def line_polyline(line_abc, size: Size) -> np.ndarray:
    """The visible part of the straight line a x + b y + c = 0 (e.g. an epipolar line l = F x) as a
    2-point polyline clipped to the image rectangle [-0.5, W-0.5] x [-0.5, H-0.5]; (0, 2) if it misses."""
    w, h = _check_size(size)
    a, b, c = (float(v) for v in np.asarray(line_abc, float).reshape(3))
    if a == 0.0 and b == 0.0:
        raise SpecError("a line needs a or b non-zero")
    x_lo, x_hi, y_lo, y_hi = -0.5, w - 0.5, -0.5, h - 0.5
    pts = []
    if b != 0.0:
        for x in (x_lo, x_hi):
            y = -(a * x + c) / b
            if y_lo - 1e-9 <= y <= y_hi + 1e-9:
                pts.append((x, y))
    if a != 0.0:
        for y in (y_lo, y_hi):
            x = -(b * y + c) / a
            if x_lo - 1e-9 <= x <= x_hi + 1e-9:
                pts.append((x, y))
    if not pts:
        return np.zeros((0, 2))
    pts = np.unique(np.round(np.array(pts), 12), axis=0)
    if len(pts) == 1:
        return pts
    # the two extreme points along the line's direction
    d = np.array([b, -a])
    s = pts @ d
    return np.array([pts[np.argmin(s)], pts[np.argmax(s)]])


def draw_lines(size: Size, lines_abc: Iterable, thickness_px: float = 3.0, value=255,
               antialias: bool = False, background: np.ndarray | None = None) -> np.ndarray:
    """Draw straight lines given as (a, b, c) with a x + b y + c = 0 (pixel coordinates)."""
    polys = [line_polyline(l, size) for l in lines_abc]
    return draw_polylines(size, [p for p in polys if len(p)], thickness_px, value, antialias, background)
