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

import math
import threading

import numpy as np

from calib.errors import SpecError
from calib.models.camera import CameraModel
from calib.models.result import CalibrationResult
from calib.transforms import make_T, rotation_about, rotation_angle_deg
from calib.models.vocab import MirrorMethod, RenderQuality, RigKind, Step
from drivers.base import Frame
from drivers.clock import Clock, SimClock
from drivers.errors import DeviceError, DeviceTimeout
from drivers.sim.hardware import (
    AE_TARGET_LEVEL,
    EXPOSURE_LIMITS_US,
    GAIN_LIMITS,
    REFERENCE_EXPOSURE_US,
    CameraSettingsTimeline,
    HardwareModel,
    ProjectorTimeline,
    emitter_dots,
    flicker_amplitude,
    flicker_phase,
)
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


#: Frames the simulated camera's driver queues: a caller that asks for the frame after one it has seen
#: gets that frame while it is among the newest FRAME_QUEUE, else the oldest one still queued.
FRAME_QUEUE = 2


class SimCamera:
    """CameraDriver and ExposureControl: renders what the rig showed during each frame's exposure.

    Hardware-like (the default): frames follow the camera's own 30 fps clock from start(); frame n is
    exposed from t0 + n / fps for the exposure in force, delivered one frame period after that, and
    rendered lazily when asked for (never before it is delivered). A frame whose exposure spans a
    projector change blends the images by the time each was visible; what it saw is kept in
    `rig.frame_truth[n]` = ((ticket, fraction), ...). Ideal (`ideal=True`): a new frame on every
    request, showing the projector's current image, no exposure model.
    """

    def __init__(self, rig: "SimRig", expose_intrinsics: bool = False):
        self._rig = rig
        self._expose = expose_intrinsics
        self._running = False
        self._frame_number = 0
        self._last_ts = 0.0
        self._lock = threading.Lock()
        self._t0 = 0.0
        self._cached: Frame | None = None
        self._floor = 0  # the first frame number this run of the clock may deliver
        self._ae_exposure_us = rig.hardware.initial_exposure_us
        self.settings_timeline = CameraSettingsTimeline(rig.hardware)

    @property
    def clock(self) -> Clock:
        """The rig's simulated clock: frame times are on it (drivers.clock)."""
        return self._rig.clock

    @property
    def size(self) -> tuple[int, int]:
        return self._rig.scenario.rig.camera.size

    @property
    def model(self) -> CameraModel:
        """The true camera model (ground truth; a real driver has no such thing)."""
        return self._rig.scenario.rig.camera

    def start(self) -> None:
        self._rig.renderer.warm_up()
        if not self._running:  # the clock starts; after a stop, frame numbers go on after the last one
            self._floor = self._frame_number + 1 if self._cached is not None else 0
            self._t0 = self._rig.clock.now() - self._floor * self._rig.hardware.period_s
            self._cached = None
        self._running = True

    def stop(self) -> None:
        self._running = False

    @property
    def running(self) -> bool:
        return self._running

    # ---- the frame clock ---------------------------------------------------------------------------
    def exposure_start_s(self, n: int) -> float:
        """Host time at which frame n's exposure starts (hardware-like mode)."""
        return self._t0 + n * self._rig.hardware.period_s

    def _newest_delivered(self, now: float) -> int:
        return int(math.floor((now - self._t0) / self._rig.hardware.period_s + 1e-9)) - 1

    def get_frame(self, timeout_s: float = 2.0, newer_than: int | None = None) -> Frame:
        if not self._running:
            raise DeviceError("the simulated camera is not started; call camera.start() first")
        if self._rig.hardware.ideal:
            return self._ideal_frame(newer_than)
        hw = self._rig.hardware
        with self._lock:
            now = self._rig.clock.now()
            n = max(self._newest_delivered(now), self._floor)
            if newer_than is not None:  # the oldest frame newer than that still in the driver's queue
                n = max(int(newer_than) + 1, n - (FRAME_QUEUE - 1))
            delivered = self._t0 + (n + 1) * hw.period_s
            if delivered - now > timeout_s:
                self._rig.clock.sleep(max(0.0, timeout_s))
                raise DeviceTimeout(f"no simulated camera frame newer than {newer_than} within {timeout_s:g} s")
            if delivered > now:
                self._rig.clock.sleep(delivered - now)  # no frame from the future
            if self._cached is not None and self._cached.frame_number == n:
                return self._cached
            frame = self._clocked_frame(n)
            self._cached = frame
            self._frame_number = n
            return frame

    def _ideal_frame(self, newer_than):
        with self._lock:
            n = max(self._frame_number, -1 if newer_than is None else int(newer_than)) + 1
            self._frame_number = n
            if self._rig.clock.simulated:  # a frame takes its period, never waits
                self._rig.clock.advance(self._rig.hardware.period_s)
            t = self._rig.clock.now()
            with self._rig._lock:
                tk = self._rig.projector.ticket
            image, meta = self._rig._render_frame(n)
            self._rig._record_truth(n, ((tk, 1.0),))
            ts = max(t * 1000.0, self._last_ts + 1e-3)
            self._last_ts = ts
        return Frame(image, n, ts, meta, exposure_start_s=t)

    def _clocked_frame(self, n: int) -> Frame:
        hw = self._rig.hardware
        t_start = self.exposure_start_s(n)
        st = self.settings_timeline.at(t_start)
        exposure_us = self._ae_exposure_us if st["auto_exposure"] else float(st["exposure_us"])
        exposure_us = float(np.clip(exposure_us, EXPOSURE_LIMITS_US[0], hw.period_s * 1e6))
        gain = float(st["gain"])
        t_end = t_start + exposure_us * 1e-6
        with self._rig._lock:
            segments = self._rig.projector.timeline.segments(t_start, t_end)
        image, meta = self._rig._render_frame(n, segments, exposure_us, gain, st["emitter_enabled"])
        self._rig._record_truth(n, tuple((tk, f) for tk, _, f in segments))
        if st["auto_exposure"]:  # auto exposure reacts to what it saw, a little late and overshooting
            mean = float(meta["mean_level"])
            ratio = AE_TARGET_LEVEL / max(mean, 1.0)
            step = ratio ** 0.5 if abs(math.log(ratio)) > 0.15 else ratio ** 1.6  # slow far off, hunting near
            self._ae_exposure_us = float(np.clip(self._ae_exposure_us * step, EXPOSURE_LIMITS_US[0],
                                                 EXPOSURE_LIMITS_US[1]))
        meta.update({"exposure_us": exposure_us, "gain": gain, "auto_exposure": bool(st["auto_exposure"]),
                     "emitter_enabled": bool(st["emitter_enabled"])})
        return Frame(image, n, t_end * 1000.0, meta, exposure_start_s=t_start)

    # ---- ExposureControl ---------------------------------------------------------------------------
    def exposure_limits(self) -> dict:
        return {"exposure_us": EXPOSURE_LIMITS_US, "gain": GAIN_LIMITS}

    def set_auto_exposure(self, enabled: bool) -> None:
        self.settings_timeline.set(self._rig.clock.now(), auto_exposure=bool(enabled))

    def set_manual_exposure(self, exposure_us: float, gain: float) -> dict:
        lo, hi, step = EXPOSURE_LIMITS_US
        glo, ghi, gstep = GAIN_LIMITS
        e = float(np.clip(round(float(exposure_us) / step) * step, lo, hi))
        g = float(np.clip(round(float(gain) / gstep) * gstep, glo, ghi))
        self.settings_timeline.set(self._rig.clock.now(), auto_exposure=False, exposure_us=e, gain=g)
        return {"exposure_us": e, "gain": g}

    def set_emitter(self, enabled: bool) -> None:
        self.settings_timeline.set(self._rig.clock.now(), emitter_enabled=bool(enabled))

    def factory_intrinsics(self) -> CameraModel | None:
        return self.model if self._expose else None

    def response(self) -> dict:
        """The camera's tone curve, as a session records it (calib.detection.response): the simulated
        camera knows its own (drivers/sim/render.py, `camera_gamma`, BT.709-shaped): "source" "known" (a
        RealSense's is "measured" by the rig check, drivers.exposure.measure_response)."""
        return {"model": "bt709", "gamma": float(self._rig.settings.camera_gamma), "source": "known"}

    def settings(self) -> dict:
        st = self._rig.settings
        out = {"driver": "sim", "scenario": self._rig.scenario.name, "seed": self._rig.scenario.seed,
               "quality": self._rig.quality, **{k: v for k, v in st.to_dict().items()}}
        out["response"] = self.response()
        if getattr(self._rig, "bump", None):
            out["bump"] = self._rig.bump
        if not self._rig.hardware.ideal:
            cur = self.settings_timeline.current
            out.update({"auto_exposure": bool(cur["auto_exposure"]), "exposure_us": float(cur["exposure_us"]),
                        "gain": float(cur["gain"]), "emitter_enabled": bool(cur["emitter_enabled"])})
        return out


