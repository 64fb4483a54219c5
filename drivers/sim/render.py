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

from dataclasses import dataclass, replace

import cv2
import numpy as np

from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.result import MirrorPlane
from calib.models.vocab import RenderQuality, choices
from calib.synthetic import BoardLayout, MirrorRect
from calib.transforms import invert_T
from drivers.sim._render_board import (
    TEX_BLUR,
    TEX_BLUR_SS,
    TEX_OVERSAMPLE,
    blurred,
    board_texture,
)
from drivers.sim._render_photometry import (
    LUT_STEPS,
    decode_gamma,
    defocus_sigma_px,
    encode_gamma,
    encode_lut,
    vignetting_map,
)
from drivers.sim._render_projector import DEFOCUS_SIGMAS, ProjectorLight
from drivers.sim._render_rays import normalized_grid

__all__ = ["DEFOCUS_SIGMAS", "QUALITIES", "Mark", "PlacedBoard", "RenderSettings", "Renderer", "SceneState",
           "board_texture", "decode_gamma", "defocus_sigma_px", "encode_gamma", "layout_for", "normalized_grid",
           "vignetting_map"]
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
    def for_quality(cls, quality: str, **overrides) -> RenderSettings:
        """'live': 1 sample per pixel (fast, for the live demo); 'session': 3 x 3 samples."""
        if quality not in QUALITIES:
            raise ValueError(f"unknown quality '{quality}' (one of {', '.join(QUALITIES)})")
        base = cls(supersample=1 if quality == RenderQuality.LIVE else 3)
        return replace(base, **overrides)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def without_noise(self) -> RenderSettings:
        return replace(self, blur_sigma_px=0.0, read_noise_dn=0.0, electrons_per_dn=0.0)

    def photometrically_neutral(self) -> RenderSettings:
        """The same settings with every photometric-realism effect off (the renderer before issue 18)."""
        return replace(self, projector_gamma=1.0, projector_black_level=0.0, projector_aperture_mm=0.0,
                       projector_focus_mm=0.0, vignetting_corner=1.0, camera_gamma=1.0)


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


def _background(dx, dy, dz, level: float) -> np.ndarray:
    """A smooth room-like background as a function of the direction: broad gradients and soft
    bands, nothing with corners or blobs at the scale of a board."""
    az = np.arctan2(dx, dz)
    el = np.arctan2(dy, np.hypot(dx, dz))
    v = (level + 0.07 * np.sin(1.7 * az + 0.4) * np.cos(2.3 * el - 0.3) + 0.05 * np.sin(3.1 * az - 2.0 * el + 1.1)
         + 0.04 * np.cos(0.9 * az + 4.2 * el) - 0.06 * el)
    return np.clip(v, 0.02, 1.0).astype(np.float32)


# ---- the renderer -----------------------------------------------------------------------------------
class Renderer(ProjectorLight):
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
                idx = np.clip(img * np.float32(LUT_STEPS) + np.float32(0.5), 0, 255 * LUT_STEPS).astype(np.int32)
                return cv2.cvtColor(encode_lut(float(st.camera_gamma))[idx], cv2.COLOR_GRAY2BGR)
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
                tex = blurred(tex, sigma)
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
