"""The pattern the projector shows: an asymmetric circle grid (default 4x9) or a chessboard, shifted
over several positions (default 13) that cover the projector's whole image, corners included.

All coordinates are projector pixels with (0, 0) the centre of the top-left pixel. Point order is the
order OpenCV's findCirclesGrid / findChessboardCorners report them in an unmirrored view.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.errors import FormatError, SpecError
from calib.models.vocab import PatternKind, choices

KINDS = choices(PatternKind)
#: bounds of a pattern's values: its spacing from a pixel to the largest image side a file may state
#: (calib.models.camera.MAX_IMAGE_SIDE), far more points and positions than any projector shows
SPACING_PX_RANGE = (1.0, 65536.0)
MAX_POINTS_PER_SIDE = 100
MAX_POSITIONS = 1000


@dataclass(frozen=True)
class PatternSpec:
    """`cols` x `rows` as OpenCV's patternSize. Circles: asymmetric grid, point (i row, j col) at
    ((2 j + i % 2) * spacing_px, i * spacing_px), radius `radius_px`. Chessboard: inner corners, squares
    of side `spacing_px`, with a white quiet zone of one square around them."""

    kind: str = PatternKind.CIRCLES
    cols: int = 4
    rows: int = 9
    spacing_px: float = 40.0
    radius_px: float = 12.0
    positions: int = 13
    margin_px: float = 8.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise SpecError(f"unknown pattern kind '{self.kind}' (one of {', '.join(KINDS)})")
        if not (2 <= self.cols <= MAX_POINTS_PER_SIDE and 2 <= self.rows <= MAX_POINTS_PER_SIDE):
            raise SpecError(f"pattern needs 2 to {MAX_POINTS_PER_SIDE} points a side, got {self.cols}x{self.rows}")
        lo, hi = SPACING_PX_RANGE
        if not lo <= self.spacing_px <= hi:
            raise SpecError(f"pattern spacing_px must be {lo:g} to {hi:g} px, got {self.spacing_px:g}")
        if not 1 <= self.positions <= MAX_POSITIONS:
            raise SpecError(f"pattern positions must be 1 to {MAX_POSITIONS}, got {self.positions}")
        if not 0 <= self.margin_px <= hi:
            raise SpecError(f"pattern margin_px must be 0 to {hi:g} px, got {self.margin_px:g}")
        if self.kind == PatternKind.CIRCLES and not (0 < self.radius_px < 0.7 * self.spacing_px):
            raise SpecError(
                f"circle radius {self.radius_px} px must be > 0 and < 0.7 x spacing ({self.spacing_px} px), "
                "or neighbouring circles merge"
            )

    @classmethod
    def default_for(cls, proj_width: int, proj_height: int, kind: str = PatternKind.CIRCLES, **kw) -> "PatternSpec":
        """A pattern about a third of the projector's height, as the paper's protocol uses."""
        if kind == PatternKind.CIRCLES:
            spacing = max(8.0, round(proj_height / 26.0))
            return cls(PatternKind.CIRCLES, kw.pop("cols", 4), kw.pop("rows", 9), spacing, round(spacing * 0.3, 1), **kw)
        spacing = max(8.0, round(proj_height / 16.0))
        return cls(PatternKind.CHESSBOARD, kw.pop("cols", 5), kw.pop("rows", 6), spacing, 0.0, **kw)

    @property
    def n_points(self) -> int:
        return self.cols * self.rows

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    def local_points(self) -> np.ndarray:
        """(N, 2) points relative to the pattern's first point, in detection order."""
        i, j = np.divmod(np.arange(self.n_points), self.cols)
        s = self.spacing_px
        if self.kind == PatternKind.CIRCLES:
            return np.column_stack([(2 * j + i % 2) * s, i * s]).astype(float)
        return np.column_stack([j * s, i * s]).astype(float)

    def extent_px(self) -> tuple[float, float]:
        """(width, height) of the drawn pattern including circles / quiet zone."""
        p = self.local_points()
        pad = self.radius_px if self.kind == PatternKind.CIRCLES else self.spacing_px * 2
        return (p[:, 0].max() + 2 * pad, p[:, 1].max() + 2 * pad)

    def _pad(self) -> float:
        return self.radius_px if self.kind == PatternKind.CIRCLES else 2 * self.spacing_px

    def offsets(self, proj_width: int, proj_height: int) -> np.ndarray:
        """(positions, 2) projector-pixel position of the first point for each pattern position.

        13 positions = a 3x3 grid (corners, edge middles, centre) plus the 4 centres between them; in
        general k x k plus (k-1) x (k-1) when `positions` has that form, else a near-square grid."""
        ew, eh = self.extent_px()
        free_w = proj_width - ew - 2 * self.margin_px
        free_h = proj_height - eh - 2 * self.margin_px
        if free_w < 0 or free_h < 0:
            raise SpecError(
                f"pattern of {ew:.0f}x{eh:.0f} px does not fit a {proj_width}x{proj_height} projector; "
                "reduce spacing_px"
            )
        fracs = _position_fractions(self.positions)
        first = self.margin_px + self._pad() - 0.5
        if self.kind == PatternKind.CHESSBOARD:
            first = self.margin_px + self._pad()
        xy = np.column_stack([first + fracs[:, 0] * free_w, first + fracs[:, 1] * free_h])
        if self.kind == PatternKind.CHESSBOARD:
            # corners on pixel boundaries so that the drawn squares need no anti-aliasing
            xy = np.round(xy) - 0.5
        return xy

    def points_px(self, proj_width: int, proj_height: int, position: int) -> np.ndarray:
        """(N, 2) projector pixels of the pattern points at `position` (0-based)."""
        if not 0 <= position < self.positions:
            raise SpecError(f"pattern position {position} out of range 0..{self.positions - 1}")
        return self.local_points() + self.offsets(proj_width, proj_height)[position]

    def render(self, proj_width: int, proj_height: int, position: int) -> tuple[np.ndarray, np.ndarray]:
        """(image (H, W) uint8, points (N, 2)): white pattern on black, anti-aliased so that every
        blob's intensity centroid is its circle's centre."""
        pts = self.points_px(proj_width, proj_height, position)
        if self.kind == PatternKind.CIRCLES:
            img = render_circles(proj_width, proj_height, pts, self.radius_px)
        else:
            img = _render_chessboard(proj_width, proj_height, pts[0], self.cols, self.rows, self.spacing_px)
        return img, pts

    def find(self, gray: np.ndarray) -> np.ndarray | None:
        """Run OpenCV's grid finder on an (unmirrored) grayscale image of the pattern as drawn (bright
        circles on dark); (N, 2) or None. Robust detection in camera images lives in calib.detection.detect."""
        if self.kind == PatternKind.CIRCLES:
            ok, pts = cv2.findCirclesGrid(255 - gray, self.pattern_size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
        else:
            ok, pts = cv2.findChessboardCorners(gray, self.pattern_size)
        return pts.reshape(-1, 2).astype(float) if ok else None

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("kind", "cols", "rows", "spacing_px", "radius_px", "positions", "margin_px")}

    @classmethod
    def from_dict(cls, d, where: str = "pattern", path="<dict>") -> "PatternSpec":
        if not isinstance(d, dict):
            raise FormatError(path, where, "must be an object")
        kw = {}
        for key, typ in (("kind", str), ("cols", int), ("rows", int), ("spacing_px", (int, float)),
                         ("radius_px", (int, float)), ("positions", int), ("margin_px", (int, float))):
            if key not in d:
                if key in ("margin_px",):
                    continue
                raise FormatError(path, f"{where}.{key}", "missing")
            if not isinstance(d[key], typ) or isinstance(d[key], bool):
                raise FormatError(path, f"{where}.{key}", f"has the wrong type ({type(d[key]).__name__})")
            kw[key] = d[key]
        try:
            return cls(**kw)
        except SpecError as e:
            raise FormatError(path, where, str(e)) from None


