"""The camera's response (tone curve) as a session records it, and its inverse for the detector.

A camera encodes the sensor's linear signal with a tone curve before 8 bits (video cameras: about
BT.709). Levels averaged for a sub-pixel position (the intensity-weighted circle centroids) are then
weighted by encoded, not received, light, which biases blurred circles' centres (docs/DETECTION.md).
With the response recorded in the manifest (rig.camera_settings["response"], e.g.
{"model": "bt709", "gamma": 2.2}), the detector linearises the levels first. A session file is
untrusted: anything but a known model with a plausible gamma counts as not recorded (no correction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: the models a session may record: "bt709" is V = (1 + a) L^(1/gamma) - a above a threshold and a straight
#: line through 0 below it, joined with the same value and slope, a = 0.099 (gamma 1/0.45 is BT.709 itself)
RESPONSE_MODELS = ("bt709",)
BT709_OFFSET = 0.099
GAMMA_RANGE = (1.0, 4.0)


@dataclass(frozen=True)
class CameraResponse:
    model: str
    gamma: float

    def to_dict(self) -> dict:
        return {"model": self.model, "gamma": float(self.gamma)}

    @property
    def linear(self) -> bool:
        return self.gamma == 1.0

    def decode(self, level) -> np.ndarray:
        """Relative level in [0, 1] -> relative light in [0, 1] (the inverse of the camera's curve)."""
        V = np.asarray(level, np.float64)
        if self.linear:
            return V.copy()
        p, a = 1.0 / self.gamma, BT709_OFFSET
        t = (a / ((1 + a) * (1 - p))) ** (1 / p)  # the light where the straight toe meets the power law
        slope = (1 + a) * p * t ** (p - 1)
        knee = slope * t
        power = ((np.maximum(V, knee) + a) / (1 + a)) ** self.gamma
        return np.where(V < knee, V / slope, power)

    def lut(self) -> np.ndarray:
        """float64 (256,): 8-bit level -> linear light in the same 0..255 units (read-only)."""
        return _lut(self.model, float(self.gamma))


@lru_cache(maxsize=8)
def _lut(model: str, gamma: float) -> np.ndarray:
    out = 255.0 * CameraResponse(model, gamma).decode(np.arange(256) / 255.0)
    out.setflags(write=False)
    return out


def parse_response(value) -> CameraResponse | None:
    """A recorded response (the manifest's dict) -> CameraResponse, or None when it is absent or not a
    known model with a finite gamma in GAMMA_RANGE."""
    if not isinstance(value, dict):
        return None
    model, gamma = value.get("model"), value.get("gamma")
    if model not in RESPONSE_MODELS or isinstance(gamma, bool) or not isinstance(gamma, (int, float)):
        return None
    if not (math.isfinite(gamma) and GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]):
        return None
    return CameraResponse(str(model), float(gamma))


def recorded_response(camera_settings) -> CameraResponse | None:
    """The response a manifest's rig.camera_settings recorded (see parse_response), or None."""
    return parse_response(camera_settings.get("response")) if isinstance(camera_settings, dict) else None