class SimProjector:
    """ProjectorDriver: an image shown is swapped at the next vsync and visible after the projector's
    latency (hardware-like mode), or at once (ideal). `settle_s` is the latency the caller believes
    (measured, drivers/settle.py): wait_presented returns the swap time plus `settle_s`."""

    def __init__(self, rig: "SimRig"):
        self._rig = rig
        self._ticket = 0
        self._closed = False
        W, H = self.size
        self._image = np.zeros((H, W), np.uint8)
        self._image.setflags(write=False)
        self.settle_s = 0.0
        self.blanked = False  # blank(): the projector's image no longer reaches the scene
        self.timeline = ProjectorTimeline(rig.hardware, rig.scenario.seed, self._rig.clock.now(), self._image)

    @property
    def clock(self) -> Clock:
        """The rig's simulated clock: presentation times are on it (drivers.clock)."""
        return self._rig.clock

    @property
    def size(self) -> tuple[int, int]:
        return self._rig.scenario.rig.projector.size

    @property
    def refresh_hz(self) -> float:
        return float(self._rig.hardware.refresh_hz)

    @property
    def ticket(self) -> int:
        """The ticket of the last image asked for (0: the black image at power-on)."""
        return self._ticket

    @property
    def image(self) -> np.ndarray:
        """The image last asked for ((H, W) uint8, read-only); on screen once its latency has passed."""
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
            self.timeline.add(t, img, self._rig.clock.now())
        return t

    def wait_presented(self, ticket: int, timeout_s: float = 2.0) -> float:
        swap = self.timeline.swaps.get(int(ticket))
        if swap is None:
            raise DeviceError(f"unknown projector ticket {ticket}")
        visible = swap + float(self.settle_s)
        delay = visible - self._rig.clock.now()
        if delay > timeout_s:
            raise DeviceTimeout(f"projector image {ticket} is not visible within {timeout_s:g} s")
        if delay > 0:
            self._rig.clock.sleep(delay)
        return visible

    def true_visible_s(self, ticket: int) -> float:
        """When the image of `ticket` really became visible (the simulator's truth, for tests)."""
        t = self.timeline
        return t._times[[e[0] for e in t._entries].index(int(ticket))]

    def blank(self, on: bool = True) -> None:
        """A test hook: the projector goes blank (its screen blanked, asleep or unplugged) while the station
        still shows its image; its light stops reaching the scene until blank(False)."""
        self.blanked = bool(on)

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
        self.last_pose: np.ndarray | None = None

    #: how far a person holds a pose shown as an outline from it: 1-sigma rotation (degrees, about a random
    #: axis through the board's blank centre) and shift (mm per axis)
    FOLLOW_DEG = 3.0
    FOLLOW_MM = 10.0

    def _held(self, pos: int, T: np.ndarray, pose_index: int) -> np.ndarray:
        """The pose the scripted person holds when asked for T: off by FOLLOW_DEG / FOLLOW_MM (drawn from
        the scenario's seed, the position and the pose index), redrawn until the pattern lands on the
        blank area and the camera sees the board; T itself when no draw does."""
        from calib.synthetic import held_pose

        sc = self._rig.scenario
        rng = np.random.default_rng([sc.seed, 7919, pos, int(pose_index)])
        return held_pose(sc.rig, sc.layout, sc.pattern, pos, T, self.FOLLOW_DEG, self.FOLLOW_MM, rng)

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int, asked=None,
                     on_stand: bool = False) -> str:
        sc = self._rig.scenario
        if step not in OPERATOR_STEPS:
            raise SpecError(f"unknown step '{step}' (one of {', '.join(OPERATOR_STEPS)})")
        pose_index = int(pose_index)
        if step == STEP_PROJECTOR:
            if pattern_position is None or not 0 <= int(pattern_position) < sc.pattern.positions:
                raise SpecError(f"projector step needs a pattern position in 0..{sc.pattern.positions - 1}")
            pos = int(pattern_position)
            layout = sc.layout
            if asked is not None:
                A = np.asarray(asked, float).reshape(4, 4)
                if not np.isfinite(A).all():
                    raise SpecError("the asked board pose is not a finite 4x4 matrix")
                T = self._held(pos, A, pose_index)
                text = (f"Pattern position {pos + 1} of {sc.pattern.positions}, the pose asked for: hold the board on "
                        f"the dashed outline; {self._describe(T)}.")
            else:
                scripted = [T for p, T in sc.projector_poses if p == pos]
                T = scripted[pose_index] if pose_index < len(scripted) else sc.extra_projector_pose(pos, pose_index)
                text = (f"Pattern position {pos + 1} of {sc.pattern.positions}, pose {pose_index + 1}: hold the board "
                        f"so the projected pattern lands on its blank area; {self._describe(T)}.")
        elif step == STEP_VERIFICATION:
            T = sc.verification_pose_for(pose_index)
            layout = sc.layout
            text = (f"Verification: set the board on a stand, facing the projector, in the middle of its image; "
                    f"{self._describe(T)}.")
        else:
            if sc.rig.mirror is None:
                raise DeviceError(f"scenario '{sc.name}' has no mirror: there is no mirror step")
            method = MirrorMethod.REAL_VIRTUAL if step == STEP_REAL_VIRTUAL else MirrorMethod.REAL_MIRROR
            poses = sc.mirror_poses if sc.mirror_method == method else self._rig._other_mirror_poses(method)
            if pose_index < len(poses):
                T = poses[pose_index]
            else:
                T = sc.mirror_poses_for(method, 1, seed=sc.seed * 1000 + 17 + pose_index)[0]
            layout = layout_for(sc.mirror_board)
            if step == STEP_REAL_VIRTUAL:
                how = "set the small board on a stand" if on_stand else "hold the small board"
                text = (f"Mirror placement {pose_index + 1}: {how} between the camera and the mirror so "
                        f"the camera sees it both directly and in the mirror; {self._describe(T)}.")
            else:
                text = f"Mirror placement {pose_index + 1}: lay the small board flat on the mirror, printed side up."
        self._rig._place(layout, T, step, on_stand)
        self.last_request = (step, pattern_position, pose_index)
        self.last_pose = T  # where the board was put (T_cam_board)
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

    kind = RigKind.SIM  # as drivers.factory names rigs

    def __init__(self, scenario: Scenario, quality: str = RenderQuality.LIVE, expose_intrinsics: bool = False,
                 settling_frames: int = 0, motion_jitter_mm: float = 0.0, ideal: bool = False,
                 latency_ms: float | None = None, hardware: HardwareModel | None = None,
                 clock: Clock | None = None, realtime: bool = True, faults=(), fps: float | None = None,
                 hold: str | None = None, **settings):
        if quality not in QUALITIES:
            raise SpecError(f"unknown quality '{quality}' (one of {', '.join(QUALITIES)})")
        self.scenario = scenario
        self.quality = quality
        base = scenario.render
        ss = 1 if quality == RenderQuality.LIVE else 3
        unknown = set(settings) - set(RenderSettings.__dataclass_fields__)
        if unknown:
            raise SpecError(f"unknown render setting(s) {sorted(unknown)}; known: "
                            f"{', '.join(RenderSettings.__dataclass_fields__)}")
        from dataclasses import replace

        self.settings = replace(base, **{"supersample": ss, **settings})
        r = scenario.rig
        self.renderer = Renderer(r.camera, r.projector, r.T_cam_proj, r.mirror, r.mirror_rect, self.settings)
        self.motion_jitter_mm = float(motion_jitter_mm)
        from drivers.sim.hold import Hold

        try:  # None: each step's board held as drivers.sim.hold.STEP_HOLD says (still on the ideal rig)
            self.hold = None if hold is None else Hold(hold)
        except ValueError:
            raise SpecError(f"unknown hold '{hold}' (one of {', '.join(Hold)})") from None
        try:
            from drivers.sim.faults import hardware_overrides

            self.faults = frozenset(faults)  # drivers/sim/faults.py
            overrides = {} if ideal else hardware_overrides(self.faults)
            if fps is not None:  # the camera's frame rate (a RealSense mode's, sim-realsense)
                overrides["fps"] = float(fps)
            self.hardware = hardware or HardwareModel.for_seed(scenario.seed, latency_ms, ideal=ideal, **overrides)
        except ValueError as e:
            raise SpecError(str(e)) from None
        #: frame number -> ((projector ticket, fraction of the exposure it was visible), ...)
        self.frame_truth: dict[int, tuple[tuple[int, float], ...]] = {}
        self._dots = None
        self._lock = threading.RLock()
        self._board: PlacedBoard | None = None
        self._prev: PlacedBoard | None = None
        self._frames_since_move = 0
        self._move_id = 0
        self._placed_at_s = 0.0
        self._hold_model = None  # drivers.sim.hold.HoldModel of the board now placed
        self._other_mirror: dict = {}
        #: the one clock camera, projector and operator share: simulated time (drivers.clock), so a
        #: starved CPU changes nothing the simulated hardware does
        self.clock = clock if clock is not None else SimClock(realtime=realtime)
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

    def hold_for(self, step, on_stand: bool = False):
        """How the board of `step` is held (a drivers.sim.hold.HoldModel): the rig's `hold` when given,
        else as a person holds it (hold_of), and still on the ideal rig."""
        from drivers.sim.hold import HOLD_MODELS, Hold, hold_of

        if self.hold is not None:
            return HOLD_MODELS[self.hold]
        if self.hardware.ideal or step is None:
            return HOLD_MODELS[Hold.STILL]
        return HOLD_MODELS[hold_of(step, on_stand)]

    def _place(self, layout, T, step=None, on_stand: bool = False) -> None:
        with self._lock:
            self._prev = self._board
            self._board = None if layout is None else PlacedBoard(layout, np.array(T, float))
            self._frames_since_move = 0
            self._move_id += 1
            self._placed_at_s = self.clock.now()
            self._hold_model = None if layout is None else self.hold_for(step, on_stand)

    def _frame_time_s(self, frame_number: int) -> float:
        """When frame `frame_number`'s exposure started (now, on the ideal rig)."""
        if self.hardware.ideal:
            return self.clock.now()
        return self.camera.exposure_start_s(frame_number)

    def _held_pose(self, layout, T: np.ndarray, held: tuple, t_s: float) -> np.ndarray:
        """T_cam_board of a board placed at T, `held` = (HoldModel, move id, placement time), at time t_s."""
        from drivers.sim.hold import held_pose

        model, move_id, placed_at_s = held
        if model is None:
            return T
        return held_pose(model, (self.scenario.seed, 4243, move_id), T, layout.outline, t_s - placed_at_s)

    def state(self, frame_number: int | None = None) -> SceneState:
        """The scene for a frame: while settling, the board is on its way from the previous pose."""
        with self._lock:
            b, prev = self._board, self._prev
            k = self._frames_since_move
            n_settle = self.operator.settling_frames
            held = (self._hold_model, self._move_id, self._placed_at_s)
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
            if frame_number is not None:
                T = self._held_pose(b.layout, T, held, self._frame_time_s(frame_number))
            if self.motion_jitter_mm > 0 and frame_number is not None:
                rng = np.random.default_rng([self.scenario.seed, 555, frame_number])
                T = T.copy()
                T[:3, 3] += rng.normal(0, self.motion_jitter_mm, 3)
            boards = (PlacedBoard(b.layout, T),)
        return SceneState(boards, img)

    def _record_truth(self, frame_number: int, seen) -> None:
        with self._lock:
            self.frame_truth[int(frame_number)] = tuple((int(t), float(f)) for t, f in seen)
            if len(self.frame_truth) > 20000:
                for k in sorted(self.frame_truth)[:5000]:
                    del self.frame_truth[k]

    def _render_frame(self, frame_number: int, segments=None, exposure_us: float | None = None,
                      gain: float = 1.0, emitter: bool = False):
        """The camera image of frame `frame_number` and its meta. Ideal (segments None): the projector's
        current image. Hardware-like: the linear images of the projector images in `segments`
        ((ticket, image, fraction)) blended by fraction, scaled by exposure x gain, its projector light
        flickering when the exposure is not a whole number of refresh periods, with the emitter's dots when it is on."""
        with self._lock:
            moving = self._board is not None and self._frames_since_move < self.operator.settling_frames
            move_id = self._move_id
        st = self.state(frame_number)
        if self.projector.blanked:  # a blank projector lights nothing (SimProjector.blank)
            st = SceneState(st.boards, None)
            if segments is not None:
                segments = [(tk, None, frac) for tk, _, frac in segments]
        rng = np.random.default_rng([self.scenario.seed, 1, frame_number])
        meta = {"sim": True, "moving": moving, "move_id": move_id,
                "T_cam_board": None if not st.boards else st.boards[0].T_cam_board.tolist()}
        if segments is None:
            img = self.renderer.render(st, rng)
            meta["mean_level"] = float(img[:, :, 0].mean())
            return img, meta
        hw = self.hardware
        lin = None
        for _, proj_img, frac in segments:
            part = self.renderer.render_linear(SceneState(st.boards, proj_img)) * np.float32(frac)
            lin = part if lin is None else lin + part
        amp = flicker_amplitude(exposure_us, hw.refresh_hz, hw.flicker_depth)
        factor = 1.0
        if amp > 0 and any(np.any(s[1]) for s in segments):
            # the projector's share of the light (ambient is steady) in the whole frame (global shutter)
            ambient = self.renderer.render_linear(SceneState(st.boards, None))
            phase = flicker_phase(hw, self.scenario.seed, frame_number, self.camera.exposure_start_s(frame_number))
            factor = 1.0 + amp * math.sin(2 * math.pi * phase)
            lin = ambient + (lin - ambient) * np.float32(factor)
        lin = lin * np.float32(exposure_us / REFERENCE_EXPOSURE_US * gain)
        if emitter:
            if self._dots is None:
                self._dots = emitter_dots(lin.shape, self.scenario.seed)
            lin = lin + self._dots * np.float32(exposure_us / REFERENCE_EXPOSURE_US * gain)
        img = self.renderer.finish(lin, self.renderer.settings, rng)
        meta["mean_level"] = float(img[:, :, 0].mean())
        meta["flicker_amplitude"] = amp
        meta["flicker_factor"] = factor  # the projector light's share in this frame, 1 without flicker
        return img, meta

    def render_still(self, noise_key: int, T_cam_board: np.ndarray | None = None) -> np.ndarray:
        """The image of the current (settled) state, noise seeded by (seed, 2, noise_key): for writing
        sessions reproducibly whatever the order frames are rendered in. `T_cam_board`: the placed board
        at this pose instead (where a held board is at one frame)."""
        with self._lock:
            b = self._board
            img = self.projector.image
        if b is not None and T_cam_board is not None:
            b = PlacedBoard(b.layout, np.asarray(T_cam_board, float))
        st = SceneState(() if b is None else (b,), img)
        return self.renderer.render(st, np.random.default_rng([self.scenario.seed, 2, int(noise_key)]))


