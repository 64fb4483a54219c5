"""`procam simulate SCENARIO --out DIR`: render a complete capture session of a simulated rig.

Writes DIR as a live capture would (session.json + images/*.png, via calib.formats.session.SessionStore), plus
DIR/ground_truth.json (the true calibration, CalibrationResult schema) and DIR/scene.json (the full
scene: devices, mirror rectangle, board poses per capture, render settings). With `--projector-pattern
structured` the projector step is a few placements (`--placements`), each the structured-light sequence
(calib.models.structured_light) rendered while the board stands still, stored as one structured capture.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.commands import _types
from app.commands._rig_options import add_projector_pattern_options, structured_placements
from calib.formats import session_files
from calib.models.structured_light import StructuredLightSpec
from calib.models.vocab import MirrorMethod, PatternKind, RenderQuality, Step, choices
from drivers.sim.hold import MirrorHold

NAME = "simulate"
HELP = "render a capture session of a simulated rig (with ground truth), or --list the scenarios"
DESCRIPTION = (
    "Renders every capture of the paper's protocol (mirror calibration, then 13 pattern positions x 4 "
    "board poses) for a named simulated rig and writes a session folder in the format live captures use, "
    "plus ground_truth.json and scene.json. With --projector-pattern structured the projector step is "
    "--placements board placements, each showing the structured-light sequence. `procam simulate --list` "
    "lists the scenarios."
)


def _scenario_default(name: str):
    """A Scenario field's default, so that the help says what the code does."""
    from drivers.sim.scenarios import Scenario

    return Scenario.__dataclass_fields__[name].default


def add_arguments(p) -> None:
    p.add_argument("scenario", nargs="?", metavar="SCENARIO", help="scenario name (see --list)")
    p.add_argument("--list", action="store_true", help="print the scenarios, one per line, and exit")
    p.add_argument("--out", metavar="DIR", help="session folder to create (new or empty, unless --force)")
    p.add_argument("--seed", type=_types.seed, default=0,
                   help="seed of the board poses and the noise (default %(default)s)")
    p.add_argument("--noise", type=_types.noise_dn, default=None, metavar="SIGMA",
                   help="read noise sigma in 8-bit levels (default: the scenario's); 0 turns all noise off "
                        "unless --shot is given")
    p.add_argument("--shot", type=_types.shot_e_per_dn, default=None, metavar="E_PER_DN",
                   help="shot noise: photo-electrons per 8-bit level (default: the scenario's; 0 = off)")
    p.add_argument("--blur", type=_types.blur_px, default=None, metavar="SIGMA", help="optical blur sigma in pixels")
    p.add_argument("--quality", choices=choices(RenderQuality), default=RenderQuality.SESSION,
                   help="anti-aliasing: session = 3x3 samples per pixel (default), live = 1")
    p.add_argument("--per-position", type=_types.int_range(1, 100), default=None, metavar="N",
                   help=f"board poses per pattern position (default: the scenario's, "
                        f"{_scenario_default('per_position')} as in the paper)")
    p.add_argument("--mirror-count", type=_types.int_range(1, 500), default=None, metavar="N",
                   help=f"mirror-calibration captures (default: the scenario's, {_scenario_default('mirror_count')})")
    add_projector_pattern_options(p, "scripted pose")
    p.add_argument("--workers", type=_types.workers, default=2, help="render processes (default %(default)s)")
    p.add_argument("--force", action="store_true", help="write into DIR even if it holds a session")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress output (default: a bar on a terminal, a line at start and end otherwise)")


def run(args) -> int:
    from calib.errors import SpecError
    from drivers.sim.scenarios import get_scenario, list_scenarios

    if args.list:
        for name, desc in list_scenarios():
            print(f"{name}  {desc}")
        return 0
    if not args.scenario:
        raise SpecError("name a scenario (procam simulate --list shows them), e.g. procam simulate nonoverlap-136 --out DIR")
    if not args.out:
        raise SpecError("give the session folder to write with --out DIR")
    scenario = get_scenario(args.scenario, args.seed)
    from app.commands._outputs import check_output_folder

    check_output_folder(args.out)
    changes = {}
    # the options' ranges are checked while parsing them (app/commands/_types.py)
    if args.per_position is not None:
        changes["per_position"] = args.per_position
    if args.mirror_count is not None:
        changes["mirror_count"] = args.mirror_count
    settings = {}
    if args.noise is not None:
        settings["read_noise_dn"] = args.noise
        if args.noise == 0 and args.shot is None:
            settings["electrons_per_dn"] = 0.0
    if args.shot is not None:
        settings["electrons_per_dn"] = args.shot
    if args.blur is not None:
        settings["blur_sigma_px"] = args.blur
    if settings:
        changes["render"] = replace(scenario.render, **settings)
    if changes:
        scenario = replace(scenario, **changes)
    placements = structured_placements(args)
    simulate_session(scenario, args.out, quality=args.quality, workers=args.workers, force=args.force,
                     progress=not args.no_progress, structured_placements=placements)
    print(f"wrote {args.out}: session.json, images/, ground_truth.json, scene.json")
    return 0


