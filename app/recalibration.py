"""The headless recalibration flow: a session folder whose captures are asked for by the recalibration
(a few to check, then only what the moved parts need), driven by the station as any session is
(Station + SessionMachine), and the calibration math of calib/recalib/. docs/RECALIBRATION.md.

    previous/calibration.json   the calibration recalibrated, archived (never overwritten)
    calibration.json            the recalibrated result (the previous one when nothing moved)
    recalibration.json          verdicts, numbers, where the previous calibration came from
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path

from app.station.machine import (
    CAPTURE_STATES, MIRROR_CAPTURE, PROJECTOR_CAPTURE, Plan, SessionMachine, Target, write_calibration,
)
from app.station.station import Station
from app.station.structured_step import slot_of
from app.words import signed
from calib.errors import CalibrationError, SessionError
from calib.formats import session_files
from calib.formats.fileio import atomic_write_text
from calib.formats.session import MANIFEST, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.observations import STEP_PROJECTOR, VIEW_DIRECT, VIEW_MIRROR
from calib.models.pattern import PatternSpec
from calib.models.result import CalibrationResult
from calib.models.vocab import MirrorMethod, PatternKind, RigKind
from drivers.clock import clock_of

PREVIOUS_DIR = session_files.PREVIOUS_DIR
RECALIBRATION_FILE = session_files.RECALIBRATION
CHECK_MIRROR_CAPTURES = 2
CHECK_PROJECTOR_CAPTURES = 2
ROUND_CAPTURES = 2  # captures added per round of the re-estimate before its 1-sigma is looked at again
DEFAULT_MAX_CAPTURES = 24
#: the session plan of a recalibration (its capture plan is set by the flow): one pose per pattern position
RECALIBRATION_PLAN = Plan(poses_per_position=1, min_real_virtual=1, min_projector_captures=1)
CAPTURE_TIMEOUT_S = 120.0  # the simulated operator: no capture in this long is an error
PROMPTED_CAPTURE_TIMEOUT_S = 600.0  # a person: a board never still and detected in 10 minutes stops the flow


#: the prompt before an epipolar verification (the projector draws curves on the board; the camera measures them)
VERIFY_PROMPT = ("Verification: set the projector board on a stand, facing the projector, in the middle of its image, "
                 "where the camera sees it in the mirror, and leave it there until the verification is done.")


class RecalibrationStopped(SessionError):
    """The recalibration stopped part-way (the technician's input closed, or no capture came): every capture
    taken is on disk and the folder continues with `procam recalibrate PREVIOUS --out DIR --resume`."""


def find_previous(path) -> Path:
    """The previous calibration.json: PATH itself, or PATH/calibration.json for a session folder."""
    p = Path(path)
    if p.is_dir():
        p = p / session_files.CALIBRATION
    if not p.is_file():
        raise SessionError(f"no previous calibration at {path}: give a session folder holding calibration.json, "
                           "or a calibration.json")
    return p


def load_previous(path) -> tuple[Path, CalibrationResult]:
    """(the file, the calibration) of PREVIOUS (find_previous), read by the one calibration reader and
    trust-checked: a calibration no calibration would be allowed to give (a negative focal length, an
    absurd distortion) is refused with the check's reasons before any capture, and so is never written
    back as the recalibrated result. A low-quality one is accepted (the recalibration may improve it)."""
    from calib.quality.trust import check_calibration

    src = find_previous(path)
    previous = CalibrationResult.load_json(src)
    report = check_calibration(previous)
    if not report.passed:
        raise CalibrationError(f"PREVIOUS {src} is not a trustworthy calibration ({report.reasons_text()}): give the calibration "
                               "the rig was installed with, or calibrate the rig anew (procam session)",
                               code="untrusted_previous")
    return src, previous


def archive_previous(previous: Path, folder: Path) -> tuple[Path, str]:
    """Copy the previous calibration into folder/previous/calibration.json; (path, sha256 of the
    original). Never overwrites: an existing archive is an error."""
    from calib.recalib import sha256_file

    dest = Path(folder) / PREVIOUS_DIR / session_files.CALIBRATION
    if dest.exists():
        raise SessionError(f"{dest} already exists: a recalibration never overwrites an archived calibration")
    dest.parent.mkdir(parents=True, exist_ok=True)
    digest = sha256_file(previous)
    tmp = dest.with_name(".calibration.json.tmp")
    shutil.copyfile(previous, tmp)
    tmp.rename(dest)
    if sha256_file(dest) != digest:
        raise SessionError(f"the archived copy {dest} differs from {previous} (changed while copying?)")
    return dest, digest


def check_resumed_previous(previous: Path, folder: Path) -> str:
    """Resuming: PREVIOUS must be the calibration the recalibration in `folder` started from (sha256 of
    the archive, or of the state's record when the archive was never written). Its sha256, else SessionError."""
    from calib.recalib import sha256_file

    folder = Path(folder)
    dest = folder / PREVIOUS_DIR / session_files.CALIBRATION
    try:
        rec = (SessionStore.open(folder).manifest.state or {}).get("recalibration") or {}
    except SessionError:
        rec = {}
    want = rec.get("previous_sha256") if isinstance(rec.get("previous_sha256"), str) else None
    if want is None and dest.is_file():
        want = sha256_file(dest)
    if want is None:
        raise SessionError(f"{folder} is not a recalibration (no {PREVIOUS_DIR}/calibration.json): continue a session "
                           f"with `procam session --resume {folder}`")
    got = sha256_file(previous)
    if got != want:
        was = f" ({rec['previous']})" if isinstance(rec.get("previous"), str) else ""
        raise SessionError(f"{previous} (sha256 {got[:12]}...) is not the calibration the recalibration in {folder} "
                           f"started from{was} (sha256 {want[:12]}..., archived as {PREVIOUS_DIR}/calibration.json): "
                           "resume with that PREVIOUS")
    if dest.is_file() and sha256_file(dest) != want:
        raise SessionError(f"{dest} changed since it was archived (sha256 differs): this recalibration cannot be "
                           "trusted any more; start a new one")
    return want


# ---- the boards of the previous calibration -----------------------------------------------------------
@dataclass(frozen=True)
class BoardSpecs:
    """The physical boards, projected pattern and view a recalibration must use: those of the calibration
    it checks. `rig_request` is the previous session's (the simulated rig's scenario and seed)."""

    board: CharucoSpec
    mirror_board: CharucoSpec | None
    pattern: PatternSpec
    view: str
    source: str  # where they were read from, for the log
    rig_request: dict | None = None

    def manifest_kw(self) -> dict:
        """The keyword arguments of app.station.setup.new_manifest / create_session."""
        return {"board": self.board, "mirror_board": self.mirror_board, "pattern": self.pattern, "view": self.view}

    def describe(self) -> str:
        p = self.pattern
        mb = f", mirror board {self.mirror_board}" if self.mirror_board is not None else ", no mirror"
        return f"board {self.board}{mb}, pattern {p.cols}x{p.rows} {p.kind} ({self.source})"


def previous_session_folder(previous_path) -> Path | None:
    """The session folder PREVIOUS belongs to (PREVIOUS itself, or the folder of its calibration.json),
    when it holds a session.json; None for a calibration.json on its own."""
    p = Path(previous_path)
    folder = p if p.is_dir() else p.parent
    return folder if (folder / MANIFEST).is_file() else None


def previous_board_specs(previous_path, previous: CalibrationResult, board: str | None = None,
                         mirror_board: str | None = None, units: str | None = None,
                         simulated: bool = False) -> BoardSpecs | None:
    """The boards of PREVIOUS: from its session.json; for a calibration.json on its own (which records the
    devices' image sizes and units, not the boards) from `board` / `mirror_board` (COLSxROWS:DICT:SQUARE
    [:MARKER], in `units`, default the calibration's) with the default pattern of its projector. None on a
    simulated rig when nothing names them (the scenario's boards are the rig's); SessionError on a real
    rig, naming what to add. Given specs that contradict the session's are refused."""
    units = units or previous.units
    given = CharucoSpec.parse(board, units) if board else None
    given_mirror = CharucoSpec.parse(mirror_board, units) if mirror_board else None
    for spec, opt in ((given, "--board"), (given_mirror, "--mirror-board")):
        if spec is not None and spec.units != previous.units:
            raise SessionError(f"{opt} is in {spec.units} but PREVIOUS is calibrated in {previous.units}: give the "
                               f"board lengths in {previous.units} (--units {previous.units})")
    view = VIEW_MIRROR if previous.mirror is not None else VIEW_DIRECT
    folder = previous_session_folder(previous_path)
    if folder is not None:
        man = SessionStore.open(folder).manifest  # read only; a session.json that does not load is an error
        where = folder / MANIFEST
        for what, a, b in (("camera", man.rig.camera_size, previous.camera.size),
                           ("projector", man.rig.projector_size, previous.projector.size)):
            if tuple(a) != tuple(b):
                raise SessionError(f"{where} records a {a[0]}x{a[1]} {what} but its calibration is for "
                                   f"{b[0]}x{b[1]}: PREVIOUS mixes two sessions; give the calibration.json alone "
                                   "with --board")
        if man.units != previous.units:
            raise SessionError(f"{where} has boards in {man.units} but the calibration is in {previous.units}")
        if man.rig.view != view:
            raise SessionError(f"{where} is a {man.rig.view} session but its calibration "
                               + ("has no mirror" if previous.mirror is None else "has a mirror"))
        specs = BoardSpecs(man.projector_board, man.mirror_board, man.pattern, view, str(where),
                           (man.state or {}).get("rig_request"))
        for spec, opt, have in ((given, "--board", specs.board), (given_mirror, "--mirror-board", specs.mirror_board)):
            if spec is not None and spec != have:
                raise SessionError(f"{opt} {spec} is not the board PREVIOUS was captured with ({have}, {where}): "
                                   f"a recalibration measures with the same boards; leave {opt} out")
        return specs
    if given is not None:
        mb = (given_mirror or given) if view == VIEW_MIRROR else None
        return BoardSpecs(given, mb, PatternSpec.default_for(*previous.projector.size), view, "--board")
    if simulated:
        return None
    rec = previous.diagnostics.get("session") if isinstance(previous.diagnostics, dict) else None
    hint = f" (it was calibrated from {rec}: give that session folder as PREVIOUS, or)" if isinstance(rec, str) else ""
    raise SessionError(f"{previous_path} does not record the boards it was calibrated with (no session.json beside "
                       f"it){hint}: add --board COLSxROWS:DICT:SQUARE[:MARKER] (and --mirror-board if the mirror "
                       "board differs), the boards given to `procam session` for that calibration")


def check_rig_matches(previous: CalibrationResult, specs: BoardSpecs | None, rig, scenario: str | None = None) -> None:
    """The connected rig is the one PREVIOUS calibrated: camera resolution as its camera model's, projector
    screen as its projector's; on a simulated rig the scenario's boards are PREVIOUS's. SessionError."""
    cw, ch = (int(v) for v in rig.camera.size)
    pw, ph = (int(v) for v in rig.projector.size)
    if (cw, ch) != tuple(previous.camera.size):
        raise SessionError(f"the camera streams {cw}x{ch} but PREVIOUS's camera model is for {previous.camera.size[0]}x"
                           f"{previous.camera.size[1]}: connect the same camera at that resolution")
    if (pw, ph) != tuple(previous.projector.size):
        raise SessionError(f"the projector screen is {pw}x{ph} but PREVIOUS calibrated a {previous.projector.size[0]}x"
                           f"{previous.projector.size[1]} projector: connect that projector (or choose its screen with "
                           "--projector-screen) at its resolution")
    from drivers.factory import is_simulated

    if specs is not None and is_simulated(getattr(rig, "kind", RigKind.SIM)):
        from app.station.setup import sim_specs

        s = sim_specs(rig)
        # a structured step's pattern is the circle grid's geometry naming its slots: compare that
        want_pattern = replace(specs.pattern, kind=s["pattern"].kind) if is_structured_pattern(specs.pattern) \
            else specs.pattern
        for what, have, want in (("board", s["board"], specs.board), ("mirror board", s["mirror_board"], specs.mirror_board),
                                 ("pattern", s["pattern"], want_pattern)):
            if have != want:
                raise SessionError(f"the simulated scenario '{scenario}' has the {what} {have}, PREVIOUS was captured "
                                   f"with {want}: choose the scenario PREVIOUS was captured on (--scenario)")


def is_structured_pattern(pattern) -> bool:
    """PREVIOUS's projector step showed the structured-light sequence (its recalibration does too)."""
    return getattr(pattern, "kind", None) == PatternKind.STRUCTURED.value


class RecalibrationMachine(SessionMachine):
    """A session machine whose capture plan is set by the recalibration: `mirror_quota` real-virtual
    captures and one projector capture per entry of `projector_queue` (pattern positions; with the
    structured-light step, the slot each placement's board pose is asked for)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.mirror_quota = 0
        self.projector_queue: list[int] = []

    @property
    def mirror_total(self) -> int:
        return 0 if self.mirror_method is None else self.mirror_quota

    @property
    def projector_total(self) -> int:
        return len(self.projector_queue)

    @property
    def target(self) -> Target | None:
        if self.state == PROJECTOR_CAPTURE:
            caps = self.captures_of(STEP_PROJECTOR)
            if self.structured:  # one placement per queue entry, each the whole coded sequence
                if len(caps) >= len(self.projector_queue):
                    return None
                pos = self.projector_queue[len(caps)]
                taken = [k for p, k in map(slot_of, caps) if p == pos]
                return Target(STEP_PROJECTOR, pos, next(k for k in range(len(taken) + 1) if k not in taken))
            seen: dict[int, int] = {}
            for pos in self.projector_queue:
                seen[pos] = seen.get(pos, 0) + 1
                at = [c for c in caps if c.pattern_position == pos]
                if len(at) < seen[pos]:
                    return Target(STEP_PROJECTOR, pos, self._free_pose(at, len(at) + 1))
            return None
        return super().target


class RecalibrationStation(Station):
    """The station's auto mode up to the captures: it never starts a full calibration by itself."""

    def _drive(self) -> None:
        m = self.machine
        if m.state in CAPTURE_STATES and m.target is None:
            return
        if m.state not in CAPTURE_STATES and m.state != "check_rig":
            return
        super()._drive()


def spread_positions(pattern, w: int, h: int, n: int, start: int = 0) -> list[int]:
    """n pattern positions spread over the projector image (the centre first, then the farthest from
    those taken), continuing from the `start`-th of that order."""
    import numpy as np

    centres = np.array([pattern.points_px(w, h, p).mean(axis=0) for p in range(pattern.positions)])
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    order = [int(np.argmin(np.linalg.norm(centres - c, axis=1)))]
    while len(order) < pattern.positions:
        d = np.min(np.linalg.norm(centres[:, None] - centres[order][None], axis=2), axis=1)
        d[order] = -1
        order.append(int(np.argmax(d)))
    return [order[(start + i) % len(order)] for i in range(n)]


@dataclass
class Outcome:
    record: dict
    result: CalibrationResult
    ok: bool
    message: str


def _verification_summary(report) -> dict:
    return {"passed": bool(report.passed), "mean_proj_px": report.mean_proj_px, "mean_px": report.mean_px,
            "threshold_px": report.threshold_px, "measured": report.n_measured,
            "response": getattr(report, "response", None)}  # the camera's tone curve the frames were read with


def run_recalibration(previous_path, station: Station, machine: RecalibrationMachine, log=print,
                      max_captures: int = DEFAULT_MAX_CAPTURES, workers: int = 2, verify=None,
                      on_stage=None, prompt=None, resume: bool = False) -> Outcome:
    """Check, re-measure what moved, compare. The station and machine are those of a new session, or of
    the stopped recalibration being resumed (`resume`: its captures are kept, PREVIOUS must be the archived
    calibration, the check already done is not re-taken).
    `verify(result, final)` (optional): the epipolar verification of a calibration on the rig; the
    previous calibration is verified during the check (evidence recorded; a failure with an
    "unchanged" verdict is an inconsistency, not a sign-off), the recalibrated one at the end
    (final=True: its report is the session's verification.json; a failure fails the recalibration).
    `on_stage(stage, value)` (optional; the station's panel): "verdict" with the check's report (may block
    until the operator accepts it; a dict it returns is recorded as recalibration.json's sign_off),
    "reestimate" with each round's re-estimate (progress towards the 1-sigma targets), "done" with the
    Outcome.
    `prompt(text)` (optional; a person moves the board): called before each capture with what to do (the
    station's own guidance: which board, where, which tilt); it returns when the person is ready (Enter)
    or raises RecalibrationStopped to stop (the folder stays resumable). Auto-capture then takes the frame
    when the board is still and detected, exposed after the projector's image became visible."""
    def stage(name, value):
        if on_stage is not None:
            return on_stage(name, value)

    from calib.detection.detect import detect_session
    from calib.recalib import (
        RecalibrationRecord, check_rig, compare_calibrations, reestimate, with_own_residuals,
    )

    folder = Path(machine.store.folder)
    src, previous = load_previous(previous_path)
    archived = folder / PREVIOUS_DIR / session_files.CALIBRATION
    if resume:
        digest = check_resumed_previous(src, folder)
        if not archived.exists():
            archive_previous(src, folder)
        log(f"previous calibration {src} (sha256 {digest[:12]}...) is the one archived in {PREVIOUS_DIR}/")
    else:
        archived, digest = archive_previous(src, folder)
        log(f"previous calibration {src} (sha256 {digest[:12]}...) archived as {archived.relative_to(folder)}")
    state = dict(machine.extra_state.get("recalibration") or {})
    state.update(previous=str(src.resolve()), previous_sha256=digest)
    machine.extra_state["recalibration"] = state
    machine.persist()
    man = machine.manifest
    w, h = man.rig.projector_size
    mirrored = man.mirror_board is not None and previous.mirror is not None
    t0 = time.monotonic()
    timeout_s = CAPTURE_TIMEOUT_S if prompt is None else PROMPTED_CAPTURE_TIMEOUT_S

    def capture(n_mirror: int, n_projector: int, label, more: bool = True):
        """Take n_mirror real-virtual and n_projector projector captures through the station: that many
        more (`more`), or until there are that many (the check's, so a resumed check takes only the rest).
        Captures on disk (a resumed recalibration) count."""
        if mirrored and n_mirror:
            on_disk = machine.counts()["mirror"]
            machine.mirror_quota = (max(machine.mirror_quota, on_disk) + n_mirror) if more else max(
                machine.mirror_quota, n_mirror)
            if machine.target is None and machine.state == PROJECTOR_CAPTURE and on_disk < machine.mirror_quota:
                machine.go_back()
            _take(station, machine, MIRROR_CAPTURE, prompt, label, log, timeout_s)
        if n_projector:
            if machine.state == MIRROR_CAPTURE:
                machine.proceed()
            on_disk = len(machine.captures_of(STEP_PROJECTOR))
            k = (max(len(machine.projector_queue), on_disk) + n_projector) if more else max(
                len(machine.projector_queue), n_projector)
            machine.projector_queue = spread_positions(man.pattern, w, h, k)
            _take(station, machine, PROJECTOR_CAPTURE, prompt, label, log, timeout_s)
        station.wait_for_detections()
        return detect_session(machine.store, workers)

    # start: rig check (again, on a resumed recalibration: exposure and latency re-applied), then the
    # mirror step (the station chooses real-virtual)
    if machine.state != "check_rig":
        bad = [c for c in station.check_rig() if not c.ok]
        if bad:
            raise SessionError("the rig check failed: " + "; ".join(f"{c.name}: {c.detail}" for c in bad))
    while machine.state == "check_rig":
        station.tick()
    if mirrored and machine.mirror_method is None:
        machine.choose_mirror_method(MirrorMethod.REAL_VIRTUAL)  # the check's mirror test needs real-virtual captures
    n_m, n_p = (CHECK_MIRROR_CAPTURES if mirrored else 0), CHECK_PROJECTOR_CAPTURES
    n_check = n_m + n_p
    check_ids = state.get("check_captures")
    if isinstance(check_ids, list):
        log(f"check: done before the stop ({len(check_ids)} captures)")
    else:
        log(f"check: {n_check} captures")
    obs = capture(n_m, n_p, lambda: f"Check, capture {len(machine.manifest.captures) + 1} of {n_check}", more=False)
    if not isinstance(check_ids, list):
        check_ids = [c.id for c in machine.manifest.captures]
        state["check_captures"] = check_ids
        machine.persist()
    report = check_rig(previous, only_captures(obs, set(check_ids)))
    for p, c in report.parts.items():
        log(f"  {p}: {c.status} ({part_line(c, previous.units)})")
    log(f"check verdict: {report.verdict} after {time.monotonic() - t0:.1f} s")
    re = None
    comparison = None
    ok, message = True, report.verdict
    result = previous
    verification = {}
    if verify is not None:
        if prompt is not None:
            prompt(f"Epipolar verification of the previous calibration: {VERIFY_PROMPT}")
        v = verify(previous, False)
        verification["previous"] = _verification_summary(v)
        log(f"epipolar verification of the previous calibration: {'passed' if v.passed else 'FAILED'} "
            f"(mean {v.mean_proj_px if v.mean_proj_px is not None else float('nan'):.2f} projector px)")
    sign_off = stage("verdict", report)  # the panel: the operator's acceptance (who, which button, when)
    if report.verdict == "unchanged" and verification.get("previous", {}).get("passed") is False:
        ok, message = False, ("the captures say nothing moved but the epipolar verification of the previous "
                              "calibration fails: something the check does not model changed; run a full session")
    elif report.verdict == "incomplete":
        ok, message = False, "the check could not test every part: " + "; ".join(
            f"{p}: {c.reason}" for p, c in report.parts.items() if c.status == "not checked")
    elif report.moved:
        moved = report.moved
        rounds = 0
        while True:
            re = reestimate(report.current, obs, moved)
            n = len(machine.manifest.captures)
            log(f"re-estimate of {', '.join(moved)} from {n} captures: " + (
                "1-sigma targets reached" if re.reached else "; ".join(re.missing)) + (
                "; " + "; ".join(re.floor) if re.floor else ""))
            stage("reestimate", re)
            if re.reached:
                break
            if n + ROUND_CAPTURES > max_captures:
                ok, message = False, (f"the re-estimate did not reach its 1-sigma targets within {max_captures} "
                                      f"captures: {'; '.join(re.missing)}")
                break
            rounds += 1
            n_m = ROUND_CAPTURES if ("mirror" in moved or "camera" in moved) and mirrored else 0
            n_p = ROUND_CAPTURES if ("projector" in moved or ("camera" in moved and not n_m)) else 0
            if n_m and n_p:
                n_m = n_p = ROUND_CAPTURES // 2
            obs = capture(n_m, n_p, lambda: (f"Re-measure {', '.join(moved)} (round {rounds}), capture "
                                             f"{len(machine.manifest.captures) + 1}"))
        result = re.result
        comparison = compare_calibrations(previous, result, re.sigma)
        if ok:
            message = f"{report.verdict}; re-estimated {', '.join(moved)}"
    diag = dict(result.diagnostics) if isinstance(result.diagnostics, dict) else {}
    diag["recalibration"] = {"verdict": report.verdict, "previous_sha256": digest}
    result = result.with_(diagnostics=diag, method=result.method if not report.moved else "recalibration")
    result = with_own_residuals(result, obs, bool(report.moved))
    if ok:
        write_calibration(folder, result, log)  # before verifying: the report records its hash
        machine.result = result
        if verify is not None and report.moved:
            if prompt is not None:
                prompt(f"Epipolar verification of the recalibrated calibration: {VERIFY_PROMPT}")
            v = verify(result, True)
            verification["recalibrated"] = _verification_summary(v)
            log(f"epipolar verification of the recalibration: {'passed' if v.passed else 'FAILED'}")
            if not v.passed:
                ok, message = False, f"{message}; but the epipolar verification of the result fails"
    n_caps = len(machine.manifest.captures)
    counts = machine.counts()
    rec = RecalibrationRecord(str(src.resolve()), digest, str(archived.relative_to(folder)), report, re, comparison,
                              {"total": n_caps, "mirror": counts["mirror"], "projector": counts["projector"],
                               "check": len(check_ids), "elapsed_s": round(time.monotonic() - t0, 2)}).to_dict()
    rec["ok"] = ok
    rec["message"] = message
    rec["verification"] = verification or None
    if resume:
        rec["resumed"] = True
    rec["sign_off"] = sign_off if isinstance(sign_off, dict) else None
    from calib.models.result import _jsonable

    atomic_write_text(folder / RECALIBRATION_FILE, json.dumps(_jsonable(rec), indent=2) + "\n")
    state.update(verdict=report.verdict, ok=ok, previous_sha256=digest)
    settings = getattr(man.rig, "camera_settings", None) or {}
    if settings.get("bump"):
        state["sim_bump"] = settings["bump"]
    machine.persist()
    outcome = Outcome(rec, result, ok, message)
    stage("done", outcome)
    return outcome


def part_line(check, units: str) -> str:
    """A checked part's movement in physical units, then the statistic that decided its status."""
    from calib.recalib import describe_movement

    move = describe_movement(check, units)
    return f"{move}; {check.reason}" if move else check.reason


def only_captures(obs, ids: set):
    """The observations of the captures `ids` alone (the check's, when more were taken since)."""
    return replace(obs, projector_views=tuple(v for v in obs.projector_views if v.capture_id in ids),
                   mirror_views=tuple(v for v in obs.mirror_views if v.capture_id in ids),
                   skipped=tuple(s for s in obs.skipped if s.capture_id in ids))


def rig_verify_fn(rig, folder):
    """The `verify(result, final)` of run_recalibration on this rig (None where the rig cannot verify):
    the previous calibration checked on the rig, the final one written as the session's verification;
    both with the camera's response the recalibration session's rig check recorded."""
    from app.station.setup import make_verify_fn

    final_fn = make_verify_fn(rig, folder)
    if final_fn is None:
        return None

    def verify(result, final):
        if final:
            return final_fn(result)
        from app.verification import session_response, verify as check

        return check(rig.camera, rig.projector, rig.operator, result, response=session_response(folder))

    return verify


def step_instruction(station: Station) -> str:
    """What the person should do for the capture the machine asks for: the station's own guidance (which
    board, where, which tilt), without the hint about the last frame."""
    text = station.instruction()
    hint = station.live_hint(station.live)
    return text[: -len(hint)] if hint and text.endswith(hint) else text


def describe_capture(cap, pattern_points: int | None = None) -> str:
    """What a capture got, in a person's words (the live detection kept in its metadata; a projector
    capture is only taken with every pattern point detected)."""
    m = cap.meta or {}
    parts = [f"{m['corners']} board corners" if "corners" in m else "the board"]
    if "virtual_corners" in m:
        parts.append(f"{m['virtual_corners']} in the mirror")
    if cap.pattern_position is not None:
        parts.append(f"the pattern{f' ({pattern_points} points)' if pattern_points else ''} at position "
                     f"{cap.pattern_position + 1}")
    return f"got {cap.id}: " + ", ".join(parts)


def _take(station: Station, machine: RecalibrationMachine, state: str, prompt, label, log,
          timeout_s: float = CAPTURE_TIMEOUT_S) -> None:
    """Take every capture the machine asks for in `state`. With `prompt` (a person), each one is announced
    first (`label()`: the stage, then the station's guidance) and waited for; auto-capture keeps the frame
    when the board is still, detected and exposed after the image became visible; the person is told
    what it got, and while waiting what the live frame lacks."""
    while machine.state == state and machine.target is not None:
        tgt = machine.target
        if prompt is not None:
            prompt(f"{label()}: {step_instruction(station)}")
        before = machine.last_capture
        clock = clock_of(station.rig.camera)  # the rig's time: frames delivered, not the CPU's speed
        t_end = clock.now() + timeout_s
        said, said_s = "", 0.0
        while machine.state == state and machine.target == tgt:
            if clock.now() > t_end:
                why = station.live.decision.message if station.live is not None and station.live.decision else ""
                raise RecalibrationStopped(f"no capture for {tgt.step} in {timeout_s:.0f} s"
                                           + (f" ({why})" if why else ""))
            station.tick()
            if prompt is not None:
                hint = station.live_hint(station.live).strip()
                if hint and hint != said and time.monotonic() - said_s > 2.0:
                    log(hint)
                    said, said_s = hint, time.monotonic()
        cap = machine.last_capture
        if prompt is not None and cap is not None and cap is not before:
            log(describe_capture(cap, machine.manifest.pattern.n_points))


def comparison_lines(rec: dict) -> list[str]:
    """New against previous, with the uncertainty of each change (recalibration.json's comparison)."""
    cmp = rec.get("comparison")
    caps = rec["captures"]
    out = [f"captures: {caps['total']} (check {caps['check']}; mirror {caps['mirror']}, projector {caps['projector']})"]
    if not cmp:
        return out + ["no part moved: calibration.json is the previous calibration"]
    u = cmp["units"]
    pj = cmp["projector"]
    out.append(f"projector moved {pj[f'position_change_{u}']:.2f} {u} (1-sigma {pj[f'position_sigma_{u}']:.2f}), "
               f"turned {pj['rotation_change_deg']:.3f} deg (1-sigma {pj['rotation_sigma_deg']:.3f})")
    if cmp.get("mirror"):
        m = cmp["mirror"]
        out.append(f"mirror tilted {m['normal_change_deg']:.3f} deg (1-sigma {m['normal_sigma_deg']:.3f}), "
                   f"offset {m[f'd_change_{u}']:+.2f} {u}")
    c = cmp["camera"]
    out.append(f"camera fx {signed(c['fx_change_px'])} px, fy {signed(c['fy_change_px'])} px; projection difference mean "
               f"{c['projection_difference']['mean_px']:.2f} px, max {c['projection_difference']['max_px']:.2f} px")
    for k, v in (rec.get("verification") or {}).items():
        out.append(f"epipolar verification of the {k} calibration: {'passed' if v['passed'] else 'FAILED'}")
    return out
