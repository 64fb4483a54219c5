"""The projector's light on the boards (behind drivers/sim/render.py): its image through its response
(gamma, black level) as a pyramid, looked up where its rays meet a board, with the cosine and 1/r^2
fall-off and the thin-lens defocus away from its focus."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from drivers.sim._render_photometry import defocus_sigma_px

if TYPE_CHECKING:
    from drivers.sim.render import RenderSettings

# defocus blur of the projector's light is interpolated between copies blurred by these sigmas (level px)
DEFOCUS_SIGMAS = (0.0, 0.4, 0.8, 1.2, 1.6, 2.4, 3.2, 4.8, 6.4, 9.6, 12.8, 19.2, 25.6)


class ProjectorLight:
    """The projector's part of drivers.sim.render.Renderer (not a renderer of its own): it reads the
    renderer's `projector`, `camera`, `T_proj_cam` and `settings`, and keeps the last few projector
    images' light pyramids in `_proj_cache`."""

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
