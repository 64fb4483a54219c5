"""Detection of a projected curve (a bright stroke the projector draws on the board) in camera images.

Pure functions on numpy images; no device, no calibration. Used by the epipolar verification
(app/verification.py): the projector draws the epipolar curve of a camera pixel, the camera sees it
(through the mirror: nothing here cares about mirroring, all coordinates are in the ORIGINAL camera
image, pixel (0, 0) the centre of the top-left pixel), and the distance from the pixel to the detected
centre line is the measurement.

Method:
1. Signal: `on - off` (the frame with the curve minus the frame without it). With a third frame lit by
   a full-white projector image, the signal is normalised, s = (on - off) / (white - off): the fraction
   of the projector's full light each pixel receives. That removes the board's albedo (black squares,
   printed marks) and the projector's fall-off, which would otherwise skew the stripe's profile.
   Pixels the projector barely lights (white - off small) are invalid.
2. Threshold at max(min_contrast, 6 sigma) of the robust noise of s, drop small specks, and choose the
   scan direction from the principal axis of what is left: a stripe running left-right is scanned
   column by column (its centre is a y per column), otherwise row by row.
3. Per scan line: the strongest run above threshold, its peak, and the intensity-weighted centroid of
   s - level over the contiguous window where s exceeds level = `level_fraction` x peak (symmetric
   profile -> unbiased centre). Lines whose window touches invalid pixels or the image border, or is
   wider than `max_width_px`, are skipped: a truncated profile gives a biased centre.
4. Outliers (specks, a reflection elsewhere) are removed against a running median of the centres.

A failed detection is a value (`CurveDetection.reason` says why), never an exception.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calib.epipolar import distance_to_polyline

#: A full-white projector image must raise the brightest lit pixels by at least this many 8-bit levels,
#: or the projector is taken to light nothing the camera sees.
MIN_LIT_DN = 12.0


@dataclass(frozen=True, eq=False)
class CurveDetection:
    """The centre line of a detected stripe: `centre_px` (M, 2) ordered along the scan direction
    ('cols': by x, 'rows': by y), `peak` (M,) the signal at each centre (fraction of full white when a
    white frame was given, else of 255), `width_px` the median stripe width (area / peak, across the
    scan lines), `reason` None when detected, else why not. `cross_section_px`: the integral of the
    normalised signal across the curve (median over scan lines; NaN without a white frame), which is
    the drawn stroke's width as the camera sees it, whatever the blur: drawn `w` projector pixels wide,
    the stroke shows the local scale, cross_section_px / w camera pixels per projector pixel."""

    centre_px: np.ndarray
    peak: np.ndarray
    scan: str
    width_px: float
    noise: float
    threshold: float
    reason: str | None = None
    cross_section_px: float = float("nan")

    @property
    def ok(self) -> bool:
        return self.reason is None

    def __bool__(self) -> bool:
        return self.ok


def _failed(reason, noise=0.0, threshold=0.0) -> CurveDetection:
    return CurveDetection(np.zeros((0, 2)), np.zeros(0), "cols", 0.0, float(noise), float(threshold), reason)


def _plane(img, channel) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 3:
        if channel is None:
            a = a.astype(np.float32).mean(axis=2)
        else:
            a = a[:, :, int(channel)]
    if a.ndim != 2:
        raise ValueError(f"expected a grey or BGR image, got shape {np.shape(img)}")
    return a.astype(np.float32)


def stripe_signal(frame_on, frame_off, frame_white=None, channel: int | None = None,
                  min_white_fraction: float = 0.12) -> tuple[np.ndarray, np.ndarray]:
    """(s, valid): the curve's signal per pixel and where it can be trusted (see the module docstring).
    `channel` picks one BGR channel (curves drawn in different colours), None = mean of channels."""
    on, off = _plane(frame_on, channel), _plane(frame_off, channel)
    if on.shape != off.shape:
        raise ValueError(f"frames differ in size: {on.shape} vs {off.shape}")
    diff = on - off
    if frame_white is None:
        return diff / 255.0, np.ones(diff.shape, bool)
    lit = _plane(frame_white, channel) - off
    if lit.shape != on.shape:
        raise ValueError(f"white frame differs in size: {lit.shape} vs {on.shape}")
    ref = float(np.percentile(lit, 99.5))
    valid = lit > max(min_white_fraction * ref, 4.0)
    if ref < MIN_LIT_DN:
        valid[:] = False
    s = np.zeros_like(diff)
    s[valid] = diff[valid] / lit[valid]
    return s, valid


def lit_region(frame_off, frame_white, channel: int | None = None, min_fraction: float = 0.4,
               erode_px: int = 3) -> np.ndarray:
    """Bool mask of the surfaces the projector lights brightly (white - off above `min_fraction` of
    its bright level): the board's blank region and white squares, as the camera sees them."""
    lit = _plane(frame_white, channel) - _plane(frame_off, channel)
    ref = float(np.percentile(lit, 99.5))
    mask = (lit > max(min_fraction * ref, 4.0)).astype(np.uint8)
    if ref < MIN_LIT_DN:
        mask[:] = 0
    if erode_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode_px + 1, 2 * erode_px + 1))
        mask = cv2.erode(mask, k)
    return mask.astype(bool)


