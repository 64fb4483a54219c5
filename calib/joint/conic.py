"""Where a detector sees a projected circle: conic centres and area centroids.

A circle drawn in the projector image lands on the board as an ellipse and is imaged (through the
mirror) as another ellipse. Its area centroid, which is what a blob detector measures, is not the
image of the circle's centre (docs/GEOMETRY.md, "Circles are not points"). Two ways to model it:

* `ellipse_image_centre`: the exact centre of the image of an ellipse under a 3x3 projective map,
  through the dual conic (C* -> M C* M^T, centre = C* e3). With no lens distortion between the
  circle and the image this IS the area centroid of the imaged blob.
* `polygon_centroid`: the area centroid of a closed polygon (shoelace formula); with the circle's
  boundary mapped point by point through a full model (distortion included) it is the reference.

Everything here is plain numpy arithmetic without abs/max/comparisons, so it can be evaluated with
complex numbers (complex-step derivatives in calib.joint.method).
"""

from __future__ import annotations

import numpy as np


def ellipse_image_centre(M: np.ndarray) -> np.ndarray:
    """Centre of the image of the unit circle under the 3x3 map(s) M (..., 3, 3), as (..., 2).

    The unit circle's dual conic is diag(1, 1, -1); its image is M diag(1, 1, -1) M^T and the centre of
    a conic is its pole of the line at infinity, C* e3. An ellipse {c + B u : |u| = 1} is the image of
    the unit circle under [[B, c], [0, 1]], so composing that with a homography H gives M = H @ G."""
    m2 = M[..., 2, :]
    h = M[..., :, 0] * m2[..., 0, None] + M[..., :, 1] * m2[..., 1, None] - M[..., :, 2] * m2[..., 2, None]
    return h[..., :2] / h[..., 2:3]


def circle_frame(centre: np.ndarray, A: np.ndarray, radius: float) -> np.ndarray:
    """G (..., 3, 3) = [[radius A, centre], [0, 0, 1]]: maps the unit circle to the image of a circle of
    `radius` around a point whose local linear map is A (..., 2, 2) and which lands at `centre` (..., 2)."""
    shape = centre.shape[:-1]
    G = np.zeros(shape + (3, 3), dtype=np.result_type(centre, A))
    G[..., :2, :2] = radius * A
    G[..., :2, 2] = centre
    G[..., 2, 2] = 1.0
    return G


def polygon_centroid(poly: np.ndarray) -> np.ndarray:
    """Area centroid(s) of closed polygon(s) (..., n, 2), vertices in order (either orientation)."""
    x, y = poly[..., 0], poly[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    c = x * y1 - x1 * y
    area6 = 3.0 * c.sum(axis=-1)
    return np.stack([((x + x1) * c).sum(axis=-1) / area6, ((y + y1) * c).sum(axis=-1) / area6], axis=-1)


def circle_boundary(q: np.ndarray, radius: float, n: int = 32) -> np.ndarray:
    """(N, n, 2) points on circles of `radius` around the (N, 2) centres `q`."""
    th = 2.0 * np.pi * np.arange(n) / n
    ring = radius * np.column_stack([np.cos(th), np.sin(th)])
    return np.asarray(q, float).reshape(-1, 1, 2) + ring[None]