# ---- the work ------------------------------------------------------------------------------------------
def capture_plan(scenario, structured_placements: int | None = None, mirror_frames: int = 1,
                 mirror_hold: str = MirrorHold.STILL) -> list[dict]:
    """Every capture of a session, in order: mirror calibration first (each capture the mean of
    `mirror_frames` frames of the board, still or, with `mirror_hold` "person", held as the simulated
    operator holds it), then the projector step (with `structured_placements`, that many of the
    scenario's poses, each a structured-light capture). Each capture is a placement of its own (`key`)."""
    jobs = []
    if scenario.mirror_method is not None:
        step = Step.REAL_VIRTUAL if scenario.mirror_method == MirrorMethod.REAL_VIRTUAL else Step.REAL_MIRROR
        for k in range(len(scenario.mirror_poses)):
            jobs.append({"step": step, "position": None, "index": k, "frames": int(mirror_frames),
                         "hold": mirror_hold})
    if structured_placements is not None:
        from drivers.sim.structured import placement_poses

        jobs += [{"step": Step.PROJECTOR, "position": pos, "index": k, "structured": True}
                 for pos, k in placement_poses(scenario, structured_placements)]
    else:
        count: dict[int, int] = {}
        for pos, _ in scenario.projector_poses:
            k = count.get(pos, 0)
            count[pos] = k + 1
            jobs.append({"step": Step.PROJECTOR, "position": pos, "index": k})
    for i, j in enumerate(jobs):
        j["key"] = i
    return jobs


_worker_rig = None
#: the sequence a structured simulated session shows (the default: docs/STRUCTURED_LIGHT.md)
STRUCTURED_SPEC = StructuredLightSpec()
#: a structured capture's frames draw their noise from keys FRAME_KEY_BASE * (1 + capture key) + frame
FRAME_KEY_BASE = 1000


def _single_channel(image: np.ndarray) -> np.ndarray:
    """The simulator's grey camera image as one channel: a third of the bytes to send between processes
    (the session stores it so anyway)."""
    if image.ndim == 3 and np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 1], image[..., 2]):
        return np.ascontiguousarray(image[..., 0])
    return image


def _init_worker(scenario, quality):
    global _worker_rig
    from drivers.sim.rig import SimRig

    _worker_rig = SimRig(scenario, quality, ideal=True)  # each capture rendered from a settled state
    _worker_rig.renderer.warm_up()


def _render_job(job: dict):
    """Place the board, show the pattern (or black), render: (key, image, T_cam_board, points or None,
    averages refused for motion: held_frames); a structured job's image is the list of its sequence's
    frames."""
    rig = _worker_rig
    sc = rig.scenario
    W, H = sc.rig.projector.size
    rig.operator.request_pose(job["step"], job["position"], job["index"])
    if job.get("structured"):
        frames = []
        for f, img in enumerate(STRUCTURED_SPEC.images(W, H)):
            rig.projector.show(img)
            # one noise draw per frame, none shared with another capture's
            frames.append(_single_channel(rig.render_still(FRAME_KEY_BASE * (1 + job["key"]) + f)))
        return job["key"], frames, rig.board.T_cam_board.copy(), None, 0
    pts = None
    if job["step"] == Step.PROJECTOR:
        img, pts = sc.pattern.render(W, H, job["position"])
    else:
        img = np.zeros((H, W), np.uint8)
    rig.projector.show(img)
    n = int(job.get("frames", 1))
    if n <= 1:
        return job["key"], rig.render_still(job["key"]), rig.board.T_cam_board.copy(), pts, 0
    # the mean of n frames of the board, each its own noise draw (as a structured capture's)
    poses, refused = held_frames(rig, job, n)
    acc = sum(rig.render_still(FRAME_KEY_BASE * (1 + job["key"]) + f, T).astype(np.float64)
              for f, T in enumerate(poses))
    image = np.clip(np.rint(acc / n), 0, 255).astype(np.uint8)
    return job["key"], image, rig.board.T_cam_board.copy(), pts, refused


#: the camera's frame period while the station averages a placement's frames (30 fps), and the frames
#: it lets the board settle after the placement first looks still
FRAME_S = 1 / 30
SETTLE_FRAMES = 3
#: how often a held placement is taken again after the station refused its average
MAX_HOLD_ATTEMPTS = 8