def _interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    import cv2

    dR = T1[:3, :3] @ T0[:3, :3].T
    rvec, _ = cv2.Rodrigues(dR)
    R = rotation_about(rvec.reshape(3), np.degrees(np.linalg.norm(rvec)) * a) @ T0[:3, :3] \
        if np.linalg.norm(rvec) > 1e-12 else T0[:3, :3]
    return make_T(R, (1 - a) * T0[:3, 3] + a * T1[:3, 3])


def open_sim_rig(scenario: str = DEFAULT_SCENARIO, seed: int = 0, quality: str = RenderQuality.LIVE, bump: str | None = None,
                 **settings) -> SimRig:
    """A simulated rig for a named scenario. Keyword settings: expose_intrinsics, settling_frames,
    motion_jitter_mm, ideal (no latency, no frame clock, no exposure model: the fast mode for unit tests),
    latency_ms (the projector's latency; default drawn in 60-120 ms from the seed), realtime (False: the
    simulated clock never waits for the wall clock; drivers.clock.SimClock), clock (another clock: the
    RealSense emulation runs the rig on drivers.clock.MONOTONIC, the clock librealsense stamps on), faults
    (names of drivers.sim.faults.FAULTS: the hardware faults to emulate), and any RenderSettings field (ambient, projector_gain, blur_sigma_px, read_noise_dn,
    electrons_per_dn, ...). bump: 'projector' | 'mirror' | 'camera' | 'none' (drivers.sim.bump): the
    rig as it is after that part was bumped on site; its ground truth is the bumped rig."""
    sc = get_scenario(scenario, seed)
    if bump is not None:
        from drivers.sim.bump import bump_scenario

        sc = bump_scenario(sc, bump)
    rig = SimRig(sc, quality, **settings)
    rig.bump = bump
    return rig
