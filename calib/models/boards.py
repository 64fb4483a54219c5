"""ChArUco board specifications.

Board frame (OpenCV's): origin at the top-left outer corner of the printed ChArUco area, +x along the
columns, +y along the rows (down the printed page), z = 0 on the printed face, +z into the board.
Lengths are in the board's `units` (mm, cm, m), which are the units of every calibrated translation.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from calib.errors import FormatError, SpecError
from calib.models.vocab import LengthUnit, choices

UNITS = choices(LengthUnit)
#: millimetres per unit of UNITS
MM_PER_UNIT = {u.value: u.mm for u in LengthUnit}
#: the range of a board's square side in millimetres: a printed board from a fingertip to a wall; beyond it
#: a length is a corrupt value (and OpenCV's board geometry fails on it)
SQUARE_MM_RANGE = (0.1, 10000.0)
#: a marker at least this share of its square: smaller ones cannot be read in any image
MIN_MARKER_FRACTION = 0.1


def _aruco_dictionary_id(name: str) -> int:
    value = getattr(cv2.aruco, name, None)
    if not name.startswith("DICT_") or not isinstance(value, int):
        raise SpecError(f"unknown ArUco dictionary '{name}' (use a name like DICT_5X5_50, DICT_4X4_250)")
    return value


@dataclass(frozen=True)
class CharucoSpec:
    """cols x rows squares, ArUco dictionary, square and marker side lengths in `units`."""

    cols: int
    rows: int
    dictionary: str
    square_length: float
    marker_length: float
    units: str = LengthUnit.MM

    def __post_init__(self):
        if self.cols < 2 or self.rows < 2:
            raise SpecError(f"a ChArUco board needs at least 2x2 squares, got {self.cols}x{self.rows}")
        if self.units not in UNITS:
            raise SpecError(f"unknown length unit '{self.units}' (one of {', '.join(UNITS)})")
        lo, hi = (v / MM_PER_UNIT[self.units] for v in SQUARE_MM_RANGE)
        if not lo <= self.square_length <= hi:
            raise SpecError(f"square_length {self.square_length:g} {self.units} is outside {lo:g}-{hi:g} {self.units} "
                            f"(no printed board has it): give the square side in {self.units}")
        if not 0 < self.marker_length < self.square_length:
            raise SpecError(
                f"need 0 < marker_length < square_length, got square {self.square_length}, "
                f"marker {self.marker_length}"
            )
        if self.marker_length < MIN_MARKER_FRACTION * self.square_length:
            raise SpecError(f"marker_length {self.marker_length:g} is under {MIN_MARKER_FRACTION:g} x square_length "
                            f"{self.square_length:g} {self.units}: no camera reads so small a marker")
        dict_id = _aruco_dictionary_id(self.dictionary)
        n_markers = (self.cols * self.rows) // 2
        size = cv2.aruco.getPredefinedDictionary(dict_id).bytesList.shape[0]
        if n_markers > size:
            raise SpecError(f"a {self.cols}x{self.rows} board needs {n_markers} markers; {self.dictionary} has {size}")

    @classmethod
    def parse(cls, text: str, units: str = LengthUnit.MM) -> "CharucoSpec":
        """'COLSxROWS:DICT:SQUARE[:MARKER]', e.g. '8x6:DICT_5X5_50:4.43' (marker defaults to square / 2)."""
        m = re.fullmatch(r"\s*(\d+)[xX](\d+):(DICT_\w+):([0-9.eE+-]+)(?::([0-9.eE+-]+))?\s*", text)
        if not m:
            raise SpecError(
                f"board spec '{text}' does not parse; expected COLSxROWS:DICTIONARY:SQUARE[:MARKER], "
                "e.g. 8x6:DICT_5X5_50:4.43"
            )
        try:
            square = float(m.group(4))
            marker = float(m.group(5)) if m.group(5) else square / 2.0
        except ValueError:
            raise SpecError(f"board spec '{text}': square/marker length is not a number") from None
        return cls(int(m.group(1)), int(m.group(2)), m.group(3), square, marker, units)

    def in_units(self, units: str) -> "CharucoSpec":
        """The same physical board with its lengths expressed in `units`."""
        if units == self.units:
            return self
        if units not in MM_PER_UNIT:
            raise SpecError(f"unknown length unit '{units}' (one of {', '.join(UNITS)})")
        f = MM_PER_UNIT[self.units] / MM_PER_UNIT[units]
        return CharucoSpec(self.cols, self.rows, self.dictionary, self.square_length * f, self.marker_length * f, units)

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows}:{self.dictionary}:{self.square_length:g}:{self.marker_length:g} {self.units}"

    # ---- geometry -------------------------------------------------------------------------------
    @property
    def n_corners(self) -> int:
        return (self.cols - 1) * (self.rows - 1)

    @property
    def size(self) -> tuple[float, float]:
        """(width, height) of the printed ChArUco area in `units`."""
        return (self.cols * self.square_length, self.rows * self.square_length)

    def corner_points(self) -> np.ndarray:
        """(n_corners, 3) board-frame positions of the ChArUco corners, indexed by corner id."""
        return _corner_points(self.cols, self.rows, self.square_length).copy()

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        return _cv_board(self)

    def render(self, px_per_unit: float, margin_px: int = 0) -> np.ndarray:
        """The printed board as a grayscale image; pixel (i, j) covers board x in [j, j+1)/px_per_unit
        (shifted by the margin), so board point (x, y) is at pixel (x * s - 0.5 + margin, ...)."""
        w = int(round(self.size[0] * px_per_unit))
        h = int(round(self.size[1] * px_per_unit))
        img = self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)
        if margin_px:
            img = cv2.copyMakeBorder(img, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
        return img

    # ---- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "cols": self.cols,
            "rows": self.rows,
            "dictionary": self.dictionary,
            "square_length": self.square_length,
            "marker_length": self.marker_length,
            "units": self.units,
        }

    @classmethod
    def from_dict(cls, d, where: str = "board", path="<dict>") -> "CharucoSpec":
        if not isinstance(d, dict):
            raise FormatError(path, where, "must be an object")
        for key, typ in (("cols", int), ("rows", int), ("dictionary", str), ("square_length", (int, float)),
                         ("marker_length", (int, float)), ("units", str)):
            if key not in d:
                raise FormatError(path, f"{where}.{key}", "missing")
            if not isinstance(d[key], typ) or isinstance(d[key], bool):
                raise FormatError(path, f"{where}.{key}", f"has the wrong type ({type(d[key]).__name__})")
        if d["units"] not in UNITS:
            raise FormatError(path, f"{where}.units", f"unknown length unit '{d['units']}' (one of {', '.join(UNITS)})")
        try:
            return cls(d["cols"], d["rows"], d["dictionary"], float(d["square_length"]),
                       float(d["marker_length"]), d["units"])
        except SpecError as e:
            raise FormatError(path, where, str(e)) from None


@lru_cache(maxsize=32)
def _corner_points(cols: int, rows: int, square: float) -> np.ndarray:
    j, i = np.meshgrid(np.arange(1, cols), np.arange(1, rows))
    return np.column_stack([j.ravel() * square, i.ravel() * square, np.zeros(j.size)])


@lru_cache(maxsize=32)
def _cv_board(spec: CharucoSpec) -> cv2.aruco.CharucoBoard:
    dictionary = cv2.aruco.getPredefinedDictionary(_aruco_dictionary_id(spec.dictionary))
    return cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_length, spec.marker_length, dictionary)
