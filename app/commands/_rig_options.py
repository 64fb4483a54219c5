"""Options shared by the commands that open a rig (`procam session`, `procam station`, `procam
recalibrate`): the rig, the simulated rig, the real rig's devices and boards, each declared once as an
argument group (evo's parent parsers; a private module: not a sub-command)."""

from app.commands import _types
from calib.models.vocab import LengthUnit, PatternKind, RenderQuality, RigKind, choices
from calib.formats.session import MAX_MIRROR_FRAMES

#: the capture plan's ranges: a plan outside them is either empty or a session that never ends
POSES_PER_POSITION = (1, 100)
MIRROR_CAPTURES = (1, 500)


#: what --projector-pattern offers: the circle grid (the scenario's own pattern on the simulated rig), or the
#: structured-light sequence (docs/STRUCTURED_LIGHT.md)
PROJECTOR_PATTERNS = (PatternKind.CIRCLES.value, PatternKind.STRUCTURED.value)
#: projector placements of a structured-light step (its maximum when it stops on confidence)
DEFAULT_PLACEMENTS = 6
PLACEMENTS = (1, 52)


def add_projector_pattern_options(p, what: str) -> None:
    """--projector-pattern and --placements (`procam session`, `procam station`, `procam simulate`)."""
    p.add_argument("--projector-pattern", choices=PROJECTOR_PATTERNS, default=None,
                   help=f"the projector step: the circle grid at every {what} (default), or structured: the "
                        "structured-light sequence at a few board placements, the board held still for each "
                        "(--placements; docs/STRUCTURED_LIGHT.md)")
    p.add_argument("--placements", type=_types.int_range(*PLACEMENTS), default=None, metavar="N",
                   help=f"projector placements with --projector-pattern structured, %d to %d (default "
                        f"{DEFAULT_PLACEMENTS}; a maximum with --stop-on-confidence)" % PLACEMENTS)


def structured_placements(args) -> int | None:
    """The structured step's placements the arguments ask for (None: the circle grid); SpecError for
    --placements without --projector-pattern structured."""
    from calib.errors import SpecError

    structured = getattr(args, "projector_pattern", None) == PatternKind.STRUCTURED.value
    if getattr(args, "placements", None) is not None and not structured:
        raise SpecError("--placements counts structured-light placements: give it with --projector-pattern structured")
    return (args.placements or DEFAULT_PLACEMENTS) if structured else None


#: --rig's choices (drivers.factory.RIG_KINDS)
RIG_CHOICES = choices(RigKind)


def add_camera_option(p) -> None:
    """--camera (the uvc rig's camera)."""
    p.add_argument("--camera", type=_types.camera_source, default=None, metavar="INDEX|URL",
                   help="--rig uvc: the camera, an index (0: /dev/video0 on Linux; `procam devices` lists them) or "
                        "a stream URL / file (default 0)")
    p.add_argument("--camera-fps", type=_types.float_range(1.0, 1000.0), default=None, metavar="FPS",
                   help="--rig uvc: the camera's frame rate, asked of it and used to time its frames (default: what "
                        "the backend reports; FFmpeg says 25 for any MJPEG stream)")


# ---- the option groups: each option declared once, for every command that opens a rig ----------------------
# `previous`: the command continues an earlier calibration (procam recalibrate), whose session supplies
# the defaults the other commands take from the scenario or the board flags.

def add_rig_choice(p, previous: bool = False) -> None:
    """--rig: which rig to open."""
    p.add_argument("--rig", choices=RIG_CHOICES, default=None,
                   help="rig to use (default: realsense when one is connected, else sim" +
                        ("; with --resume the stopped one's" if previous else "") +
                        "; sim-realsense: the simulated rig with its camera through the RealSense driver and "
                        "librealsense; uvc: any camera OpenCV opens (--camera); sim-uvc: the simulated camera as a "
                        "live MJPEG stream read through the OpenCV driver)")