def detect_projected_curve(frame_on, frame_off, frame_white=None, *, channel: int | None = None,
                           roi=None, min_contrast: float = 0.12, level_fraction: float = 0.15,
                           max_width_px: float = 30.0, min_points: int = 12,
                           smooth_sigma_px: float = 1.0, signal=None) -> CurveDetection:
    """Sub-pixel centre line of the curve drawn in `frame_on` and absent from `frame_off` (BGR or grey
    arrays of the same size; `frame_white` optional, see stripe_signal). `roi`: optional bool mask of
    where to look. `signal`: (s, valid) as stripe_signal returns for these frames, when the caller
    computed it once for several curves in one frame (frame_on and frame_off are then not read)."""
    s, valid = signal if signal is not None else stripe_signal(frame_on, frame_off, frame_white, channel)
    if roi is not None:
        roi = np.asarray(roi, bool)
        if roi.shape != s.shape:
            raise ValueError(f"roi must be a {s.shape} bool mask, got {roi.shape}")
        valid = valid & roi
    if valid.sum() < 100:
        return _failed("the projector lights (almost) nothing the camera sees")
    vals = s[valid]
    med = float(np.median(vals))
    noise = 1.4826 * float(np.median(np.abs(vals - med)))
    thr = max(min_contrast, 6.0 * noise)
    sm = cv2.GaussianBlur(s, (0, 0), smooth_sigma_px) if smooth_sigma_px > 0 else s
    mask = ((sm > thr) & valid).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= 8
    if not keep.any():
        peak = float(np.max(sm[valid]))
        return _failed(f"no projected curve visible: strongest signal {peak:.2f} of full white, "
                       f"needs {thr:.2f} (is the board in the projector's light?)", noise, thr)
    mask = keep[labels]
    ys, xs = np.nonzero(mask)
    w = sm[ys, xs]
    cx, cy = np.average(xs, weights=w), np.average(ys, weights=w)
    cov = np.cov(np.vstack([xs - cx, ys - cy]), aweights=w)
    evals, evecs = np.linalg.eigh(cov)
    major = evecs[:, 1]
    scan = "cols" if abs(major[0]) >= abs(major[1]) else "rows"
    if scan == "rows":  # work on the transpose: always scan columns
        s_t, v_t, m_t = s.T, valid.T, mask.T
    else:
        s_t, v_t, m_t = s, valid, mask
    pts, aux = _scan_columns(s_t, v_t, m_t, level_fraction, max_width_px)
    if len(pts) == 0:
        return _failed("a bright stroke is visible but no clean stripe profile was found across it "
                       f"(wider than {max_width_px:g} px, or cut by dark or unlit areas)", noise, thr)
    pts, aux, slope = _select_curve(pts, aux)
    pts, aux, slope = _drop_outliers(pts, aux, slope)
    if len(pts) < min_points:
        return _failed(f"only {len(pts)} points of the curve found (need {min_points}); "
                       "is the curve on the board?", noise, thr)
    if scan == "rows":
        pts = pts[:, ::-1]
    # the integral across a scan line, times cos(angle between the curve and the scan line's normal),
    # is the integral across the curve: with a normalised signal, its width in camera pixels
    cross = aux[:, 2] / np.sqrt(1.0 + slope**2)
    cross = cross[np.isfinite(cross)]
    cross_px = float(np.median(cross)) if frame_white is not None and len(cross) >= min_points else float("nan")
    return CurveDetection(pts, aux[:, 0], scan, float(np.median(aux[:, 1])), noise, thr, None, cross_px)


