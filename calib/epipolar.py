"""Epipolar geometry of a projector-camera rig, through a planar mirror or direct, with lens distortion.

A camera pixel `u` is a ray from the camera centre. On a mirrored rig the camera sees the board through
the mirror, so the physical points imaged at `u` lie on the camera ray *reflected* by the mirror:
X(t) = S (t r), with r the unit ray direction of `u` and t the optical path length from the camera
centre (the distance of the virtual point S X from the camera), valid beyond the mirror (t > t_mirror).
On a direct rig X(t) = t r. Projected into the projector (with its distortion) these points draw a
CURVE, the epipolar curve of `u`: a straight line without distortion (the fundamental-matrix line),
slightly bent with it. When the projector draws that curve on the board, the camera must see it pass
through `u`, whatever the board's pose: that is the verification of calibration.

Depth range (documented default): the part of the ray whose optical path length from the camera lies
in DEFAULT_DEPTH_RANGE_M = 0.2 .. 5 m (converted to the result's units), beyond the mirror, in front of
the projector, and imaged inside the projector's image; when the projector sees several pieces of the
ray (only possible with a pathological distortion) the longest one is kept. The board cannot be
anywhere else and be lit by the projector.

The inverse direction (`camera_curve_for_projector_pixel`) is the same with the roles exchanged: the
projector ray X(s) = P + s d (s the distance from the projector, same default range), the part in front
of the mirror, seen by the camera at project(S X(s)).

Curves are sampled uniformly in the angle of the device's viewing ray (so about uniformly in pixels),
then refined by subdivision until every chord is within `tol_px` of the true curve: the polyline is
exact to `tol_px` (default 1e-3 px; pass 1e-8 for tests). Distances from points to polylines are exact
(segment-wise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult
from calib.models.vocab import LengthUnit
from calib.transforms import invert_T, transform_points

#: Optical path length interval (metres) where a board can plausibly be: see the module docstring.
DEFAULT_DEPTH_RANGE_M = (0.2, 5.0)

_UNITS_PER_M = {u.value: 1000.0 / u.mm for u in LengthUnit}

#: Coarse angular step (degrees) used to find where a ray enters and leaves a device's image.
_COARSE_STEP_DEG = 0.05


def units_per_metre(units: str) -> float:
    """How many `units` make a metre (mm -> 1000). ValueError for an unknown unit."""
    try:
        return _UNITS_PER_M[units]
    except KeyError:
        raise ValueError(f"unknown length unit '{units}' (one of {', '.join(_UNITS_PER_M)})") from None


def default_depth_range(units: str) -> tuple[float, float]:
    """DEFAULT_DEPTH_RANGE_M in `units`."""
    k = units_per_metre(units)
    return (DEFAULT_DEPTH_RANGE_M[0] * k, DEFAULT_DEPTH_RANGE_M[1] * k)


# ---- rays --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ViewingRay:
    """Physical points a device pixel sees, in camera coordinates: X(t) = origin + (t - t_start) *
    direction for t >= t_start, with t the optical path length from the device centre (the mirror
    hit point is `origin` and t_start its distance on a mirrored camera ray; the device centre and 0
    otherwise). `direction` is a unit vector."""

    origin: np.ndarray
    direction: np.ndarray
    t_start: float

    def points(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float).reshape(-1)
        return self.origin + (t - self.t_start)[:, None] * self.direction


def camera_ray(result: CalibrationResult, cam_px) -> ViewingRay | None:
    """The physical points imaged at camera pixel `cam_px` (reflected by the mirror when there is
    one). None when the pixel's ray does not meet the mirror in front of the camera."""
    r = result.camera.rays(np.asarray(cam_px, float).reshape(1, 2))[0]
    if not np.all(np.isfinite(r)):
        return None
    if result.mirror is None:
        return ViewingRay(np.zeros(3), r, 0.0)
    n, d = result.mirror.normal, result.mirror.d
    rn = float(r @ n)
    if rn >= -1e-12:  # parallel to the mirror or going away from it (n points towards the camera)
        return None
    t_m = -d / rn
    return ViewingRay(t_m * r, r - 2.0 * rn * n, float(t_m))


def projector_ray(result: CalibrationResult, proj_px) -> ViewingRay | None:
    """The physical points lit by projector pixel `proj_px`, in camera coordinates."""
    r = result.projector.rays(np.asarray(proj_px, float).reshape(1, 2))[0]
    if not np.all(np.isfinite(r)):
        return None
    R, P = result.T_cam_proj[:3, :3], result.T_cam_proj[:3, 3]
    return ViewingRay(P.copy(), R @ r, 0.0)


