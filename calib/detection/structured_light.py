"""Decoding a structured-light sequence: per camera pixel, the projector column and row it sees.

Input: the camera images of calib.models.structured_light.StructuredLightSpec.frames, in that order,
taken while nothing moved. Output: a DecodedMap with the projector coordinates (pixel (0, 0) the centre
of the top-left pixel) of every camera pixel, and why each rejected pixel was rejected.

Per pixel, vectorised over the image:
  1. lit = white - black (the projector's contribution; ambient light cancels);
  2. every Gray-code bit = pattern > inverse (no threshold: a pixel on a stripe's edge reads either
     neighbour, an error of one stripe that the phase corrects), decoded to a stripe index;
  3. with phase shifting, the phase of the N sinusoids, phi = atan2(sum I_k sin(2 pi k / N),
     sum I_k cos(2 pi k / N)), gives x mod period; the Gray stripe (half a period wide) gives a coarse
     x to within half a stripe plus blur, and the period whose position is nearest it is taken;
     without phase shifting x is the centre of the stripe;
  4. validity, first failing rule named (Invalid): SATURATED (white frame at the top of the range: the
     difference carries no information), UNLIT (lit below `min_contrast`: outside the projection, in
     shadow, the background), DARK_PRINT (lit below `dark_fraction` of the brightest lit board surface:
     the board's black squares and markers, whose low albedo leaves a weak, blur-contaminated signal),
     EDGE (next to a pixel rejected so far: blur mixes in the light of the neighbouring surface, which
     saw another projector position, and biases the coordinate by up to half a pixel's footprint),
     LOW_MODULATION (the sinusoids' amplitude below `min_modulation` of lit: stripes blurred away, or a
     pixel straddling an edge of the board), INCONSISTENT (a coordinate more than `max_jump_px` from the
     median of its valid 3 x 3 neighbours: a wrongly unwrapped period, a reflection, a wrong bit).

Entry point: `decode_sequence(images, spec, projector_size) -> DecodedMap`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np

from calib.detection.response import CameraResponse
from calib.errors import SpecError
from calib.models.structured_light import Axis, FrameRole, StructuredLightSpec, gray_decode

#: a white frame at or above this 8-bit level is saturated
SATURATED_LEVEL = 250
#: lit below this (8-bit levels of the camera's output) is not lit by the projector
MIN_CONTRAST = 10.0
#: lit below this fraction of the brightest lit surface (its 99th percentile) is the board's black print
DARK_FRACTION = 0.4
#: sinusoid amplitude below this fraction of lit (half of it for a perfect sinusoid) has lost its stripes
MIN_MODULATION = 0.15


class Invalid(enum.IntEnum):
    """Why a pixel has no projector coordinate (VALID: it has one). The first failing rule is kept."""

    VALID = 0
    SATURATED = 1
    UNLIT = 2
    DARK_PRINT = 3
    EDGE = 4
    LOW_MODULATION = 5
    INCONSISTENT = 6


@dataclass(frozen=True, eq=False)
class DecodedMap:
    """Per camera pixel (H, W): projector x and y (float32, NaN where invalid), `reason` (Invalid codes,
    uint8), `lit` (white - black, the camera levels the projector adds) and the phase modulation (its
    amplitude as a fraction of lit; zeros without phase shifting). `counts`: pixels per reason."""

    proj_x: np.ndarray
    proj_y: np.ndarray
    reason: np.ndarray
    lit: np.ndarray
    modulation: np.ndarray
    projector_size: tuple[int, int]
    counts: MappingProxyType

    @property
    def valid(self) -> np.ndarray:
        return self.reason == Invalid.VALID

    @property
    def shape(self) -> tuple[int, int]:
        return self.reason.shape


def decode_sequence(images, spec: StructuredLightSpec, projector_size: tuple[int, int], *,
                    response: CameraResponse | None = None, min_contrast: float = MIN_CONTRAST,
                    dark_fraction: float = DARK_FRACTION, min_modulation: float = MIN_MODULATION,
                    max_jump_px: float | None = None) -> DecodedMap:
    """Decode the camera images of `spec`'s sequence for a projector of `projector_size` (W, H).

    `response`: the camera's recorded tone curve; the sinusoids are then read in linear light (a tone
    curve bends a sinusoid and biases its phase; the Gray bits and the validity levels are read on the
    camera's own levels either way). `max_jump_px` (default: half a period, 16 px without phase
    shifting): the neighbour-consistency limit in projector pixels."""
    pw, ph = (int(v) for v in projector_size)
    frames = spec.frames(pw, ph)
    images = list(images)
    if len(images) != len(frames):
        raise SpecError(f"a structured-light sequence for a {pw}x{ph} projector has {len(frames)} frames "
                        f"({spec.to_dict()}), got {len(images)}: a frame is missing or the sequence is another one")
    shapes = {np.asarray(im).shape[:2] for im in images}
    if len(shapes) != 1:
        raise SpecError(f"structured-light frames differ in size: {sorted(shapes)}")
    gray = [_gray8(im) for im in images]
    raw = [g.astype(np.float32) for g in gray]
    lut = response.lut().astype(np.float32) if response is not None and not response.linear else None
    white, black = raw[0], raw[1]
    lit = white - black
    lit_linear = lut[gray[0]] - lut[gray[1]] if lut is not None else lit
    H, W = white.shape
    coords = {}
    modulation = np.zeros((H, W), np.float32)
    amp_min = np.full((H, W), np.inf, np.float32)
    for axis, extent in ((Axis.COLUMNS, pw), (Axis.ROWS, ph)):
        idx = {(f.role, f.index): i for i, f in enumerate(frames) if f.axis is axis}
        n = spec.n_bits(extent)
        code = np.zeros((H, W), np.int64)
        for b in range(n):
            bit = raw[idx[(FrameRole.GRAY, b)]] > raw[idx[(FrameRole.GRAY_INVERSE, b)]]
            code = (code << 1) | bit
        stripe = gray_decode(code)
        cell = spec.cell_px
        coarse = (stripe * cell + (cell - 1) / 2.0).astype(np.float32)
        if not spec.phase_shifting:
            coords[axis] = coarse
            continue
        N, P = spec.phase_steps, spec.period_px
        ang = 2 * np.pi * np.arange(N) / N
        S = np.zeros((H, W), np.float32)
        C = np.zeros((H, W), np.float32)
        for k in range(N):
            i = idx[(FrameRole.PHASE, k)]
            im = lut[gray[i]] if lut is not None else raw[i]
            S += np.float32(np.sin(ang[k])) * im
            C += np.float32(np.cos(ang[k])) * im
        amp = (2.0 / N) * np.hypot(S, C)
        phase_x = (np.arctan2(S, C) * np.float32(P / (2 * np.pi))) % np.float32(P)
        periods = np.round((coarse - phase_x) / np.float32(P))
        coords[axis] = (phase_x + periods * np.float32(P)).astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where(lit_linear > 0, amp / lit_linear, 0.0).astype(np.float32)
        amp_min = np.minimum(amp_min, m)
    if spec.phase_shifting:
        modulation = amp_min

    reason = np.zeros((H, W), np.uint8)

    def mark(mask, why):
        np.copyto(reason, np.uint8(why), where=mask & (reason == 0))

    mark(white >= SATURATED_LEVEL, Invalid.SATURATED)
    mark(lit < min_contrast, Invalid.UNLIT)
    lit_ok = lit[reason == 0]
    if lit_ok.size:
        bright = float(np.percentile(lit_ok, 99))
        mark(lit < dark_fraction * bright, Invalid.DARK_PRINT)
    # next to a rejected surface, the optics' blur mixes in a neighbour's light from another projector
    # position, weighted by its albedo: a bias of up to half a pixel's footprint
    dark = (reason != 0).astype(np.uint8)
    mark(cv2.dilate(dark, np.ones((3, 3), np.uint8)) > 0, Invalid.EDGE)
    if spec.phase_shifting:
        mark(modulation < min_modulation, Invalid.LOW_MODULATION)
    jump = float(max_jump_px) if max_jump_px is not None else (spec.period_px / 2.0 if spec.phase_shifting else 16.0)
    x, y = coords[Axis.COLUMNS], coords[Axis.ROWS]
    for c in (x, y):
        med = _valid_median3(c, reason == 0)
        mark(np.abs(c - med) > jump, Invalid.INCONSISTENT)
    # a coordinate off the projector's image is a wrong code (e.g. a stripe index past the last stripe)
    mark((x < -0.5) | (x > pw - 0.5) | (y < -0.5) | (y > ph - 0.5), Invalid.INCONSISTENT)
    ok = reason == 0
    x = np.where(ok, x, np.float32(np.nan)).astype(np.float32)
    y = np.where(ok, y, np.float32(np.nan)).astype(np.float32)
    counts = {r.name.lower(): int(np.count_nonzero(reason == r)) for r in Invalid}
    for a in (x, y, reason, lit, modulation):
        a.setflags(write=False)
    return DecodedMap(x, y, reason, lit, modulation, (pw, ph), MappingProxyType(counts))


def _gray8(img) -> np.ndarray:
    a = np.asarray(img)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise SpecError(f"structured-light frames must be 8-bit grey or BGR images, got {a.dtype} {a.shape}")
    if a.ndim == 3:
        return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) if a.shape[2] == 3 else np.ascontiguousarray(a[:, :, 0])
    return a


def _valid_median3(c: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Median of each pixel's valid 3 x 3 neighbourhood (itself included); the pixel's own value where it
    has no valid neighbour. Invalid neighbours are NaN and ignored."""
    out = c.astype(np.float32).copy()
    ys, xs = np.nonzero(ok)
    if not len(ys):
        return out
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    v = np.where(ok[y0:y1, x0:x1], c[y0:y1, x0:x1], np.nan).astype(np.float32)
    p = np.pad(v, 1, constant_values=np.nan)
    H, W = v.shape
    stack = np.stack([p[i : i + H, j : j + W] for i in range(3) for j in range(3)])
    # an all-NaN neighbourhood keeps the pixel's own value; filled first, since nanmedian warns about it
    # (and silencing warnings is not thread-safe: captures are decoded in detection threads)
    has = np.isfinite(stack).any(axis=0)
    stack[:, ~has] = 0.0
    med = np.nanmedian(stack, axis=0)
    out[y0:y1, x0:x1] = np.where(has, med, out[y0:y1, x0:x1])
    return out
