"""Auto-capture: take a frame when the board (and in the projector step the whole pattern) is detected,
the board has been still for a moment, and its pose differs enough from the poses already taken.

Also the live detection of one frame for a capture step (`detect_for_step`), the pose features used to
compare poses (`pose_features`), and the pose-diversity bars the panel shows (`diversity_bars`).
Pixel coordinates are in the original camera image (calib.detection.detect maps mirrored views back).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

from calib.formats.session import SessionManifest
from calib.models.boards import CharucoSpec
from calib.models.camera import CameraModel
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, VIEW_MIRROR, BoardObservation
from calib.models.vocab import PatternKind


# ---- pose features ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class PoseFeatures:
    """How a board pose looks: centre (fractions of the image), apparent size (sqrt of the fraction of
    the image its corners cover), tilt from facing the camera (deg) and orientation (rotation vector of
    the board in the (virtual) camera frame, from PnP with an approximate camera model)."""

    centre: tuple[float, float]
    size: float
    tilt_deg: float
    rvec: tuple[float, float, float] | None = None
    tvec: tuple[float, float, float] | None = None  # board units, same frame as rvec

    def to_dict(self) -> dict:
        d = {"centre": [round(self.centre[0], 5), round(self.centre[1], 5)], "size": round(self.size, 5),
             "tilt_deg": round(self.tilt_deg, 3)}
        if self.rvec is not None:
            d["rvec"] = [round(float(v), 6) for v in self.rvec]
        if self.tvec is not None:
            d["tvec"] = [round(float(v), 4) for v in self.tvec]
        return d

    @classmethod
    def from_dict(cls, d) -> "PoseFeatures | None":
        try:
            rv, tv = d.get("rvec"), d.get("tvec")
            return cls((float(d["centre"][0]), float(d["centre"][1])), float(d["size"]), float(d["tilt_deg"]),
                       None if rv is None else tuple(float(v) for v in rv),
                       None if tv is None else tuple(float(v) for v in tv))
        except (KeyError, TypeError, ValueError, IndexError, AttributeError):
            return None


def approximate_camera(size: tuple[int, int], model: CameraModel | None = None) -> CameraModel:
    """The camera model used to judge poses: the device's own when it reports one, else 90 deg hfov."""
    if model is not None and tuple(model.size) == tuple(size):
        return model
    return CameraModel.from_fov(size[0], size[1], 90.0)


def pose_features(obs: BoardObservation, spec: CharucoSpec, camera: CameraModel) -> PoseFeatures | None:
    """Features of one board observation, None with fewer than 4 corners."""
    if obs is None or len(obs.ids) < 4:
        return None
    uv = np.asarray(obs.corners_px, float)
    W, H = camera.size
    centre = (float(uv[:, 0].mean() / W), float(uv[:, 1].mean() / H))
    hull = cv2.convexHull(uv.astype(np.float32))
    size = float(np.sqrt(max(cv2.contourArea(hull), 0.0) / (W * H)))
    obj = spec.corner_points()[np.asarray(obs.ids)]
    cam = camera
    pts = uv
    if obs.mirrored:  # a right-handed view of the mirrored board: the flipped image's virtual camera
        cam = camera.flipped()
        pts = camera.flip_points(uv)
    try:
        ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), pts.astype(np.float64), np.asarray(cam.K),
                                      np.asarray(cam.dist), flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        ok = False
    if not ok:
        return PoseFeatures(centre, size, 0.0, None)
    R, _ = cv2.Rodrigues(rvec)
    t = np.asarray(tvec, float).reshape(3)
    c = R @ obj.mean(axis=0) + t
    normal = R[:, 2]
    cosang = abs(float(normal @ c) / max(np.linalg.norm(c), 1e-12))
    tilt = float(np.degrees(np.arccos(np.clip(cosang, 0.0, 1.0))))
    return PoseFeatures(centre, size, tilt, tuple(float(v) for v in np.asarray(rvec).reshape(3)),
                        tuple(float(v) for v in t))


def pose_distance(a: PoseFeatures, b: PoseFeatures) -> dict:
    """Differences between two poses: centre shift (image fractions), size ratio (log) and rotation."""
    d_centre = float(np.hypot(a.centre[0] - b.centre[0], a.centre[1] - b.centre[1]))
    d_size = abs(float(np.log(max(a.size, 1e-6) / max(b.size, 1e-6))))
    if a.rvec is not None and b.rvec is not None:
        Ra, _ = cv2.Rodrigues(np.array(a.rvec, float))
        Rb, _ = cv2.Rodrigues(np.array(b.rvec, float))
        c = (np.trace(Ra.T @ Rb) - 1) / 2
        d_rot = float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    else:
        d_rot = abs(a.tilt_deg - b.tilt_deg)
    return {"centre": d_centre, "size": d_size, "rotation_deg": d_rot}


