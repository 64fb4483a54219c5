"""The board pose to ask for next in a projector step: of candidate poses (position and tilt), the one
whose predicted observations leave the step's worst 1-sigma against its target least (ask_pose).

Unlike calib.quality.next_pose (which picks a pattern position from the projection-uncertainty grids
and leaves the tilt to the operator), a candidate here is a whole board pose, and its effect on every
quantity the step constrains (the projector's pose and intrinsics as well as its distortion over the
image) is predicted by calib.joint.predict: the joint covariance linearised at the calibration so far,
over its observations plus the candidate's exact observations through the estimated rig. One Jacobian
per candidate, not an adjustment.

candidate_poses draws candidates as a person would hold the board (calib.synthetic.projector_pose,
through the estimated rig), a few per pattern position, and predicts each one's observations. What
the estimated rig does not know is the mirror's extent: `mirror_rect` bounds where a mirrored board
can be seen; mirror_seen gives the part of the mirror boards were seen in so far (None: the mirror is
taken as unbounded, and a candidate can ask for a board the camera only sees past the mirror's edge). benchmarks/next_pose.py measures the choice against the plan's
order with an operator who holds the asked pose off by a few degrees and millimetres.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from calib.errors import ProcamError
from calib.joint.predict import predict_uncertainty
from calib.models.observations import MirrorView, ProjectorView, SessionObservations
from calib.models.result import CalibrationResult
from calib.models.vocab import MirrorMethod, Step
from calib.quality.confidence import confidence_of


@dataclass(frozen=True, eq=False)
class Candidate:
    """A board pose the station could ask for: its pattern position (None for a mirror-step pose),
    T_cam_board, and the view it would give (exact observations through the estimated rig: a projector
    view, or a mirror view for the mirror step)."""

    position: int | None
    T_cam_board: np.ndarray
    view: ProjectorView | MirrorView


@dataclass(frozen=True, eq=False)
class AskedPose:
    """The candidate chosen, its predicted worst 1-sigma / target and which quantity that is."""

    candidate: Candidate
    need: float  # the worst predicted 1-sigma / target with the candidate's observations added
    worst: str  # that quantity's label
    sigma: float
    target: float
    unit: str
    considered: int  # candidates predicted

    @property
    def position(self) -> int:
        return self.candidate.position

    def reason(self) -> str:
        where = "a board" if self.position is None else f"a board at pattern position {self.position + 1}"
        return (f"{where}, held at the pose shown, leaves the worst "
                f"predicted 1-sigma least of {self.considered} poses: {self.worst} {self.sigma:.3g} {self.unit} "
                f"(target {self.target:.3g})")


def ask_pose(obs: SessionObservations, result: CalibrationResult, candidates: Iterable[Candidate],
             step: str = Step.PROJECTOR) -> AskedPose | None:
    """The candidate whose observations, added to `obs` (what `result` was calibrated from), leave the
    least worst predicted 1-sigma / target of `step`'s quantities (a mirror step's candidates are mirror
    views: mirror_candidates). None when no candidate could be predicted (each one's failure is a
    degenerate prediction: skipped)."""
    best: AskedPose | None = None
    considered = 0
    for cand in candidates:
        if isinstance(cand.view, MirrorView):
            merged = replace(obs, mirror_views=tuple(obs.mirror_views) + (cand.view,))
        else:
            merged = replace(obs, projector_views=tuple(obs.projector_views) + (cand.view,))
        try:
            conf = confidence_of(predict_uncertainty(merged, result), step)
        except (ProcamError, np.linalg.LinAlgError):
            continue
        considered += 1
        q = max(conf.quantities, key=lambda q: q.sigma / q.target)
        need = q.sigma / q.target
        if not math.isfinite(need):
            continue
        if best is None or need < best.need:
            best = AskedPose(cand, need, q.label, q.sigma, q.target, q.unit, 0)
    return None if best is None else replace(best, considered=considered)


def mirror_seen(obs: SessionObservations, result: CalibrationResult, margin_mm: float = 0.0):
    """The part of the mirror the camera has seen a board in so far, as a rectangle on the estimated
    mirror plane (calib.synthetic.MirrorRect): every pixel observed through the mirror (the projector
    step's boards and pattern points on a mirrored rig, the mirror step's virtual views) or on it (the
    real-mirror step's boards lying on the mirror) cast through the
    estimated camera onto the plane, their least-area rectangle widened by `margin_mm` on every side.
    What a station knows of the mirror's extent: a candidate seen inside it is seen in the mirror. None
    without a mirror or mirrored pixels."""
    import cv2

    from calib.synthetic import MirrorRect
    from calib.transforms import tangent_basis

    if result.mirror is None:
        return None
    uv = [pv.board.corners_px for pv in obs.projector_views if pv.board is not None and pv.board.mirrored]
    uv += [pv.pattern_cam_px for pv in obs.projector_views if pv.board is not None and pv.board.mirrored]
    uv += [mv.virtual.corners_px for mv in obs.mirror_views if mv.virtual is not None]
    # a board lying on the mirror (real-mirror) is seen directly, on the mirror's face
    uv += [mv.real.corners_px for mv in obs.mirror_views if mv.virtual is None and mv.real is not None]
    uv = [np.asarray(a, float).reshape(-1, 2) for a in uv if len(a)]
    if not uv:
        return None
    rays = result.camera.rays(np.concatenate(uv))
    n, d = np.asarray(result.mirror.normal, float), float(result.mirror.d)
    along = rays @ n
    ok = np.abs(along) > 1e-9
    t = -d / along[ok]
    X = rays[ok] * t[:, None]
    X = X[t > 0]
    if len(X) < 3:
        return None
    u, v = tangent_basis(n)
    foot = -d * n
    (cx, cy), (w, h), angle = cv2.minAreaRect(np.stack([(X - foot) @ u, (X - foot) @ v], 1).astype(np.float32))
    a = np.radians(angle)
    axis_u = np.cos(a) * u + np.sin(a) * v
    axis_v = -np.sin(a) * u + np.cos(a) * v
    return MirrorRect(foot + cx * u + cy * v, axis_u, axis_v, (w + 2 * margin_mm, h + 2 * margin_mm))


def _unbounded(mirror) -> "object":
    """The estimated mirror plane as a rectangle larger than any rig: a mirror of unknown extent."""
    from calib.synthetic import MirrorRect
    from calib.transforms import tangent_basis

    n = np.asarray(mirror.normal, float)
    u, v = tangent_basis(n)
    return MirrorRect(-float(mirror.d) * n, u, v, (1e9, 1e9))


def _board_distance_mm(obs: SessionObservations, result: CalibrationResult, layout) -> float:
    """The median distance from the projector to the blank centres of the projector step's boards the
    result solved."""
    poses = (result.diagnostics or {}).get("board_poses") if isinstance(result.diagnostics, dict) else None
    ids = {pv.capture_id for pv in obs.projector_views}
    T_cp = np.asarray(result.T_cam_proj, float)
    ds = []
    for cid, T in (poses or {}).items():
        if cid not in ids:
            continue
        T = np.asarray(T, float)
        c = T[:3, :3] @ layout.blank_centre + T[:3, 3]
        ds.append(float(np.linalg.norm(c - T_cp[:3, 3])))
    if not ds:
        raise ProcamError("the calibration so far has no board poses to tell how far the board stands")
    return float(np.median(ds))


def candidate_poses(obs: SessionObservations, result: CalibrationResult, layout, pattern, positions: Sequence[int], rng: np.random.Generator,
                    per_position: int = 3, mirror_rect=None, distance_mm: float | None = None) -> list[Candidate]:
    """`per_position` board poses at each of `positions`, drawn through the rig `result` estimates as a
    person would hold the board (calib.synthetic.projector_pose: within 15% of `distance_mm` from the
    projector, None: the median of the projector step's boards of `obs` that `result` solved), each with
    its exact predicted view. A position no valid pose reaches is left out."""
    from calib.synthetic import SyntheticRig, SyntheticSession, observe, projector_pose

    mirror = result.mirror
    if mirror is not None and mirror_rect is None:
        mirror_rect = _unbounded(mirror)
    D = _board_distance_mm(obs, result, layout) if distance_mm is None else float(distance_mm)
    rig = SyntheticRig(result.camera, result.projector, np.asarray(result.T_cam_proj, float), mirror, mirror_rect,
                       np.zeros(3), D, 0.0, result.units)
    out: list[Candidate] = []
    for pos in positions:
        for _k in range(per_position):
            try:
                pose = projector_pose(rig, layout, pattern, pos, rng)
            except RuntimeError:
                break
            ss = SyntheticSession(rig, layout, None, pattern, [(pos, pose)], [], None)
            view = observe(ss, 0.0, 0, circle_centroids=True).projector_views[0]
            out.append(Candidate(pos, pose, replace(view, capture_id=f"asked-{pos}-{len(out)}")))
    return out


def mirror_candidates(obs: SessionObservations, result: CalibrationResult, count: int, rng: np.random.Generator,
                      mirror_rect=None) -> list[Candidate]:
    """`count` mirror-step board poses drawn through the rig `result` estimates, as the mirror step's own
    plan draws them (calib.synthetic.mirror_poses, the session's mirror method and board: real-virtual,
    the board between the camera and the mirror, seen directly and whole in the mirror; real-mirror,
    lying on the mirror), each with its exact predicted mirror view. `mirror_rect` is the part of the
    mirror a board may be seen in (mirror_seen); None: unbounded for real-virtual. A real-mirror board
    lies on the mirror, so its candidates need the rectangle (ProcamError without one). Fewer than
    `count` when the rig allows no more."""
    from calib.synthetic import BoardLayout, SyntheticRig, SyntheticSession, mirror_poses, observe

    mirror = result.mirror
    if mirror is None or obs.mirror_board is None or not obs.mirror_views:
        raise ProcamError("asking for a mirror-step pose needs a mirror calibration with mirror captures")
    step = obs.mirror_views[0].method  # a capture step; the synthetic session takes the mirror method
    method = next(m for m in MirrorMethod if m.step == step)
    if mirror_rect is None:
        if method == MirrorMethod.REAL_MIRROR:
            raise ProcamError("a board lying on the mirror can be asked for only inside the part of the mirror "
                              "seen so far (no real-mirror board was seen)")
        mirror_rect = _unbounded(mirror)
    rig = SyntheticRig(result.camera, result.projector, np.asarray(result.T_cam_proj, float), mirror, mirror_rect,
                       np.zeros(3), 0.0, 0.0, result.units)
    thickness = float(obs.board_thickness or 0.0)
    poses = []
    for k in range(count, 0, -1):  # as many as the rig allows
        try:
            poses = mirror_poses(rig, obs.mirror_board, method, k, int(rng.integers(1 << 31)), thickness)
            break
        except RuntimeError:
            continue
    ss = SyntheticSession(rig, BoardLayout(obs.projector_board), obs.mirror_board, obs.pattern, [], poses,
                          method, thickness)
    views = observe(ss, 0.0, 0).mirror_views
    return [Candidate(None, T, replace(v, capture_id=f"asked-mirror-{i}")) for i, (T, v) in enumerate(zip(poses, views))]


__all__ = ["AskedPose", "Candidate", "ask_pose", "candidate_poses", "mirror_candidates", "mirror_seen"]
