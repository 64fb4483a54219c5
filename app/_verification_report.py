"""The epipolar verification's records and verdict (behind app/verification.py): one verified pixel
(PixelCheck), the automatic check's report and its file verification.json (VerificationReport), and
the verdict over the checks (`judge`)."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib.errors import FormatError, ProcamError
from calib.formats.fileio import RESULT_MAX_BYTES, atomic_write_text, read_json

SCHEMA = "procam-verification"
VERSION = 1

#: Default verdict threshold on the mean distance, in projector pixels (the worst may reach twice it).
DEFAULT_THRESHOLD_PX = 1.5
#: The worst check may be this many times the threshold.
WORST_FACTOR = 2.0


class VerificationError(ProcamError):
    """The verification cannot run (no lit region seen, projector and session disagree...)."""


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
    def from_dict(cls, d: dict, path="<dict>", where="checks[]") -> PixelCheck:
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


def _read_response_record(value) -> dict | None:
    """verification.json's "response" (untrusted): a known tone curve (calib.detection.response) with
    the short strings saying where it came from, or None; anything else in the file is dropped."""
    from calib.detection.response import parse_response

    r = parse_response(value)
    if r is None:
        return None
    extra = {k: value[k] for k in ("from", "source") if isinstance(value.get(k), str) and len(value[k]) <= 40}
    return {**r.to_dict(), **extra}


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
    def from_dict(cls, d: dict, path="<dict>") -> VerificationReport:
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
    def from_json(cls, path) -> VerificationReport:
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
    need = max(int(min_measured), math.ceil(len(checks) / 2))
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
