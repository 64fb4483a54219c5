"""Links and special files inside a session folder, grouped by input. Every file a
session folder holds is read through calib.formats.fileio.read_regular: never through a link, never a
FIFO or device (which would block), never more bytes than its kind of file holds, a PNG's header size
checked against the session's camera before decoding. Each case also checks that nothing outside the
folder changed, and the command-line cases that a hostile file gives one line (exit 2), never an
"unexpected" error or a hang: they run in a subprocess whose timeout (generous) fails the test."""

import json
import os
import resource
import subprocess
import sys
import zlib

import cv2
import numpy as np
import pytest

from app.station.panel_results import captures_html, results_zip
from calib.detection.detect import detect_session
from calib.errors import FormatError, SessionError, UnsafeFileError
from calib.formats.fileio import MANIFEST_MAX_BYTES, remove_stale_temporaries
from calib.formats.session import MANIFEST, SessionStore
from calib.formats.session_lock import LOCK_FILE
from calib.models.observations import STEP_REAL_VIRTUAL
from calib.synthetic import make_rig
from _station_helpers import CAM_SIZE, REPO, make_store, run_procam, snapshot

GRAY = np.full((CAM_SIZE[1], CAM_SIZE[0]), 128, np.uint8)  # a capture of the session's camera size
MEMORY_LIMIT = 2 * 2**30  # bytes a child may map: reading a hostile file whole would exceed it


@pytest.fixture
def outside(tmp_path):
    d = tmp_path / "outside"
    d.mkdir()
    ok, buf = cv2.imencode(".png", np.full((CAM_SIZE[1], CAM_SIZE[0]), 200, np.uint8))
    (d / "outside.png").write_bytes(buf.tobytes())
    (d / "secret.txt").write_text("the secret\n")
    return d


def make_session(folder, n: int = 2):
    """A session of `n` captures of the camera's size, closed (unlocked)."""
    store = make_store(folder)
    for _ in range(n):
        store.add_capture(STEP_REAL_VIRTUAL, GRAY)
    store.close()
    return folder


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def procam(*args):
    """`procam ARGS` in a child that may not map more than MEMORY_LIMIT; a hang fails the test."""
    return run_procam(*args, timeout=240, preexec_fn=_limit_memory)


def one_line_error(r, *words):
    """The run ended with one project error line (exit 2) holding `words`."""
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(lines) == 1 and "unexpected" not in lines[0] and "Traceback" not in r.stderr, r.stderr[-2000:]
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


DETECT = ("import sys\nfrom calib.detection.detect import detect_session\n"
          "from calib.formats.session import SessionStore\n"
          "from app.station.panel_results import captures_html\n"
          "s = SessionStore.open(sys.argv[1])\n"
          "print(captures_html(s.manifest.captures, s, {}, {}).count('<img'))\n"
          "for k in detect_session(s, workers=1, cache='off').skipped: print(k.capture_id, k.reason)\n")


def detect_in_child(folder) -> tuple[int, dict]:
    """(thumbnails the Captures tab shows, {capture id: reason skipped}) of `folder`, computed in a child."""
    r = subprocess.run([sys.executable, "-c", DETECT, str(folder)], cwd=REPO, capture_output=True, text=True,
                       timeout=240, preexec_fn=_limit_memory)
    assert r.returncode == 0, r.stderr[-2000:]
    first, *rest = r.stdout.strip().splitlines()
    return int(first), dict(line.split(" ", 1) for line in rest)


# ---- session.json: a link, a FIFO, a huge file ------------------------------------------------------
def test_a_manifest_linked_to_a_valid_outside_manifest_is_refused(tmp_path, outside):
    folder = make_session(tmp_path / "s")
    os.rename(folder / MANIFEST, outside / MANIFEST)
    os.symlink(outside / MANIFEST, folder / MANIFEST)
    before = snapshot(outside)
    with pytest.raises(UnsafeFileError, match="is a link"):
        SessionStore.open(folder)
    with pytest.raises(UnsafeFileError, match="is a link"):
        SessionStore.open(folder, lock=True)
    assert snapshot(outside) == before


def test_a_manifest_linked_to_dev_zero_is_one_line_not_memory(tmp_path):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / MANIFEST)
    os.symlink("/dev/zero", folder / MANIFEST)
    one_line_error(procam("calibrate", str(folder)), "session.json", "is a link")