def _scan_columns(s, valid, mask, level_fraction, max_width_px):
    """Every clean stripe profile crossing each column: (K, 2) centres (x, y), and (K, 3) peaks,
    widths (area / peak) and integrals of the signal across the stripe (tails included; NaN when the
    wider window leaves the valid pixels)."""
    H, W = s.shape
    cols = np.flatnonzero(mask.any(axis=0))
    pts, aux = [], []
    for x in cols:
        col_m = mask[:, x]
        col = s[:, x]
        d = np.diff(np.concatenate([[0], col_m.astype(np.int8), [0]]))
        starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
        for a, b in zip(starts, ends):
            p = a + int(np.argmax(col[a:b]))
            peak = float(col[p])
            if not peak > 0:  # the smoothed signal passed the threshold, the pixels themselves do not
                continue
            level = level_fraction * peak
            lo = p
            while lo > 0 and valid[lo - 1, x] and col[lo - 1] > level:
                lo -= 1
            hi = p
            while hi < H - 1 and valid[hi + 1, x] and col[hi + 1] > level:
                hi += 1
            # the profile must fall below the level on both sides inside valid pixels: a truncated
            # profile gives a biased centre
            if lo == 0 or hi == H - 1 or not valid[lo - 1, x] or not valid[hi + 1, x]:
                continue
            if hi - lo + 1 > max_width_px:
                continue
            wts = col[lo : hi + 1] - level
            y = np.arange(lo, hi + 1)
            pts.append((float(x), float(np.sum(wts * y) / np.sum(wts))))
            ext = max(3, (hi - lo + 1) // 2)
            a2, b2 = lo - ext, hi + ext + 1
            integral = float(np.sum(col[a2:b2])) if a2 >= 0 and b2 <= H and valid[a2:b2, x].all() else np.nan
            aux.append((peak, float(np.sum(col[lo : hi + 1]) / peak), integral))
    return np.array(pts, float).reshape(-1, 2), np.array(aux, float).reshape(-1, 3)


def _select_curve(pts, aux, degree: int = 3, tol_px: float = 3.0, iterations: int = 300):
    """The one smooth curve among the candidate centres: RANSAC of a polynomial y(x) (weighted by the
    peaks), then per column the candidate nearest to it. Deterministic. Returns the kept centres, their
    aux rows and the slope dy/dx of the fit at each."""
    n = len(pts)
    peaks = aux[:, 0]
    if n <= degree + 1:
        return pts, aux, np.zeros(n)
    x, y = pts[:, 0], pts[:, 1]
    xm, xs = x.mean(), max(np.ptp(x), 1.0)
    t = (x - xm) / xs
    rng = np.random.default_rng(0)
    best, best_score = None, -1.0
    for _ in range(iterations):
        idx = rng.choice(n, degree + 1, replace=False)
        if len(np.unique(x[idx])) < degree + 1:
            continue
        coef = np.polyfit(t[idx], y[idx], degree)
        inl = np.abs(np.polyval(coef, t) - y) < tol_px
        score = float(np.sum(peaks[inl]))
        if score > best_score:
            best, best_score = inl, score
    if best is None:
        return pts, aux, np.zeros(n)
    for _ in range(3):  # refit on the inliers and re-collect
        coef = np.polyfit(t[best], y[best], min(degree, int(best.sum()) - 1))
        res = np.abs(np.polyval(coef, t) - y)
        best = res < tol_px
    res = np.where(best, res, np.inf)
    # one centre per column: the inlier nearest to the fit
    order = np.lexsort((res, x))
    xo = x[order]
    first = np.concatenate([[True], xo[1:] != xo[:-1]])
    keep = order[first & np.isfinite(res[order])]
    keep = np.sort(keep)
    slope = np.polyval(np.polyder(coef), t[keep]) / xs if len(coef) > 1 else np.zeros(len(keep))
    return pts[keep], aux[keep], slope


def _drop_outliers(pts, aux, slope, half_window: int = 7, max_dev_px: float = 1.5):
    """Drop centres more than max_dev_px from the running median of their neighbours (by scan order)."""
    if len(pts) < 3:
        return pts, aux, slope
    y = pts[:, 1]
    n = len(y)
    keep = np.ones(n, bool)
    for i in range(n):
        j0, j1 = max(0, i - half_window), min(n, i + half_window + 1)
        neigh = np.concatenate([y[j0:i], y[i + 1 : j1]])
        # compare to the neighbours that are close along the scan direction too
        near = np.abs(np.concatenate([pts[j0:i, 0], pts[i + 1 : j1, 0]]) - pts[i, 0]) <= 3 * half_window
        if near.sum() >= 2 and abs(y[i] - np.median(neigh[near])) > max_dev_px:
            keep[i] = False
    return pts[keep], aux[keep], slope[keep]


# ---- distance of a pixel to the detected curve ------------------------------------------------------
@dataclass(frozen=True)
class CurveDistance:
    """Distance from a picked pixel to the detected curve, from a local fit of the centre line.
    `distance_px` >= 0, `signed_px` its sign (see calib.epipolar.PolylineDistance), `n_points` the
    centres used, `fit_rms_px` their scatter about the fit (the detection's own noise), `reason` None
    when measured, else why not."""

    distance_px: float
    signed_px: float
    n_points: int
    fit_rms_px: float
    closest_px: tuple[float, float]
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.reason is None


def distance_to_curve(detection: CurveDetection, pixel, window_px: float = 40.0, degree: int = 2,
                      min_points: int = 8, max_extrapolation_px: float = 6.0) -> CurveDistance:
    """Distance from `pixel` to the detected curve, measured on a polynomial fit (`degree`) of the
    centres within `window_px` of the pixel along the scan direction (which averages the per-line
    noise). The curve must reach the pixel: centres on both sides within the window, or at most
    `max_extrapolation_px` beyond the last one."""
    nan = float("nan")
    if not detection.ok:
        return CurveDistance(nan, nan, 0, nan, (nan, nan), detection.reason)
    p = np.asarray(pixel, float).reshape(2)
    pts = detection.centre_px
    if detection.scan == "rows":
        pts, p = pts[:, ::-1], p[::-1]
    # x along the curve, y across it; the scan direction keeps the curve's slope within 45 degrees, so
    # the foot of the perpendicular is near the pixel's own x: look there, widening the window until
    # the curve is seen on both sides of the foot (the stripe vanishes on black squares and the fit
    # then bridges the gap)
    x0 = float(p[0])
    q = pts[:0]
    for win in (window_px, 2 * window_px, 4 * window_px):
        q = pts[np.abs(pts[:, 0] - x0) <= win]
        if len(q) >= min_points and q[:, 0].min() <= x0 <= q[:, 0].max():
            break
    if len(q) < min_points:
        return CurveDistance(nan, nan, int(len(q)), nan, (nan, nan),
                             f"the detected curve does not reach the picked pixel: only {len(q)} of its points "
                             f"lie within {4 * window_px:g} px of it (hidden or off the board there)")
    lo, hi = q[:, 0].min(), q[:, 0].max()
    xm = q[:, 0].mean()
    coef = np.polyfit(q[:, 0] - xm, q[:, 1], min(degree, len(q) - 1))
    rms = float(np.sqrt(np.mean((np.polyval(coef, q[:, 0] - xm) - q[:, 1]) ** 2)))
    xs = np.linspace(min(lo, x0) - 2.0, max(hi, x0) + 2.0, 400)
    fit = np.column_stack([xs, np.polyval(coef, xs - xm)])
    d = distance_to_polyline(p, fit)
    closest = d.closest[0]
    if not (lo - max_extrapolation_px <= closest[0] <= hi + max_extrapolation_px):
        return CurveDistance(nan, nan, int(len(q)), rms, (nan, nan), "the detected curve does not reach the picked pixel: it stops before it")
    signed = float(d.signed[0])
    if detection.scan == "rows":
        closest = closest[::-1]
        signed = -signed  # swapping the axes mirrors the orientation
    return CurveDistance(float(d.distance[0]), signed, int(len(q)), rms, (float(closest[0]), float(closest[1])))
