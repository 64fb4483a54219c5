"""The simulated rig: a camera, a projector and an operator behind the driver protocols (drivers/base.py).

    rig = open_sim_rig("nonoverlap-136", seed=0, quality="live")
    rig.camera.start()
    rig.operator.request_pose("projector", 3, 0)     # the scripted person moves the board
    ticket = rig.projector.show(pattern_image)
    rig.projector.wait_presented(ticket)
    frame = rig.camera.get_frame(newer_than=last)    # rendered on request
    truth = rig.ground_truth()

SimCamera, SimProjector and SimOperator share one SimRig (the scene state, under a lock). Frames are
rendered when asked for; their noise is seeded by (seed, frame_number), so a run is reproducible.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from calib.camera import CameraModel
from calib.errors import SpecError
from calib.result import CalibrationResult
from calib.transforms import make_T, rotation_about, rotation_angle_deg
from drivers.base import Frame
from drivers.errors import DeviceError
from drivers.sim.render import QUALITIES, PlacedBoard, Renderer, RenderSettings, SceneState, layout_for
from drivers.sim.scenarios import (
    DEFAULT_SCENARIO,
    OPERATOR_STEPS,
    STEP_PROJECTOR,
    STEP_REAL_VIRTUAL,
    STEP_VERIFICATION,
    Scenario,
    get_scenario,
)


class SimCamera:
    """CameraDriver: renders the rig's current state whenever a frame is asked for."""

    def __init__(self, rig: "SimRig", expose_intrinsics: bool = False):
        self._rig = rig
        self._expose = expose_intrinsics
        self._running = False
        self._frame_number = 0
        self._last_ts = 0.0
        self._lock = threading.Lock()

    @property
    def size(self) -> tuple[int, int]:
        return self._rig.scenario.rig.camera.size

    @property
    def model(self) -> CameraModel:
        """The true camera model (ground truth; a real driver has no such thing)."""
        return self._rig.scenario.rig.camera

    def start(self) -> None:
        self._rig.renderer.warm_up()
        self._running = True

    def stop(self) -> None:
        self._running = False

    @property
    def running(self) -> bool:
        return self._running

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None) -> Frame:
        if not self._running:
            raise DeviceError("the simulated camera is not started; call camera.start() first")
        with self._lock:
            n = max(self._frame_number, -1 if newer_than is None else int(newer_than)) + 1
            self._frame_number = n
            image, meta = self._rig._render_frame(n)
            ts = max(time.monotonic() * 1000.0, self._last_ts + 1e-3)
            self._last_ts = ts
        return Frame(image, n, ts, meta)

    def factory_intrinsics(self) -> CameraModel | None:
        return self.model if self._expose else None

    def settings(self) -> dict:
        st = self._rig.settings
        return {"driver": "sim", "scenario": self._rig.scenario.name, "seed": self._rig.scenario.seed,
                "quality": self._rig.quality, **{k: v for k, v in st.to_dict().items()}}


class SimProjector:
    """ProjectorDriver: the image shown is what lights the board in the next rendered frame."""

    def __init__(self, rig: "SimRig"):
        self._rig = rig
        self._ticket = 0
        self._presented: dict[int, float] = {}
        self._closed = False
        W, H = self.size
        self._image = np.zeros((H, W), np.uint8)

    @property
    def size(self) -> tuple[int, int]:
        return self._rig.scenario.rig.projector.size

    @property
    def image(self) -> np.ndarray:
        """The image shown now ((H, W) uint8, read-only)."""
        return self._image

    def show(self, image: np.ndarray) -> int:
        if self._closed:
            raise DeviceError("the simulated projector is closed")
        img = np.asarray(image)
        W, H = self.size
        if img.dtype != np.uint8 or img.ndim not in (2, 3) or img.shape[:2] != (H, W) \
                or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
            raise DeviceError(f"projector image must be uint8 of {W}x{H} pixels (H, W) or (H, W, 3); "
                              f"got {img.dtype} of shape {img.shape}")
        if img.ndim == 3:
            img = img[:, :, :3].mean(axis=2).round().astype(np.uint8) if img.shape[2] > 1 else img[:, :, 0]
        img = np.array(img, np.uint8)
        img.setflags(write=False)
        with self._rig._lock:
            self._image = img
            self._ticket += 1
            t = self._ticket
            self._presented[t] = time.monotonic()
            if len(self._presented) > 64:
                for k in sorted(self._presented)[:-32]:
                    del self._presented[k]
        return t

    def wait_presented(self, ticket: int, timeout_s: float = 2.0) -> float:
        if ticket not in self._presented:
            if 0 < ticket <= self._ticket:
                return time.monotonic()
            raise DeviceError(f"unknown projector ticket {ticket}")
        return self._presented[ticket]

    def close(self) -> None:
        self._closed = True