# ---- curves ------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Curve:
    """A sampled image curve: `px` (M, 2) pixels of the viewing device, `depths` (M,) the optical path
    lengths along the source ray, `points` (M, 3) the physical points (camera coordinates)."""

    px: np.ndarray
    depths: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return len(self.px)


def _empty_curve() -> Curve:
    return Curve(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)))


def _trace(model: CameraModel, ray: ViewingRay, to_dev: np.ndarray, t_lo: float, t_hi: float,
           samples: int, tol_px: float) -> Curve:
    """Image curve in `model` (device pose: `to_dev` maps camera coordinates into the device frame;
    it may be improper, e.g. T_proj_cam or the mirror S) of ray points with t in [t_lo, t_hi]."""
    if not (np.isfinite(t_lo) and np.isfinite(t_hi)) or t_hi <= t_lo:
        return _empty_curve()
    A, B = to_dev[:3, :3], to_dev[:3, 3]
    # device-frame points are h(t) = a + t b (linear in t, so homogeneous image points are too)
    a = A @ (ray.origin - ray.t_start * ray.direction) + B
    b = A @ ray.direction
    h_lo, h_hi = a + t_lo * b, a + t_hi * b
    n_lo, n_hi = np.linalg.norm(h_lo), np.linalg.norm(h_hi)
    if n_lo < 1e-12 or n_hi < 1e-12:
        return _empty_curve()
    e_lo, e_hi = h_lo / n_lo, h_hi / n_hi
    theta = float(np.arccos(np.clip(e_lo @ e_hi, -1.0, 1.0)))

    def t_of(w):
        """t whose viewing direction is the slerp(w) of the end directions (monotonic in w)."""
        w = np.asarray(w, float)
        if theta < 1e-12:
            return t_lo + w * (t_hi - t_lo)
        al = np.sin((1.0 - w) * theta) / n_lo
        be = np.sin(w * theta) / n_hi
        return (al * t_lo + be * t_hi) / (al + be)

    def px_of(t):
        return model.project(a + np.asarray(t, float).reshape(-1)[:, None] * b)

    def inside(w):
        return model.in_image(px_of(t_of(w)))

    n0 = max(int(np.ceil(np.degrees(theta) / _COARSE_STEP_DEG)) + 1, samples, 2)
    w0 = np.linspace(0.0, 1.0, n0)
    ok = inside(w0)
    if not ok.any():
        return _empty_curve()
    # longest run of in-image samples
    edges = np.diff(np.concatenate([[0], ok.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    k = int(np.argmax(ends - starts))
    i0, i1 = int(starts[k]), int(ends[k])

    def boundary(w_in, w_out):
        for _ in range(60):
            m = 0.5 * (w_in + w_out)
            if inside(np.array([m]))[0]:
                w_in = m
            else:
                w_out = m
        return w_in

    wa = w0[i0] if i0 == 0 else boundary(w0[i0], w0[i0 - 1])
    wb = w0[i1] if i1 == n0 - 1 else boundary(w0[i1], w0[i1 + 1])
    if wb <= wa:
        w = np.array([wa])
    else:
        w = np.linspace(wa, wb, max(samples, 2))
        # subdivide until every chord is within tol_px of the curve at its parameter midpoint
        for _ in range(40):
            p = px_of(t_of(w))
            wm = 0.5 * (w[:-1] + w[1:])
            pm = px_of(t_of(wm))
            err = _point_segment_distance(pm, p[:-1], p[1:])
            bad = ~(err <= tol_px)
            if not bad.any():
                break
            w = np.sort(np.concatenate([w, wm[bad]]))
    t = t_of(w)
    pts = ray.points(t)
    return Curve(px_of(t), t, pts)


def epipolar_curve_samples(result: CalibrationResult, cam_px, depth_range=None, samples: int = 64,
                           tol_px: float = 1e-3) -> Curve:
    """The epipolar curve of camera pixel `cam_px` in the projector image, with the depths and 3D
    points of its samples (see the module docstring for the depth range). Empty when the projector
    sees no part of the ray."""
    ray = camera_ray(result, cam_px)
    if ray is None:
        return _empty_curve()
    lo, hi = default_depth_range(result.units) if depth_range is None else map(float, depth_range)
    lo = max(lo, ray.t_start)
    T_proj_cam = invert_T(result.T_cam_proj)
    # in front of the projector: z_proj(t) > 0, linear in t
    a = T_proj_cam[:3, :3] @ (ray.origin - ray.t_start * ray.direction) + T_proj_cam[:3, 3]
    b = T_proj_cam[:3, :3] @ ray.direction
    lo, hi = _clip_positive(a[2], b[2], lo, hi)
    return _trace(result.projector, ray, T_proj_cam, lo, hi, samples, tol_px)


def epipolar_curve(result: CalibrationResult, cam_px, depth_range=None, samples: int = 64,
                   tol_px: float = 1e-3) -> np.ndarray:
    """(M, 2) projector-pixel polyline of the epipolar curve of camera pixel `cam_px` (M = 0 when
    the projector cannot light any point the pixel sees). `depth_range` = (near, far) optical path
    lengths from the camera in the result's units (default 0.2 .. 5 m)."""
    return epipolar_curve_samples(result, cam_px, depth_range, samples, tol_px).px


def camera_curve_for_projector_pixel(result: CalibrationResult, proj_px, depth_range=None, samples: int = 64,
                                     tol_px: float = 1e-3) -> Curve:
    """Where the camera can see the point lit by projector pixel `proj_px`: its epipolar curve in the
    camera image (through the mirror on a mirrored rig), for distances from the projector in
    `depth_range` (result units, default 0.2 .. 5 m) and in front of the mirror."""
    ray = projector_ray(result, proj_px)
    if ray is None:
        return _empty_curve()
    lo, hi = default_depth_range(result.units) if depth_range is None else map(float, depth_range)
    if result.mirror is None:
        to_cam = np.eye(4)
    else:
        n, d = result.mirror.normal, result.mirror.d
        lo, hi = _clip_positive(n @ ray.origin + d, n @ ray.direction, lo, hi)
        to_cam = result.mirror.reflection()
    # in front of the camera (as seen): z of to_cam X(s) > 0
    a = to_cam[:3, :3] @ ray.origin + to_cam[:3, 3]
    b = to_cam[:3, :3] @ ray.direction
    lo, hi = _clip_positive(a[2], b[2], lo, hi)
    return _trace(result.camera, ray, to_cam, lo, hi, samples, tol_px)


def _clip_positive(c0: float, c1: float, lo: float, hi: float) -> tuple[float, float]:
    """[lo, hi] restricted to where c0 + c1 t > 0 (strictly, with a relative margin)."""
    eps = 1e-9 * max(1.0, abs(c0), abs(c1) * max(abs(lo), abs(hi)))
    if abs(c1) < 1e-300:
        return (lo, hi) if c0 > eps else (np.inf, -np.inf)
    root = (eps - c0) / c1
    if c1 > 0:
        lo = max(lo, root)
    else:
        hi = min(hi, root)
    return lo, hi


def predicted_camera_curve(result: CalibrationResult, cam_px, board_plane, depth_range=None, samples: int = 64,
                           tol_px: float = 1e-3) -> np.ndarray:
    """Where the camera should see the drawn epipolar curve of `cam_px` on a board whose plane is
    `board_plane` = (normal (3,), offset) with normal . X + offset = 0 in camera coordinates, or a
    4x4 T_cam_board (its z = 0 plane). The projector's rays through the curve form the epipolar plane,
    which meets the board in a 3D line through the point `cam_px` sees; this returns that line's image
    (through the mirror), (M, 2) camera pixels, empty when the board does not meet the curve. By
    construction it passes through `cam_px` for any calibration: it shows the expected shape, while
    the measurement is the detected curve."""
    n, off = _plane(board_plane)
    curve = epipolar_curve_samples(result, cam_px, depth_range, samples, tol_px)
    if len(curve) < 2:
        return np.zeros((0, 2))
    P = result.T_cam_proj[:3, 3]
    X = curve.points
    # the epipolar plane (projector centre + the ray) meets the board in a line: its two ends are the
    # projector rays through the curve's ends, cut by the board plane
    D = X - P
    den = D @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(P @ n + off) / den
    good = np.isfinite(s) & (s > 0)
    if good.sum() < 2:
        return np.zeros((0, 2))
    Y = P + s[good, None] * D[good]
    ray = ViewingRay(Y[0], Y[-1] - Y[0], 0.0)
    to_cam = np.eye(4) if result.mirror is None else result.mirror.reflection()
    return _trace(result.camera, ray, to_cam, 0.0, 1.0, samples, tol_px).px


def _plane(board_plane) -> tuple[np.ndarray, float]:
    if isinstance(board_plane, np.ndarray) and board_plane.shape == (4, 4):
        n = board_plane[:3, 2].astype(float)
        return n, float(-n @ board_plane[:3, 3])
    n, off = board_plane
    n = np.asarray(n, float).reshape(3)
    k = np.linalg.norm(n)
    return n / k, float(off) / k


def fundamental_matrix(result: CalibrationResult) -> np.ndarray:
    """F with q~^T F u~ = 0 for UNDISTORTED projector pixel q and camera pixel u (homogeneous): the
    epipolar line of u in the projector is l = F u~ (valid only without distortion). On a mirrored rig
    the camera is replaced by its (left-handed) virtual camera S."""
    T_pc = invert_T(result.T_cam_proj)
    M = T_pc @ (np.eye(4) if result.mirror is None else result.mirror.reflection())
    A, b = M[:3, :3], M[:3, 3]
    bx = np.array([[0, -b[2], b[1]], [b[2], 0, -b[0]], [-b[1], b[0], 0]])
    return np.linalg.inv(result.projector.K).T @ bx @ A @ np.linalg.inv(result.camera.K)


# ---- distances ---------------------------------------------------------------------------------------
def _point_segment_distance(p, a, b) -> np.ndarray:
    """Distance of points p[i] to segments a[i] b[i] (row-wise)."""
    ab = b - a
    L2 = np.einsum("ij,ij->i", ab, ab)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(L2 > 0, np.einsum("ij,ij->i", p - a, ab) / L2, 0.0)
    u = np.clip(u, 0.0, 1.0)
    return np.linalg.norm(p - (a + u[:, None] * ab), axis=1)


@dataclass(frozen=True, eq=False)
class PolylineDistance:
    """Distances of K points to a polyline: `distance` (K,), `signed` (K,) positive when cross(direction,
    point - closest) > 0 (for a polyline running towards +x, points below it, at larger y, are positive),
    `closest` (K, 2) nearest polyline points, `segment` (K,) their segment index, `u` (K,) their
    parameter in the segment, `interior` (K,) False when the nearest point is an end of the polyline
    (the point lies beyond the curve, the distance is not perpendicular)."""

    distance: np.ndarray
    signed: np.ndarray
    closest: np.ndarray
    segment: np.ndarray
    u: np.ndarray
    interior: np.ndarray


def distance_to_polyline(points, polyline) -> PolylineDistance:
    """Exact Euclidean distances of (K, 2) points to a (M, 2) polyline (M >= 1), segment by segment."""
    P = np.asarray(points, float).reshape(-1, 2)
    L = np.asarray(polyline, float).reshape(-1, 2)
    if len(L) == 0:
        raise ValueError("distance to an empty polyline")
    if len(L) == 1:
        L = np.vstack([L, L])
    A, B = L[:-1], L[1:]
    AB = B - A
    L2 = np.einsum("ij,ij->i", AB, AB)
    seg = np.zeros(len(P), int)
    uu = np.zeros(len(P))
    chunk = max(1, 2_000_000 // len(A))
    for i in range(0, len(P), chunk):
        Pc = P[i : i + chunk]
        AP = Pc[:, None, :] - A[None, :, :]  # (K, S, 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(L2[None] > 0, np.einsum("ksj,sj->ks", AP, AB) / L2[None], 0.0)
        u = np.clip(u, 0.0, 1.0)
        D2 = np.sum((AP - u[..., None] * AB[None]) ** 2, axis=2)
        s_i = np.argmin(D2, axis=1)
        seg[i : i + chunk] = s_i
        uu[i : i + chunk] = u[np.arange(len(Pc)), s_i]
    closest = A[seg] + uu[:, None] * AB[seg]
    dist = np.linalg.norm(P - closest, axis=1)
    # sign from the local direction of the polyline at the closest point
    d = AB[seg]
    zero = L2[seg] == 0
    if np.any(zero):
        d = d.copy()
        d[zero] = (L[-1] - L[0])
    v = P - closest
    cross = d[:, 0] * v[:, 1] - d[:, 1] * v[:, 0]
    signed = np.where(cross >= 0, dist, -dist)
    interior = ~(((seg == 0) & (uu <= 0)) | ((seg == len(A) - 1) & (uu >= 1)))
    return PolylineDistance(dist, signed, closest, seg, uu, interior | (dist == 0))
