"""Opening a rig by name, so the station swaps the simulated rig and the hardware with one flag
(`--rig sim|sim-realsense|sim-uvc|realsense|uvc`).

    rig = open_rig("realsense", serial=None, projector_screen=1, settle_s=0.1)
    rig.camera.start(); ...; rig.close()

Every rig has `.kind`, `.camera` (drivers.base.CameraDriver), `.projector` (ProjectorDriver) and
`.operator` (Operator). On the real rig the operator is a person: HumanOperator.request_pose returns
the instruction the panel shows and does nothing else. The simulated rig is the colleague's
drivers.sim.rig.open_sim_rig, imported only when asked for; `sim-realsense` is the same simulated
world with its camera delivered through drivers/realsense.py by a librealsense software device
(drivers.sim.realsense_bridge); `uvc` is any camera OpenCV opens (drivers/opencv_camera.py) with the
projector window, and `sim-uvc` the simulated world with its camera served as a live MJPEG stream and
read through that driver (drivers.sim.stream).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

from calib.errors import SpecError
from calib.models.vocab import RigKind, Step, choices

RIG_KINDS = choices(RigKind)
#: rigs whose world is simulated (a scripted operator, a ground truth), whatever the camera path
SIMULATED_KINDS = tuple(k for k in RigKind if k.is_simulated)


def is_simulated(kind: str | None) -> bool:
    """True for the rigs whose world is simulated (`sim`, `sim-realsense`, `sim-uvc`)."""
    return kind in SIMULATED_KINDS

STEP_PROJECTOR = Step.PROJECTOR
STEP_REAL_VIRTUAL = Step.REAL_VIRTUAL
STEP_REAL_MIRROR = Step.REAL_MIRROR
STEP_VERIFICATION = Step.VERIFICATION
STEPS = tuple(Step)


class HumanOperator:
    """A person moves the board; request_pose only words the request (the panel shows it)."""

    def __init__(self, pattern_positions: int | None = None):
        self.pattern_positions = pattern_positions
        self.last_request: tuple | None = None

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int, asked=None,
                     on_stand: bool = False) -> str:
        pose = int(pose_index) + 1
        hold = "set the board on a stand" if on_stand else "hold the board"
        if step == STEP_PROJECTOR:
            if pattern_position is None or int(pattern_position) < 0:
                raise SpecError("the projector step needs a pattern position (0-based)")
            k = int(pattern_position) + 1
            of = f" of {self.pattern_positions}" if self.pattern_positions else ""
            if asked is not None:
                text = (f"Pattern position {k}{of}, the pose asked for: {hold} on the dashed outline in the "
                        "camera image, the projected pattern on its blank area, and keep it still until the "
                        "capture is taken.")
            else:
                text = (f"Pattern position {k}{of}, pose {pose}: {hold} so the projected pattern lands "
                        "completely on its blank area, at a different angle from the previous poses, and keep it "
                        "still until the capture is taken.")
        elif step == STEP_REAL_VIRTUAL:
            text = (f"Mirror placement {pose}: {'set the small board on a stand' if on_stand else 'hold the small board'} "
                    "between the camera and the mirror so the camera sees it both directly and in the mirror, and "
                    + ("leave it there until the station has taken its frames." if on_stand else "keep it still."))
        elif step == STEP_REAL_MIRROR:
            text = (f"Mirror placement {pose}: lay the small board flat on the mirror, printed side up, where "
                    "the camera sees it; use a new place on the mirror for each capture.")
        elif step == STEP_VERIFICATION:
            text = ("Verification: set the board on a stand, facing the projector, in the middle of its image, "
                    "and leave it there until the check is done.")
        else:
            raise SpecError(f"unknown step '{step}' (one of {', '.join(STEPS)})")
        self.last_request = (step, pattern_position, pose_index)
        return text

    def move_out(self) -> str:
        self.last_request = None
        return "Take the board out of view."


@dataclass
class HardwareRig:
    """The real rig: a RealSense (or OpenCV) camera, a projector window and a person."""

    camera: Any
    projector: Any
    operator: HumanOperator
    kind: str = RigKind.REALSENSE
    options: dict = field(default_factory=dict)

    def close(self) -> None:
        try:
            self.camera.stop()
        finally:
            self.projector.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def open_rig(kind: str, **options):
    """The rig `kind` names, opened with its entry of `RIGS` (each entry's docstring lists its options)."""
    entry = RIGS.get(kind)
    if entry is None:
        raise SpecError(f"unknown rig '{kind}' (one of {', '.join(RIG_KINDS)})")
    if entry.known_options is not None:
        unknown = sorted(set(options) - entry.known_options)
        if unknown:
            raise SpecError(f"unknown option(s) for the {kind} rig: {', '.join(unknown)} "
                            f"(known: {', '.join(sorted(entry.known_options))})")
    return entry.open(**options)


def _open_sim(**options):
    """sim: scenario, seed, quality and the simulator's own options (drivers.sim.rig.open_sim_rig, which
    checks them)."""
    from drivers.sim.rig import open_sim_rig

    opts = dict(options)
    scenario = opts.pop("scenario", None)
    rig = open_sim_rig(*(() if scenario is None else (scenario,)), **opts)
    if not hasattr(rig, "kind"):
        try:
            rig.kind = RigKind.SIM
        except AttributeError:
            pass
    return rig


def _open_sim_realsense(**options):
    """sim-realsense: the sim options, plus camera_mode ((width, height, fps): the simulated camera's size,
    a listed rate); its camera is drivers.realsense.RealSenseCamera on a librealsense software device
    (drivers.sim.realsense_bridge)."""
    from drivers.sim.realsense_bridge import open_sim_realsense_rig

    return open_sim_realsense_rig(**options)


def _open_sim_uvc(**options):
    """sim-uvc: the sim options, plus controls ("honour", or "ignore": a camera that ignores manual
    exposure); its camera is drivers.opencv_camera.OpenCVCamera on an MJPEG stream (drivers.sim.stream)."""
    from drivers.sim.stream import open_sim_uvc_rig

    return open_sim_uvc_rig(**options)


def _projector_window(options):
    from drivers.projector_window import ProjectorWindow

    return ProjectorWindow(options.get("projector_screen"), size=options.get("projector_size"),
                           fullscreen=options.get("fullscreen", True), settle_s=options.get("settle_s", 0.0),
                           quit_keys=())


def _open_realsense(**options) -> HardwareRig:
    """realsense: serial, width (1280), height (800), fps (30), exact_mode (False: a mode the device does
    not list falls back to the fastest one of that size; True: refused with the list), projector_screen
    (None: the non-primary screen of two), projector_size (None: the screen's), fullscreen (True),
    settle_s (0.0), pattern_positions, context (librealsense context or a software device, for tests).
    The projector window is created here, so call open_rig on the main thread (pyglet's) and run the
    station's logic in a worker (drivers.projector_window.run_projector_loop)."""
    from drivers.realsense import RealSenseCamera

    camera = RealSenseCamera(options.get("serial"), options.get("width", 1280), options.get("height", 800),
                             options.get("fps", 30), context=options.get("context"),
                             exact_mode=bool(options.get("exact_mode", False)))
    projector = _projector_window(options)
    return HardwareRig(camera, projector, HumanOperator(options.get("pattern_positions")), RigKind.REALSENSE,
                       {k: v for k, v in options.items() if k != "context"})


def _open_uvc(**options) -> HardwareRig:
    """uvc: camera (an index, default 0, or a URL / file), width, height, fps (None: the camera's),
    intrinsics (a pre-calibrated CameraModel), and the projector window's options as for realsense."""
    from drivers.opencv_camera import OpenCVCamera

    camera = OpenCVCamera(options.get("camera", 0), options.get("width"), options.get("height"), options.get("fps"),
                          intrinsics=options.get("intrinsics"))
    camera.start()  # its size is known once it streams; a missing camera is refused before the window opens
    try:
        projector = _projector_window(options)
    except BaseException:
        camera.stop()
        raise
    return HardwareRig(camera, projector, HumanOperator(options.get("pattern_positions")), RigKind.UVC,
                       {k: v for k, v in options.items() if k != "intrinsics"})


def _sim_args(args) -> dict:
    """A simulated rig's options from a command line: its projector latency and faults, a bump."""
    out = dict(getattr(args, "sim_hardware", None) or {})
    if getattr(args, "sim_bump", None):
        out["bump"] = args.sim_bump
    return out


def _sim_realsense_args(args) -> dict:
    out = _sim_args(args)
    if getattr(args, "camera_mode", None):
        out["camera_mode"] = args.camera_mode
    return out


def _realsense_args(args) -> dict:
    opts = {"serial": getattr(args, "serial", None), "projector_screen": getattr(args, "projector_screen", None),
            "settle_s": getattr(args, "settle_s", None)}
    out = {k: v for k, v in opts.items() if v is not None}
    if getattr(args, "camera_mode", None):
        out.update(dict(zip(("width", "height", "fps"), args.camera_mode)), exact_mode=True)
    return out


def _uvc_args(args) -> dict:
    camera = getattr(args, "camera", None)
    opts = {"camera": 0 if camera is None else camera, "projector_screen": getattr(args, "projector_screen", None),
            "settle_s": getattr(args, "settle_s", None), "fps": getattr(args, "camera_fps", None)}
    model = getattr(args, "camera_intrinsics_model", None)
    if model is not None:
        # a pre-calibration holds for one image size: the camera is asked for it, and refused if it
        # delivers another; its model is the camera's own for live detection
        opts.update(intrinsics=model, width=model.width, height=model.height)
    return {k: v for k, v in opts.items() if v is not None}


_WINDOW_OPTIONS = frozenset({"projector_screen", "projector_size", "fullscreen", "settle_s", "pattern_positions"})


@dataclass(frozen=True)
class RigEntry:
    """One kind of rig: how it opens, which options it takes, and how a command line's options become
    them (`from_args` reads an argparse namespace's attributes; app.commands.session.rig_options)."""

    kind: RigKind
    summary: str
    open: Callable[..., Any]
    known_options: frozenset | None  # None: the opener checks its own
    from_args: Callable[[Any], dict]


#: every rig the station drives, by kind: `--rig`'s choices, `open_rig` and the command-line options read it
RIGS: dict[str, RigEntry] = {e.kind: e for e in (
    RigEntry(RigKind.SIM, "the simulated rig: a rendered world, a scripted operator, ground truth",
             _open_sim, None, _sim_args),
    RigEntry(RigKind.SIM_REALSENSE, "the simulated world, its camera through librealsense's software device",
             _open_sim_realsense, None, _sim_realsense_args),
    RigEntry(RigKind.SIM_UVC, "the simulated world, its camera an MJPEG stream read by the OpenCV driver",
             _open_sim_uvc, None, _sim_args),
    RigEntry(RigKind.REALSENSE, "a RealSense D455 and the projector window, a person moving the board",
             _open_realsense, _WINDOW_OPTIONS | {"serial", "width", "height", "fps", "exact_mode", "context"},
             _realsense_args),
    RigEntry(RigKind.UVC, "any camera OpenCV opens and the projector window, a person moving the board",
             _open_uvc, _WINDOW_OPTIONS | {"camera", "width", "height", "fps", "intrinsics"}, _uvc_args),
)}
assert set(RIGS) == set(RigKind), "every RigKind needs an entry of RIGS"


def default_rig_kind(context=None) -> str:
    """'realsense' when a RealSense camera is connected, else 'sim'."""
    try:
        from drivers.realsense import list_realsense_devices

        return RigKind.REALSENSE if list_realsense_devices(context) else RigKind.SIM
    except Exception:  # no librealsense, no USB access (DeviceError or the library's own): the simulated rig
        return RigKind.SIM
