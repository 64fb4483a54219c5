"""Renderer of what the simulated camera sees: a physically plausible, per-pixel ray-traced image.

Scene (camera frame = world frame, lengths in mm):
- the camera: CameraModel with Brown-Conrady distortion; one ray per sample, precomputed and cached;
- an optional finite first-surface mirror (MirrorPlane + MirrorRect): camera rays that meet the plane
  inside the rectangle continue reflected, scaled by the mirror's reflectance;
- boards (BoardLayout: printed ChArUco area, white border, blank region where the pattern lands), each
  at a pose T_cam_board; the printed face is z = 0 facing -z (board frame), the back is plain grey;
- the projector: an inverse camera (its own intrinsics and distortion) at T_cam_proj lighting every
  board face turned towards it with its current image (Lambertian, cosine and 1/r^2 fall-off);
- ambient light and a smooth, non-uniform background (a function of the ray direction).

Per sample, the nearest hit wins: a board seen directly, the mirror (then the board seen through it,
i.e. the board at pose S @ T_cam_board seen directly, or the background in the reflected direction),
or the background. Board and projector images are looked up with cv2.remap from maps computed in
numpy; the plane-to-plane steps use exact homographies on undistorted normalized coordinates.

Then: box-filter supersampling (anti-aliasing), Gaussian optical blur, shot + read noise, 8-bit
quantisation; each can be switched off. Pixel (0, 0) is the centre of the top-left pixel; the
`supersample` x `supersample` samples of pixel (i, j) sit symmetrically about that centre.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np

from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.result import MirrorPlane
from calib.models.vocab import RenderQuality, choices
from calib.synthetic import BoardLayout, MirrorRect
from calib.transforms import invert_T

# ---- settings -------------------------------------------------------------------------------------
QUALITIES = choices(RenderQuality)


@dataclass(frozen=True)
class RenderSettings:
    """Everything that shapes the image, apart from the geometry. Intensities are relative to a
    white (albedo 1) surface under unit light mapping to 255."""

    supersample: int = 3  # samples per pixel along each axis (anti-aliasing); 1 = off
    ambient: float = 0.5  # ambient illumination
    projector_gain: float = 0.5  # illumination of a full-white projector pixel at the reference distance
    projector_falloff: bool = True  # cosine and 1/r^2 fall-off of the projector's light
    reference_distance_mm: float = 950.0  # distance at which the projector's light has `projector_gain`
    white_albedo: float = 0.85
    black_albedo: float = 0.04
    back_albedo: float = 0.45  # the board's unprinted back
    mirror_reflectance: float = 0.92
    background: bool = True  # False: a flat dark grey background
    background_level: float = 0.22
    blur_sigma_px: float = 0.0  # optical blur (Gaussian), 0 = off
    read_noise_dn: float = 0.0  # read noise sigma in 8-bit levels, 0 = off
    electrons_per_dn: float = 0.0  # shot noise: photo-electrons per 8-bit level, 0 = off
    quantize: bool = True  # 8-bit output (False: float32 levels, for tests)
    # photometric realism (docs/SIMULATOR.md "Photometric realism"); each value here switches it off
    projector_gamma: float = 1.0  # light = level ** gamma (level in [0, 1] of the projector's image)
    projector_black_level: float = 0.0  # light of a projector pixel at level 0, fraction of full white
    projector_aperture_mm: float = 0.0  # lens aperture diameter: defocus blur away from the focus; 0 = pinhole
    projector_focus_mm: float = 0.0  # distance (along the projector's axis) in focus; 0 = reference_distance_mm
    vignetting_corner: float = 1.0  # relative irradiance at the farthest image corner (cos^4-shaped fall-off)
    camera_gamma: float = 1.0  # the camera's encoding: level ~ light ** (1 / gamma), BT.709-like toe

    def __post_init__(self):
        if int(self.supersample) < 1:
            raise ValueError("supersample must be >= 1")
        if not (self.projector_gamma > 0 and self.camera_gamma >= 1.0):
            raise ValueError("projector_gamma must be > 0 and camera_gamma >= 1")
        if not (0.0 <= self.projector_black_level < 1.0 and 0.0 < self.vignetting_corner <= 1.0):
            raise ValueError("projector_black_level must be in [0, 1) and vignetting_corner in (0, 1]")
        if not (self.projector_aperture_mm >= 0 and self.projector_focus_mm >= 0):
            raise ValueError("projector_aperture_mm and projector_focus_mm must be >= 0")

    @classmethod
    def for_quality(cls, quality: str, **overrides) -> "RenderSettings":
        """'live': 1 sample per pixel (fast, for the live demo); 'session': 3 x 3 samples."""
        if quality not in QUALITIES:
            raise ValueError(f"unknown quality '{quality}' (one of {', '.join(QUALITIES)})")
        base = cls(supersample=1 if quality == "live" else 3)
        return replace(base, **overrides)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def without_noise(self) -> "RenderSettings":
        return replace(self, blur_sigma_px=0.0, read_noise_dn=0.0, electrons_per_dn=0.0)

    def photometrically_neutral(self) -> "RenderSettings":
        """The same settings with every photometric-realism effect off (the renderer before issue 18)."""
        return replace(self, projector_gamma=1.0, projector_black_level=0.0, projector_aperture_mm=0.0,
                       projector_focus_mm=0.0, vignetting_corner=1.0, camera_gamma=1.0)


# ---- photometric curves ---------------------------------------------------------------------------
from calib.detection.response import BT709_OFFSET as _TOE_OFFSET  # with exponent 0.45: BT.709 itself


def encode_gamma(light: np.ndarray, gamma: float) -> np.ndarray:
    """A camera's tone curve: relative light in [0, 1] -> relative level, V = (1 + a) L^(1/gamma) - a
    above a threshold and a straight line through 0 below it, joined with the same value and slope
    (BT.709's construction; gamma = 1 / 0.45 gives BT.709). gamma = 1 returns `light` unchanged."""
    if gamma == 1.0:
        return light
    p = 1.0 / gamma
    a = _TOE_OFFSET
    t = (a / ((1 + a) * (1 - p))) ** (1 / p)
    slope = (1 + a) * p * t ** (p - 1)
    L = np.asarray(light, np.float32)
    hi = np.float32(1 + a) * np.power(np.maximum(L, np.float32(t)), np.float32(p)) - np.float32(a)
    return np.where(L < t, np.float32(slope) * L, hi).astype(np.float32)


_LUT_STEPS = 256  # linear levels per 8-bit level in the encoding table


@lru_cache(maxsize=4)
def _encode_lut(gamma: float) -> np.ndarray:
    """uint8 output level of each linear level k / _LUT_STEPS (0..255): the tone curve and the 8-bit
    rounding as one table. A pixel lands within 1/512 of a linear level of its exact value, so it differs
    from the exact rounding by one level only right at a rounding threshold (under 2 % of pixels in the
    steepest part of the curve, near black, where the noise is several levels)."""
    lin = np.arange(255 * _LUT_STEPS + 1, dtype=np.float32) / np.float32(255 * _LUT_STEPS)
    out = np.clip(255.0 * encode_gamma(lin, gamma) + 0.5, 0, 255).astype(np.uint8)
    out.setflags(write=False)
    return out


def decode_gamma(level: np.ndarray, gamma: float) -> np.ndarray:
    """The inverse of encode_gamma: relative level -> relative light (the detector's own inverse,
    calib.detection.response, so the simulator and the correction share one curve)."""
    if gamma == 1.0:
        return level
    from calib.detection.response import CameraResponse

    return CameraResponse("bt709", float(gamma)).decode(level).astype(np.float32)


def defocus_sigma_px(depth_mm, aperture_mm: float, focus_mm: float, f_px: float):
    """Thin-lens defocus of a projector focused at `focus_mm`: the circle of confusion of a point at
    `depth_mm` (along the axis) has diameter aperture * f * |1/depth - 1/focus| in image pixels; the
    returned Gaussian sigma is that of a uniform disc of this diameter (diameter / 4)."""
    return np.float32(aperture_mm * f_px / 4.0) * np.abs(np.float32(1.0) / depth_mm - np.float32(1.0 / focus_mm))


def vignetting_map(camera: CameraModel, corner: float) -> np.ndarray:
    """Relative irradiance per pixel, (H, W) float32: 1 on the optical axis, cos^4 of the ray's angle
    rescaled so that the farthest image corner receives `corner` (a lens whose cos^4 fall-off the
    image processor partly corrects keeps this shape with a smaller depth)."""
    nx, ny = normalized_grid(camera, 1)
    c4 = 1.0 / (1.0 + nx.astype(np.float64) ** 2 + ny.astype(np.float64) ** 2) ** 2  # cos^4 of the angle
    W, H = camera.size
    ends = _undistort_exact(camera, np.array([[0.0, 0.0], [W - 1.0, 0.0], [0.0, H - 1.0], [W - 1.0, H - 1.0]]))
    c4_corner = float((1.0 / (1.0 + (ends ** 2).sum(axis=1)) ** 2).min())
    v = 1.0 - (1.0 - corner) * (1.0 - c4) / (1.0 - c4_corner)
    return np.maximum(v, 0.0).astype(np.float32)


# ---- scene state ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Mark:
    """A disc painted on a board (board coordinates, radius in board units, albedo)."""

    x: float
    y: float
    radius: float
    albedo: float = 1.0


@dataclass(frozen=True, eq=False)
class PlacedBoard:
    layout: BoardLayout
    T_cam_board: np.ndarray
    marks: tuple = ()  # Mark(s), painted on top of the print (used by tests: a bright dot)


@dataclass(frozen=True, eq=False)
class SceneState:
    boards: tuple = ()  # PlacedBoard(s)
    projector_image: np.ndarray | None = None  # (H, W) uint8 or float32 in [0, 1]; None = dark


def layout_for(board: CharucoSpec) -> BoardLayout:
    """A plain ChArUco board (no blank region): the mirror-calibration board."""
    return BoardLayout(board, blank_width=0.0, gap=0.0)


# ---- caches ---------------------------------------------------------------------------------------
def _cam_key(cam: CameraModel) -> tuple:
    return (cam.width, cam.height, cam.K.tobytes(), cam.dist.tobytes())


_grid_lock = threading.Lock()
_grid_cache: dict = {}


def normalized_grid(camera: CameraModel, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalized coordinates (x/z, y/z) of every sample, (H*s, W*s) float32 each.

    Sample (I, J) of the supersampled grid is at pixel ((J + 0.5) / s - 0.5, (I + 0.5) / s - 0.5):
    the s x s samples of a pixel are symmetric about its centre. Cached per camera and s."""
    key = (_cam_key(camera), int(supersample))
    with _grid_lock:
        hit = _grid_cache.get(key)
        if hit is not None:
            return hit
    s = int(supersample)
    W, H = camera.size
    xs = (np.arange(W * s) + 0.5) / s - 0.5
    ys = (np.arange(H * s) + 0.5) / s - 0.5
    X, Y = np.meshgrid(xs, ys)
    uv = np.column_stack([X.ravel(), Y.ravel()])
    xy = _undistort_exact(camera, uv)
    nx = xy[:, 0].reshape(H * s, W * s).astype(np.float32)
    ny = xy[:, 1].reshape(H * s, W * s).astype(np.float32)
    nx.setflags(write=False)
    ny.setflags(write=False)
    with _grid_lock:
        if len(_grid_cache) > 6:
            _grid_cache.clear()
        _grid_cache[key] = (nx, ny)
    return nx, ny


def _undistort_exact(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    """CameraModel.undistort_normalized, done fast for millions of pixels: OpenCV's iteration run to
    convergence, checked by re-projection; points it leaves off by > 1e-6 px get Newton steps."""
    if camera.dist.size == 0 or not np.any(camera.dist):
        return camera.undistort_normalized(uv)
    crit = (cv2.TERM_CRITERIA_COUNT, 10, 0.0)  # converges to ~1e-11 px for lens-like distortion
    out = np.empty_like(uv)
    step = 1 << 20
    for a in range(0, len(uv), step):
        chunk = uv[a : a + step]
        xy = cv2.undistortPoints(chunk.reshape(-1, 1, 2), camera.K, camera.dist, criteria=crit).reshape(-1, 2)
        err = np.abs(camera.normalized_to_pixels(camera.distort_normalized(xy)) - chunk).max(axis=1)
        bad = ~(err < 1e-6)
        if np.any(bad):
            xy[bad] = camera.undistort_normalized(chunk[bad])
        out[a : a + step] = xy
    return out


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


def _blurred(tex: np.ndarray, sigma: float) -> np.ndarray:
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


def _background(dx, dy, dz, level: float) -> np.ndarray:
    """A smooth room-like background as a function of the direction: broad gradients and soft
    bands, nothing with corners or blobs at the scale of a board."""
    az = np.arctan2(dx, dz)
    el = np.arctan2(dy, np.hypot(dx, dz))
    v = (level + 0.07 * np.sin(1.7 * az + 0.4) * np.cos(2.3 * el - 0.3) + 0.05 * np.sin(3.1 * az - 2.0 * el + 1.1)
         + 0.04 * np.cos(0.9 * az + 4.2 * el) - 0.06 * el)
    return np.clip(v, 0.02, 1.0).astype(np.float32)


# ---- the renderer -----------------------------------------------------------------------------------
class Renderer:
    """Renders camera images of a rig (camera, projector, optional finite mirror) for a SceneState."""

    def __init__(self, camera: CameraModel, projector: CameraModel, T_cam_proj: np.ndarray,
                 mirror: MirrorPlane | None = None, mirror_rect: MirrorRect | None = None,
                 settings: RenderSettings | None = None):
        if (mirror is None) != (mirror_rect is None):
            raise ValueError("give both the mirror plane and its rectangle, or neither")
        self.camera = camera
        self.projector = projector
        self.T_cam_proj = np.array(T_cam_proj, float)
        self.T_proj_cam = invert_T(self.T_cam_proj)
        self.mirror = mirror
        self.mirror_rect = mirror_rect
        self.settings = settings or RenderSettings()
        self._static: dict = {}
        # the last few projector images' light pyramids and defocused copies: (image, key, levels,
        # {(level, k): blurred}); a hardware-like frame blends the images shown during its exposure
        self._proj_cache: list = []
        self._vignetting: tuple | None = None

    # ---- static (per camera / supersampling) data ------------------------------------------------
    def _static_for(self, s: int) -> dict:
        st = self._static.get(s)
        if st is not None:
            return st
        nx, ny = normalized_grid(self.camera, s)
        st = {"nx": nx, "ny": ny}
        st["bg"] = self._background_grid(nx, ny, None)
        if self.mirror is not None:
            n, d = self.mirror.normal.astype(np.float32), np.float32(self.mirror.d)
            den = n[0] * nx + n[1] * ny + n[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = -d / den  # depth (z) where the ray meets the mirror plane
            rect = self.mirror_rect
            c = rect.centre.astype(np.float32)
            mask = np.isfinite(lam) & (lam > 0)
            for axis, half in ((rect.axis_u, rect.size[0] / 2), (rect.axis_v, rect.size[1] / 2)):
                a = axis.astype(np.float32)
                coord = lam * (a[0] * nx + a[1] * ny + a[2]) - np.float32(a @ c)
                mask &= np.abs(coord) <= half
            ys, xs = np.nonzero(mask)
            if len(ys):
                box = (ys.min(), ys.max() + 1, xs.min(), xs.max() + 1)
                y0, y1, x0, x1 = box
                sub = (slice(y0, y1), slice(x0, x1))
                cx, cy = nx[sub], ny[sub]
                bgr = self._background_grid(cx, cy, n)
                st["mirror"] = {"box": box, "mask": mask[sub].copy(), "lam": np.where(mask, lam, np.inf)[sub].astype(np.float32),
                                "bg": bgr}
            else:
                st["mirror"] = None
        else:
            st["mirror"] = None
        self._static[s] = st
        return st

    def _background_grid(self, nx, ny, n) -> np.ndarray:
        """The background seen along the rays of a grid (reflected by the plane of normal n, if given).
        It is smooth: computed on a 4x coarser grid and interpolated."""
        if not self.settings.background:
            return np.full(nx.shape, self.settings.background_level, np.float32)
        cx, cy = nx[::4, ::4], ny[::4, ::4]
        if n is None:
            rx, ry, rz = cx, cy, np.ones_like(cx)
        else:
            dn = n[0] * cx + n[1] * cy + n[2]
            rx, ry, rz = cx - 2 * dn * n[0], cy - 2 * dn * n[1], 1 - 2 * dn * n[2]
        small = _background(rx, ry, rz, self.settings.background_level)
        big = cv2.resize(small, (small.shape[1] * 4, small.shape[0] * 4), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(big[: nx.shape[0], : nx.shape[1]])

    def warm_up(self) -> None:
        """Compute the cached rays etc. now rather than on the first frame."""
        self._static_for(int(self.settings.supersample))

    # ---- projector image pyramid ---------------------------------------------------------------------
    def _projector_levels(self, image, st: RenderSettings | None = None) -> list[np.ndarray] | None:
        """The projector's light (relative to full white) as a pyrDown pyramid: its image's levels
        through the projector's response (gamma, black level). None: the projector is off (dark)."""
        if image is None:
            return None
        st = st or self.settings
        key = (float(st.projector_gamma), float(st.projector_black_level))
        for entry in self._proj_cache:
            if entry[0] is image and entry[1] == key:
                return entry[2]
        img = np.asarray(image)
        gamma, black = key
        if img.ndim == 3:
            img = img.astype(np.float32).mean(axis=2)
        if img.dtype == np.uint8 and (gamma != 1.0 or black > 0):
            # the response of each of the 256 levels, looked up (the same numbers, faster)
            lut = np.power(np.arange(256, dtype=np.float32) / np.float32(255.0), np.float32(gamma))
            img = np.take(np.float32(black) + np.float32(1.0 - black) * lut, img)
            gamma, black = 1.0, 0.0
        elif img.dtype == np.uint8:
            img = img.astype(np.float32) / 255.0
        img = np.ascontiguousarray(img, np.float32)
        if img.shape != (self.projector.height, self.projector.width):
            raise ValueError(f"projector image is {img.shape[1]}x{img.shape[0]}, the projector is "
                             f"{self.projector.width}x{self.projector.height}")
        if gamma != 1.0:
            img = np.power(np.clip(img, 0.0, 1.0), np.float32(gamma))
        if black > 0:
            img = np.float32(black) + np.float32(1.0 - black) * img
        levels = [img]
        while min(levels[-1].shape) > 64 and len(levels) < 6:
            # pyrDown: output pixel i is centred on input pixel 2 i, so q_level = q / 2^level exactly
            levels.append(cv2.pyrDown(levels[-1]))
        self._proj_cache = [(image, key, levels, {})] + self._proj_cache[:3]
        return levels

    def _defocused(self, levels, level: int, k: int) -> np.ndarray:
        """Pyramid `level` blurred by DEFOCUS_SIGMAS[k] (in that level's pixels), cached per image."""
        if k == 0:
            return levels[level]
        cache = next((entry[3] for entry in self._proj_cache if entry[2] is levels), {})
        hit = cache.get((level, k))
        if hit is None:
            hit = cv2.GaussianBlur(levels[level], (0, 0), DEFOCUS_SIGMAS[k], borderType=cv2.BORDER_CONSTANT)
            cache[(level, k)] = hit
        return hit

    # ---- rendering -------------------------------------------------------------------------------
    def render(self, state: SceneState, rng: np.random.Generator | None = None,
               settings: RenderSettings | None = None) -> np.ndarray:
        """The camera image: (H, W, 3) uint8 BGR (or (H, W) float32 levels if settings.quantize is off)."""
        st = settings or self.settings
        img = self.render_linear(state, st)
        return self.finish(img, st, rng)

    def finish(self, img: np.ndarray, st: RenderSettings, rng: np.random.Generator | None = None) -> np.ndarray:
        """Blur, noise, the camera's tone curve and quantisation of a linear image in 8-bit levels."""
        if st.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), st.blur_sigma_px)
        if st.read_noise_dn > 0 or st.electrons_per_dn > 0:
            rng = rng or np.random.default_rng()
            if st.electrons_per_dn > 0:
                sigma = np.sqrt(np.maximum(img, 0) / np.float32(st.electrons_per_dn) + np.float32(st.read_noise_dn) ** 2)
            else:
                sigma = np.float32(st.read_noise_dn)
            img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        if st.camera_gamma != 1.0:
            # the image processor encodes the sensor's linear signal (noise included) before 8 bits
            if st.quantize:  # encoding and quantisation in one table lookup (1/256-level steps)
                idx = np.clip(img * np.float32(_LUT_STEPS) + np.float32(0.5), 0, 255 * _LUT_STEPS).astype(np.int32)
                return cv2.cvtColor(_encode_lut(float(st.camera_gamma))[idx], cv2.COLOR_GRAY2BGR)
            img = np.float32(255.0) * encode_gamma(np.minimum(img, np.float32(255.0)) / np.float32(255.0),
                                                   st.camera_gamma)
        if not st.quantize:
            return img
        g = np.clip(img + 0.5, 0, 255).astype(np.uint8)  # round half up, clipped
        return cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)

    def render_linear(self, state: SceneState, settings: RenderSettings | None = None) -> np.ndarray:
        """Radiance in 8-bit levels (float32, (H, W)), anti-aliased, before blur, noise, quantisation."""
        st = settings or self.settings
        s = int(st.supersample)
        static = self._static_for(s)
        img = (static["bg"] * np.float32(255.0)).copy()
        depth = np.full(img.shape, np.inf, np.float32)
        levels = self._projector_levels(state.projector_image, st)
        mir = static["mirror"]
        if mir is not None:
            y0, y1, x0, x1 = mir["box"]
            sub = (slice(y0, y1), slice(x0, x1))
            refl = np.float32(st.mirror_reflectance * 255.0)
            region = mir["bg"] * refl
            vdepth = np.full(region.shape, np.inf, np.float32)
            S = self.mirror.reflection()
            for b in state.boards:
                self._draw_board(b, S @ b.T_cam_board, static["nx"], static["ny"], mir["box"], region, vdepth,
                                 mir["lam"], levels, st, s, refl)
            img[sub] = np.where(mir["mask"], region, img[sub])
            depth[sub] = mir["lam"]
        for b in state.boards:
            self._draw_board(b, b.T_cam_board, static["nx"], static["ny"], (0, img.shape[0], 0, img.shape[1]),
                             img, depth, None, levels, st, s, np.float32(255.0))
        if s > 1:
            H, W = self.camera.height, self.camera.width
            img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA)  # exact s x s box average
        if st.vignetting_corner < 1.0:
            # the lens passes less light off axis: irradiance on the sensor, before blur and noise
            if self._vignetting is None or self._vignetting[0] != st.vignetting_corner:
                self._vignetting = (st.vignetting_corner, vignetting_map(self.camera, st.vignetting_corner))
            img = img * self._vignetting[1]
        return img

    def _board_box(self, T_view: np.ndarray, layout: BoardLayout, shape, s: int):
        """Sample-grid bounding box (y0, y1, x0, x1) where the board plane at T_view can be, or None."""
        x0, y0, x1, y1 = layout.outline
        t = np.linspace(0, 1, 25)
        edge = np.concatenate([np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y0)]),
                               np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y1)]),
                               np.column_stack([np.full_like(t, x0), y0 + (y1 - y0) * t]),
                               np.column_stack([np.full_like(t, x1), y0 + (y1 - y0) * t])])
        X = np.column_stack([edge, np.zeros(len(edge))]) @ T_view[:3, :3].T + T_view[:3, 3]
        if np.all(X[:, 2] <= 0):
            return None
        uv = self.camera.project(X)
        if not np.all(np.isfinite(uv)):
            return (0, shape[0], 0, shape[1])
        uv = (uv + 0.5) * s - 0.5
        a0 = int(np.clip(np.floor(uv[:, 1].min()) - 2 * s - 1, 0, shape[0]))
        a1 = int(np.clip(np.ceil(uv[:, 1].max()) + 2 * s + 2, 0, shape[0]))
        b0 = int(np.clip(np.floor(uv[:, 0].min()) - 2 * s - 1, 0, shape[1]))
        b1 = int(np.clip(np.ceil(uv[:, 0].max()) + 2 * s + 2, 0, shape[1]))
        if a1 <= a0 or b1 <= b0:
            return None
        return (a0, a1, b0, b1)

    def _draw_board(self, board: PlacedBoard, T_view: np.ndarray, nx, ny, window, out, depth, min_depth, levels,
                    st: RenderSettings, s: int, scale):
        """Composite one board plane (pose T_view in the (virtual) camera frame) into `out` (the sample
        grid's `window` (y0, y1, x0, x1)) where it is the nearest hit (and, seen through the mirror,
        beyond the mirror: depth > min_depth)."""
        box = self._board_box(T_view, board.layout, nx.shape, s)
        if box is None:
            return
        wy0, wy1, wx0, wx1 = window
        a0, a1, b0, b1 = max(box[0], wy0), min(box[1], wy1), max(box[2], wx0), min(box[3], wx1)
        if a1 <= a0 or b1 <= b0:
            return
        px, py = nx[a0:a1, b0:b1], ny[a0:a1, b0:b1]
        sub = (slice(a0 - wy0, a1 - wy0), slice(b0 - wx0, b1 - wx0))
        Hm = T_view[:3, [0, 1, 3]]
        Hi = np.linalg.inv(Hm).astype(np.float32)
        w = Hi[2, 0] * px + Hi[2, 1] * py + Hi[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = 1.0 / w  # depth z of the hit
            bx = (Hi[0, 0] * px + Hi[0, 1] * py + Hi[0, 2]) * lam
            by = (Hi[1, 0] * px + Hi[1, 1] * py + Hi[1, 2]) * lam
        ox0, oy0, ox1, oy1 = board.layout.outline
        valid = (w > 0) & (bx >= ox0) & (bx <= ox1) & (by >= oy0) & (by <= oy1) & (lam < depth[sub])
        if min_depth is not None:
            valid &= lam > min_depth[sub]
        if not np.any(valid):
            return
        # which face the camera sees: constant for a plane not through the (virtual) camera centre
        front = float(T_view[:3, 2] @ T_view[:3, 3]) > 0  # camera on the -z (printed) side
        if front:
            # texture resolution about matched to the sample spacing on the board
            depth_c = float(np.median(lam[valid]))
            px_per_unit = self.camera.fx * s / depth_c
            want = board.layout.charuco.square_length * px_per_unit * TEX_OVERSAMPLE
            T = int(np.clip(2 ** np.round(np.log2(max(want, 1.0))), 16, 256))
            tex, ts, tx0, ty0 = board_texture(board.layout, T, board.marks)
            sigma = TEX_BLUR if s == 1 else TEX_BLUR_SS
            if sigma > 0:
                tex = _blurred(tex, sigma)
            mx = (bx - np.float32(tx0)) * np.float32(ts) - np.float32(0.5)
            my = (by - np.float32(ty0)) * np.float32(ts) - np.float32(0.5)
            t = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
            albedo = np.float32(st.black_albedo) + np.float32(st.white_albedo - st.black_albedo) * t
            light = np.float32(st.ambient) + self._projector_light(board.T_cam_board, bx, by, levels, st, s, depth_c)
            val = albedo * light
        else:
            val = np.full(bx.shape, st.back_albedo * st.ambient, np.float32)
        np.copyto(out[sub], val * scale, where=valid)
        np.copyto(depth[sub], lam, where=valid)

    def _projector_light(self, T_cam_board, bx, by, levels, st: RenderSettings, s: int, depth_c: float):
        if levels is None or st.projector_gain <= 0:
            return np.float32(0.0)
        T_pb = self.T_proj_cam @ T_cam_board
        # the projector lights the printed face only if it is on its -z side
        if float(T_pb[:3, 2] @ T_pb[:3, 3]) <= 0:
            return np.float32(0.0)
        Hp = T_pb[:3, [0, 1, 3]].astype(np.float32)
        # rays that miss the board carry inf board coordinates (masked out by the caller)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            X = Hp[0, 0] * bx + Hp[0, 1] * by + Hp[0, 2]
            Y = Hp[1, 0] * bx + Hp[1, 1] * by + Hp[1, 2]
            Z = Hp[2, 0] * bx + Hp[2, 1] * by + Hp[2, 2]
            return self._projector_light_rays(T_pb, X, Y, Z, levels, st, s, depth_c)

    def _projector_light_rays(self, T_pb, X, Y, Z, levels, st: RenderSettings, s: int, depth_c: float):
        x, y = X / Z, Y / Z
        P = self.projector
        dd = np.zeros(8)
        dd[: P.dist.size] = P.dist
        k1, k2, p1, p2, k3, k4, k5, k6 = (np.float32(v) for v in dd)
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if k4 or k5 or k6:
            radial = radial / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = P.K.astype(np.float32)
        qx = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        qy = K[1, 1] * yd + K[1, 2]
        bad = ~((Z > 0) & (r2 < np.float32(P.max_radius ** 2)))
        # projector pixels per sample: pick the pyramid level where one sample covers about a pixel
        n_b = T_pb[:3, 2]
        dist_p = abs(float(n_b @ T_pb[:3, 3]))
        proj_px_per_unit = P.fx / max(dist_p, 1e-9)
        cam_samples_per_unit = self.camera.fx * s / depth_c
        ratio = proj_px_per_unit / cam_samples_per_unit
        level = int(np.clip(np.floor(np.log2(max(ratio, 1.0))), 0, len(levels) - 1))
        f = np.float32(2.0 ** -level)
        qx[bad] = -1e6
        qy[bad] = -1e6
        mx, my = qx * f, qy * f
        if st.projector_aperture_mm > 0:
            v = self._defocused_lookup(levels, level, mx, my, Z, bad, st, float(f))
        else:
            v = cv2.remap(levels[level], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        gain = np.float32(st.projector_gain)
        if st.projector_falloff:
            R2 = X * X + Y * Y + Z * Z
            D0 = np.float32(st.reference_distance_mm)
            # cos(incidence) = dist_p / |X|, irradiance ~ cos / |X|^2
            v = v * (np.float32(dist_p) * D0 * D0 / (R2 * np.sqrt(R2)))
        return gain * v

    def _defocused_lookup(self, levels, level: int, mx, my, Z, bad, st: RenderSettings, f: float):
        """The projector's light at level-pixel coordinates (mx, my), blurred by the thin-lens defocus
        of each point's depth Z: interpolated between copies of the level blurred at DEFOCUS_SIGMAS."""
        focus = st.projector_focus_mm or st.reference_distance_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            sig = defocus_sigma_px(Z, st.projector_aperture_mm, focus, self.projector.fx) * np.float32(f)
        sig = np.where(bad | ~np.isfinite(sig), np.float32(0.0), np.minimum(sig, np.float32(DEFOCUS_SIGMAS[-1])))
        lo, hi = float(sig.min()), float(sig.max())
        grid = DEFOCUS_SIGMAS
        if hi - lo < 0.1:  # nearly one blur over the whole board: one lookup
            k = int(np.searchsorted(grid, 0.5 * (lo + hi)))
            k = min(k, len(grid) - 1)
            if k > 0 and (grid[k] - 0.5 * (lo + hi)) > (0.5 * (lo + hi) - grid[k - 1]):
                k -= 1
            return cv2.remap(self._defocused(levels, level, k), mx, my, cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        k0 = max(int(np.searchsorted(grid, lo, side="right")) - 1, 0)
        k1 = min(int(np.searchsorted(grid, hi, side="left")), len(grid) - 1)
        out = np.zeros(mx.shape, np.float32)
        for k in range(k0, k1 + 1):
            # hat weight of grid point k (linear interpolation in sigma between neighbours)
            w = np.ones(mx.shape, np.float32)
            if k > 0:
                w = np.where(sig < grid[k], np.clip((sig - grid[k - 1]) / np.float32(grid[k] - grid[k - 1]), 0, 1), w)
            if k < len(grid) - 1:
                w = np.where(sig > grid[k], np.clip((grid[k + 1] - sig) / np.float32(grid[k + 1] - grid[k]), 0, 1), w)
            if not np.any(w > 0):
                continue
            v = cv2.remap(self._defocused(levels, level, k), mx, my, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            out += w * v
        return out


# defocus blur of the projector's light is interpolated between copies blurred by these sigmas (level px)
DEFOCUS_SIGMAS = (0.0, 0.4, 0.8, 1.2, 1.6, 2.4, 3.2, 4.8, 6.4, 9.6, 12.8, 19.2, 25.6)