def add_sim_rig_options(p, previous: bool = False) -> None:
    """The simulated rig: its scenario, seed, rendering and hardware behaviour (latency, faults, a bump)."""
    g = p.add_argument_group("simulated rig (--rig sim, sim-realsense, sim-uvc)")
    from_prev = "PREVIOUS's, else " if previous else ""
    g.add_argument("--scenario", default=None, help=f"scenario (default {from_prev}nonoverlap-136)")
    g.add_argument("--seed", type=_types.seed, default=None, help=f"seed (default {from_prev}0)")
    g.add_argument("--quality", choices=choices(RenderQuality), default=None, help="rendering quality (default live)")
    add_sim_latency_option(g)
    add_sim_faults_option(g)
    add_sim_bump_option(g)


def add_device_options(p) -> None:
    """The real rig's devices: the camera (RealSense or any OpenCV camera) and the projector's screen."""
    g = p.add_argument_group("real rig (--rig realsense, uvc)")
    g.add_argument("--serial", default=None, help="RealSense serial number (default: the first one)")
    g.add_argument("--camera-mode", type=_types.camera_mode, default=None, metavar="WxH@FPS",
                   help="RealSense rigs: the colour mode, one the camera lists (an unlisted one is refused with the "
                        "list; default 1280x800@30, or the fastest mode of that size the USB link offers)")
    add_camera_option(g)
    g.add_argument("--projector-screen", type=_types.screen, default=None,
                   help="screen the projector is connected to, from `procam devices` (default: the non-primary one "
                        "of two screens; required with more)")
    g.add_argument("--settle-s", type=_types.seconds, default=None,
                   help="projector latency to wait after each image, seconds")


def add_board_options(p, previous: bool = False) -> None:
    """The boards of a real rig (the simulated rig's are its scenario's)."""
    g = p.add_argument_group("boards")
    if previous:
        g.add_argument("--board", default=None,
                       help="projector board COLSxROWS:DICT:SQUARE[:MARKER], only when PREVIOUS is a calibration.json "
                            "without its session.json (else the boards are PREVIOUS's)")
    else:
        g.add_argument("--board", default=None, help="real rig: projector board COLSxROWS:DICT:SQUARE[:MARKER]")
        g.add_argument("--blank-area", default=None, metavar="WIDTH[:GAP]",
                       help="real rig: the projector board's blank area, WIDTH wide, GAP (default 20 mm) right of the "
                            "squares, in --units, as printed by `procam board --blank-area` (default: the blank area of "
                            "`procam board --assets`' projector board, 320:20 mm); --ask-pose draws the board with it")
    g.add_argument("--mirror-board", default=None, help="mirror board spec, as --board (default: --board)")
    g.add_argument("--units", choices=choices(LengthUnit), default=None if previous else LengthUnit.MM,
                   help="unit of the --board lengths (default " + ("PREVIOUS's)" if previous else "mm)"))


def add_workers_option(p) -> None:
    p.add_argument("--workers", type=_types.workers, default=2, help="detection threads (default 2)")