# ---- live detection -------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LiveDetection:
    """What one camera frame shows for the current capture step."""

    step: str | None
    frame_number: int
    image_size: tuple[int, int]
    board: BoardObservation | None = None  # the pose the capture is judged on (real board for mirror steps)
    virtual: BoardObservation | None = None  # real-virtual: the board in the mirror
    pattern_px: np.ndarray | None = None  # projector step: the pattern points in the camera image
    features: PoseFeatures | None = None
    failure: str | None = None  # why the frame is not usable (None: usable)
    detect_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.failure is None


def detect_for_step(image: np.ndarray, step: str | None, manifest: SessionManifest, camera: CameraModel,
                    frame_number: int = 0) -> LiveDetection:
    """Detect what `step` needs in one frame: never raises for a bad frame, reports why instead."""
    from calib.detection import detect as D

    t0 = time.perf_counter()
    size = (int(image.shape[1]), int(image.shape[0]))
    kw = {"step": step, "frame_number": frame_number, "image_size": size}

    def done(**more):
        return LiveDetection(**kw, **more, detect_s=time.perf_counter() - t0)

    if step is None:
        return done(failure="no capture step is active")
    if step == STEP_PROJECTOR:
        spec = manifest.projector_board
        mirrored = manifest.rig.view == VIEW_MIRROR
        board = D.detect_board(image, spec, mirrored)
        if not board:
            return done(failure=f"board: {board.reason}")
        feats = pose_features(board, spec, camera)
        if manifest.pattern.kind == PatternKind.STRUCTURED.value:  # the sequence comes once the board is still
            return done(board=board, features=feats)
        pts = D.detect_pattern(image, manifest.pattern, mirrored, board=board, board_spec=spec)
        if isinstance(pts, D.DetectionFailure):
            return done(board=board, features=feats, failure=f"pattern: {pts.reason}")
        pts = np.asarray(pts, float).reshape(-1, 2)
        if len(pts) != manifest.pattern.n_points:
            return done(board=board, features=feats,
                        failure=f"pattern: {len(pts)} of {manifest.pattern.n_points} points")
        return done(board=board, features=feats, pattern_px=pts)
    spec = manifest.mirror_board or manifest.projector_board
    if step == STEP_REAL_VIRTUAL:
        view = D.detect_real_virtual(image, spec)
    elif step == STEP_REAL_MIRROR:
        view = D.detect_real_mirror(image, spec)
    else:
        return done(failure=f"unknown step '{step}'")
    if isinstance(view, D.DetectionFailure):
        return done(failure=view.reason)
    feats = pose_features(view.real, spec, camera)
    return done(board=view.real, virtual=view.virtual, features=feats)


# ---- stillness and novelty ------------------------------------------------------------------------
@dataclass(frozen=True)
class AutoCaptureSettings:
    still_frames: int = 3  # consecutive frames (motion measured between neighbours) the board must be still
    still_px: float = 1.0  # median corner motion between two frames below which the board is still
    min_common_corners: int = 6
    novelty_centre: float = 0.06  # a pose is new when it differs by this much centre shift (image fraction)
    novelty_size: float = 0.12  # ... or by this log size ratio
    novelty_rotation_deg: float = 6.0  # ... or by this rotation


@dataclass(frozen=True)
class Decision:
    capture: bool
    still: bool
    novel: bool
    message: str
    motion_px: float | None = None
    similar_to: str | None = None


def corner_motion(a: BoardObservation, b: BoardObservation, min_common: int = 6) -> float | None:
    """Median displacement (px) of the corners both observations share, None if too few are shared."""
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    if len(common) < min_common:
        return None
    return float(np.median(np.linalg.norm(a.corners_px[ia] - b.corners_px[ib], axis=1)))


