"""The exporters by name: EXPORTERS {name: Exporter(file names, writer)}. `procam calibrate` and the
station write the DEFAULTS beside calibration.json; `procam export` writes any of them."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

from calib.errors import ExportError
from calib.export import engine, mrcal, opencv, opengl, ros
from calib.export.common import ExportOptions, metres_per_unit


@dataclass(frozen=True)
class Exporter:
    files: tuple[str, ...]  # file names; {stem} is the calibration file's name without .json
    write: Callable  # write(result, paths, options) -> warnings (one line each)
    summary: str
    default: bool = False
    metric: bool = False  # converts lengths to metres (needs a known unit)

    def paths(self, folder, stem: str) -> tuple[Path, ...]:
        return tuple(Path(folder) / f.format(stem=stem) for f in self.files)


EXPORTERS = {
    "opencv": Exporter(("{stem}.yaml",), opencv.write, "OpenCV FileStorage YAML (both devices, pose, mirror)",
                       default=True),
    "ros": Exporter(("{stem}-camera.ros.yaml", "{stem}-projector.ros.yaml"), ros.write,
                    "ROS camera_info YAML per device", metric=True),
    "mrcal": Exporter(("{stem}-camera.cameramodel", "{stem}-projector.cameramodel"), mrcal.write,
                      "mrcal .cameramodel per device"),
    "opengl": Exporter(("{stem}-opengl.json",), opengl.write, "OpenGL projection and view matrices", metric=True),
    "unity": Exporter(("{stem}-unity.json",), partial(engine.write, "unity"), "Unity physical cameras", metric=True),
    "threejs": Exporter(("{stem}-threejs.json",), partial(engine.write, "threejs"), "three.js cameras", metric=True),
}
DEFAULTS = tuple(name for name, e in EXPORTERS.items() if e.default)


def parse_formats(text: str) -> tuple[str, ...]:
    """`--format` NAME[,NAME...] or `all` -> names in registry order; an unknown name lists the formats."""
    if text.strip() == "all":
        return tuple(EXPORTERS)
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in EXPORTERS]
    if unknown or not names:
        what = f"unknown export format '{unknown[0]}'" if unknown else "no export format given"
        raise ExportError(f"{what}; the formats are {', '.join(EXPORTERS)} (or all; several: ros,mrcal)")
    return tuple(n for n in EXPORTERS if n in names)


def output_paths(names, folder, stem: str) -> list[Path]:
    return [p for n in names for p in EXPORTERS[n].paths(folder, stem)]


def write_exports(result, names, folder, stem: str, options: ExportOptions | None = None) -> list[str]:
    """Write the formats `names` of `result` into `folder`; the warnings (a distortion a target cannot
    represent, with its residual in px)."""
    options = options or ExportOptions()
    if any(EXPORTERS[n].metric for n in names):
        metres_per_unit(result.units)  # an unknown unit fails here, before any file is written
    warnings = []
    for name in names:
        exporter = EXPORTERS[name]
        warnings += exporter.write(result, exporter.paths(folder, stem), options)
    return warnings


def trust_reasons(result) -> list[str]:
    """Why the trust check rejects `result` (empty when it does not): the reasons recorded in the file
    (a calibration written with --accept-untrusted) or found by running the check again."""
    from calib.quality.trust import check_calibration

    recorded = (result.diagnostics or {}).get("trust") if isinstance(result.diagnostics, dict) else None
    if isinstance(recorded, dict) and recorded.get("passed") is False:
        reasons = recorded.get("reasons") or []
        return [f"[{r.get('code')}] {r.get('message')}" if isinstance(r, dict) else str(r) for r in reasons] \
            or ["the file records a failed trust check"]
    return [f"[{r.code}] {r.message}" for r in check_calibration(result).reasons]