class SimOperator:
    """Operator: a scripted person who places the board at the scenario's poses.

    `settling_frames`: after every move, that many frames show the board still moving from the old pose
    to the new one (so an auto-capture stillness check has something to reject)."""

    def __init__(self, rig: "SimRig", settling_frames: int = 0):
        self._rig = rig
        self.settling_frames = int(settling_frames)
        self.last_request: tuple | None = None

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int) -> str:
        sc = self._rig.scenario
        if step not in OPERATOR_STEPS:
            raise SpecError(f"unknown step '{step}' (one of {', '.join(OPERATOR_STEPS)})")
        pose_index = int(pose_index)
        if step == STEP_PROJECTOR:
            if pattern_position is None or not 0 <= int(pattern_position) < sc.pattern.positions:
                raise SpecError(f"projector step needs a pattern position in 0..{sc.pattern.positions - 1}")
            pos = int(pattern_position)
            scripted = [T for p, T in sc.projector_poses if p == pos]
            T = scripted[pose_index] if pose_index < len(scripted) else sc.extra_projector_pose(pos, pose_index)
            layout = sc.layout
            text = (f"Pattern position {pos + 1} of {sc.pattern.positions}, pose {pose_index + 1}: hold the board so "
                    f"the projected pattern lands on its blank area; {self._describe(T)}.")
        elif step == STEP_VERIFICATION:
            T = sc.verification_pose_for(pose_index)
            layout = sc.layout
            text = f"Verification: hold the board still, facing the projector, in the middle of its image; {self._describe(T)}."
        else:
            if sc.rig.mirror is None:
                raise DeviceError(f"scenario '{sc.name}' has no mirror: there is no mirror step")
            method = "real-virtual" if step == STEP_REAL_VIRTUAL else "real-mirror"
            poses = sc.mirror_poses if sc.mirror_method == method else self._rig._other_mirror_poses(method)
            if pose_index < len(poses):
                T = poses[pose_index]
            else:
                T = sc.mirror_poses_for(method, 1, seed=sc.seed * 1000 + 17 + pose_index)[0]
            layout = layout_for(sc.mirror_board)
            if step == STEP_REAL_VIRTUAL:
                text = (f"Mirror placement {pose_index + 1}: hold the small board between the camera and the mirror so "
                        f"the camera sees it both directly and in the mirror; {self._describe(T)}.")
            else:
                text = f"Mirror placement {pose_index + 1}: lay the small board flat on the mirror, printed side up."
        self._rig._place(layout, T)
        self.last_request = (step, pattern_position, pose_index)
        return text

    def move_out(self) -> str:
        """Take the board out of view."""
        self._rig._place(None, None)
        self.last_request = None
        return "Take the board out of view."

    @staticmethod
    def _describe(T: np.ndarray) -> str:
        dist = float(np.linalg.norm(T[:3, 3]))
        tilt = rotation_angle_deg(T[:3, :3])
        return f"about {dist / 1000:.2f} m from the camera, turned {tilt:.0f} deg"


