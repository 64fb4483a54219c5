"""The session folder (calib.formats.session): paths that would escape it (read, hash, delete), one process per folder
(the lock), file modes under the umask, malformed session.json (not UTF-8, non-finite numbers, a
wrong-typed `state`) and a full disk. A session folder is untrusted input: every test also checks that
nothing outside it changed."""

import errno
import hashlib
import json
import os
import signal
import stat
import subprocess
import sys
import warnings

import cv2
import numpy as np
import pytest

import calib.formats.fileio as fileio
from app.station.machine import MIRROR_CAPTURE, Plan, RigCheck, SessionMachine
from calib.detection import cache as detect_cache
from calib.detection.detect import detect_session
from calib.errors import DiskFullError, FormatError, SessionError
from calib.formats.session import MANIFEST, SessionStore
from calib.formats.session_lock import LOCK_FILE, read_holder
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL
from _station_helpers import REPO, TINY, Recorder, make_store, run_procam, snapshot

OK = [RigCheck("camera", True, "streaming"), RigCheck("projector", True, "up")]



@pytest.fixture
def outside(tmp_path):
    """A folder beside the session with a PNG that must never be read, hashed or deleted."""
    d = tmp_path / "outside"
    d.mkdir()
    ok, buf = cv2.imencode(".png", np.full((800, 1280), 128, np.uint8))
    (d / "victim.png").write_bytes(buf.tobytes())
    return d


def session_with_captures(folder, n=2):
    store = make_store(folder)
    for _ in range(n):
        store.add_capture(STEP_REAL_VIRTUAL, TINY)
    store.close()
    return folder


def edit_manifest(folder, edit):
    data = json.loads((folder / MANIFEST).read_text())
    edit(data)
    (folder / MANIFEST).write_text(json.dumps(data))


# ---- 1. paths stay inside the session folder ------------------------------------------------------
@pytest.mark.parametrize("image", [
    "/tmp/outside/victim.png", "../outside/victim.png", "images/../../outside/victim.png", "images\\p0000.png",
    "C:/images/p0000.png", "images/sub/p0000.png", "images/.hidden.png", "images/p0000.jpg", "images/", "",
])
def test_a_capture_image_outside_the_images_folder_is_refused_at_load(tmp_path, image):
    folder = session_with_captures(tmp_path / "s")
    edit_manifest(folder, lambda d: d["captures"][1].__setitem__("image", image))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == "captures[1].image" and "images/NAME.png" in e.value.problem


def test_the_command_line_names_the_image_field_in_one_line(tmp_path, outside):
    folder = session_with_captures(tmp_path / "s")
    edit_manifest(folder, lambda d: d["captures"][0].__setitem__("image", str(outside / "victim.png")))
    r = run_procam("calibrate", str(folder), timeout=60)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "captures[0].image" in lines[0] and "Traceback" not in r.stderr


def test_links_out_of_the_folder_are_not_read_hashed_or_named(tmp_path, outside):
    folder = session_with_captures(tmp_path / "s", 3)
    before = snapshot(outside)
    os.unlink(folder / "images/mrv0000.png")
    os.symlink(outside / "victim.png", folder / "images/mrv0000.png")  # exists outside
    os.unlink(folder / "images/mrv0001.png")
    os.symlink(outside / "absent.png", folder / "images/mrv0001.png")  # does not exist outside
    store = SessionStore.open(folder)
    msgs = []
    for cid in ("mrv0000", "mrv0001"):
        cap = next(c for c in store.manifest.captures if c.id == cid)
        with pytest.raises(SessionError) as e:
            store.load_image(cap)
        msgs.append(str(e.value).replace(cid, "ID"))
    assert msgs[0] == msgs[1] and "out of the session folder" in msgs[0]  # existence outside does not show

    obs = detect_session(store, workers=1)
    reasons = {s.capture_id: s.reason for s in obs.skipped}
    assert reasons["mrv0000"].replace("mrv0000", "ID") == reasons["mrv0001"].replace("mrv0001", "ID")
    assert "outside" not in reasons["mrv0000"] and "victim" not in reasons["mrv0000"]
    assert "image is 8x6" in reasons["mrv0002"]  # the capture inside was read as usual
    cache = (folder / detect_cache.CACHE_FILE).read_text()
    assert hashlib.sha1((outside / "victim.png").read_bytes()).hexdigest() not in cache
    entries = json.loads(cache)["captures"]
    assert "image_sha1" in entries["mrv0002"] and "mrv0000" not in entries
    assert snapshot(outside) == before