class AutoCapture:
    """Feed it one LiveDetection per frame; it says when to capture. `taken` holds the features of the
    poses already captured that a new pose is compared with (set by the caller for the current target).

    Thread-safe: the station's loop calls `update` while the operator's buttons (Move board, Capture,
    Retake) call `reset` from the panel's threads; one lock makes each call see the history whole (a
    reset in the middle of `motion()` once raised IndexError and killed the capture loop)."""

    def __init__(self, settings: AutoCaptureSettings | None = None):
        self.settings = settings or AutoCaptureSettings()
        self._lock = threading.RLock()
        self._history: list[BoardObservation] = []
        self.taken: list[tuple[str, PoseFeatures]] = []
        # poses a retake must differ from (the deleted capture's): kept over resets until a capture
        # is decided or forget_avoided() is called
        self.avoided: list[tuple[str, PoseFeatures]] = []
        self.last: Decision | None = None

    def avoid(self, label: str, feats: PoseFeatures | None) -> None:
        """After a retake: the next capture must not be this pose again (the operator was asked to move)."""
        if feats is not None:
            with self._lock:
                self.avoided = [a for a in self.avoided if a[0] != label] + [(label, feats)]

    def forget_avoided(self) -> None:
        with self._lock:
            self.avoided = []

    def reset(self, taken: list[tuple[str, PoseFeatures]] | None = None) -> None:
        """Start over (new target, projector moved, board asked to move)."""
        with self._lock:
            self._history = []
            if taken is not None:
                self.taken = list(taken)
            self.last = None

    def history(self) -> tuple[BoardObservation, ...]:
        """The board observations the stillness is judged on (oldest first), a snapshot."""
        with self._lock:
            return tuple(self._history)

    def motion(self) -> list[float | None]:
        h = self.history()
        return [corner_motion(h[i - 1], h[i], self.settings.min_common_corners) for i in range(1, len(h))]

    def novelty(self, feats: PoseFeatures | None) -> tuple[bool, str | None, str]:
        """(new enough, id of the most similar pose taken, explanation)."""
        if feats is None:
            return False, None, "the board pose cannot be measured"
        s = self.settings
        worst, worst_id = None, None
        for cid, other in list(self.taken) + list(self.avoided):
            d = pose_distance(feats, other)
            score = max(d["centre"] / s.novelty_centre, d["size"] / s.novelty_size,
                        d["rotation_deg"] / s.novelty_rotation_deg)
            if worst is None or score < worst:
                worst, worst_id = score, cid
        if worst is None or worst >= 1.0:
            return True, None, "new pose"
        return False, worst_id, f"this pose is too close to {worst_id}: move or tilt the board"

    def update(self, det: LiveDetection) -> Decision:
        with self._lock:
            return self._update(det)

    def _update(self, det: LiveDetection) -> Decision:
        s = self.settings
        if det.board is None:
            self._history = []
            self.last = Decision(False, False, False, det.failure or "board not found")
            return self.last
        self._history = (self._history + [det.board])[-s.still_frames:]
        motions = self.motion()
        known = [m for m in motions if m is not None]
        still = len(self._history) >= s.still_frames and len(known) == len(motions) and all(m < s.still_px for m in known)
        motion = known[-1] if known else None
        if not det.ok:
            self.last = Decision(False, still, False, det.failure, motion)
            return self.last
        novel, similar, why = self.novelty(det.features)
        if not still:
            if motion is not None and motion >= s.still_px:
                msg = f"hold the board still (it moves {motion:.1f} px per frame)"
            else:
                msg = "keep the board still a moment"
            self.last = Decision(False, False, novel, msg, motion, similar)
        elif not novel:
            self.last = Decision(False, True, False, why, motion, similar)
        else:
            self.last = Decision(True, True, True, "capturing", motion)
            self.avoided = []
        return self.last


# ---- diversity bars -------------------------------------------------------------------------------
#: The range each bar asks for (it is full, and its target met, when the captured poses span this much):
#: (name, the range that fills the bar, that range in words)
BAR_TARGETS = (("position x", 0.45, "45% of the width"), ("position y", 0.45, "45% of the height"),
               ("size", 0.25, "25% of the image"), ("tilt", 25.0, "25 deg"))


@dataclass(frozen=True)
class Bar:
    name: str
    fraction: float  # 0..1, how well the range is covered
    detail: str
    target: str = ""  # the range that fills the bar, in words

    @property
    def met(self) -> bool:
        return self.fraction >= 0.999


def diversity_bars(features: list[PoseFeatures]) -> list[Bar]:
    """Board pose diversity as bars that fill up: horizontal and vertical position, size and tilt.
    Each is the range covered by the captured poses relative to a good range (BAR_TARGETS;
    camera_calibration's X, Y, Size and Skew bars are the model)."""
    targets = {name: (good, words) for name, good, words in BAR_TARGETS}
    if not features:
        return [Bar(n, 0.0, "no poses yet", targets[n][1]) for n, _, _ in BAR_TARGETS]
    cx = np.array([f.centre[0] for f in features])
    cy = np.array([f.centre[1] for f in features])
    sz = np.array([f.size for f in features])
    tl = np.array([f.tilt_deg for f in features])

    def bar(name, values, fmt):
        good, words = targets[name]
        rng = float(values.max() - values.min())
        return Bar(name, float(min(1.0, rng / good)), fmt(values.min(), values.max()), words)

    return [
        bar("position x", cx, lambda a, b: f"{a * 100:.0f}-{b * 100:.0f}% of the width"),
        bar("position y", cy, lambda a, b: f"{a * 100:.0f}-{b * 100:.0f}% of the height"),
        bar("size", sz, lambda a, b: f"{a * 100:.0f}-{b * 100:.0f}% of the image"),
        bar("tilt", tl, lambda a, b: f"{a:.0f}-{b:.0f} deg"),
    ]