class SimRig:
    """The shared scene state of a simulated rig, and its three devices."""

    kind = "sim"  # as drivers.factory names rigs

    def __init__(self, scenario: Scenario, quality: str = "live", expose_intrinsics: bool = False,
                 settling_frames: int = 0, motion_jitter_mm: float = 0.0, **settings):
        if quality not in QUALITIES:
            raise SpecError(f"unknown quality '{quality}' (one of {', '.join(QUALITIES)})")
        self.scenario = scenario
        self.quality = quality
        base = scenario.render
        ss = 1 if quality == "live" else 3
        unknown = set(settings) - set(RenderSettings.__dataclass_fields__)
        if unknown:
            raise SpecError(f"unknown render setting(s) {sorted(unknown)}; known: "
                            f"{', '.join(RenderSettings.__dataclass_fields__)}")
        from dataclasses import replace

        self.settings = replace(base, **{"supersample": ss, **settings})
        r = scenario.rig
        self.renderer = Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, self.settings)
        self.motion_jitter_mm = float(motion_jitter_mm)
        self._lock = threading.RLock()
        self._board: PlacedBoard | None = None
        self._prev: PlacedBoard | None = None
        self._frames_since_move = 0
        self._move_id = 0
        self._other_mirror: dict = {}
        self.camera = SimCamera(self, expose_intrinsics)
        self.projector = SimProjector(self)
        self.operator = SimOperator(self, settling_frames)

    def ground_truth(self) -> CalibrationResult:
        return self.scenario.ground_truth()

    def close(self) -> None:
        """Stop the camera and close the projector."""
        self.camera.stop()
        self.projector.close()

    @property
    def board(self) -> PlacedBoard | None:
        """The board now in the scene (layout and T_cam_board), or None."""
        return self._board

    def _other_mirror_poses(self, method: str) -> list:
        if method not in self._other_mirror:
            self._other_mirror[method] = self.scenario.mirror_poses_for(method, self.scenario.mirror_count)
        return self._other_mirror[method]

    def _place(self, layout, T) -> None:
        with self._lock:
            self._prev = self._board
            self._board = None if layout is None else PlacedBoard(layout, np.array(T, float))
            self._frames_since_move = 0
            self._move_id += 1

    def state(self, frame_number: int | None = None) -> SceneState:
        """The scene for a frame: while settling, the board is on its way from the previous pose."""
        with self._lock:
            b, prev = self._board, self._prev
            k = self._frames_since_move
            n_settle = self.operator.settling_frames
            if frame_number is not None:
                self._frames_since_move += 1
            img = self.projector.image
        boards = ()
        if b is not None:
            T = b.T_cam_board
            if k < n_settle:
                if prev is not None and prev.layout is b.layout:
                    a = (k + 1) / (n_settle + 1)
                    T = _interpolate_pose(prev.T_cam_board, T, a)
                else:  # coming into view: sliding in along the board's x axis
                    T = T.copy()
                    T[:3, 3] += T[:3, 0] * 60.0 * (n_settle - k) / n_settle
            if self.motion_jitter_mm > 0 and frame_number is not None:
                rng = np.random.default_rng([self.scenario.seed, 555, frame_number])
                T = T.copy()
                T[:3, 3] += rng.normal(0, self.motion_jitter_mm, 3)
            boards = (PlacedBoard(b.layout, T),)
        return SceneState(boards, img)

    def _render_frame(self, frame_number: int):
        with self._lock:
            moving = self._board is not None and self._frames_since_move < self.operator.settling_frames
            move_id = self._move_id
        st = self.state(frame_number)
        rng = np.random.default_rng([self.scenario.seed, 1, frame_number])
        img = self.renderer.render(st, rng)
        meta = {"sim": True, "moving": moving, "move_id": move_id,
                "T_cam_board": None if not st.boards else st.boards[0].T_cam_board.tolist()}
        return img, meta

    def render_still(self, noise_key: int) -> np.ndarray:
        """The image of the current (settled) state, noise seeded by (seed, 2, noise_key): for writing
        sessions reproducibly whatever the order frames are rendered in."""
        with self._lock:
            b = self._board
            img = self.projector.image
        st = SceneState(() if b is None else (b,), img)
        return self.renderer.render(st, np.random.default_rng([self.scenario.seed, 2, int(noise_key)]))


def _interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    import cv2

    dR = T1[:3, :3] @ T0[:3, :3].T
    rvec, _ = cv2.Rodrigues(dR)
    R = rotation_about(rvec.reshape(3), np.degrees(np.linalg.norm(rvec)) * a) @ T0[:3, :3] \
        if np.linalg.norm(rvec) > 1e-12 else T0[:3, :3]
    return make_T(R, (1 - a) * T0[:3, 3] + a * T1[:3, 3])


def open_sim_rig(scenario: str = DEFAULT_SCENARIO, seed: int = 0, quality: str = "live", **settings) -> SimRig:
    """A simulated rig for a named scenario. Keyword settings: expose_intrinsics, settling_frames,
    motion_jitter_mm, and any RenderSettings field (ambient, projector_gain, blur_sigma_px, read_noise_dn,
    electrons_per_dn, ...)."""
    return SimRig(get_scenario(scenario, seed), quality, **settings)