def test_delete_and_retake_never_touch_a_file_outside(tmp_path, outside):
    """The station's Delete and Retake (the state machine) on a session whose images are links out."""
    store = make_store(tmp_path / "s")
    m = SessionMachine(store, Plan(real_virtual_captures=4), calibrate_fn=Recorder().calibrate)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    for _ in range(3):
        m.record_capture(TINY)
    (outside / "second.png").write_bytes(b"not yours")
    before = snapshot(outside)
    for cid, target in (("mrv0000", "victim.png"), ("mrv0001", "second.png")):
        os.unlink(store.folder / f"images/{cid}.png")
        os.symlink(outside / target, store.folder / f"images/{cid}.png")
    m.delete_capture("mrv0000")
    m.retake("mrv0001")
    assert m.state == MIRROR_CAPTURE
    assert snapshot(outside) == before
    assert not os.path.lexists(store.folder / "images/mrv0000.png")  # the link itself is gone
    assert [c.id for c in SessionStore.open(store.folder).manifest.captures] == ["mrv0002"]


def test_an_images_folder_linked_outside_is_never_written_or_emptied(tmp_path, outside):
    folder = session_with_captures(tmp_path / "s", 1)
    (outside / "mrv0000.png").write_bytes(b"outside")
    os.rename(folder / "images", tmp_path / "moved")
    os.symlink(outside, folder / "images")
    before = snapshot(outside)
    store = SessionStore.open(folder)
    with pytest.raises(SessionError, match="out of the session folder"):
        store.load_image(store.manifest.captures[0])
    with pytest.raises(SessionError, match="out of the session folder"):
        store.add_capture(STEP_REAL_VIRTUAL, TINY)
    store.delete_capture("mrv0000")
    assert snapshot(outside) == before
    assert json.loads((folder / MANIFEST).read_text())["captures"] == []


def test_a_detection_cache_linked_outside_is_not_read_or_overwritten(tmp_path, outside):
    folder = session_with_captures(tmp_path / "s", 1)
    (outside / "cache.json").write_text(json.dumps({"format": "procam-detections", "secret": 1}))
    os.symlink(outside / "cache.json", folder / detect_cache.CACHE_FILE)
    before = snapshot(outside)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        detect_session(SessionStore.open(folder), workers=1)
    assert any("not a plain file" in str(x.message) for x in w)
    assert snapshot(outside) == before
    assert not os.path.islink(folder / detect_cache.CACHE_FILE)  # replaced by the session's own cache


# ---- 4. one process per session folder ------------------------------------------------------------
HOLD = ("import sys, time\nfrom calib.formats.session import SessionStore\n"
        "s = SessionStore.open(sys.argv[1], lock=True)\nprint('locked', flush=True)\ntime.sleep(120)\n")


def hold(folder):
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], cwd=REPO, stdout=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert p.stdout.readline().strip() == "locked"
    return p


