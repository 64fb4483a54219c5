"""A Sheet (app/board_sheet.py) as a file: vector PDF, vector SVG, or a PNG rasterised at a given dpi.

The PDF and SVG are written here directly, a few dozen lines each: a sheet is filled rectangles and
lines of text, nothing a library would add to. Both are deterministic (no dates, no ids, an uncompressed
content stream), so regenerated assets compare byte for byte. The PDF uses the standard Helvetica font,
which every PDF reader has, so nothing is embedded.

PNG pixel convention (as CharucoSpec.render): pixel (i, j) covers page x in [j, j + 1) / s mm and y in
[i, i + 1) / s mm with s = dpi / 25.4, so a page point (x, y) mm is at pixel (x s - 0.5, y s - 0.5).
Rectangles are drawn with their exact area coverage; text with OpenCV's Hershey font (annotation only).
"""

from __future__ import annotations

import io
from xml.sax.saxutils import escape

import cv2
import numpy as np

from app.board_sheet import CHAR_WIDTH_EM, Fill, Sheet, Text
from calib.errors import SpecError

PT_PER_MM = 72.0 / 25.4
MAX_PNG_PIXELS = 400_000_000


def _f(v: float) -> str:
    """A length for a vector file: 4 decimals (0.1 um in mm), no trailing zeros."""
    s = f"{float(v):.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _ascii(text: str) -> str:
    if not text.isascii():
        raise SpecError(f"sheet text must be ASCII, got {text!r}")
    return text


# ---- PDF --------------------------------------------------------------------------------------------
def _pdf_string(text: str) -> str:
    return "(" + _ascii(text).replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)") + ")"


def sheet_pdf(sheet: Sheet) -> bytes:
    """A one-page PDF 1.4 of `sheet` at true size (MediaBox in points, content drawn in mm)."""
    W, H = sheet.width_mm * PT_PER_MM, sheet.height_mm * PT_PER_MM
    ops = [f"{_f(PT_PER_MM)} 0 0 {_f(-PT_PER_MM)} 0 {_f(H)} cm"]  # user space: mm, y down, page top-left
    for item in sheet.items:
        if isinstance(item, Fill):
            ops.append(f"{_f(item.gray)} g")
            ops.extend(f"{_f(x)} {_f(y)} {_f(w)} {_f(h)} re" for x, y, w, h in item.rects)
            ops.append("f")
        elif isinstance(item, Text):
            x = item.x
            if item.anchor == "middle":
                x -= len(item.text) * item.size_mm * CHAR_WIDTH_EM / 2
            font = "/F2" if item.bold else "/F1"
            # the text matrix flips y back, so glyphs stand upright in the y-down user space
            ops.append(f"0 g BT {font} {_f(item.size_mm)} Tf 1 0 0 -1 {_f(x)} {_f(item.y)} Tm "
                       f"{_pdf_string(item.text)} Tj ET")
    content = ("\n".join(ops) + "\n").encode("ascii")
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_f(W)} {_f(H)}] "
         "/Resources << /Font << /F1 4 0 R /F2 5 0 R >> >> /Contents 6 0 R >>").encode("ascii"),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica-Bold /Encoding /WinAnsiEncoding >>",
        b"<< /Length %d >>\nstream\n" % len(content) + content + b"endstream",
        (f"<< /Title {_pdf_string(sheet.title)} /Subject {_pdf_string('print at 100% / actual size')} "
         f"/Producer (procam-station procam board) >>").encode("ascii"),
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for k, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % k + body + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R /Info 7 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (len(objects) + 1, xref)
    return bytes(out)


# ---- SVG --------------------------------------------------------------------------------------------
def _gray_hex(g: float) -> str:
    v = int(round(float(g) * 255))
    return f"#{v:02x}{v:02x}{v:02x}"


