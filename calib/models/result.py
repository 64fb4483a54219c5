"""The calibration result: a frozen dataclass and its file (calibration.json; exports: calib.export).

calibration.json keys (other tools read them; keep their meaning):
  camera, projector: {"width", "height", "K": 3x3, "dist": [k1, k2, p1, p2, k3, ...]}
  T_cam_proj: 4x4, maps projector coordinates to camera coordinates (p_cam = T_cam_proj @ p_proj)
  mirror: {"normal": [a, b, c], "d": d}, unit normal, a x + b y + c z + d = 0 in camera coordinates,
          normal oriented towards the camera (d > 0); null without a mirror
  units: length unit of the boards (and so of T_cam_proj's translation and mirror d)
  method, rms (per stage, pixels), per_view (residuals), skipped (images and why),
  uncertainty (1-sigma values, see README), diagnostics (free-form, per stage)
  projection_uncertainty: per-device grids of the 1-sigma pixel motion of a ray over the image
          (calib.quality.projection_uncertainty; null when the method gives no covariance; absent in older files)
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from calib.errors import FormatError
from calib.formats.fileio import RESULT_MAX_BYTES, atomic_write_text, read_json
from calib.models.boards import UNITS
from calib.models.camera import CameraModel, read_numbers

SCHEMA = "procam-calibration"
VERSION = 1


@dataclass(frozen=True, eq=False)
class MirrorPlane:
    """n . x + d = 0 in camera coordinates, n unit and pointing to the camera side (d > 0)."""

    normal: np.ndarray
    d: float

    def __post_init__(self):
        n = np.array(self.normal, float).reshape(3)
        norm = np.linalg.norm(n)
        if not norm > 0:
            raise ValueError("mirror normal must be non-zero")
        n, d = n / norm, float(self.d) / norm
        if d < 0:
            n, d = -n, -d
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "d", d)

    def reflection(self) -> np.ndarray:
        from calib.transforms import reflection_T

        return reflection_T(self.normal, self.d)

    def signed_distance(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, float).reshape(-1, 3) @ self.normal + self.d

    def to_dict(self) -> dict:
        return {"normal": self.normal.tolist(), "d": self.d}


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    camera: CameraModel
    projector: CameraModel
    T_cam_proj: np.ndarray
    mirror: MirrorPlane | None
    units: str
    method: str = "ground-truth"
    rms: dict = field(default_factory=dict)
    per_view: tuple = ()
    skipped: tuple = ()
    uncertainty: dict | None = None
    diagnostics: dict = field(default_factory=dict)
    projection_uncertainty: dict | None = None

    def __post_init__(self):
        T = np.array(self.T_cam_proj, float).reshape(4, 4)
        T.setflags(write=False)
        object.__setattr__(self, "T_cam_proj", T)

    def with_(self, **changes) -> "CalibrationResult":
        return replace(self, **changes)

    # ---- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "version": VERSION,
            "method": self.method,
            "units": self.units,
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "T_cam_proj": self.T_cam_proj.tolist(),
            "mirror": None if self.mirror is None else self.mirror.to_dict(),
            "rms": dict(self.rms),
            "per_view": list(self.per_view),
            "skipped": list(self.skipped),
            "uncertainty": self.uncertainty,
            "diagnostics": self.diagnostics,
            "projection_uncertainty": self.projection_uncertainty,
        }

    @classmethod
    def from_dict(cls, d: dict, path="<dict>") -> "CalibrationResult":
        """The result a calibration file's dict (untrusted) holds; FormatError naming the field of any value
        of the wrong type, shape or size (read_numbers). Well-formed values that are absurd (a negative
        focal length) load: the trust check (calib.quality.trust) says what is wrong with them."""
        if not isinstance(d, dict):
            raise FormatError(path, "<root>", "must be a JSON object")
        for key in ("camera", "projector", "T_cam_proj", "mirror", "units"):
            if key not in d:
                raise FormatError(path, key, "missing")
        cam = CameraModel.from_dict(d["camera"], "camera", path)
        proj = CameraModel.from_dict(d["projector"], "projector", path)
        T = read_numbers(d["T_cam_proj"], path, "T_cam_proj", (4, 4))
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise FormatError(path, "T_cam_proj", "must be a 4x4 rigid transform with last row [0, 0, 0, 1]")
        if not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) < 0:
            raise FormatError(path, "T_cam_proj", "rotation part is not a proper rotation matrix")
        if not isinstance(d["units"], str) or d["units"] not in UNITS:
            raise FormatError(path, "units", f"must be one of {', '.join(UNITS)}, got {str(d['units'])[:20]!r}")
        _check_types(d, path)
        return cls(
            camera=cam, projector=proj, T_cam_proj=T, mirror=_read_mirror(d["mirror"], path), units=d["units"],
            method=d.get("method") or "unknown", rms=d.get("rms") or {}, per_view=tuple(d.get("per_view") or ()),
            skipped=tuple(d.get("skipped") or ()), uncertainty=d.get("uncertainty"),
            diagnostics=d.get("diagnostics") or {},
            projection_uncertainty=_read_projection_uncertainty(d.get("projection_uncertainty"), path),
        )

    def save_json(self, path) -> None:
        atomic_write_text(path, json.dumps(_jsonable(self.to_dict()), indent=2) + "\n")

    @classmethod
    def load_json(cls, path) -> "CalibrationResult":
        """The one reader of calibration files (every command's and the station's): a regular file of the
        folder read as read_regular reads it, its bytes checked as untrusted JSON (calib.formats.jsonfile),
        then from_dict's checks of the values."""
        path = Path(path)
        try:
            data = read_json(path, RESULT_MAX_BYTES, "calibration file")
        except FileNotFoundError:
            raise FormatError(path, "<file>", "cannot be read: it does not exist") from None
        return cls.from_dict(data, path)


