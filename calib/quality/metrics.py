"""The paper's evaluation metrics (Vanherck et al. 2025, Sect. 5.2): a result against ground truth.

  CamK / ProjK   Frobenius norm of (K_est - K_true), pixels
  CamD / ProjD   Euclidean norm of (dist_est - dist_true), the shorter padded with zeros
  Distance       |t_est - t_true| of T_cam_proj's translation (board units)
  Angle          rotation angle of R_est^T R_true (degrees)
  Mirror         angle between the normals (degrees) and |d_est - d_true| (board units)
  RMS            the reprojection errors the result carries (camera, projector, stereo; mirror plane)

Entry point: `compare(result, ground_truth) -> PaperMetrics`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult
from calib.transforms import rotation_angle_deg
from calib.models.vocab import LengthUnit

#: The paper's headline numbers on its synthetic scenes (circle grid, non-overlapping fields of view,
#: estimated camera, real-virtual mirror calibration), from docs/GEOMETRY.md. Lengths in millimetres.
PAPER_HEADLINE = {
    "distance": 3.2,  # mm
    "angle_deg": 0.18,
    "proj_k_px": 7.6,
    "proj_d": 0.02,
    "mirror_offset": 0.6,  # mm
    "mirror_angle_deg": 0.09,
}


@dataclass(frozen=True)
class PaperMetrics:
    cam_k_px: float
    cam_d: float
    proj_k_px: float
    proj_d: float
    distance: float  # board units
    angle_deg: float
    mirror_angle_deg: float | None
    mirror_offset: float | None  # board units
    cam_rms_px: float | None
    proj_rms_px: float | None
    stereo_rms_px: float | None
    mirror_rms: float | None  # plane residual RMS, board units
    units: str = LengthUnit.MM
    joint_rms_px: float | None = None  # the joint adjustment's RMS over all its observations (camera px)

    def to_dict(self) -> dict:
        return asdict(self)

    def rows(self) -> list[tuple[str, str, str]]:
        """(name, value, unit) rows in the paper's order."""
        u = self.units

        def f(x, digits=4):
            return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"

        return [
            ("CamK", f(self.cam_k_px, 3), "px"),
            ("CamD", f(self.cam_d, 5), ""),
            ("ProjK", f(self.proj_k_px, 3), "px"),
            ("ProjD", f(self.proj_d, 5), ""),
            ("Distance", f(self.distance, 3), u),
            ("Angle", f(self.angle_deg, 4), "deg"),
            ("Mirror angle", f(self.mirror_angle_deg, 4), "deg"),
            ("Mirror offset", f(self.mirror_offset, 3), u),
            ("CamRMS", f(self.cam_rms_px, 4), "px"),
            ("ProjRMS", f(self.proj_rms_px, 4), "px"),
            ("StereoRMS", f(self.stereo_rms_px, 4), "px"),
            ("MirrorRMS", f(self.mirror_rms, 4), u),
        ] + ([("JointRMS", f(self.joint_rms_px, 4), "px")] if self.joint_rms_px is not None else [])

    def format_table(self) -> str:
        rows = self.rows()
        w = max(len(r[0]) for r in rows)
        vw = max(len(r[1]) for r in rows)
        return "\n".join(f"{name:<{w}}  {value:>{vw}} {unit}".rstrip() for name, value, unit in rows)


def dist_diff(a: np.ndarray, b: np.ndarray) -> float:
    a = np.asarray(a, float).reshape(-1)
    b = np.asarray(b, float).reshape(-1)
    n = max(a.size, b.size)
    return float(np.linalg.norm(np.pad(a, (0, n - a.size)) - np.pad(b, (0, n - b.size))))


def distortion_error_over_image(estimated: CameraModel, true: CameraModel, grid=(32, 18)) -> float:
    """Mean distance (px) between where the estimated and the true distortion put the same ray, over a
    grid of cell centres covering the image, both with the true K (so that only the distortion is
    compared). The rays are the true model's rays through the grid pixels. A ray the estimated model
    cannot project (beyond its valid radius) counts as the image diagonal."""
    nx, ny = int(grid[0]), int(grid[1])
    xs = (np.arange(nx) + 0.5) * true.width / nx - 0.5
    ys = (np.arange(ny) + 0.5) * true.height / ny - 0.5
    X, Y = np.meshgrid(xs, ys)
    uv = np.column_stack([X.ravel(), Y.ravel()])
    rays = true.rays(uv)
    est = true.with_params(dist=np.asarray(estimated.dist, float))
    e = np.linalg.norm(est.project(rays) - true.project(rays), axis=1)
    return float(np.where(np.isfinite(e), e, float(np.hypot(true.width, true.height))).mean())


def compare(result: CalibrationResult, ground_truth: CalibrationResult) -> PaperMetrics:
    """The paper's metrics of `result` against `ground_truth` (both in the same length unit)."""
    if result.units != ground_truth.units:
        raise ValueError(f"units differ: result in {result.units}, ground truth in {ground_truth.units}")
    Te, Tt = np.asarray(result.T_cam_proj), np.asarray(ground_truth.T_cam_proj)
    m_ang = m_off = None
    if result.mirror is not None and ground_truth.mirror is not None:
        c = float(np.clip(result.mirror.normal @ ground_truth.mirror.normal, -1.0, 1.0))
        m_ang = float(np.degrees(np.arccos(c)))
        m_off = abs(result.mirror.d - ground_truth.mirror.d)
    rms = result.rms or {}

    def r(key):
        v = rms.get(key)
        return None if v is None else float(v)

    return PaperMetrics(
        cam_k_px=float(np.linalg.norm(result.camera.K - ground_truth.camera.K)),
        cam_d=dist_diff(result.camera.dist, ground_truth.camera.dist),
        proj_k_px=float(np.linalg.norm(result.projector.K - ground_truth.projector.K)),
        proj_d=dist_diff(result.projector.dist, ground_truth.projector.dist),
        distance=float(np.linalg.norm(Te[:3, 3] - Tt[:3, 3])),
        angle_deg=rotation_angle_deg(Te[:3, :3].T @ Tt[:3, :3]),
        mirror_angle_deg=m_ang,
        mirror_offset=m_off,
        cam_rms_px=r("camera"),
        proj_rms_px=r("projector"),
        stereo_rms_px=r("stereo"),
        mirror_rms=r("mirror_plane"),
        units=result.units,
        joint_rms_px=r("joint"),
    )
