"""The headless recalibration flow: a session folder whose captures are asked for by the recalibration
(a few to check, then only what the moved parts need), driven by the station as any session is
(Station + SessionMachine), and the calibration math of calib/recalib.py. docs/RECALIBRATION.md.

    previous/calibration.json   the calibration recalibrated, archived (never overwritten)
    calibration.json            the recalibrated result (the previous one when nothing moved)
    recalibration.json          verdicts, numbers, where the previous calibration came from
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from app.station.machine import CAPTURE_STATES, MIRROR_CAPTURE, PROJECTOR_CAPTURE, SessionMachine, Target
from app.station.station import Station
from calib.errors import SessionError
from calib.fileio import atomic_write_text
from calib.observations import STEP_PROJECTOR
from calib.result import CalibrationResult

PREVIOUS_DIR = "previous"
RECALIBRATION_FILE = "recalibration.json"
CHECK_MIRROR_CAPTURES = 2
CHECK_PROJECTOR_CAPTURES = 2
ROUND_CAPTURES = 2  # captures added per round of the re-estimate before its 1-sigma is looked at again
DEFAULT_MAX_CAPTURES = 24


def find_previous(path) -> Path:
    """The previous calibration.json: PATH itself, or PATH/calibration.json for a session folder."""
    p = Path(path)
    if p.is_dir():
        p = p / "calibration.json"
    if not p.is_file():
        raise SessionError(f"no previous calibration at {path}: give a session folder holding calibration.json, "
                           "or a calibration.json")
    return p


def archive_previous(previous: Path, folder: Path) -> tuple[Path, str]:
    """Copy the previous calibration into folder/previous/calibration.json; (path, sha256 of the
    original). Never overwrites: an existing archive is an error."""
    from calib.recalib import sha256_file

    dest = Path(folder) / PREVIOUS_DIR / "calibration.json"
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


class RecalibrationMachine(SessionMachine):
    """A session machine whose capture plan is set by the recalibration: `mirror_quota` real-virtual
    captures and one projector capture per entry of `projector_queue` (pattern positions)."""

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
            "threshold_px": report.threshold_px, "measured": report.n_measured}


def run_recalibration(previous_path, station: Station, machine: RecalibrationMachine, log=print,
                      max_captures: int = DEFAULT_MAX_CAPTURES, workers: int = 2, verify=None,
                      on_stage=None) -> Outcome:
    """Check, re-measure what moved, compare. The station and machine are those of a new session.
    `verify(result, final)` (optional): the epipolar verification of a calibration on the rig; the
    previous calibration is verified during the check (evidence recorded; a failure with an
    "unchanged" verdict is an inconsistency, not a sign-off), the recalibrated one at the end
    (final=True: its report is the session's verification.json; a failure fails the recalibration).
    `on_stage(stage, value)` (optional; the station's panel): "verdict" with the check's report (may block
    until the operator accepts it; a dict it returns is recorded as recalibration.json's sign_off),
    "reestimate" with each round's re-estimate (progress towards the 1-sigma targets), "done" with the
    Outcome."""
    def stage(name, value):
        if on_stage is not None:
            return on_stage(name, value)

    from calib.detect import detect_session
    from calib.recalib import (
        RecalibrationRecord, check_rig, compare_calibrations, reestimate,
    )

    folder = Path(machine.store.folder)
    src = find_previous(previous_path)
    previous = CalibrationResult.load_json(src)
    archived, digest = archive_previous(src, folder)
    log(f"previous calibration {src} (sha256 {digest[:12]}...) archived as {archived.relative_to(folder)}")
    man = machine.manifest
    w, h = man.rig.projector_size
    mirrored = man.mirror_board is not None and previous.mirror is not None
    t0 = time.monotonic()

    def capture(n_mirror: int, n_projector: int):
        """Take n_mirror more real-virtual and n_projector more projector captures through the station."""
        if mirrored and n_mirror:
            if machine.state == PROJECTOR_CAPTURE:
                machine.go_back()
            machine.mirror_quota += n_mirror
            _tick_until(station, machine, MIRROR_CAPTURE)
        if n_projector:
            if machine.state == MIRROR_CAPTURE:
                machine.proceed()
            done = len(machine.projector_queue)
            machine.projector_queue += spread_positions(man.pattern, w, h, n_projector, start=done)
            _tick_until(station, machine, PROJECTOR_CAPTURE)
        station.wait_for_detections()
        return detect_session(machine.store, workers)

    # start: rig check, then the mirror step (the station chooses real-virtual)
    while machine.state == "check_rig":
        station.tick()
    if mirrored and machine.mirror_method is None:
        machine.choose_mirror_method("real-virtual")  # the check's mirror test needs real-virtual captures
    n_check = (CHECK_MIRROR_CAPTURES if mirrored else 0) + CHECK_PROJECTOR_CAPTURES
    log(f"check: {n_check} captures")
    obs = capture(CHECK_MIRROR_CAPTURES if mirrored else 0, CHECK_PROJECTOR_CAPTURES)
    report = check_rig(previous, obs)
    for p, c in report.parts.items():
        log(f"  {p}: {c.status} ({c.reason})")
    log(f"check verdict: {report.verdict} after {time.monotonic() - t0:.1f} s")
    re = None
    comparison = None
    ok, message = True, report.verdict
    result = previous
    verification = {}
    if verify is not None:
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
        while True:
            re = reestimate(report.current, obs, moved)
            n = len(machine.manifest.captures)
            log(f"re-estimate of {', '.join(moved)} from {n} captures: " + (
                "1-sigma targets reached" if re.reached else "; ".join(re.missing)))
            stage("reestimate", re)
            if re.reached:
                break
            if n + ROUND_CAPTURES > max_captures:
                ok, message = False, (f"the re-estimate did not reach its 1-sigma targets within {max_captures} "
                                      f"captures: {'; '.join(re.missing)}")
                break
            n_m = ROUND_CAPTURES if ("mirror" in moved or "camera" in moved) and mirrored else 0
            n_p = ROUND_CAPTURES if ("projector" in moved or ("camera" in moved and not n_m)) else 0
            if n_m and n_p:
                n_m = n_p = ROUND_CAPTURES // 2
            obs = capture(n_m, n_p)
        result = re.result
        comparison = compare_calibrations(previous, result, re.sigma)
        if ok:
            message = f"{report.verdict}; re-estimated {', '.join(moved)}"
    diag = dict(result.diagnostics) if isinstance(result.diagnostics, dict) else {}
    diag["recalibration"] = {"verdict": report.verdict, "previous_sha256": digest}
    result = result.with_(diagnostics=diag, method=result.method if not report.moved else "recalibration")
    if ok:
        result.save_json(folder / "calibration.json")  # before verifying: the report records its hash
        machine.result = result
        if verify is not None and report.moved:
            v = verify(result, True)
            verification["recalibrated"] = _verification_summary(v)
            log(f"epipolar verification of the recalibration: {'passed' if v.passed else 'FAILED'}")
            if not v.passed:
                ok, message = False, f"{message}; but the epipolar verification of the result fails"
    n_caps = len(machine.manifest.captures)
    counts = machine.counts()
    rec = RecalibrationRecord(str(src.resolve()), digest, str(archived.relative_to(folder)), report, re, comparison,
                              {"total": n_caps, "mirror": counts["mirror"], "projector": counts["projector"],
                               "check": n_check, "elapsed_s": round(time.monotonic() - t0, 2)}).to_dict()
    rec["ok"] = ok
    rec["message"] = message
    rec["verification"] = verification or None
    rec["sign_off"] = sign_off if isinstance(sign_off, dict) else None
    from calib.result import _jsonable

    atomic_write_text(folder / RECALIBRATION_FILE, json.dumps(_jsonable(rec), indent=2) + "\n")
    machine.extra_state["recalibration"] = {"verdict": report.verdict, "ok": ok, "previous_sha256": digest}
    settings = getattr(man.rig, "camera_settings", None) or {}
    if settings.get("bump"):
        machine.extra_state["recalibration"]["sim_bump"] = settings["bump"]
    machine._persist()
    outcome = Outcome(rec, result, ok, message)
    stage("done", outcome)
    return outcome


def rig_verify_fn(rig, folder):
    """The `verify(result, final)` of run_recalibration on this rig (None where the rig cannot verify):
    the previous calibration checked on the rig, the final one written as the session's verification."""
    from app.station.setup import make_verify_fn

    final_fn = make_verify_fn(rig, folder)
    if final_fn is None:
        return None

    def verify(result, final):
        if final:
            return final_fn(result)
        from app.verification import verify as check

        return check(rig.camera, rig.projector, rig.operator, result)

    return verify


def _tick_until(station: Station, machine: RecalibrationMachine, state: str, timeout_s: float = 120.0) -> None:
    t_end = time.monotonic() + timeout_s
    while machine.state == state and machine.target is not None:
        if time.monotonic() > t_end:
            raise SessionError(f"no capture for {machine.target.step} in {timeout_s:.0f} s")
        station.tick()


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
    out.append(f"camera fx {c['fx_change_px']:+.2f} px, fy {c['fy_change_px']:+.2f} px; projection difference mean "
               f"{c['projection_difference']['mean_px']:.2f} px, max {c['projection_difference']['max_px']:.2f} px")
    for k, v in (rec.get("verification") or {}).items():
        out.append(f"epipolar verification of the {k} calibration: {'passed' if v['passed'] else 'FAILED'}")
    return out