def test_a_fifo_as_manifest_is_a_clear_error_for_calibrate_and_the_station(tmp_path):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / MANIFEST)
    os.mkfifo(folder / MANIFEST)
    one_line_error(procam("calibrate", str(folder)), "session.json", "not a regular file")
    one_line_error(procam("station", "--resume", str(folder), "--port", "0"), "session.json", "not a regular file")


def test_a_manifest_larger_than_the_cap_is_refused_before_it_is_parsed(tmp_path):
    folder = make_session(tmp_path / "s")
    data = json.loads((folder / MANIFEST).read_text())
    data["state"]["junk"] = [0] * (MANIFEST_MAX_BYTES // 2)
    (folder / MANIFEST).write_text(json.dumps(data))
    with pytest.raises(UnsafeFileError, match="larger than"):
        SessionStore.open(folder)


def test_unknown_bulk_in_the_manifest_is_refused_naming_the_key(tmp_path):
    folder = make_session(tmp_path / "s")
    data = json.loads((folder / MANIFEST).read_text())
    nested = leaf = []
    for _ in range(50):  # nested (within the nesting limit of calib.formats.jsonfile) and bulky
        leaf.append([0.5] * 40)
        leaf = leaf[-1]
    data["junk"] = [nested] * 40
    data["note"] = "a short note from a newer program is still read"
    (folder / MANIFEST).write_text(json.dumps(data))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert e.value.field == "junk" and "remove it" in e.value.problem
    del data["junk"]
    (folder / MANIFEST).write_text(json.dumps(data))
    assert len(SessionStore.open(folder).manifest.captures) == 2


# ---- an image: a FIFO, a loop, a link out, a sparse file, a lying PNG header ----------------------------
def test_a_fifo_as_an_image_is_skipped_with_a_reason_not_a_hang(tmp_path):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / "images/mrv0000.png")
    os.mkfifo(folder / "images/mrv0000.png")
    thumbs, skipped = detect_in_child(folder)
    assert "not a regular file" in skipped["mrv0000"] and "board not found" in skipped["mrv0001"]
    assert thumbs == 1


def test_an_image_linked_to_itself_is_one_line_not_unexpected(tmp_path):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / "images/mrv0000.png")
    os.symlink("mrv0000.png", folder / "images/mrv0000.png")
    thumbs, skipped = detect_in_child(folder)
    assert "link" in skipped["mrv0000"] and thumbs == 1
    r = procam("calibrate", str(folder))
    assert "unexpected" not in r.stderr and "Traceback" not in r.stderr and r.returncode == 2, r.stderr[-2000:]


def test_an_image_linked_outside_is_not_shown_in_the_captures_tab(tmp_path, outside):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / "images/mrv0000.png")
    os.symlink(outside / "outside.png", folder / "images/mrv0000.png")
    before = snapshot(outside)
    store = SessionStore.open(folder)
    html = captures_html(store.manifest.captures, store, {}, {})
    assert html.count("<img") == 1  # the capture inside only
    assert snapshot(outside) == before


def test_an_image_linked_to_another_image_of_the_folder_is_refused_too(tmp_path):
    folder = make_session(tmp_path / "s")
    os.unlink(folder / "images/mrv0000.png")
    os.symlink("mrv0001.png", folder / "images/mrv0000.png")
    store = SessionStore.open(folder)
    with pytest.raises(UnsafeFileError, match="is a link"):
        store.load_image(store.manifest.captures[0])
    assert store.load_image(store.manifest.captures[1]).shape == (CAM_SIZE[1], CAM_SIZE[0], 3)


def test_a_sparse_3gb_image_is_refused_by_its_size_without_reading_it(tmp_path):
    folder = make_session(tmp_path / "s")
    with open(folder / "images/mrv0000.png", "r+b") as f:
        f.truncate(3 * 2**30)
    _, skipped = detect_in_child(folder)
    assert "larger than" in skipped["mrv0000"]
    store = SessionStore.open(folder)
    with pytest.raises(UnsafeFileError, match="larger than"):
        store.load_image(store.manifest.captures[0])


def _png_claiming(width: int, height: int) -> bytes:
    """A small PNG whose header claims `width` x `height` (its CRC fixed, so decoders believe it)."""
    ok, buf = cv2.imencode(".png", np.zeros((8, 8), np.uint8))
    data = bytearray(buf.tobytes())
    data[16:24] = width.to_bytes(4, "big") + height.to_bytes(4, "big")
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")
    return bytes(data + b"\0" * 2**20)