def held_frames(rig, job: dict, n: int) -> tuple[list, int]:
    """The board's pose at each of a mirror placement's n frames, and how many averages the station
    would have refused first: held as the simulated operator holds the step's board (`job["hold"]`
    "person"; drivers/sim/hold.py), a placement whose board moved more than the station allows
    (app.station.mirror_frames.MAX_MEAN_MOTION_PX, here read from the true corners, which the check reads
    to within a few hundredths of a pixel) is taken again with the next n frames, as the station asks."""
    from app.station.mirror_frames import MAX_MEAN_MOTION_PX
    from calib.transforms import transform_points
    from drivers.sim.hold import HOLD_MODELS, held_pose, hold_of

    T = rig.board.T_cam_board.copy()
    if job.get("hold", MirrorHold.STILL) != MirrorHold.PERSON:
        return [T] * n, 0
    model = HOLD_MODELS[hold_of(job["step"], False)]
    if not model.moves:
        return [T] * n, 0
    sc = rig.scenario
    outline = rig.board.layout.outline
    X = sc.mirror_board.corner_points()
    key = (sc.seed, 4244, job["key"])
    best = None
    for attempt in range(MAX_HOLD_ATTEMPTS):
        t0 = (SETTLE_FRAMES + attempt * n) * FRAME_S
        poses = [held_pose(model, key, T, outline, t0 + f * FRAME_S) for f in range(n)]
        a, b = (sc.rig.camera.project(transform_points(P, X)) for P in (poses[0], poses[-1]))
        moved = float(np.hypot(*(b - a).T).max())
        if moved <= MAX_MEAN_MOTION_PX:
            return poses, attempt
        if best is None or moved < best[0]:
            best = (moved, poses)
    return best[1], MAX_HOLD_ATTEMPTS  # a person who never held it still enough: the stillest average


def simulate_session(scenario, out, quality: str = RenderQuality.SESSION, workers: int = 2, force: bool = False,
                     progress: bool = True, structured_placements: int | None = None, mirror_frames: int = 1,
                     mirror_hold: str = MirrorHold.STILL):
    """Render the scenario's session into folder `out` (its projector step `structured_placements`
    structured-light captures when given; each mirror capture the mean of `mirror_frames` frames, the
    board still or, `mirror_hold` "person", held as the simulated operator holds it: held_frames);
    returns the SessionStore."""
    from calib.formats.session import RigInfo, SessionManifest, SessionStore
    from drivers.sim.rig import SimRig

    out = Path(out)
    jobs = capture_plan(scenario, structured_placements, mirror_frames, mirror_hold)
    probe = SimRig(scenario, quality, ideal=True)
    rig = scenario.rig
    manifest = SessionManifest(
        rig=RigInfo(rig.camera.size, rig.projector.size, rig.view, probe.camera.settings(), "sim"),
        projector_board=scenario.projector_board,
        pattern=scenario.pattern if structured_placements is None else replace(scenario.pattern,
                                                                              kind=PatternKind.STRUCTURED.value),
        mirror_board=scenario.mirror_board if scenario.mirror_method else None,
        mirror_method=scenario.mirror_method,
        board_thickness=float(scenario.board_thickness_mm) if scenario.mirror_method == MirrorMethod.REAL_MIRROR else 0.0,
        state={"simulated": True, "scenario": scenario.name, "seed": scenario.seed},
        blank_area=(float(scenario.layout.blank_width), float(scenario.layout.gap)),
    )
    store = SessionStore.create(out, manifest, exist_ok=force)
    from app.commands._progress import Progress, progress_mode

    bars = Progress(progress_mode(not progress))
    tick = bars.callback(f"simulate {scenario.name}", unit="images")
    tick(0, len(jobs))
    results: dict[int, tuple] = {}
    scene_caps = []
    next_key = 0

    def flush():
        nonlocal next_key
        while next_key in results:
            key, image, T, pts, refused = results.pop(next_key)
            job = jobs[key]
            meta = {"sim_pose_index": job["index"]}
            if job.get("frames", 1) > 1:
                meta["frames_averaged"] = job["frames"]
                if job.get("hold", MirrorHold.STILL) != MirrorHold.STILL:
                    meta["sim_hold"] = job["hold"]
                    meta["sim_refused_averages"] = int(refused)
            if job.get("structured"):
                meta["sim_pattern_position"] = job["position"]
                cap = store.add_structured_capture(image, STRUCTURED_SPEC, placement=key, meta=meta)
            else:
                cap = store.add_capture(job["step"], image, job["position"], pts, meta=meta, placement=key)
            scene_caps.append({"id": cap.id, "step": job["step"], "image": cap.image,
                               "pattern_position": job["position"], "pose_index": job["index"],
                               "T_cam_board": T.tolist(), **({"frames": list(cap.frames)} if cap.frames else {})})
            next_key += 1
            tick(next_key, len(jobs))

    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # not plain fork: a process that has run OpenCV's thread pool can hang in a forked child
        ctx = mp.get_context("forkserver")
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                 initargs=(scenario, quality)) as ex:
            for res in ex.map(_render_job, jobs, chunksize=1):
                results[res[0]] = res
                flush()
    else:
        _init_worker(scenario, quality)
        for job in jobs:
            res = _render_job(job)
            results[res[0]] = res
            flush()
    bars.close()
    scenario.ground_truth().save_json(out / session_files.GROUND_TRUTH)
    scene = scenario.to_dict()
    scene.update({
        "format": "procam-sim-scene",
        "version": 1,
        "quality": quality,
        "render_used": probe.settings.to_dict(),
        "captures": scene_caps,
        "verification_T_cam_board": scenario.verification_pose.tolist(),
    })
    from calib.formats.fileio import atomic_write_text

    atomic_write_text(out / session_files.SCENE, json.dumps(scene, indent=1) + "\n")
    return store
