"""The joint adjustment's problem assembled from a session (build_problem): every usable view's
observations gathered into point sets, its board pose initialised by PnP under the initial calibration,
and the reference state the parameters start from."""

from __future__ import annotations

import numpy as np

from calib.errors import CalibrationError
from calib.joint.lens import dist8
from calib.joint.options import PATTERN_MODELS, JointOptions
from calib.joint.points import (
    KIND_BOARD,
    KIND_REAL,
    KIND_VIRTUAL,
    CornerSet,
    PatternSet,
)
from calib.joint.problem import JointProblem, ReferenceState, View, plane_params
from calib.joint.solver import DIST_MODELS
from calib.models.camera import CameraModel
from calib.models.observations import STEP_REAL_MIRROR, VIEW_DIRECT, SessionObservations
from calib.models.result import CalibrationResult
from calib.paper.board_pose import pose_from_points, pose_through_mirror
from calib.transforms import tangent_basis
from calib.models.vocab import PatternKind

#: the fewest ChArUco corners a view's board pose is initialised from
MIN_VIEW_CORNERS = 6
#: bounds of a pattern point's noise relative to its class's median (PatternSet.rel): a local fit's
#: covariance comes from a few hundred pixels and can be optimistic, so no point counts for more than
#: 16 times (1/REL_MIN^2) the median one, and none is nearly ignored
REL_MIN, REL_MAX = 0.25, 4.0


def _camera_K4(cam: CameraModel) -> np.ndarray:
    return np.array([cam.fx, cam.fy, cam.cx, cam.cy])


def _cat(lst, shape, dtype=float):
    return np.concatenate(lst).astype(dtype) if lst else np.zeros(shape, dtype)


def relative_noise(sigma_px: np.ndarray) -> np.ndarray:
    """Each pattern point's noise relative to the median of those with a sigma of their own (NaN: none,
    relative 1), within [REL_MIN, REL_MAX]. The class's sigma, estimated from the residuals, sets the
    scale; a point's own sigma only says how much noisier or cleaner than its class it is."""
    rel = np.ones(len(sigma_px))
    own = np.isfinite(sigma_px)
    if own.any():
        rel[own] = np.clip(sigma_px[own] / np.median(sigma_px[own]), REL_MIN, REL_MAX)
    return rel


class _Gatherer:
    """The views, their initial poses and their observations, collected view by view."""

    def __init__(self):
        self.poses: list[View] = []
        self.captures: list[str] = []
        self.Rs, self.ts, self.planes = [], [], []
        self.C = {k: [] for k in ("pose", "X", "uv", "mirror", "kind", "cid", "pid")}
        self.P = {k: [] for k in ("pose", "q", "uv", "mirror", "cid", "pid", "sigma")}

    def add_view(self, view: View, T: np.ndarray, plane: np.ndarray) -> int:
        self.poses.append(view)
        self.captures.append(view.capture_id)
        self.Rs.append(T[:3, :3])
        self.ts.append(T[:3, 3])
        self.planes.append(plane)
        return len(self.poses) - 1

    def add_corners(self, v: int, bo, X_all: np.ndarray, kind: int, through: bool) -> None:
        C, k = self.C, len(bo.ids)
        C["pose"].append(np.full(k, v))
        C["X"].append(X_all[bo.ids])
        C["uv"].append(np.asarray(bo.corners_px, float))
        C["mirror"].append(np.full(k, through))
        C["kind"].append(np.full(k, kind))
        C["cid"].append(np.full(k, len(self.captures) - 1))
        C["pid"].append(np.asarray(bo.ids, int))

    def add_pattern(self, v: int, pv, through: bool) -> None:
        P, k = self.P, len(pv.pattern_proj_px)
        P["pose"].append(np.full(k, v))
        P["q"].append(np.asarray(pv.pattern_proj_px, float))
        P["uv"].append(np.asarray(pv.pattern_cam_px, float))
        P["mirror"].append(np.full(k, through))
        P["cid"].append(np.full(k, len(self.captures) - 1))
        P["pid"].append(np.arange(k))
        P["sigma"].append(np.full(k, np.nan) if pv.pattern_sigma_px is None else np.asarray(pv.pattern_sigma_px, float))

    def corner_set(self) -> CornerSet:
        C = self.C
        return CornerSet(_cat(C["pose"], (0,), int), _cat(C["X"], (0, 3)), _cat(C["uv"], (0, 2)),
                         _cat(C["mirror"], (0,), bool), _cat(C["kind"], (0,), int), _cat(C["cid"], (0,), int),
                         _cat(C["pid"], (0,), int))

    def pattern_set(self) -> PatternSet:
        P = self.P
        return PatternSet(_cat(P["pose"], (0,), int), _cat(P["q"], (0, 2)), _cat(P["uv"], (0, 2)),
                          _cat(P["mirror"], (0,), bool), _cat(P["cid"], (0,), int), _cat(P["pid"], (0,), int),
                          relative_noise(_cat(P["sigma"], (0,))))