def _position_fractions(n: int) -> np.ndarray:
    k = 1
    while k * k + (k - 1) * (k - 1) < n:
        k += 1
    if n == 1:
        return np.array([[0.5, 0.5]])
    if k * k + (k - 1) * (k - 1) == n:
        g = np.linspace(0, 1, k)
        outer = [(x, y) for y in g for x in g]
        h = (g[:-1] + g[1:]) / 2
        inner = [(x, y) for y in h for x in h]
        # interleave so that consecutive positions are spread out: outer grid row by row, inner between
        return np.array(outer + inner, float)
    cols = int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    gx = np.linspace(0, 1, cols) if cols > 1 else np.array([0.5])
    gy = np.linspace(0, 1, rows) if rows > 1 else np.array([0.5])
    return np.array([(x, y) for y in gy for x in gx][:n], float)


def render_circles(width: int, height: int, centres: np.ndarray, radius_px: float, supersample: int = 8) -> np.ndarray:
    """White filled circles on black; coverage by `supersample`^2 samples per pixel, symmetric about
    each pixel centre, so the intensity centroid of each blob is its centre."""
    img = np.zeros((height, width), np.float32)
    n = supersample
    sub = (np.arange(n) + 0.5) / n - 0.5
    r2 = radius_px * radius_px
    R = int(np.ceil(radius_px + 1))
    for cx, cy in np.asarray(centres, float):
        x0, x1 = int(np.floor(cx)) - R, int(np.ceil(cx)) + R + 1
        y0, y1 = int(np.floor(cy)) - R, int(np.ceil(cy)) + R + 1
        xs = (np.arange(x0, x1)[:, None] + sub[None, :]).ravel() - cx
        ys = (np.arange(y0, y1)[:, None] + sub[None, :]).ravel() - cy
        inside = (ys[:, None] ** 2 + xs[None, :] ** 2) <= r2
        cover = inside.reshape(y1 - y0, n, x1 - x0, n).mean(axis=(1, 3))
        ya, yb, xa, xb = max(y0, 0), min(y1, height), max(x0, 0), min(x1, width)
        if ya < yb and xa < xb:
            img[ya:yb, xa:xb] = np.maximum(img[ya:yb, xa:xb], cover[ya - y0 : yb - y0, xa - x0 : xb - x0])
    return np.round(img * 255).astype(np.uint8)


def _render_chessboard(width, height, first_corner, cols, rows, s) -> np.ndarray:
    img = np.zeros((height, width), np.uint8)
    # squares: (cols + 1) x (rows + 1), quiet zone of one square around them (white)
    x0 = int(round(first_corner[0] + 0.5 - 2 * s))
    y0 = int(round(first_corner[1] + 0.5 - 2 * s))
    si = int(round(s))
    img[max(y0, 0) : y0 + (rows + 3) * si, max(x0, 0) : x0 + (cols + 3) * si] = 255
    for r in range(rows + 1):
        for c in range(cols + 1):
            if (r + c) % 2 == 0:
                ya, xa = y0 + (r + 1) * si, x0 + (c + 1) * si
                img[ya : ya + si, xa : xa + si] = 0
    return img