def add_rig_options(p) -> None:
    """`procam session` and `procam station`: the rig, the capture plan and the calibration's choices."""
    add_rig_choice(p)
    p.add_argument("--poses-per-position", type=_types.int_range(*POSES_PER_POSITION), default=None,
                   help="board poses per pattern position, %d to %d (default 4)" % POSES_PER_POSITION)
    p.add_argument("--mirror-captures", type=_types.int_range(*MIRROR_CAPTURES), default=None,
                   help="mirror captures to take, %d to %d (default 14, as in the published ProcamCalib "
                        "recordings)" % MIRROR_CAPTURES)
    p.add_argument("--stop-on-confidence", action="store_true", default=None,
                   help="end each capture step once its 1-sigmas meet their targets (docs/CALIBRATION.md): "
                        "5 mirror captures, the projector step, then mirror captures until the mirror normal is "
                        "confident; the plan's counts are then maximums")
    p.add_argument("--next-best", action="store_true", default=None,
                   help="with --stop-on-confidence: once the captures so far are calibrated, ask for the pattern "
                        "position where the projector's projection uncertainty is largest instead of the plan's "
                        "order (docs/CALIBRATION.md; no more accurate than the plan's order, docs/BENCHMARKS.md)")
    p.add_argument("--ask-pose", action="store_true", default=None,
                   help="with --stop-on-confidence: once the captures so far are calibrated, ask for the whole board "
                        "pose (position and tilt, its outline dashed on the camera image) predicted to leave the "
                        "projector step's worst 1-sigma least (docs/CALIBRATION.md \"Asking for the pose\")")
    p.add_argument("--mirror-frames", type=_types.int_range(1, MAX_MIRROR_FRAMES), default=None, metavar="N",
                   help="each mirror placement the mean of N frames of the board (default 1; a hand's sway up to "
                        "1.5 px is allowed, a board that moves more meanwhile is refused and its frames taken again; "
                        "docs/CALIBRATION.md \"Several frames per mirror placement\")")
    add_projector_pattern_options(p, "pose")
    p.add_argument("--camera-intrinsics", metavar="FILE", type=_types.regular_file, default=None,
                   help="pre-calibrated camera (calibration.json or OpenCV YAML): skip the camera step")
    p.add_argument("--board-thickness", type=_types.float_range(0.0, 1000.0), default=None, metavar="T",
                   help="real-mirror: height of the board's printed face above the mirror, board units "
                        "(default: the scenario's on the simulated rig, else 0)")
    p.add_argument("--direct", action="store_true", help="real rig: camera sees the board directly (no mirror)")
    add_workers_option(p)
    p.add_argument("--method", default=None,
                   help="calibration method (default: the calibration core's default; 'paper' is the method of "
                        "Vanherck et al.)")
    add_sim_rig_options(p)
    add_device_options(p)
    add_board_options(p)


def add_sim_latency_option(p) -> None:
    """--sim-latency-ms (any command that opens the simulated rig)."""
    p.add_argument("--sim-latency-ms", type=float, default=None, metavar="MS",
                   help="simulated rig: the projector's latency in ms, 0 allowed (default: 60-120 ms, drawn from "
                        "the seed, with a few ms of jitter, as real projectors)")


def add_sim_faults_option(p) -> None:
    """--sim-faults (any command that opens the simulated rig): drivers/sim/faults.py's registry."""
    from drivers.sim.faults import help_text

    p.add_argument("--sim-faults", default=None, metavar="NAME,...|all", help=help_text())


def sim_hardware_options(args) -> dict:
    """The simulated rig's hardware options from --sim-latency-ms and --sim-faults, checked."""
    from drivers.sim.faults import parse_faults

    latency = sim_latency_ms(args)
    faults = parse_faults(getattr(args, "sim_faults", None))
    return {**({} if latency is None else {"latency_ms": latency}), **({"faults": faults} if faults else {})}


def add_sim_bump_option(p) -> None:
    """--sim-bump (the simulated rig after a part was bumped on site: drivers/sim/bump.py)."""
    from drivers.sim.bump import BUMP_PARTS

    p.add_argument("--sim-bump", choices=BUMP_PARTS, default=None, metavar="PART",
                   help="simulated rig: the rig after PART (projector|mirror|camera|none) was bumped on site "
                        "(projector turned 1 deg and shifted 10-20 mm, mirror tilted 0.5 deg, camera refocused "
                        "+0.5%% focal length); ground_truth.json is the bumped rig")


def sim_latency_ms(args) -> float | None:
    """The --sim-latency-ms value, checked (a clear error for a negative or non-finite one)."""
    import math

    from calib.errors import SpecError

    v = getattr(args, "sim_latency_ms", None)
    if v is not None and not (math.isfinite(v) and 0 <= v <= 2000):
        raise SpecError(f"--sim-latency-ms must be between 0 and 2000 ms, got {v:g}")
    return v