def _add_projector_views(g: _Gatherer, obs: SessionObservations, cam: CameraModel, S: np.ndarray,
                         mirrored: bool, left_out: list) -> None:
    Xp = obs.projector_board.corner_points()
    for pv in obs.projector_views:
        bo = pv.board
        if bo is None or len(bo.ids) < MIN_VIEW_CORNERS:
            left_out.append({"capture_id": pv.capture_id, "reason": "fewer than 6 ChArUco corners"})
            continue
        X = Xp[bo.ids]
        T = pose_through_mirror(cam, S, X, bo.corners_px) if mirrored else pose_from_points(cam, X, bo.corners_px)
        if T is None:
            left_out.append({"capture_id": pv.capture_id, "reason": "board pose (PnP) failed"})
            continue
        v = g.add_view(View(pv.capture_id, "projector", False), T, np.zeros(3))
        g.add_corners(v, bo, Xp, KIND_BOARD, mirrored)
        if len(pv.pattern_proj_px):
            g.add_pattern(v, pv, mirrored)


def _add_mirror_views(g: _Gatherer, obs: SessionObservations, cam: CameraModel, S: np.ndarray,
                      init: CalibrationResult, thickness: float, left_out: list) -> None:
    if obs.mirror_board is None or not obs.mirror_views:
        raise CalibrationError("a mirrored session needs mirror-calibration images (real-virtual or "
                               "real-mirror) to locate the mirror")
    n, d = init.mirror.normal, init.mirror.d
    ref = tangent_basis(n)[0]
    Xm = obs.mirror_board.corner_points()
    for mv in obs.mirror_views:
        on_mirror = mv.method == STEP_REAL_MIRROR
        T = None
        if mv.real is not None and len(mv.real.ids) >= MIN_VIEW_CORNERS:
            T = pose_from_points(cam, Xm[mv.real.ids], mv.real.corners_px)
        elif mv.virtual is not None and len(mv.virtual.ids) >= MIN_VIEW_CORNERS and not on_mirror:
            T = pose_through_mirror(cam, S, Xm[mv.virtual.ids], mv.virtual.corners_px)
        if T is None:
            left_out.append({"capture_id": mv.capture_id, "reason": "too few corners or PnP failed"})
            continue
        plane = plane_params(T, ref, n, d, thickness) if on_mirror else np.zeros(3)
        v = g.add_view(View(mv.capture_id, mv.method, on_mirror), T, plane)
        if mv.real is not None and len(mv.real.ids):
            g.add_corners(v, mv.real, Xm, KIND_REAL, False)
        if mv.virtual is not None and len(mv.virtual.ids) and not on_mirror:
            g.add_corners(v, mv.virtual, Xm, KIND_VIRTUAL, True)


def build_problem(obs: SessionObservations, init: CalibrationResult, options: JointOptions,
                  cam_model: str, proj_model: str) -> tuple[JointProblem, list]:
    """Gather the observations, initialise every board pose, and return the problem and the list of
    views left out (with reasons)."""
    mirrored = obs.view != VIEW_DIRECT
    if mirrored and init.mirror is None:
        raise CalibrationError("the joint refinement of a mirrored rig needs an initial mirror plane; "
                               "calibrate the mirror first (paper method) or pass one in the initial result")
    S = init.mirror.reflection() if mirrored else np.eye(4)
    cam = init.camera
    thickness = float(obs.board_thickness)
    left_out: list = []
    g = _Gatherer()
    _add_projector_views(g, obs, cam, S, mirrored, left_out)
    if mirrored:
        _add_mirror_views(g, obs, cam, S, init, thickness, left_out)
    if not any(ps.role == "projector" for ps in g.poses):
        raise CalibrationError("no usable projector-calibration view: every board detection failed or had "
                               "fewer than 6 corners")
    n = init.mirror.normal if mirrored else None
    d = init.mirror.d if mirrored else 0.0
    state = ReferenceState(_camera_K4(cam), dist8(cam.dist), _camera_K4(init.projector), dist8(init.projector.dist),
                           np.array(init.T_cam_proj[:3, :3]), np.array(init.T_cam_proj[:3, 3]),
                           None if n is None else np.array(n), float(d), np.array(g.Rs), np.array(g.ts),
                           np.array(g.planes), cam_model, proj_model)
    for key, free in (("cam_d", DIST_MODELS[cam_model]), ("proj_d", DIST_MODELS[proj_model])):
        dd = getattr(state, key)
        mask = np.ones(8, bool)
        mask[list(free)] = False
        dd[mask] = 0.0
    pm = options.pattern_model
    if pm == "auto":
        pm = "conic" if obs.pattern.kind == PatternKind.CIRCLES else "point"
    if pm not in ("point", "conic"):
        raise CalibrationError(f"unknown pattern model '{options.pattern_model}' (one of {', '.join(PATTERN_MODELS)})")
    prob = JointProblem(obs, state, pm, thickness, g.poses, g.corner_set(), g.pattern_set(),
                        float(obs.pattern.radius_px), g.captures, fix_camera=options.fix_camera)
    return prob, left_out