def test_a_second_process_is_refused_and_a_stale_lock_is_taken_over(tmp_path):
    folder = session_with_captures(tmp_path / "s")
    manifest = (folder / MANIFEST).read_bytes()
    holder = hold(folder)
    try:
        assert read_holder(folder)["pid"] == holder.pid
        with pytest.raises(SessionError) as e:
            SessionStore.open(folder, lock=True)
        assert f"in use by pid {holder.pid} since " in str(e.value)
        # the real command: refused in one line, before opening the rig, the session untouched
        for cmd in (("session", "--rig", "sim", "--auto"), ("station", "--rig", "sim", "--port", "0")):
            r = run_procam(*cmd, "--resume", str(folder), timeout=60)
            assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
            assert len(r.stderr.strip().splitlines()) == 1 and f"in use by pid {holder.pid}" in r.stderr
        # reading is allowed; a reader that tries to write is refused too
        reader = SessionStore.open(folder)
        with pytest.raises(SessionError, match=f"pid {holder.pid}"):
            reader.add_capture(STEP_REAL_VIRTUAL, TINY)
        assert (folder / MANIFEST).read_bytes() == manifest
        assert sorted(p.name for p in (folder / "images").iterdir()) == ["mrv0000.png", "mrv0001.png"]
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(10)
    assert read_holder(folder)["pid"] == holder.pid  # the dead holder's file is still there: stale
    store = SessionStore.open(folder, lock=True)
    assert store._lock.took_over["pid"] == holder.pid
    assert read_holder(folder)["pid"] == os.getpid()
    store.add_capture(STEP_REAL_VIRTUAL, TINY)
    store.close()
    assert not (folder / LOCK_FILE).exists()  # removed when released


def test_a_reader_does_not_write_over_a_manifest_changed_since_it_read_it(tmp_path):
    folder = session_with_captures(tmp_path / "s")
    reader = SessionStore.open(folder)
    writer = SessionStore.open(folder, lock=True)
    writer.add_capture(STEP_REAL_VIRTUAL, TINY)
    writer.close()
    with pytest.raises(SessionError, match="changed since this program read it"):
        reader.update(state={"step": "check_rig"})
    assert len(SessionStore.open(folder).manifest.captures) == 3


# ---- 6. the umask decides file modes ----------------------------------------------------------------
@pytest.mark.parametrize("umask", [0o022, 0o002])
def test_written_files_respect_the_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        store = make_store(tmp_path / "s")
        store.add_capture(STEP_PROJECTOR, TINY, 0, store.manifest.pattern.points_px(1920, 1080, 0))
        store.update(state={"step": "check_rig"})
        detect_cache.save(store.folder, {})
        with open(tmp_path / "plain.txt", "w") as f:  # what a normal open() gives
            f.write("x")
    finally:
        os.umask(old)
    want = 0o666 & ~umask
    assert stat.S_IMODE(os.stat(tmp_path / "plain.txt").st_mode) == want
    for name in (MANIFEST, "images/p0000.png", detect_cache.CACHE_FILE):
        assert stat.S_IMODE(os.stat(store.folder / name).st_mode) == want, name


# ---- 9. malformed files: one-line errors naming the field ------------------------------------------------
def test_a_manifest_that_is_not_utf8_is_a_format_error(tmp_path):
    folder = session_with_captures(tmp_path / "s")
    raw = (folder / MANIFEST).read_bytes()
    (folder / MANIFEST).write_bytes(raw.replace(b'"test"', b'"t\xe9st"'))  # Latin-1, not UTF-8
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == "<file>" and "not UTF-8" in e.value.problem
    r = run_procam("calibrate", str(folder), timeout=60)
    assert r.returncode == 2 and "not UTF-8" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def _projector_session(folder):
    store = make_store(folder)
    store.add_capture(STEP_PROJECTOR, TINY, 2, store.manifest.pattern.points_px(1920, 1080, 2))
    store.close()
    return folder


