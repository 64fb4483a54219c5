"""A frame's capture time carried in the image itself: a strip of black and white cells under the picture.

    strip = encode_stamp(FrameStamp(frame_number=7, exposure_start_us=1_000_033_333, exposure_us=16_667.0, gain=2.0), 1280)
    image_with_strip = np.vstack([image, strip])          # what a source streams
    image, stamp = split_stamp(image_with_strip)          # what drivers/opencv_camera.py hands on

Why: a stream that OpenCV opens (MJPEG over HTTP, the simulated camera's live stream in
drivers/sim/stream.py) carries no per-frame metadata VideoCapture can read, so the moment a frame's
exposure began, its exposure and its gain travel in the pixels. The strip survives JPEG: every bit is
an 8x8 cell, black (0) or white (1), read at its centre; the strip's height is a multiple of 16 rows, so
no JPEG block (16x16 with chroma subsampling) mixes the strip with the picture when the picture's
height is a multiple of 16. Layout, row by row, left to right, `width // 8` cells a row:
MAGIC (16 bits), frame_number (32), exposure_start_us (64, the source's clock), exposure in 1/100 us
(32), gain in 1/1000 (32), a CRC-16/CCITT of the fields (16). A strip that does not decode (another
source, a damaged frame) is None: the caller drops the frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MAGIC = 0x9C5A
CELL_PX = 8
#: (field, bits) in order
FIELDS = (("magic", 16), ("frame_number", 32), ("exposure_start_us", 64), ("exposure_cus", 32), ("gain_milli", 32))
CRC_BITS = 16
BITS = sum(b for _, b in FIELDS) + CRC_BITS


@dataclass(frozen=True)
class FrameStamp:
    """What the source knew about one frame: its own frame counter, the start of its exposure on the
    source's clock (microseconds), the exposure (us) and the gain it was taken with."""

    frame_number: int
    exposure_start_us: int
    exposure_us: float
    gain: float

    @property
    def exposure_start_s(self) -> float:
        return self.exposure_start_us * 1e-6


def strip_rows(width: int) -> int:
    """Rows of the strip under a picture `width` pixels wide (a multiple of 16)."""
    per_row = int(width) // CELL_PX
    if per_row < 1:
        raise ValueError(f"a picture {width} px wide is too narrow for a frame stamp")
    rows = math.ceil(BITS / per_row) * CELL_PX
    return int(math.ceil(rows / 16) * 16)


def _crc16(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def _field_values(stamp: FrameStamp) -> list[int]:
    return [MAGIC, int(stamp.frame_number) & 0xFFFFFFFF, int(stamp.exposure_start_us) & (2**64 - 1),
            int(round(stamp.exposure_us * 100.0)) & 0xFFFFFFFF, int(round(stamp.gain * 1000.0)) & 0xFFFFFFFF]


def _payload(values: list[int]) -> bytes:
    return b"".join(v.to_bytes(bits // 8, "big") for v, (_, bits) in zip(values, FIELDS))


def encode_stamp(stamp: FrameStamp, width: int) -> np.ndarray:
    """The strip ((strip_rows(width), width, 3) uint8) that carries `stamp`."""
    values = _field_values(stamp)
    bits = []
    for v, (_, n) in zip(values + [_crc16(_payload(values))], FIELDS + (("crc", CRC_BITS),)):
        bits.extend((v >> (n - 1 - k)) & 1 for k in range(n))
    per_row = int(width) // CELL_PX
    strip = np.zeros((strip_rows(width), int(width), 3), np.uint8)
    for i, b in enumerate(bits):
        if b:
            r, c = divmod(i, per_row)
            strip[r * CELL_PX:(r + 1) * CELL_PX, c * CELL_PX:(c + 1) * CELL_PX] = 255
    return strip


def decode_stamp(strip: np.ndarray) -> FrameStamp | None:
    """The stamp a strip carries, or None when it carries none (wrong magic or checksum)."""
    a = np.asarray(strip)
    if a.ndim == 3:
        a = a.mean(axis=2)
    h, w = a.shape[:2]
    per_row = w // CELL_PX
    if per_row < 1 or h < math.ceil(BITS / per_row) * CELL_PX:
        return None
    q = CELL_PX // 4
    bits = []
    for i in range(BITS):
        r, c = divmod(i, per_row)
        cell = a[r * CELL_PX + q:(r + 1) * CELL_PX - q, c * CELL_PX + q:(c + 1) * CELL_PX - q]
        bits.append(1 if float(cell.mean()) >= 128.0 else 0)
    values, k = [], 0
    for _, n in FIELDS + (("crc", CRC_BITS),):
        v = 0
        for b in bits[k:k + n]:
            v = (v << 1) | b
        values.append(v)
        k += n
    if values[0] != MAGIC or _crc16(_payload(values[:-1])) != values[-1]:
        return None
    return FrameStamp(values[1], values[2], values[3] / 100.0, values[4] / 1000.0)


def split_stamp(image: np.ndarray) -> tuple[np.ndarray, FrameStamp | None]:
    """(the picture above the strip, the stamp) of a frame that carries one."""
    rows = strip_rows(image.shape[1])
    if image.shape[0] <= rows:
        return image, None
    return image[:-rows], decode_stamp(image[-rows:])