#: calibration.json's optional fields -> the JSON types they may have (null: absent)
_OPTIONAL_TYPES = {"method": (str,), "rms": (dict,), "per_view": (list,), "skipped": (list,),
                   "uncertainty": (dict,), "diagnostics": (dict,)}
_TYPE_NAMES = {str: "a string", dict: "an object", list: "a list"}


def _check_types(d: dict, path) -> None:
    """The optional fields' types; rms values numbers (or null), per_view and skipped entries objects."""
    for key, types in _OPTIONAL_TYPES.items():
        v = d.get(key)
        if v is not None and not isinstance(v, types):
            raise FormatError(path, key, f"must be {_TYPE_NAMES[types[0]]} or null, got {type(v).__name__}")
    for k, v in (d.get("rms") or {}).items():
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise FormatError(path, f"rms.{k}", f"must be a number (pixels) or null, got {type(v).__name__}")
    for key in ("per_view", "skipped"):
        for i, v in enumerate(d.get(key) or ()):
            if not isinstance(v, dict):
                raise FormatError(path, f"{key}[{i}]", f"must be an object, got {type(v).__name__}")


def _read_mirror(m, path) -> MirrorPlane | None:
    if m is None:
        return None
    if not isinstance(m, dict) or "normal" not in m or "d" not in m:
        raise FormatError(path, "mirror", 'must be null or {"normal": [a, b, c], "d": d}')
    n = read_numbers(m["normal"], path, "mirror.normal", (3,))
    dd = read_numbers(m["d"], path, "mirror.d", ())
    if not math.isclose(np.linalg.norm(n), 1.0, abs_tol=1e-6):
        raise FormatError(path, "mirror.normal", "must be a unit vector")
    return MirrorPlane(n, float(dd))


def _read_projection_uncertainty(pu, path):
    """Check calibration.json's "projection_uncertainty" (untrusted input): null/absent -> None; else
    each device's grid must be [nx, ny] with sigma_px ny rows of nx numbers (null = unbounded) or null."""
    if pu is None:
        return None
    where = "projection_uncertainty"
    if not isinstance(pu, dict):
        raise FormatError(path, where, "must be null or an object")
    out = dict(pu)
    for dev in ("camera", "projector"):
        g = pu.get(dev)
        if g is None:
            continue
        if not isinstance(g, dict):
            raise FormatError(path, f"{where}.{dev}", "must be an object")
        grid = g.get("grid")
        if (not isinstance(grid, list) or len(grid) != 2 or not all(isinstance(v, int) and 0 < v <= 1000 for v in grid)):
            raise FormatError(path, f"{where}.{dev}.grid", "must be [nx, ny], two positive integers")
        g = dict(g)
        s = g.get("sigma_px")
        if s is not None:
            try:
                a = np.array([[math.inf if v is None else float(v) for v in row] for row in s], float)
            except (TypeError, ValueError):
                raise FormatError(path, f"{where}.{dev}.sigma_px", "must be rows of numbers") from None
            if a.shape != (grid[1], grid[0]) or np.any(a < 0) or np.any(np.isnan(a)):
                raise FormatError(path, f"{where}.{dev}.sigma_px",
                                  f"must be {grid[1]} rows of {grid[0]} non-negative numbers")
            g["sigma_px"] = a.tolist()
        out[dev] = g
    return out


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
