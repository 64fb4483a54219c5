"""Epipolar verification of a calibration, live at the rig and automatic (the paper's check, measured).

For a camera pixel u the calibration predicts the curve of projector pixels that can light what u sees
(calib.epipolar.epipolar_curve). The projector draws that curve as a bright stroke on the board; the
camera sees it (through the mirror); calib.detection.curves finds the stroke's sub-pixel centre line;
the distance from u to it is the measurement. With a correct calibration the stroke passes through u
whatever the board's pose.

Three frames per check: projector black (`off`), projector full white (`white`, shared by all checks:
it normalises the board's albedo and gives the region the projector lights) and the curve (`on`).

Units. The distance is measured in CAMERA pixels (`distance_px`). It is also converted to PROJECTOR
pixels (`distance_proj_px`) with the local scale measured from the stroke itself: drawn `w` projector
pixels wide, the stroke's cross-section (integral of the normalised signal across it) is its width in
camera pixels, so scale = cross_section / w camera px per projector px, independent of blur. The
verdict is taken in projector pixels: they measure what the calibration is for (where the projector
draws), and they do not depend on how much finer or coarser the camera's pixels are than the
projector's on the board (on the simulated rigs one camera pixel covers about four projector pixels,
so a 5-pixel error of the projector's principal point moves the stroke by only 0.5 to 1 camera pixel).

Verdict (VerificationReport.passed): at least `min_measured` checks and half of them measured, the
mean distance <= threshold_px and the worst <= 2 x threshold_px (projector pixels). Pixels where no
curve is detected are reported with their reason and never count as passes. See docs/VERIFICATION.md
for the measurements behind the default threshold.

Entry points: `verify_pixel` (one pixel: the station's panel calls it when the operator clicks a
pixel), `verify` (the automatic grid), `VerificationReport.save_json` / `from_json` (verification.json).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from calib.detection.curves import CurveDetection, detect_projected_curve, distance_to_curve, lit_region, stripe_signal
from calib.detection.response import CameraResponse
from calib.epipolar import epipolar_curve, predicted_camera_curve
from calib.errors import FormatError, ProcamError
from calib.formats import session_files
from calib.formats.fileio import RESULT_MAX_BYTES, atomic_write_text, read_json
from calib.models.result import CalibrationResult
from calib.models.vocab import RigKind, choices
from drivers.clock import clock_of

SCHEMA = "procam-verification"
VERSION = 1

#: Default verdict threshold on the mean distance, in projector pixels (the worst may reach twice it).
DEFAULT_THRESHOLD_PX = 1.5
#: The worst check may be this many times the threshold.
WORST_FACTOR = 2.0
#: Default grid of automatically picked pixels (columns, rows).
DEFAULT_GRID = (4, 3)
#: Width of the drawn stroke in camera pixels the automatic stroke width aims for.
TARGET_STROKE_CAM_PX = 3.5
#: Stroke width (projector pixels) before the scale is known.
INITIAL_STROKE_PX = 12.0

Progress = Callable[[int, int, str], None]


class VerificationError(ProcamError):
    """The verification cannot run (no lit region seen, projector and session disagree...)."""


# ---- one pixel ---------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PixelCheck:
    """One verified pixel. `projector_curve` (M, 2): the predicted epipolar curve as drawn (projector
    pixels); `detected_curve` (K, 2): the stroke's centre line the camera saw; `predicted_curve` (L, 2)
    or None: where the calibration expects the camera to see the stroke (needs the board's plane).
    `distance_px`: camera pixels from `pixel` to the detected curve (signed_px: with a side);
    `distance_proj_px`: the same in projector pixels (None when the scale is unknown); `scale`:
    camera px per projector px across the stroke; `ok`: measured (else `reason` says why not)."""

    pixel: tuple[float, float]
    projector_curve: np.ndarray
    detected_curve: np.ndarray
    predicted_curve: np.ndarray | None
    distance_px: float | None
    signed_px: float | None
    distance_proj_px: float | None
    scale: float | None
    stroke_px: float
    fit_rms_px: float | None
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.reason is None

    @property
    def closest_px(self) -> tuple[float, float] | None:
        """The point of the detected curve nearest to the pixel (for drawing the gap)."""
        if not self.ok or len(self.detected_curve) == 0:
            return None
        from calib.epipolar import distance_to_polyline

        c = distance_to_polyline(self.pixel, self.detected_curve).closest[0]
        return (float(c[0]), float(c[1]))

    def overlay(self) -> dict:
        """What the panel draws over the camera image (camera pixels): the picked pixel, the detected
        curve, the predicted curve (or None), and a one-line label."""
        return {"pixel": self.pixel, "detected": self.detected_curve, "predicted": self.predicted_curve,
                "label": self.label()}

    def label(self) -> str:
        if not self.ok:
            return f"({self.pixel[0]:.1f}, {self.pixel[1]:.1f}): not measured: {self.reason}"
        s = f"({self.pixel[0]:.1f}, {self.pixel[1]:.1f}): {self.distance_px:.2f} camera px"
        if self.distance_proj_px is not None:
            s += f" = {self.distance_proj_px:.2f} projector px"
        return s

    def to_dict(self, curves: bool = True) -> dict:
        d = {"pixel": list(self.pixel), "ok": self.ok, "reason": self.reason,
             "distance_px": _num(self.distance_px), "signed_px": _num(self.signed_px),
             "distance_proj_px": _num(self.distance_proj_px), "scale": _num(self.scale),
             "stroke_px": _num(self.stroke_px), "fit_rms_px": _num(self.fit_rms_px)}
        if curves:
            d["projector_curve"] = np.round(self.projector_curve, 3).tolist()
            d["detected_curve"] = np.round(self.detected_curve, 3).tolist()
            d["predicted_curve"] = None if self.predicted_curve is None else np.round(self.predicted_curve, 3).tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict, path="<dict>", where="checks[]") -> "PixelCheck":
        try:
            pix = tuple(float(v) for v in d["pixel"])
            if len(pix) != 2:
                raise ValueError
        except (KeyError, TypeError, ValueError):
            raise FormatError(path, f"{where}.pixel", "must be [x, y]") from None

        def arr(key):
            v = d.get(key)
            if v is None:
                return None
            try:
                return np.array(v, float).reshape(-1, 2)
            except (TypeError, ValueError):
                raise FormatError(path, f"{where}.{key}", "must be a list of [x, y] pairs") from None

        def num(key):
            v = d.get(key)
            if v is None:
                return None
            if not isinstance(v, (int, float)) or isinstance(v, bool):
                raise FormatError(path, f"{where}.{key}", "must be a number or null")
            return float(v)

        empty = np.zeros((0, 2))
        pc, dc = arr("projector_curve"), arr("detected_curve")
        return cls(pix, empty if pc is None else pc, empty if dc is None else dc, arr("predicted_curve"),
                   num("distance_px"), num("signed_px"), num("distance_proj_px"), num("scale"),
                   num("stroke_px") or 0.0, num("fit_rms_px"), d.get("reason"))


def _num(v):
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


class _Grabber:
    """Shows an image and returns the (mean of `average`) camera frame(s) exposed after it became
    visible: frames whose exposure started at or after the time `wait_presented` returns (presentation
    + the projector's measured latency). A camera that cannot time its frames (exposure_start_s None)
    skips `settle_frames` frames after the one seen when the image was presented instead.
    `seen` keeps (frame_number, projector ticket) of every frame used, for tests."""

    def __init__(self, camera, projector, settle_frames: int = 1, average: int = 1, timeout_s: float = 3.0):
        self.camera, self.projector = camera, projector
        self.settle_frames, self.average, self.timeout_s = int(settle_frames), max(1, int(average)), timeout_s
        self.last = None
        self.seen: list[tuple[int, int]] = []

    def grab(self, image: np.ndarray) -> np.ndarray:
        ticket = self.projector.show(image)
        visible_s = self.projector.wait_presented(ticket, timeout_s=self.timeout_s)
        if self.last is None:
            self.last = self.camera.get_frame(self.timeout_s).frame_number
        acc, n, skip = None, 0, self.settle_frames
        clock = clock_of(self.projector)
        deadline = clock.now() + self.timeout_s
        while n < self.average:
            f = self.camera.get_frame(self.timeout_s, newer_than=self.last)
            self.last = f.frame_number
            early = f.exposure_start_s < visible_s if f.exposure_start_s is not None else skip > 0
            if early:
                skip -= 1
                if clock.now() > deadline:
                    raise VerificationError(f"no camera frame exposed after the projector's image became visible "
                                            f"within {self.timeout_s:g} s: check the camera's frame times")
                continue
            img = f.image.astype(np.float32)
            acc = img if acc is None else acc + img
            n += 1
            self.seen.append((int(f.frame_number), int(ticket)))
        return acc / self.average if self.average > 1 else acc


_LEVELS = np.arange(256, dtype=np.float64)


def _grey(img: np.ndarray, response: CameraResponse | None = None) -> np.ndarray:
    """(H, W) float32 light: the mean of the channels, as calib.detection.curves reads a BGR frame. With
    the camera's `response` (tone curve, not linear), each channel's levels are linearised first (the
    curve's inverse, interpolated in CameraResponse.lut: averaged frames have fractional levels), so the
    stripe signal divides light, not encoded levels, and its validity threshold (a fraction of the
    white's rise) sees the print's black squares as the few percent of the light they are, not the
    ~20 % of the levels the curve lifts them to: left out, their noisy signal no longer pulls the
    centre line (most of the gain, docs/VERIFICATION.md). The only place the verification's frames
    become grey light. (Averaged frames are averaged before they are linearised: a noise-sized error.)"""
    a = np.asarray(img)
    if response is not None and not response.linear:
        a = np.interp(a, _LEVELS, response.lut())
    return a.astype(np.float32).mean(axis=2) if a.ndim == 3 else a.astype(np.float32)


def _draw(size, curve: np.ndarray, stroke_px: float) -> np.ndarray:
    from drivers.projector_images import draw_polylines

    return draw_polylines(tuple(size), [curve], thickness_px=float(stroke_px), antialias=True)


@dataclass(frozen=True, eq=False)
class ReferenceFrames:
    """The frames every check shares: projector black and full white (as the camera delivered them), the
    lit region, and the camera's response the frames' light is read with (None: the levels as they are)."""

    off: np.ndarray
    white: np.ndarray
    lit: np.ndarray  # bool mask of what the projector lights brightly, as the camera sees it (its levels)
    response: CameraResponse | None = None

    def light(self) -> tuple[np.ndarray, np.ndarray]:
        """(off, white) as grey float32 light, linearised by `response` (see _grey)."""
        return _grey(self.off, self.response), _grey(self.white, self.response)


def capture_references(camera, projector, settle_frames: int = 1, average: int = 1, grabber=None,
                       response: CameraResponse | None = None) -> ReferenceFrames:
    """Capture the black and white reference frames (the board must be in place and still). `response`:
    the camera's tone curve (calib.detection.response), kept with the frames: every signal formed from
    them is then linear light (None: encoded levels, as before responses were recorded)."""
    W, H = projector.size
    g = grabber or _Grabber(camera, projector, settle_frames, average)
    white = g.grab(np.full((H, W), 255, np.uint8))
    off = g.grab(np.zeros((H, W), np.uint8))
    return ReferenceFrames(off, white, lit_region(off, white), response)


def verify_pixel(camera, projector, result: CalibrationResult, pixel, *, references: ReferenceFrames | None = None,
                 stroke_px: float | None = None, board_pose: np.ndarray | None = None, settle_frames: int = 1,
                 average: int = 1, leave_dark: bool = True, response: CameraResponse | None = None) -> PixelCheck:
    """Verify one camera pixel: draw its epipolar curve, detect it, measure. `references`: shared
    black/white frames (captured here when None). `stroke_px`: stroke width in projector pixels
    (default: INITIAL_STROKE_PX). `board_pose`: T_cam_board of the board (or (n, d) of its plane) for
    the predicted curve overlay. `response`: the camera's tone curve, for the references captured here
    (given `references` carry their own). The projector is left black afterwards unless `leave_dark`
    is False."""
    pixel = (float(pixel[0]), float(pixel[1]))
    cw, ch = result.camera.size
    if not (-0.5 <= pixel[0] <= cw - 0.5 and -0.5 <= pixel[1] <= ch - 0.5):
        raise VerificationError(f"pixel ({pixel[0]:g}, {pixel[1]:g}) is outside the {cw}x{ch} camera image")
    if tuple(projector.size) != tuple(result.projector.size):
        raise VerificationError(f"the projector is {projector.size[0]}x{projector.size[1]} but the calibration is for "
                                f"{result.projector.width}x{result.projector.height}")
    stroke = float(stroke_px or INITIAL_STROKE_PX)
    curve = epipolar_curve(result, pixel)
    if len(curve) < 2:
        return PixelCheck(pixel, curve, np.zeros((0, 2)), None, None, None, None, None, stroke, None,
                          "the projector cannot light what this pixel sees: its epipolar curve misses the "
                          "projector image (pick a pixel on the board in the projector's light)")
    refs = references or capture_references(camera, projector, settle_frames, average, response=response)
    g = _Grabber(camera, projector, settle_frames, average)
    on = g.grab(_draw(projector.size, curve, stroke))
    if leave_dark:
        W, H = projector.size
        projector.wait_presented(projector.show(np.zeros((H, W), np.uint8)))
    return measure_pixel(result, pixel, curve, on, refs, stroke, board_pose)


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
        signal = stripe_signal(_grey(frame_on, refs.response), *refs.light())
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


def _stroke_rois(shape, lines: list[np.ndarray], half_width_px: float) -> list[np.ndarray]:
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


# ---- the automatic check -----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class VerificationReport:
    """The automatic check. Distances: mean/worst over the measured checks, camera pixels (`*_px`) and
    projector pixels (`*_proj_px`); `threshold_px` applies to projector pixels (see the module doc);
    `passed` the verdict and `verdict` why, in words; `n_failed_detection` checks not measured;
    `response` the camera's tone curve the frames were linearised with (CameraResponse.to_dict(), plus
    where it came from when the caller says), None when the levels were used as they are."""

    checks: tuple[PixelCheck, ...]
    mean_px: float | None
    worst_px: float | None
    mean_proj_px: float | None
    worst_proj_px: float | None
    threshold_px: float
    passed: bool
    n_failed_detection: int
    verdict: str
    calibration: dict = field(default_factory=dict)  # what was verified (method, units, path)
    settings: dict = field(default_factory=dict)
    created: str = ""
    response: dict | None = None  # the camera's tone curve the frames were linearised with (None: not)

    @property
    def n_measured(self) -> int:
        return sum(1 for c in self.checks if c.ok)

    def summary(self) -> str:
        """Two lines for a terminal or the panel."""
        if self.n_measured == 0:
            dist = "no pixel could be measured"
        else:
            dist = (f"mean {self.mean_px:.2f} px, worst {self.worst_px:.2f} px (camera)")
            if self.mean_proj_px is not None:
                dist += f"; mean {self.mean_proj_px:.2f} px, worst {self.worst_proj_px:.2f} px (projector)"
        head = "PASS" if self.passed else "FAIL"
        return (f"epipolar check: {self.n_measured} of {len(self.checks)} pixels measured; {dist}\n"
                f"{head}: {self.verdict}")

    def to_dict(self) -> dict:
        return {"schema": SCHEMA, "version": VERSION, "created": self.created, "passed": self.passed,
                "verdict": self.verdict, "threshold_px": self.threshold_px, "threshold_unit": "projector px",
                "worst_factor": WORST_FACTOR,
                # camera pixels, named so (version 1 files wrote "mean_px"/"worst_px": from_dict reads both)
                "mean_camera_px": _num(self.mean_px), "worst_camera_px": _num(self.worst_px),
                "mean_proj_px": _num(self.mean_proj_px), "worst_proj_px": _num(self.worst_proj_px),
                "n_checks": len(self.checks), "n_measured": self.n_measured,
                "n_failed_detection": self.n_failed_detection, "calibration": self.calibration,
                "response": self.response, "settings": self.settings, "checks": [c.to_dict() for c in self.checks]}

    def save_json(self, path) -> None:
        """Write verification.json atomically."""
        atomic_write_text(path, json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def from_dict(cls, d: dict, path="<dict>") -> "VerificationReport":
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise FormatError(path, "schema", f"must be '{SCHEMA}'")
        if not isinstance(d.get("version"), int) or d["version"] > VERSION:
            raise FormatError(path, "version", f"must be an integer <= {VERSION}")
        checks = d.get("checks")
        if not isinstance(checks, list):
            raise FormatError(path, "checks", "must be a list")
        cs = tuple(PixelCheck.from_dict(c, path, f"checks[{i}]") for i, c in enumerate(checks))
        thr = d.get("threshold_px")
        if not isinstance(thr, (int, float)) or isinstance(thr, bool) or not thr > 0:
            raise FormatError(path, "threshold_px", "must be a number > 0")
        if not isinstance(d.get("passed"), bool):
            raise FormatError(path, "passed", "must be true or false")

        def num(k, old=None):
            v = d.get(k, d.get(old) if old else None)
            return None if v is None else float(v)

        return cls(cs, num("mean_camera_px", "mean_px"), num("worst_camera_px", "worst_px"), num("mean_proj_px"), num("worst_proj_px"), float(thr),
                   d["passed"], int(d.get("n_failed_detection", 0)), str(d.get("verdict", "")),
                   dict(d.get("calibration") or {}), dict(d.get("settings") or {}), str(d.get("created", "")),
                   _read_response_record(d.get("response")))

    @classmethod
    def from_json(cls, path) -> "VerificationReport":
        path = Path(path)
        try:  # a regular file only, never read through a link (calib.formats.fileio.read_regular)
            data = read_json(path, RESULT_MAX_BYTES, "verification report")
        except FileNotFoundError:
            raise FormatError(path, "<file>", "cannot be read: it does not exist") from None
        return cls.from_dict(data, path)


def judge(checks, threshold_px: float = DEFAULT_THRESHOLD_PX, min_measured: int = 3, calibration: dict | None = None,
          settings: dict | None = None) -> VerificationReport:
    """The report and verdict for a list of PixelChecks (see the module docstring)."""
    checks = tuple(checks)
    ok = [c for c in checks if c.ok]
    n_fail = len(checks) - len(ok)
    cam = np.array([c.distance_px for c in ok], float)
    # checks without a scale of their own use the median scale of the others (same board, same rig)
    scales = [c.scale for c in ok if c.scale]
    med_scale = float(np.median(scales)) if scales else None
    proj = np.array([c.distance_proj_px if c.distance_proj_px is not None else
                     (c.distance_px / med_scale if med_scale else np.nan) for c in ok], float)
    mean_px = float(cam.mean()) if len(cam) else None
    worst_px = float(cam.max()) if len(cam) else None
    mean_pp = float(np.mean(proj)) if len(proj) and np.all(np.isfinite(proj)) else None
    worst_pp = float(np.max(proj)) if len(proj) and np.all(np.isfinite(proj)) else None
    need = max(int(min_measured), int(math.ceil(len(checks) / 2)))
    if len(ok) < need:
        reasons = sorted({c.reason for c in checks if not c.ok})
        passed = False
        verdict = (f"only {len(ok)} of {len(checks)} pixels could be measured (need {need}); "
                   f"why: {'; '.join(reasons[:3])}" if reasons else f"only {len(ok)} pixels checked (need {need})")
    elif mean_pp is None:
        passed = False
        verdict = "the stroke's scale in the camera could not be measured, so distances cannot be judged in projector pixels"
    else:
        worst_lim = WORST_FACTOR * threshold_px
        if mean_pp > threshold_px:
            passed = False
            verdict = (f"the drawn epipolar curves miss the picked pixels by {mean_pp:.2f} projector px on average "
                       f"(threshold {threshold_px:g}): the calibration does not match the rig")
        elif worst_pp > worst_lim:
            passed = False
            verdict = (f"the worst pixel is {worst_pp:.2f} projector px off (limit {worst_lim:g} = "
                       f"{WORST_FACTOR:g} x threshold): the calibration is off in part of the view")
        else:
            passed = True
            verdict = (f"mean {mean_pp:.2f} <= {threshold_px:g} and worst {worst_pp:.2f} <= {worst_lim:g} projector px")
        if n_fail:
            verdict += f" ({n_fail} pixel(s) not measured)"
    return VerificationReport(checks, mean_px, worst_px, mean_pp, worst_pp, float(threshold_px), passed, n_fail,
                              verdict, dict(calibration or {}), dict(settings or {}),
                              time.strftime("%Y-%m-%dT%H:%M:%S%z"))


def region_mask(shape, lit: np.ndarray, board_region=None, close_px: int | None = None) -> np.ndarray:
    """Where to pick pixels: the board as the projector lights it. The lit mask's holes (the printed
    area's black squares) are closed with a disc of `close_px` (default 1/30 of the image width), the
    largest connected part is kept, within `board_region` (a bool mask, a box (x0, y0, x1, y1), or an
    (N, 2) polygon, camera pixels) when given."""
    H, W = shape
    mask = np.asarray(lit, bool).astype(np.uint8)
    k = int(close_px if close_px is not None else max(15, W // 30)) | 1
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
    if board_region is not None:
        br = board_region
        if isinstance(br, np.ndarray) and br.dtype == bool:
            if br.shape != (H, W):
                raise VerificationError(f"board_region mask must be {W}x{H}")
            mask &= br
        else:
            try:
                a = np.asarray(br, float)
            except (TypeError, ValueError):
                a = np.zeros(0)
            m = np.zeros((H, W), np.uint8)
            if a.shape == (4,):
                x0, y0, x1, y1 = a
                m[max(int(np.ceil(y0)), 0) : int(np.floor(y1)) + 1, max(int(np.ceil(x0)), 0) : int(np.floor(x1)) + 1] = 1
            elif a.ndim == 2 and a.shape[1] == 2 and len(a) >= 3:
                cv2.fillPoly(m, [np.round(a).astype(np.int32)], 1)
            else:
                raise VerificationError("board_region must be a bool mask, a box (x0, y0, x1, y1) or an (N, 2) polygon")
            mask &= m.astype(bool)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros((H, W), bool)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k


def grid_pixels(mask: np.ndarray, grid=DEFAULT_GRID, margin_px: int = 12, prefer: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) pixels spread over `mask`: its bounding box split in cols x rows cells, in each cell the
    pixel nearest to the cell's centre that is at least `margin_px` inside the mask, preferably one of
    `prefer` (e.g. the brightly lit pixels: white, not a black square) when the cell has some. Cells
    without a candidate are skipped."""
    cols, rows = int(grid[0]), int(grid[1])
    if cols < 1 or rows < 1:
        raise VerificationError(f"grid must be at least 1x1, got {cols}x{rows}")
    m = np.asarray(mask, bool).astype(np.uint8)
    inner = cv2.distanceTransform(m, cv2.DIST_L2, 5) >= margin_px
    ys, xs = np.nonzero(inner)
    if len(xs) == 0:
        return np.zeros((0, 2))
    good = np.ones(len(xs), bool) if prefer is None else np.asarray(prefer, bool)[ys, xs]
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    out = []
    for r in range(rows):
        for c in range(cols):
            cx0, cx1 = x0 + (x1 - x0) * c / cols, x0 + (x1 - x0) * (c + 1) / cols
            cy0, cy1 = y0 + (y1 - y0) * r / rows, y0 + (y1 - y0) * (r + 1) / rows
            sel = (xs >= cx0) & (xs < cx1) & (ys >= cy0) & (ys < cy1)
            if not sel.any():
                continue
            if (sel & good).any():
                sel &= good
            px, py = xs[sel], ys[sel]
            k = int(np.argmin((px - (cx0 + cx1 - 1) / 2) ** 2 + (py - (cy0 + cy1 - 1) / 2) ** 2))
            out.append((float(px[k]), float(py[k])))
    return np.array(out, float).reshape(-1, 2)


def estimate_board_pose(image: np.ndarray, board, result: CalibrationResult, response=None) -> np.ndarray | None:
    """T_cam_board of the ChArUco `board` (CharucoSpec) in a camera image, with the calibration's camera
    model (and mirror: the board is then detected mirrored). None when the board is not found. Used
    for the predicted-curve overlay only; the measurement never depends on it. `response`: the camera's
    tone curve, as detection uses it (corners refined in light)."""
    from calib.detection.detect import detect_board
    from calib.paper.board_pose import solve_board_pose, usable_reason

    img = np.clip(np.asarray(image), 0, 255).astype(np.uint8)
    obs = detect_board(img, board, mirrored=result.mirror is not None, response=response)
    if not obs or usable_reason(board, obs) is not None:
        return None
    pose = solve_board_pose(result.camera, board, obs)
    return pose.physical(None if result.mirror is None else result.mirror.reflection())


def verify(camera, projector, operator, result: CalibrationResult, pixels=None, grid=DEFAULT_GRID,
           threshold_px: float = DEFAULT_THRESHOLD_PX, board_region=None, progress: Progress | None = None, *,
           board=None, board_pose=None, stroke_px: float | None = None, settle_frames: int = 1, average: int = 1,
           min_measured: int = 3, calibration_info: dict | None = None, session_dir=None,
           curves_per_image: int = MAX_CURVES_PER_IMAGE, response: CameraResponse | None = None) -> VerificationReport:
    """The automatic epipolar check. `operator` (may be None) is asked for the 'verification' pose
    first. `pixels`: (N, 2) camera pixels to verify, default a `grid` (cols, rows) spread over the
    region the projector lights (within `board_region` when given). One pixel after another; the
    stroke width adapts to TARGET_STROKE_CAM_PX camera pixels once the scale is measured (unless
    `stroke_px` is given). `board_pose` (T_cam_board) or `board` (the CharucoSpec, found in the white
    frame; default the session's projector board when `session_dir` is given) add the predicted curve
    to each check (overlay only). `session_dir`: write the report there as verification.json. Returns
    the report (the projector is left black). `curves_per_image`: strokes drawn together in one
    projector image (pixels grouped by group_pixels; 1: one image per pixel). `response`: the camera's
    tone curve (the session's recorded one, calib.detection.response.recorded_response): every frame is
    linearised before the stroke's signal is formed, so the white and black frames divide out light
    (None: the camera's levels as they are); the report records it."""
    if tuple(projector.size) != tuple(result.projector.size):
        raise VerificationError(f"the projector is {projector.size[0]}x{projector.size[1]} but the calibration is for "
                                f"{result.projector.width}x{result.projector.height}")
    if operator is not None:
        operator.request_pose("verification", None, 0)
    ref_grabber = _Grabber(camera, projector, settle_frames, average)
    refs = capture_references(camera, projector, settle_frames, average, grabber=ref_grabber, response=response)
    H, W = refs.off.shape[:2]
    if (W, H) != tuple(result.camera.size):
        raise VerificationError(f"the camera delivers {W}x{H} frames but the calibration is for "
                                f"{result.camera.width}x{result.camera.height}")
    if board_pose is None and board is None and session_dir is not None:
        board = _session_board(session_dir)
    if board_pose is None and board is not None:
        board_pose = estimate_board_pose(refs.white, board, result, refs.response)
    if pixels is None:
        region = region_mask((H, W), refs.lit, board_region)
        if not region.any():
            raise VerificationError("the camera sees nothing lit by the projector: put the board in the projector's "
                                    "light where the camera sees it (through the mirror), and check both devices")
        pts = grid_pixels(region, grid, prefer=refs.lit)
    else:
        pts = np.asarray(pixels, float).reshape(-1, 2)
    if len(pts) == 0:
        raise VerificationError("no pixel to verify: the lit region is too small for the grid")
    stroke = float(stroke_px or INITIAL_STROKE_PX)
    Wp, Hp = projector.size
    # several pixels per projected image: their strokes lie on well separated camera-side lines
    curves = [epipolar_curve(result, (float(p[0]), float(p[1]))) for p in pts]
    lines = [stroke_line(result, p, c) for p, c in zip(pts, curves)]
    groups = group_pixels(pts, lines, curves_per_image)
    results: dict[int, PixelCheck] = {}
    g = _Grabber(camera, projector, settle_frames, average)
    off_light, white_light = refs.light()  # converted once, not per check
    done = 0
    for group in groups:
        if progress is not None:
            progress(done, len(pts), f"pixel ({pts[group[0]][0]:.0f}, {pts[group[0]][1]:.0f})"
                     + (f" and {len(group) - 1} more" if len(group) > 1 else ""))
        drawable = [i for i in group if len(curves[i]) >= 2]
        for i in group:
            if i not in drawable:
                results[i] = verify_pixel(camera, projector, result, pts[i], references=refs, stroke_px=stroke)
        if drawable:
            from drivers.projector_images import draw_polylines

            image = draw_polylines((Wp, Hp), [curves[i] for i in drawable], thickness_px=stroke, antialias=True)
            on = _grey(g.grab(image), response)
            signal = stripe_signal(on, off_light, white_light)
            rois = _stroke_rois((H, W), [lines[i] for i in drawable], MIN_SEPARATION_PX / 2) \
                if len(drawable) > 1 else [None]
            for i, roi in zip(drawable, rois):
                results[i] = measure_pixel(result, pts[i], curves[i], on, refs, stroke, board_pose, roi=roi,
                                           signal=signal)
        done += len(group)
        if stroke_px is None:
            scales = [c.scale for c in results.values() if c.scale]
            if scales:
                stroke = float(np.clip(TARGET_STROKE_CAM_PX / np.median(scales), 3.0, 60.0))
    checks = [results[i] for i in range(len(pts))]
    projector.wait_presented(projector.show(np.zeros((Hp, Wp), np.uint8)))
    if progress is not None:
        progress(len(pts), len(pts), "done")
    info = {"method": result.method, "units": result.units, **(calibration_info or {})}
    if info.get("path") and "sha256" not in info:  # which calibration file this report verified
        from calib.recalib import sha256_file

        info["sha256"] = sha256_file(info["path"], unreadable_ok=True)
    settings = {"grid": list(grid) if pixels is None else None, "settle_frames": settle_frames, "average": average,
                "stroke_px": stroke_px, "min_measured": min_measured, "board_pose_known": board_pose is not None,
                "curves_per_image": curves_per_image, "projector_images": 2 + len(groups),
                "frames": [list(x) for x in ref_grabber.seen + g.seen]}  # [camera frame, projector ticket]
    report = replace(judge(checks, threshold_px, min_measured, info, settings),
                     response=None if response is None else response.to_dict())
    if session_dir is not None:
        report.save_json(Path(session_dir) / session_files.VERIFICATION)
    return report


VERIFY_RIGS = choices(RigKind)  # procam verify's --rig choices


def verify_command(session: Path) -> str:
    """`procam verify SESSION --rig KIND` with the rig the session recorded (when verify knows it)."""
    from calib.formats.session import SessionStore

    try:
        kind = SessionStore.open(session).manifest.rig.driver
    except ProcamError:
        kind = None
    return f"procam verify {session} --rig {kind if kind in VERIFY_RIGS else '|'.join(VERIFY_RIGS)}"


def verification_is_stale(report_file, calibration_file) -> bool | None:
    """Whether the verification report in `report_file` describes another calibration than the one now in
    `calibration_file` (the report records the SHA-256 of the file it verified). None when it cannot
    tell: no report, or a report written before the hash was recorded."""
    try:
        data = read_json(report_file, RESULT_MAX_BYTES, "verification report")
        recorded = (data.get("calibration") or {}).get("sha256")
    except (OSError, ProcamError, AttributeError):
        return None
    if not isinstance(recorded, str):
        return None
    from calib.recalib import sha256_file

    return recorded != sha256_file(calibration_file, unreadable_ok=True)


def _session_board(folder):
    """The projector board of the session in `folder`, or None when it cannot be read."""
    from calib.formats.session import SessionStore

    try:
        return SessionStore.open(folder).manifest.projector_board
    except ProcamError:
        return None


def _read_response_record(value) -> dict | None:
    """verification.json's "response" (untrusted): a known tone curve (calib.detection.response) with
    the short strings saying where it came from, or None; anything else in the file is dropped."""
    from calib.detection.response import parse_response

    r = parse_response(value)
    if r is None:
        return None
    extra = {k: value[k] for k in ("from", "source") if isinstance(value.get(k), str) and len(value[k]) <= 40}
    return {**r.to_dict(), **extra}


def session_response(folder) -> CameraResponse | None:
    """The camera's response the session in `folder` recorded (rig.camera_settings["response"]; the rig
    check records it), or None when it recorded none, a malformed one, or cannot be read."""
    from calib.detection.response import recorded_response
    from calib.formats.session import SessionStore

    try:
        return recorded_response(SessionStore.open(folder).manifest.rig.camera_settings)
    except ProcamError:
        return None


def perturbed(result: CalibrationResult, rotation_deg: float = 0.0, axis=(0.0, 1.0, 0.0),
              principal_shift_px=(0.0, 0.0)) -> CalibrationResult:
    """A deliberately wrong copy of a calibration (for tests, benchmarks and demos): T_cam_proj rotated
    by `rotation_deg` about `axis` (projector frame, about the projector's centre) and the projector's
    principal point shifted by `principal_shift_px`."""
    from calib.transforms import make_T, rotation_about

    T = np.array(result.T_cam_proj) @ make_T(rotation_about(axis, rotation_deg), np.zeros(3)) \
        if rotation_deg else np.array(result.T_cam_proj)
    K = np.array(result.projector.K)
    K[0, 2] += principal_shift_px[0]
    K[1, 2] += principal_shift_px[1]
    return replace(result, T_cam_proj=T, projector=result.projector.with_params(K=K),
                   method=f"{result.method} (perturbed)")