@pytest.mark.parametrize("placeholder, field", [
    ("NaN", "captures[0].pattern_points_px[3][1]"),
    ("1e400", "captures[0].pattern_points_px[3][1]"),
    ("-Infinity", "captures[0].pattern_points_px[3][1]"),
])
def test_non_finite_pattern_points_are_refused(tmp_path, placeholder, field):
    folder = _projector_session(tmp_path / "s")
    edit_manifest(folder, lambda d: d["captures"][0]["pattern_points_px"][3].__setitem__(1, 123456.5))
    text = (folder / MANIFEST).read_text().replace("123456.5", placeholder)
    (folder / MANIFEST).write_text(text)
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == field and "not a finite number" in e.value.problem


@pytest.mark.parametrize("where, field", [
    (lambda d: d.__setitem__("board_thickness", 7777.5), "board_thickness"),
    (lambda d: d["projector_board"].__setitem__("square_length", 7777.5), "projector_board.square_length"),
    (lambda d: d["pattern"].__setitem__("spacing_px", 7777.5), "pattern.spacing_px"),
    (lambda d: d["rig"]["camera_settings"].__setitem__("exposure_us", 7777.5), "rig.camera_settings.exposure_us"),
    (lambda d: d["state"].__setitem__("updated_unix_s", 7777.5), "state.updated_unix_s"),
])
def test_non_finite_numbers_anywhere_are_refused(tmp_path, where, field):
    folder = session_with_captures(tmp_path / "s", 1)
    edit_manifest(folder, lambda d: (d["rig"].__setitem__("camera_settings", {}), d.__setitem__("state", {}),
                                     where(d)))
    (folder / MANIFEST).write_text((folder / MANIFEST).read_text().replace("7777.5", "1e400"))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == field and "inf" in e.value.problem


def test_far_away_pattern_points_are_refused(tmp_path):
    folder = _projector_session(tmp_path / "s")
    edit_manifest(folder, lambda d: d["captures"][0]["pattern_points_px"][0].__setitem__(0, 1e300))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == "captures[0].pattern_points_px" and "outside the 1920x1080" in e.value.problem


@pytest.mark.parametrize("state, field", [
    ([], "state"),
    ({"step": 3}, "state.step"),
    ({"plan": {"poses_per_position": "4"}}, "state.plan.poses_per_position"),
    ({"plan": [1, 2]}, "state.plan"),
    ({"plan": {"mirror_first": "5"}}, "state.plan.mirror_first"),
    ({"plan": {"mirror_first": -1}}, "state.plan.mirror_first"),
    ({"plan": {"next_best": 1}}, "state.plan.next_best"),
    ({"plan": {"mirror_frames": 0}}, "state.plan.mirror_frames"),
    ({"plan": {"mirror_frames": 10**9}}, "state.plan.mirror_frames"),
    ({"plan": {"ask_pose": "yes"}}, "state.plan.ask_pose"),
    ({"retake": {"step": "projector", "pattern_position": "x", "pose_index": 0}}, "state.retake.pattern_position"),
    ({"target": {"step": "elsewhere", "pose_index": 0}}, "state.target.step"),
    ({"rig_request": {"kind": "sim", "seed": "x"}}, "state.rig_request.seed"),
    ({"camera_intrinsics": 5}, "state.camera_intrinsics"),
    ({"mirror_method": 7}, "state.mirror_method"),
    ({"mirror_method": "sideways"}, "state.mirror_method"),
    ({"calibrated": "yes"}, "state.calibrated"),
])
def test_wrong_typed_state_is_a_format_error_naming_the_field(tmp_path, state, field):
    folder = session_with_captures(tmp_path / "s", 1)
    edit_manifest(folder, lambda d: d.__setitem__("state", state))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == field


