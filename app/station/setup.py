"""Opening a rig and a session for the station: new session folders, resuming, ground truth, and the
calibration / verification callables the state machine runs."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from app.station.machine import Plan, SessionMachine
from calib.errors import SessionError
from calib.formats import session_files
from calib.formats.session import MANIFEST, RigInfo, SessionManifest, SessionStore, read_manifest_json
from calib.models.boards import CharucoSpec
from calib.models.observations import VIEW_DIRECT, VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.models.vocab import MirrorMethod, PatternKind, RenderQuality, RigKind

GROUND_TRUTH_FILE = session_files.GROUND_TRUTH
VERIFICATION_FILE = session_files.VERIFICATION
DEFAULT_SCENARIO = "nonoverlap-136"


@dataclass(frozen=True)
class RigRequest:
    """What the user asked for on the command line; recorded in the session state for --resume."""

    kind: str = RigKind.SIM
    scenario: str = DEFAULT_SCENARIO
    seed: int = 0
    quality: str = RenderQuality.LIVE

    def to_dict(self) -> dict:
        return {"kind": self.kind, "scenario": self.scenario, "seed": self.seed, "quality": self.quality}

    @classmethod
    def from_dict(cls, d: dict | None, **defaults) -> "RigRequest":
        d = dict(d or {})
        kw = {k: d[k] for k in ("kind", "scenario", "seed", "quality") if k in d}
        kw.update({k: v for k, v in defaults.items() if v is not None})
        return cls(**kw)


def open_requested_rig(req: RigRequest, **options):
    """The rig the request names: the simulated rig (scenario, seed) or the real devices. On a real rig
    call this on the main thread (the projector window's) and run the station with `run_on_rig`."""
    from drivers.factory import open_rig as factory_open

    from drivers.factory import is_simulated

    if is_simulated(req.kind):
        rig = factory_open(req.kind, scenario=req.scenario, seed=req.seed, quality=req.quality, **options)
    else:
        rig = factory_open(req.kind, **options)
    start = getattr(rig.camera, "start", None)
    if callable(start) and not getattr(rig.camera, "running", False):
        start()
    return rig


def run_on_rig(rig, work):
    """Run `work()`: directly on the simulated rig; on the hardware in a worker thread while the main
    thread runs the projector window's event loop (pyglet wants the main thread)."""
    from drivers.factory import is_simulated

    if is_simulated(getattr(rig, "kind", RigKind.SIM)):
        return work()
    from drivers.projector_window import run_projector_loop

    return run_projector_loop(rig.projector, work)


def _attr(obj, *names, default=None):
    for n in names:
        if obj is not None and hasattr(obj, n):
            return getattr(obj, n)
    return default


def sim_specs(rig) -> dict:
    """Board, pattern and mirror specs of a simulated rig's scenario."""
    sc = rig.scenario
    layout = _attr(sc, "layout")
    board = _attr(layout, "charuco") or _attr(sc, "board", "projector_board")
    mirror_board = _attr(sc, "mirror_board")
    pattern = _attr(sc, "pattern")
    method = _attr(sc, "mirror_method")
    thickness = _attr(sc, "board_thickness_mm", "board_thickness", "thickness_mm", "thickness", default=0.0) or 0.0
    view = _attr(sc, "view")
    if view is None:
        srig = _attr(sc, "rig")
        view = _attr(srig, "view") or (VIEW_MIRROR if mirror_board is not None else VIEW_DIRECT)
    blank = None if layout is None else (float(layout.blank_width), float(layout.gap))
    return {"board": board, "mirror_board": mirror_board if view == VIEW_MIRROR else None, "pattern": pattern,
            "mirror_method": method if view == VIEW_MIRROR else None, "thickness": float(thickness), "view": view,
            "blank_area": blank}


def new_manifest(rig, kind: str, *, board: CharucoSpec | None = None, mirror_board: CharucoSpec | None = None,
                 pattern: PatternSpec | None = None, view: str | None = None, thickness: float = 0.0,
                 projector_pattern: str | None = None,
                 blank_area: tuple[float, float] | None = None) -> SessionManifest:
    """The manifest of a new session on `rig`: specs from the simulated scenario, or as given;
    `projector_pattern` "structured": the projector step shows the structured-light sequence
    (app.station.structured_step), the pattern's positions only naming where the board goes;
    `blank_area` (width, gap) of the projector board's blank area, board units (None: not given)."""
    cam_size = tuple(rig.camera.size)
    proj_size = tuple(rig.projector.size)
    from drivers.factory import is_simulated

    if is_simulated(kind):
        s = sim_specs(rig)
        board, mirror_board, pattern, view = s["board"], s["mirror_board"], s["pattern"], s["view"]
        thickness = s["thickness"] if s["mirror_method"] == MirrorMethod.REAL_MIRROR else 0.0
        blank_area = s["blank_area"]
    if board is None:
        raise SessionError("give the projector board spec (--board COLSxROWS:DICT:SQUARE[:MARKER])")
    view = view or VIEW_MIRROR
    if view == VIEW_MIRROR and mirror_board is None:
        mirror_board = board
    pattern = pattern or PatternSpec.default_for(*proj_size)
    if projector_pattern == PatternKind.STRUCTURED.value:
        pattern = replace(pattern, kind=PatternKind.STRUCTURED.value)
    try:
        settings = dict(rig.camera.settings())
    except Exception:  # settings are informative; a driver without them still records a session
        settings = {}
    info = RigInfo(cam_size, proj_size, view, settings, kind)
    return SessionManifest(info, board, pattern, mirror_board if view == VIEW_MIRROR else None, None,
                           float(thickness), blank_area=blank_area)


def create_session(folder, rig, req: RigRequest, plan: Plan | None = None, **manifest_kw) -> SessionStore:
    folder = Path(folder)
    if (folder / MANIFEST).exists():
        raise SessionError(f"{folder} already holds a session; continue it with --resume {folder}")
    man = new_manifest(rig, req.kind, **manifest_kw)
    store = SessionStore.create(folder, man)
    store.update(state={"step": "check_rig", "rig_request": req.to_dict(),
                        "plan": (plan or Plan()).to_dict()})
    from drivers.factory import is_simulated

    if is_simulated(req.kind) and hasattr(rig, "ground_truth"):
        rig.ground_truth().save_json(folder / GROUND_TRUTH_FILE)
    return store


def resume_request(folder, **overrides) -> RigRequest:
    """The rig a session was captured with (recorded in its state), overridden by explicit options."""
    store = SessionStore.open(folder)
    st = store.manifest.state or {}
    req = RigRequest.from_dict(st.get("rig_request") or {"kind": store.manifest.rig.driver}, **overrides)
    return req


def check_same_rig(store: SessionStore, rig) -> None:
    man = store.manifest
    if tuple(rig.camera.size) != tuple(man.rig.camera_size) or tuple(rig.projector.size) != tuple(man.rig.projector_size):
        raise SessionError(
            f"the rig ({rig.camera.size[0]}x{rig.camera.size[1]} camera, {rig.projector.size[0]}x"
            f"{rig.projector.size[1]} projector) is not the one this session was captured with "
            f"({man.rig.camera_size[0]}x{man.rig.camera_size[1]}, {man.rig.projector_size[0]}x"
            f"{man.rig.projector_size[1]})")


def make_verify_fn(rig, folder):
    """The verification callable for the state machine, or None when the verification module is absent."""
    try:
        from app import verification as V
    except ImportError:
        return None
    verify = getattr(V, "verify", None)
    if verify is None:
        return None

    def run(result, **kw):
        # the machine saved `result` as calibration.json before verifying: the report records its hash
        kw.setdefault("calibration_info", {"path": str(Path(folder) / session_files.CALIBRATION)})
        # the camera's tone curve the rig check recorded (read now: it is recorded after this is made)
        kw.setdefault("response", V.session_response(folder))
        report = verify(rig.camera, rig.projector, rig.operator, result, **kw)
        report.save_json(Path(folder) / VERIFICATION_FILE)
        return report

    return run


def make_machine(store: SessionStore, rig, plan: Plan | None = None, resume: bool = False,
                 workers: int = 2, method: str | None = None) -> SessionMachine:
    from app.station.asked import board_layout
    from app.station.machine import default_calibrate

    if method is not None:
        from calib.pipeline import METHODS

        if method not in METHODS:
            raise SessionError(f"unknown calibration method '{method}' (one of {', '.join(sorted(METHODS))})")

    def calibrate(folder, intrinsics, progress):
        return default_calibrate(folder, intrinsics, progress, workers=workers, method=method)

    verify_fn = make_verify_fn(rig, store.folder)
    if resume:
        saved = dict(store.manifest.state or {})  # before the machine rewrites it
        m = SessionMachine.from_store(store, plan, calibrate_fn=calibrate, verify_fn=verify_fn)
        m.board_layout = board_layout(rig, store.manifest)
        vfile = Path(store.folder) / VERIFICATION_FILE
        if m.result is not None and not m.result_stale and saved.get("verified") is not None and vfile.exists():
            try:
                from app.verification import VerificationReport, verification_is_stale

                if verification_is_stale(vfile, Path(store.folder) / session_files.CALIBRATION):
                    raise ValueError("it verified another calibration.json (replaced since)")

                m.report = VerificationReport.from_json(vfile)
                m.persist()
            except Exception as e:  # a report that does not load is simply re-measured
                m.log(f"the saved verification does not load ({e}); verify again")
        from app.station.confidence_watch import judge_resumed

        judge_resumed(m, m.log)
    else:
        m = SessionMachine(store, plan or Plan.from_dict((store.manifest.state or {}).get("plan")),
                           calibrate_fn=calibrate, verify_fn=verify_fn)
        m.board_layout = board_layout(rig, store.manifest)
    m.persist()
    return m


def load_ground_truth(folder):
    from calib.models.result import CalibrationResult

    p = Path(folder) / GROUND_TRUTH_FILE
    return CalibrationResult.load_json(p) if p.exists() else None


def read_state(folder) -> dict:
    return read_manifest_json(folder).get("state", {})
