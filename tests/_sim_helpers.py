"""Helpers for the simulator's tests: exact imaged-circle centroids and measured blob centroids."""

from __future__ import annotations

import numpy as np

from calib.joint.conic import polygon_centroid
from calib.synthetic import projector_points_on_board
from calib.transforms import transform_points


def imaged_circle_centroids(rig, T_cam_board, centres_px, radius_px, n: int = 720) -> np.ndarray:
    """Centroid of the camera image of each projected circle: its boundary (projector pixels) is mapped
    through the exact geometry (projector ray -> board -> (mirror) -> camera with distortion), and the
    resulting polygon's area centroid taken."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([np.cos(a), np.sin(a)]) * radius_px
    S = rig.S()
    out = []
    for c in np.asarray(centres_px, float):
        Xb = projector_points_on_board(rig, T_cam_board, c + ring)
        uv = rig.camera.project(transform_points(S @ T_cam_board, Xb))
        out.append(polygon_centroid(uv))
    return np.array(out)


def imaged_board_disc_centroid(rig, T_view, centre_xy, radius, n: int = 720) -> np.ndarray:
    """Centroid of the camera image of a disc drawn on a board at pose T_view (S @ T for a mirrored view)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.column_stack([centre_xy[0] + radius * np.cos(a), centre_xy[1] + radius * np.sin(a), np.zeros(n)])
    return polygon_centroid(rig.camera.project(transform_points(T_view, ring)))


def blob_centroids(img: np.ndarray, expected: np.ndarray, radius_px: float) -> np.ndarray:
    """Intensity-weighted centroid of `img` (a float image that is zero away from the blobs) within
    `radius_px` of each expected position."""
    H, W = img.shape
    out = []
    for ex, ey in np.asarray(expected, float):
        x0, x1 = int(np.floor(ex - radius_px)), int(np.ceil(ex + radius_px)) + 1
        y0, y1 = int(np.floor(ey - radius_px)), int(np.ceil(ey + radius_px)) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
        ys, xs = np.mgrid[y0:y1, x0:x1]
        w = img[y0:y1, x0:x1].astype(float) * (((xs - ex) ** 2 + (ys - ey) ** 2) <= radius_px**2)
        out.append([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])
    return np.array(out)