def test_a_png_claiming_32000x32000_is_refused_before_decoding(tmp_path):
    folder = make_session(tmp_path / "s")
    (folder / "images/mrv0000.png").write_bytes(_png_claiming(32000, 32000))
    thumbs, skipped = detect_in_child(folder)
    assert "image is 32000x32000, the session's camera is 1280x800" in skipped["mrv0000"]
    assert thumbs == 1
    store = SessionStore.open(folder)
    with pytest.raises(UnsafeFileError, match="32000x32000"):
        store.load_image(store.manifest.captures[0])


# ---- result files linked outside: calibration.json, calibration.yaml --------------------------------------
def test_a_calibration_json_linked_outside_is_neither_read_nor_probed(tmp_path, outside):
    folder = make_session(tmp_path / "s")
    os.symlink(outside / "secret.txt", folder / "calibration.json")
    os.chmod(outside, 0o555)  # a probe file created there would fail the run with another message
    try:
        before = snapshot(outside)
        one_line_error(procam("calibrate", str(folder)), "calibration.json", "is a link")
        assert snapshot(outside) == before
    finally:
        os.chmod(outside, 0o755)


def test_an_output_that_is_a_link_is_probed_beside_the_link(tmp_path, outside, monkeypatch):
    import tempfile

    from app.commands._outputs import check_output_file

    (tmp_path / "out").mkdir()
    os.symlink(outside / "secret.txt", tmp_path / "out/result.json")
    probed = []
    real = tempfile.mkstemp
    monkeypatch.setattr(tempfile, "mkstemp", lambda **kw: probed.append(kw["dir"]) or real(**kw))
    check_output_file(tmp_path / "out/result.json")
    assert probed == [str((tmp_path / "out").resolve())]


def test_the_results_zip_never_carries_a_file_outside(tmp_path, outside):
    make_rig(136).ground_truth().save_json(tmp_path / "calibration.json")
    os.symlink(outside / "secret.txt", tmp_path / "calibration.yaml")
    with pytest.raises(UnsafeFileError, match="calibration.yaml is a link"):
        results_zip(tmp_path)
    os.unlink(tmp_path / "calibration.yaml")
    os.mkfifo(tmp_path / "verification.json")
    with pytest.raises(UnsafeFileError, match="verification.json is not a regular file"):
        results_zip(tmp_path)
    os.unlink(tmp_path / "verification.json")
    assert results_zip(tmp_path)[1] == ["calibration.json"]


# ---- the lock file: a hard link to a file outside ---------------------------------------------------------
def test_a_hard_linked_lock_file_is_refused_and_its_other_file_kept(tmp_path, outside):
    folder = make_session(tmp_path / "s")
    os.link(outside / "secret.txt", folder / LOCK_FILE)
    before = snapshot(outside)
    with pytest.raises(SessionError, match="other hard links"):
        SessionStore.open(folder, lock=True)
    assert snapshot(outside) == before


# ---- temporaries a killed writer left behind --------------------------------------------------------------
def test_stale_temporaries_are_removed_by_the_next_writer_only_when_abandoned(tmp_path, outside):
    import fcntl

    folder = make_session(tmp_path / "s")
    stale = [folder / ".session.json.0123abcd.tmp", folder / "images/.mrv0009.png.0123abcd.tmp"]
    for p in stale:
        p.write_bytes(b"half written")
    live = folder / ".session.json.89abcdef.tmp"
    live.write_bytes(b"being written")
    fd = os.open(live, os.O_RDONLY)
    fcntl.flock(fd, fcntl.LOCK_EX)  # as a writer in another process holds it
    os.symlink(outside / "secret.txt", folder / ".session.json.fedcba98.tmp")
    before = snapshot(outside)
    try:
        SessionStore.open(folder, lock=True).close()
        assert not any(p.exists() for p in stale)
        assert live.exists() and os.path.islink(folder / ".session.json.fedcba98.tmp")
    finally:
        os.close(fd)
    assert remove_stale_temporaries(folder, ("session.json",)) == [live.name]
    assert snapshot(outside) == before


def test_calibrate_removes_the_temporary_of_a_killed_calibrate(tmp_path):
    folder = make_session(tmp_path / "s")
    orphans = [folder / ".calibration.json.0badf00d.tmp", folder / ".calibration.yaml.0badf00d.tmp"]
    for p in orphans:
        p.write_text("{")
    other = folder / ".verification.json.0badf00d.tmp"  # not calibrate's kind: left to its writer
    other.write_text("{")
    r = procam("calibrate", str(folder))  # two blank captures do not calibrate; the orphans go all the same
    assert r.returncode == 2, r.stderr[-2000:]
    assert not any(p.exists() for p in orphans) and other.exists()
