"""The RealSense colour sensor's exposure, gain and image processing (behind drivers/realsense.py).

The colour sensor's exposure and gain are only meaningful in manual mode (on the D4xx RGB sensor the
values read while auto exposure is on are stored defaults, and its colour metadata is stale:
librealsense issues #2549, #5035, #11355). RealSenseCamera therefore implements
drivers.base.ExposureControl through `RealSenseExposure`: `set_manual_exposure(exposure_us, gain)` turns
auto exposure off first, then sets both (clamped to the option's range, rounded to its step) and
returns what the device reports back; nothing is ever read from auto exposure. The depth sensor's IR
emitter (`emitter_enabled`) is switched off at start (its dots can show in the colour image,
librealsense #7181).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivers._realsense_lib import COLOUR_EXPOSURE_UNIT_US
from drivers.errors import DeviceError


class RealSenseExposure:
    """The exposure controls of drivers.realsense.RealSenseCamera (a part of that class, not a driver of
    its own): they work on the state the camera keeps, `_rs`, `_sensor` (the streaming colour sensor),
    `_depth_sensor`, `_manual` (the manual exposure last applied), `_emitter_wanted` and `_label()`."""

    # ---- drivers.base.ExposureControl ------------------------------------------------------------
    def exposure_limits(self) -> dict:
        """{"exposure_us": (min, max, step), "gain": (min, max, step)} as the colour sensor reports them
        (exposure in microseconds)."""
        rs = self._rs
        self._require_started("read the exposure limits")
        out = {}
        for key, opt, scale in (("exposure_us", rs.option.exposure, COLOUR_EXPOSURE_UNIT_US),
                                ("gain", rs.option.gain, 1.0)):
            self._require(opt, key.split("_")[0])
            r = self._sensor.get_option_range(opt)
            out[key] = (float(r.min) * scale, float(r.max) * scale, float(r.step) * scale)
        return out

    def set_auto_exposure(self, enabled: bool) -> None:
        """Auto exposure on (the manual values are forgotten) or off (the device keeps what it has)."""
        rs = self._rs
        self._require_started("change the auto exposure")
        self._require(rs.option.enable_auto_exposure, "auto exposure")
        self._set_option(rs.option.enable_auto_exposure, 1.0 if enabled else 0.0, "auto exposure")
        if enabled:
            self._manual = None

    def set_manual_exposure(self, exposure_us: float, gain: float) -> dict:
        """Auto exposure off first, then exposure (us) and gain, each clamped to the sensor's range and
        rounded to its step. Returns what the device reports back: {"exposure_us", "gain"}; the values
        are re-applied after a reconnect."""
        rs = self._rs
        self._require_started("set the exposure")
        try:
            exposure_us, gain = float(exposure_us), float(gain)
        except (TypeError, ValueError):
            raise DeviceError(f"exposure and gain must be numbers, got {exposure_us!r} and {gain!r}") from None
        if not (np.isfinite(exposure_us) and np.isfinite(gain)):
            raise DeviceError(f"exposure and gain must be finite, got {exposure_us} us and {gain}")
        if self._sensor.supports(rs.option.enable_auto_exposure):
            self._set_option(rs.option.enable_auto_exposure, 0.0, "auto exposure")
        self._require(rs.option.exposure, "exposure")
        self._require(rs.option.gain, "gain")
        applied_exposure = self._set_option(rs.option.exposure, exposure_us / COLOUR_EXPOSURE_UNIT_US, "exposure",
                                            unit_scale=COLOUR_EXPOSURE_UNIT_US, unit="us", clamp=True)
        applied_gain = self._set_option(rs.option.gain, gain, "gain", clamp=True)
        applied = {"exposure_us": applied_exposure * COLOUR_EXPOSURE_UNIT_US, "gain": applied_gain}
        if self._sensor.supports(rs.option.enable_auto_exposure) and \
                float(self._sensor.get_option(rs.option.enable_auto_exposure)) != 0.0:
            raise DeviceError(f"RealSense {self._label()}: auto exposure is still on after switching it off")
        self._manual = dict(applied)
        return applied

    def set_emitter(self, enabled: bool) -> None:
        """The depth sensor's IR emitter on or off; a device without one (or without the option) is left
        as it is. Applied again after a reconnect."""
        rs = self._rs
        self._emitter_wanted = bool(enabled)
        d = self._depth_sensor
        if d is None or not d.supports(rs.option.emitter_enabled):
            return
        try:
            d.set_option(rs.option.emitter_enabled, 1.0 if enabled else 0.0)
        except RuntimeError as e:
            raise DeviceError(f"RealSense {self._label()}: cannot switch the IR emitter "
                              f"{'on' if enabled else 'off'}: {e}") from None

    def emitter_enabled(self) -> bool | None:
        """The emitter as the depth sensor reports it; None when the device has none."""
        d = self._depth_sensor
        rs = self._rs
        try:
            if d is not None and d.supports(rs.option.emitter_enabled):
                return bool(d.get_option(rs.option.emitter_enabled))
        except RuntimeError:
            pass
        return None

    def _fix_image_processing(self) -> None:
        """Auto white balance off, at the white balance the sensor has (its colour gains would follow
        the projected image between the exposure search, the tone-curve bracket and the captures; the
        published method's own code turns it off too), and auto exposure priority off (it may lower the
        frame rate at long exposures, librealsense #7242). A sensor without a control is left as it is."""
        rs = self._rs
        for opt, label in ((rs.option.enable_auto_white_balance, "auto white balance"),
                           (rs.option.auto_exposure_priority, "auto exposure priority")):
            if self._sensor.supports(opt):
                self._set_option(opt, 0.0, label)

    def _require_started(self, what: str) -> None:
        if self._sensor is None:
            raise DeviceError(f"RealSense {self._label()}: start() the camera before trying to {what}")

    def _require(self, opt, label: str) -> None:
        if not self._sensor.supports(opt):
            raise DeviceError(f"RealSense {self._label()}: the colour sensor has no {label} control")

    def _set_option(self, opt, value: float, label: str, unit_scale: float = 1.0, unit: str = "",
                    clamp: bool = False) -> float:
        s = self._sensor
        r = s.get_option_range(opt)
        if clamp:
            value = min(max(value, r.min), r.max)
        if not (r.min - 1e-9 <= value <= r.max + 1e-9):
            raise DeviceError(
                f"RealSense {self._label()}: {label} {value * unit_scale:g}{unit} is outside the camera's "
                f"range {r.min * unit_scale:g}..{r.max * unit_scale:g}{unit}")
        if r.step > 0:
            value = r.min + round((value - r.min) / r.step) * r.step
        value = min(max(value, r.min), r.max)
        try:
            s.set_option(opt, float(value))
        except RuntimeError as e:
            raise DeviceError(f"RealSense {self._label()}: cannot set {label} to {value * unit_scale:g}{unit}: {e}") from None
        return float(s.get_option(opt))

    def _read_controls(self) -> dict:
        rs = self._rs
        s = self._sensor
        out: dict[str, Any] = {}
        if s is None:
            return out

        def read(opt):
            try:
                if s.supports(opt):
                    return float(s.get_option(opt))
            except RuntimeError:
                pass
            return None

        v = read(rs.option.enable_auto_exposure)
        out["auto_exposure"] = None if v is None else bool(v)
        v = read(rs.option.exposure)
        out["exposure_us"] = None if v is None else v * COLOUR_EXPOSURE_UNIT_US
        out["gain"] = read(rs.option.gain)
        v = read(rs.option.enable_auto_white_balance)
        out["auto_white_balance"] = None if v is None else bool(v)
        out["white_balance_k"] = read(rs.option.white_balance)
        v = read(rs.option.auto_exposure_priority)
        out["auto_exposure_priority"] = None if v is None else bool(v)
        return out