def sheet_svg(sheet: Sheet) -> str:
    """An SVG of `sheet` whose width and height are in mm (true size) and whose user unit is 1 mm."""
    w, h = _f(sheet.width_mm), _f(sheet.height_mm)
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}mm" height="{h}mm" viewBox="0 0 {w} {h}">',
           f"<title>{escape(_ascii(sheet.title))} - print at 100% / actual size</title>",
           f'<rect x="0" y="0" width="{w}" height="{h}" fill="#ffffff"/>']
    for item in sheet.items:
        if isinstance(item, Fill):
            d = " ".join(f"M{_f(x)} {_f(y)}h{_f(rw)}v{_f(rh)}h{_f(-rw)}z" for x, y, rw, rh in item.rects)
            out.append(f'<path fill="{_gray_hex(item.gray)}" d="{d}"/>')
        elif isinstance(item, Text):
            weight = ' font-weight="bold"' if item.bold else ""
            out.append(f'<text x="{_f(item.x)}" y="{_f(item.y)}" font-family="Helvetica, Arial, sans-serif" '
                       f'font-size="{_f(item.size_mm)}"{weight} text-anchor="{item.anchor}">'
                       f"{escape(_ascii(item.text))}</text>")
    out.append("</svg>")
    return "\n".join(out) + "\n"


# ---- PNG --------------------------------------------------------------------------------------------
def _coverage_1d(a: float, b: float, n: int) -> tuple[int, np.ndarray]:
    """(first pixel, coverage of pixels first..) of the interval [a, b) in pixel units, clipped to [0, n)."""
    a, b = max(a, 0.0), min(b, float(n))
    if b <= a:
        return 0, np.zeros(0)
    i0, i1 = int(np.floor(a)), int(np.ceil(b))
    edges = np.arange(i0, i1 + 1, dtype=float)
    return i0, np.clip(np.minimum(edges[1:], b) - np.maximum(edges[:-1], a), 0.0, 1.0)


def rasterise(sheet: Sheet, dpi: float) -> np.ndarray:
    """(H, W) uint8 image of `sheet` at `dpi` (white paper = 255)."""
    if not (np.isfinite(dpi) and 10 <= dpi <= 2400):
        raise SpecError(f"--dpi must be between 10 and 2400, got {dpi:g}")
    s = float(dpi) / 25.4
    W, H = int(round(sheet.width_mm * s)), int(round(sheet.height_mm * s))
    if W * H > MAX_PNG_PIXELS:
        raise SpecError(f"a {sheet.describe()} page at {dpi:g} dpi is {W} x {H} pixels; lower --dpi or write a PDF")
    out = np.empty((H, W), np.uint8)
    band = max(1, 4_000_000 // W)  # rows rendered at a time, in float: the memory stays small
    for r0 in range(0, H, band):
        r1 = min(H, r0 + band)
        view = np.ones((r1 - r0, W), np.float32)
        for item in sheet.items:
            if not isinstance(item, Fill):
                continue
            cover = np.zeros_like(view)
            for x, y, w, h in item.rects:
                i0, cy = _coverage_1d(y * s - r0, (y + h) * s - r0, r1 - r0)
                j0, cx = _coverage_1d(x * s, (x + w) * s, W)
                if cy.size and cx.size:
                    cover[i0 : i0 + cy.size, j0 : j0 + cx.size] += np.outer(cy, cx).astype(np.float32)
            np.minimum(cover, 1.0, out=cover)
            view *= 1.0 - cover
            view += np.float32(item.gray) * cover
        out[r0:r1] = np.round(view * 255.0)
    font = cv2.FONT_HERSHEY_SIMPLEX
    (_, cap_px), _ = cv2.getTextSize("H", font, 1.0, 1)
    for item in sheet.items:
        if isinstance(item, Text):
            scale = 0.72 * item.size_mm * s / cap_px
            thick = max(1, int(round(scale * (2.2 if item.bold else 1.4))))
            x = item.x * s
            if item.anchor == "middle":
                (tw, _), _ = cv2.getTextSize(item.text, font, scale, thick)
                x -= tw / 2
            cv2.putText(out, _ascii(item.text), (int(round(x)), int(round(item.y * s))), font, scale, 0, thick,
                        cv2.LINE_AA)
    return out


def png_bytes(image: np.ndarray, dpi: float | None = None) -> bytes:
    """PNG of `image` at maximum compression. With `dpi`, Pillow writes it with a pHYs chunk so that
    viewers and printers know its true size; without, OpenCV's encoder (the committed pattern images
    are its bytes)."""
    if dpi is None:
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if not ok:
            raise SpecError("OpenCV could not encode the PNG")
        return buf.tobytes()
    from PIL import Image

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(out, format="PNG", dpi=(dpi, dpi), compress_level=9)
    return out.getvalue()


def sheet_png(sheet: Sheet, dpi: float) -> bytes:
    return png_bytes(rasterise(sheet, dpi), dpi)
