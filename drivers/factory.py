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

    def request_pose(self, step: str, pattern_position: int | None, pose_index: int) -> str:
        pose = int(pose_index) + 1
        if step == STEP_PROJECTOR:
            if pattern_position is None or int(pattern_position) < 0:
                raise SpecError("the projector step needs a pattern position (0-based)")
            k = int(pattern_position) + 1
            of = f" of {self.pattern_positions}" if self.pattern_positions else ""
            text = (f"Pattern position {k}{of}, pose {pose}: hold the board so the projected pattern lands "
                    "completely on its blank area, at a different angle from the previous poses, and keep it "
                    "still until the capture is taken.")
        elif step == STEP_REAL_VIRTUAL:
            text = (f"Mirror placement {pose}: hold the small board between the camera and the mirror so the "
                    "camera sees it both directly and in the mirror, and keep it still.")
        elif step == STEP_REAL_MIRROR:
            text = (f"Mirror placement {pose}: lay the small board flat on the mirror, printed side up, where "
                    "the camera sees it; use a new place on the mirror for each capture.")
        elif step == STEP_VERIFICATION:
            text = ("Verification: hold the board still, facing the projector, in the middle of its image.")
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
    kind: str = "realsense"
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
    """The rig `kind` names.

    realsense: serial, width (1280), height (800), fps (30), exact_mode (False: a mode the device does not
      list falls back to the fastest one of that size; True: refused with the list), projector_screen (None: the non-primary screen of two),
      projector_size (None: the screen's), fullscreen (True), settle_s (0.0), pattern_positions,
      context (librealsense context or a software device, for tests). The projector window is created
      here, so call open_rig on the main thread (pyglet's) and run the station's logic in a worker
      (drivers.projector_window.run_projector_loop).
    sim: scenario, seed, quality and the simulator's own options (drivers.sim.rig.open_sim_rig).
    sim-realsense: the same, plus camera_mode ((width, height, fps): the simulated camera's size, a listed
      rate); its camera is drivers.realsense.RealSenseCamera on a
      librealsense software device (drivers.sim.realsense_bridge).
    uvc: camera (an index, default 0, or a URL / file), width, height, fps (None: the camera's), intrinsics
      (a pre-calibrated CameraModel), and the projector window's options as for realsense.
    sim-uvc: the sim options, plus controls ("honour", or "ignore": a camera that ignores manual
      exposure); its camera is drivers.opencv_camera.OpenCVCamera on an MJPEG stream (drivers.sim.stream).
    """
    if kind == "sim-realsense":
        from drivers.sim.realsense_bridge import open_sim_realsense_rig

        return open_sim_realsense_rig(**options)
    if kind == "sim-uvc":
        from drivers.sim.stream import open_sim_uvc_rig

        return open_sim_uvc_rig(**options)
    if kind == "uvc":
        return _open_uvc_rig(**options)
    if kind == "sim":
        from drivers.sim.rig import open_sim_rig

        opts = dict(options)
        scenario = opts.pop("scenario", None)
        args = () if scenario is None else (scenario,)
        rig = open_sim_rig(*args, **opts)
        if not hasattr(rig, "kind"):
            try:
                rig.kind = "sim"
            except AttributeError:
                pass
        return rig
    if kind != "realsense":
        raise SpecError(f"unknown rig '{kind}' (one of {', '.join(RIG_KINDS)})")
    from drivers.projector_window import ProjectorWindow
    from drivers.realsense import RealSenseCamera

    known = {"serial", "width", "height", "fps", "exact_mode", "projector_screen", "projector_size", "fullscreen",
             "settle_s", "pattern_positions", "context"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise SpecError(f"unknown option(s) for the realsense rig: {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    camera = RealSenseCamera(options.get("serial"), options.get("width", 1280), options.get("height", 800),
                             options.get("fps", 30), context=options.get("context"),
                             exact_mode=bool(options.get("exact_mode", False)))
    projector = ProjectorWindow(options.get("projector_screen"), size=options.get("projector_size"),
                                fullscreen=options.get("fullscreen", True), settle_s=options.get("settle_s", 0.0),
                                quit_keys=())
    return HardwareRig(camera, projector, HumanOperator(options.get("pattern_positions")), "realsense",
                       {k: v for k, v in options.items() if k != "context"})


def _open_uvc_rig(**options) -> HardwareRig:
    from drivers.opencv_camera import OpenCVCamera
    from drivers.projector_window import ProjectorWindow

    known = {"camera", "width", "height", "fps", "intrinsics", "projector_screen", "projector_size", "fullscreen",
             "settle_s", "pattern_positions"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise SpecError(f"unknown option(s) for the uvc rig: {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    camera = OpenCVCamera(options.get("camera", 0), options.get("width"), options.get("height"), options.get("fps"),
                          intrinsics=options.get("intrinsics"))
    camera.start()  # its size is known once it streams; a missing camera is refused before the window opens
    try:
        projector = ProjectorWindow(options.get("projector_screen"), size=options.get("projector_size"),
                                    fullscreen=options.get("fullscreen", True), settle_s=options.get("settle_s", 0.0),
                                    quit_keys=())
    except BaseException:
        camera.stop()
        raise
    return HardwareRig(camera, projector, HumanOperator(options.get("pattern_positions")), "uvc",
                       {k: v for k, v in options.items() if k != "intrinsics"})


def default_rig_kind(context=None) -> str:
    """'realsense' when a RealSense camera is connected, else 'sim'."""
    try:
        from drivers.realsense import list_realsense_devices

        return "realsense" if list_realsense_devices(context) else "sim"
    except Exception:  # no librealsense, no USB access (DeviceError or the library's own): the simulated rig
        return "sim"