def test_resume_with_a_wrong_typed_state_is_a_one_line_error(tmp_path):
    folder = session_with_captures(tmp_path / "s", 1)
    bad = {"step": "mirror_capture", "plan": {"poses_per_position": "4"}}
    edit_manifest(folder, lambda d: d.__setitem__("state", bad))
    before = snapshot(folder)
    r = run_procam("session", "--rig", "sim", "--auto", "--resume", str(folder), timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "state.plan.poses_per_position" in r.stderr
    assert snapshot(folder) == before


def test_the_station_state_round_trips_through_the_checks(tmp_path):
    m = SessionMachine(make_store(tmp_path / "s"), Plan(), calibrate_fn=Recorder().calibrate)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    m.record_capture(TINY)
    m.extra_state.update(rig_request={"kind": "sim", "scenario": "x", "seed": 3, "quality": "live"}, method="joint")
    m.persist()
    m2 = SessionMachine.from_store(SessionStore.open(tmp_path / "s"), calibrate_fn=Recorder().calibrate)
    assert m2.state == MIRROR_CAPTURE and m2.mirror_method == "real-virtual"


# ---- 9. a full disk ---------------------------------------------------------------------------------------
def test_a_full_disk_is_a_project_error_and_loses_nothing(tmp_path, monkeypatch):
    store = make_store(tmp_path / "s")
    m = SessionMachine(store, Plan(real_virtual_captures=6), calibrate_fn=Recorder().calibrate)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    acked = [m.record_capture(TINY).id for _ in range(2)]
    real_fsync = os.fsync
    calls = {"n": 0, "fail_at": 1}

    def fsync(fd):
        calls["n"] += 1
        if calls["n"] >= calls["fail_at"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    monkeypatch.setattr(fileio.os, "fsync", fsync)
    for fail_at in (1, 2):  # 1: the image write fails; 2: the image is written, the manifest is not
        calls.update(n=0, fail_at=fail_at)
        with pytest.raises(DiskFullError) as e:
            m.record_capture(TINY)
        assert str(e.value).startswith("disk full writing ") and "nothing already saved was lost" in str(e.value)
        assert [c.id for c in store.manifest.captures] == acked  # memory matches the disk
    monkeypatch.undo()
    assert not [p for p in store.folder.rglob("*.tmp")]  # no temporary file left
    assert [c.id for c in SessionStore.open(store.folder).manifest.captures] == acked
    acked.append(m.record_capture(TINY).id)  # space freed: the session goes on
    assert [c.id for c in SessionStore.open(store.folder).manifest.captures] == acked


def test_a_full_disk_on_the_command_line_is_one_line(tmp_path):
    """`procam simulate` writing into a full disk (ENOSPC injected into fileio's fsync in the child)."""
    code = ("import errno, os, sys\n"
            "def full(fd): raise OSError(errno.ENOSPC, 'No space left on device')\n"
            "os.fsync = full  # every write reaches a full disk\n"
            "from app.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    r = subprocess.run([sys.executable, "-c", code, "simulate", "nonoverlap-136", "--out", str(tmp_path / "sim"),
                        "--workers", "1", "--no-progress"],
                       cwd=REPO, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert r.returncode == 2, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert "Traceback" not in r.stderr and len(lines) == 1
    assert f"disk full writing {tmp_path / 'sim' / 'session.json'}" in lines[0]


def test_a_lock_collected_while_the_registry_is_busy_does_not_deadlock(tmp_path):
    """A garbage collection can finalize a SessionLock inside acquire() in the same thread, the registry
    lock held (a fresh-clone CI run hung there). The finalizer then queues its release, which the
    holder performs before it lets go: nothing waits, and the folder is free afterwards."""
    import gc
    import threading

    from calib.formats import session_lock as SL

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    done = threading.Event()

    def run():
        old = SL.acquire(tmp_path / "a")
        key = old._key
        with SL._REGISTRY_LOCK:  # as inside acquire(): a collection finalizes `old` here
            del old
            gc.collect()
            assert key in SL._held  # not released yet: queued
        SL._drain_if_free()
        assert key not in SL._held and not (tmp_path / "a" / SL.LOCK_FILE).exists()
        SL.acquire(tmp_path / "b").release()
        done.set()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(10)
    assert done.is_set(), "deadlocked"
    SL.acquire(tmp_path / "a").release()  # free again, in this process too
