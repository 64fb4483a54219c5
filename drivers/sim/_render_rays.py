"""The simulated camera's rays (behind drivers/sim/render.py): the undistorted normalized coordinates of
every sample of the (supersampled) pixel grid, computed once per camera and cached."""

from __future__ import annotations

import threading

import cv2
import numpy as np

from calib.models.camera import CameraModel


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
    xy = undistort_exact(camera, uv)
    nx = xy[:, 0].reshape(H * s, W * s).astype(np.float32)
    ny = xy[:, 1].reshape(H * s, W * s).astype(np.float32)
    nx.setflags(write=False)
    ny.setflags(write=False)
    with _grid_lock:
        if len(_grid_cache) > 6:
            _grid_cache.clear()
        _grid_cache[key] = (nx, ny)
    return nx, ny


def undistort_exact(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
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
