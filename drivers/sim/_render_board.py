"""The boards' printed faces as textures (behind drivers/sim/render.py): the ChArUco print, its white
border and blank region, and the marks painted on it, cached per board and resolution."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from calib.models.boards import CharucoSpec
from calib.synthetic import BoardLayout


@lru_cache(maxsize=24)
def _board_texture(charuco: CharucoSpec, blank_width: float, gap: float, texels_per_square: int,
                   marks: tuple) -> tuple[np.ndarray, float, float]:
    """(texture uint8, texels per unit, origin) covering the board outline; texel (i, j) covers
    board x in [origin + j / s, origin + (j + 1) / s). Printed ChArUco, white elsewhere."""
    T = int(texels_per_square)
    s = T / charuco.square_length
    img = charuco.cv_board().generateImage((charuco.cols * T, charuco.rows * T), marginSize=0, borderBits=1)
    layout = BoardLayout(charuco, blank_width, gap)
    x0, y0, x1, y1 = layout.outline
    m = T // 2  # the outline's border is half a square: T / 2 texels
    right = int(np.ceil((x1 - charuco.size[0]) * s))
    bottom = int(np.ceil((y1 - charuco.size[1]) * s))
    tex = cv2.copyMakeBorder(img, m, bottom, m, right, cv2.BORDER_CONSTANT, value=255)
    for x, y, r, a in marks:
        # anti-aliased disc: 4 x 4 samples per texel
        cx, cy, rr = (x - x0) * s - 0.5, (y - y0) * s - 0.5, r * s
        ja, jb = int(np.floor(cx - rr - 1)), int(np.ceil(cx + rr + 2))
        ia, ib = int(np.floor(cy - rr - 1)), int(np.ceil(cy + rr + 2))
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        xs = (np.arange(ja, jb)[:, None] + sub).ravel() - cx
        ys = (np.arange(ia, ib)[:, None] + sub).ravel() - cy
        cover = ((ys[:, None] ** 2 + xs[None, :] ** 2) <= rr * rr).reshape(ib - ia, 4, jb - ja, 4).mean(axis=(1, 3))
        ca, cb = max(ia, 0), min(ib, tex.shape[0])
        ra, rb = max(ja, 0), min(jb, tex.shape[1])
        if ca >= cb or ra >= rb:
            continue
        cover = cover[ca - ia : cb - ia, ra - ja : rb - ja]
        patch = tex[ca:cb, ra:rb].astype(float)
        tex[ca:cb, ra:rb] = np.round(patch * (1 - cover) + 255 * a * cover).astype(np.uint8)
    tex = tex.astype(np.float32) / 255.0
    tex.setflags(write=False)
    return tex, s, x0


# board texture: about TEX_OVERSAMPLE texels per sample, pre-filtered with a Gaussian of TEX_BLUR texels
# (sigma) at 1 sample per pixel (live mode, where it is the only anti-aliasing), TEX_BLUR_SS with more
TEX_OVERSAMPLE = 2.0
TEX_BLUR = 1.5
TEX_BLUR_SS = 0.7


_blur_cache: dict = {}


def blurred(tex: np.ndarray, sigma: float) -> np.ndarray:
    k = (id(tex), sigma)
    hit = _blur_cache.get(k)
    if hit is not None and hit[0] is tex:
        return hit[1]
    if len(_blur_cache) > 16:
        _blur_cache.clear()
    b = cv2.GaussianBlur(tex, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    _blur_cache[k] = (tex, b)
    return b


def board_texture(layout: BoardLayout, texels_per_square: int, marks=()) -> tuple[np.ndarray, float, float, float]:
    """(texture float32 in [0, 1] (1 = white print), texels per unit, x origin, y origin)."""
    key = tuple((float(m.x), float(m.y), float(m.radius), float(m.albedo)) for m in marks)
    tex, s, x0 = _board_texture(layout.charuco, float(layout.blank_width), float(layout.gap), int(texels_per_square), key)
    return tex, s, x0, layout.outline[1]
