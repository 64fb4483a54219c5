"""detections.json: a session is decoded and detected once; a changed image, job or detector is detected
again; a broken cache file is ignored with a warning; the format round-trips exactly."""

import importlib.util
import json
import shutil
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

import calib.detection.session_jobs as D
from calib.detection import cache as detect_cache
from calib.detection.detect import DetectionFailure, detect_session
from calib.formats.session import SessionStore
from calib.models.boards import CharucoSpec
from calib.models.observations import BoardObservation, MirrorView
from calib.models.pattern import PatternSpec
from test_detect_session import session  # noqa: F401  (the module-scoped session fixture)


@pytest.fixture
def store(session, tmp_path):  # noqa: F811
    """A private copy of the detect_session test folder (this module writes detections.json)."""
    src, _, ids = session
    folder = tmp_path / "copy"
    shutil.copytree(src.folder, folder)
    return SessionStore.open(folder), ids


def _count_detections(monkeypatch):
    detected = Counter()
    real = D._detect_job

    def counting(job, data):
        detected[job.capture_id] += 1
        return real(job, data)

    monkeypatch.setattr(D, "_detect_job", counting)
    return detected


def _same(a, b):
    assert [v.capture_id for v in a.projector_views] == [v.capture_id for v in b.projector_views]
    for x, y in zip(a.projector_views, b.projector_views):
        assert np.array_equal(x.board.ids, y.board.ids) and np.array_equal(x.board.corners_px, y.board.corners_px)
        assert np.array_equal(x.pattern_cam_px, y.pattern_cam_px) and x.board.mirrored == y.board.mirrored
    for x, y in zip(a.mirror_views, b.mirror_views):
        assert x.capture_id == y.capture_id and x.method == y.method
        assert np.array_equal(x.real.corners_px, y.real.corners_px)
        assert np.array_equal(x.virtual.corners_px, y.virtual.corners_px)
    assert a.skipped == b.skipped


def test_second_run_detects_nothing_and_gives_identical_observations(store, monkeypatch):
    st, ids = store
    first = detect_session(st, workers=2)
    assert (st.folder / detect_cache.CACHE_FILE).exists()
    detected = _count_detections(monkeypatch)
    again = detect_session(st, workers=2)
    assert not detected  # every present image came from the cache (bit-exact)
    _same(first, again)
    # a missing image is never cached: it stays missing (and is reported) on every run
    assert ids["missing"] not in json.loads((st.folder / detect_cache.CACHE_FILE).read_text())["captures"]
    # "refresh" detects every present image again and rewrites the file
    refreshed = detect_session(st, workers=1, cache="refresh")
    present = {c.id for c in st.manifest.captures if st.image_path(c).exists()}
    assert set(detected) == present and set(detected.values()) == {1}
    _same(first, refreshed)


def test_changed_image_or_job_is_detected_again(store, monkeypatch):
    st, ids = store
    first = detect_session(st, workers=1)
    # p0001 replaced by p0000's pixels in other PNG bytes: its entry no longer matches the file's bytes,
    # and what it finds is p0000's detections again (a copy, counted once: test_session_jobs_copies.py)
    pixels = cv2.imread(str(st.folder / "images" / "p0000.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(st.folder / "images" / "p0001.png"), pixels, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    detected = _count_detections(monkeypatch)
    again = detect_session(st, workers=1)
    assert set(detected) == {"p0001"}
    assert [v.capture_id for v in again.projector_views] == ["p0000", "p0002"]
    assert next(s for s in again.skipped if s.capture_id == "p0001").copy_of == "p0000"
    assert first.projector_views[1].capture_id == "p0001"
    # another board spec in the manifest: every board job changed, nothing may come from the cache
    data = json.loads((st.folder / "session.json").read_text())
    data["mirror_board"]["marker_length"] = 17.0
    (st.folder / "session.json").write_text(json.dumps(data))
    detected.clear()
    detect_session(SessionStore.open(st.folder), workers=1)
    assert set(detected) == {ids["rv"], ids["bad_rv"]}  # the mirror captures use the mirror board


@pytest.mark.parametrize("module", detect_cache._DETECTION_MODULES)
def test_fingerprint_changes_with_each_detection_module(module, tmp_path, monkeypatch):
    # the camera response's inverse decides centroids and corners as much as detect.py does: an edit to
    # any of these modules must make every kept detection stale
    before = detect_cache.detector_fingerprint.__wrapped__()
    real = importlib.util.find_spec
    edited = tmp_path / "edited.py"
    edited.write_bytes(Path(real(module).origin).read_bytes() + b"\n# edited\n")
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name: SimpleNamespace(origin=str(edited)) if name == module else real(name))
    assert detect_cache.detector_fingerprint.__wrapped__() != before


def test_the_fingerprint_covers_the_camera_response():
    assert "calib.detection.response" in detect_cache._DETECTION_MODULES


def test_other_detector_or_broken_file_means_detecting_again(store, monkeypatch):
    st, _ = store
    first = detect_session(st, workers=1)
    path = st.folder / detect_cache.CACHE_FILE
    present = {c.id for c in st.manifest.captures if st.image_path(c).exists()}

    monkeypatch.setattr(detect_cache, "detector_fingerprint", lambda: "another detector")
    detected = _count_detections(monkeypatch)
    detect_session(st, workers=1)
    assert set(detected) == present
    assert json.loads(path.read_text())["detector"] == "another detector"
    monkeypatch.undo()

    for broken, field in (("{ not json", "Expecting"), ('{"format": "procam-detections", "version": 1}', "captures"),
                          ('{"format": "something else", "version": 1, "captures": {}}', "format")):
        path.write_text(broken)
        detected = _count_detections(monkeypatch)
        with pytest.warns(RuntimeWarning, match=field):
            obs = detect_session(st, workers=1)
        assert set(detected) == present
        _same(first, obs)
        assert json.loads(path.read_text())["format"] == detect_cache.FORMAT  # rewritten whole
        monkeypatch.undo()

    # a malformed entry is detected again, the rest still comes from the cache
    data = json.loads(path.read_text())
    data["captures"]["p0000"]["result"] = {"board": {"ids": [1]}}
    path.write_text(json.dumps(data))
    detected = _count_detections(monkeypatch)
    with pytest.warns(RuntimeWarning, match="1 of the 8 entries .* not written by this station"):
        _same(first, detect_session(st, workers=1))
    assert set(detected) == {"p0000"}


def test_results_round_trip_exactly():
    rng = np.random.default_rng(4)
    board = BoardObservation(np.array([0, 3, 7]), rng.uniform(0, 1000, (3, 2)), True)
    real = BoardObservation(np.array([1, 2]), rng.uniform(0, 1000, (2, 2)), False)
    pts = rng.uniform(0, 1000, (36, 2))
    spec, pattern = CharucoSpec(12, 9, "DICT_5X5_100", 30.0, 22.0), PatternSpec(cols=4, rows=9)
    for res, cid, step in ((DetectionFailure("pattern partial: 30 of 36 points"), "p0003", "projector"),
                           ((board, pts), "p0001", "projector"),
                           (MirrorView("mrv0002", "mirror-real-virtual", real, board), "mrv0002", "mirror-real-virtual"),
                           (MirrorView("mrm0000", "mirror-real-mirror", real), "mrm0000", "mirror-real-mirror")):
        back = detect_cache.decode_result(json.loads(json.dumps(detect_cache.encode_result(res))), cid, step,
                                          True, spec, pattern, (1024, 1024))
        if isinstance(res, DetectionFailure):
            assert back == res
        elif isinstance(res, MirrorView):
            assert (back.capture_id, back.method) == (res.capture_id, res.method)
            assert np.array_equal(back.real.corners_px, res.real.corners_px) and back.real.mirrored == res.real.mirrored
            assert (back.virtual is None) == (res.virtual is None)
            if res.virtual is not None:
                assert np.array_equal(back.virtual.ids, res.virtual.ids) and back.virtual.mirrored
        else:
            assert np.array_equal(back[0].corners_px, board.corners_px) and np.array_equal(back[0].ids, board.ids)
            assert np.array_equal(back[1], pts)  # floats survive JSON bit for bit


def test_unwritable_folder_still_detects_and_warns(store, monkeypatch):
    st, _ = store

    def refuse(path, text):
        raise PermissionError(13, "Read-only file system")

    monkeypatch.setattr(detect_cache, "atomic_write_text", refuse)
    with pytest.warns(RuntimeWarning, match="could not write the detection cache.*Read-only"):
        obs = detect_session(st, workers=1)
    assert len(obs.projector_views) == 3 and not (st.folder / detect_cache.CACHE_FILE).exists()


def test_detect_capture_keeps_exactly_what_calibration_would_detect(store, monkeypatch):
    """The station detects each capture in the background as it is taken (calib.detection.detect.detect_capture);
    calibrating afterwards decodes and detects nothing, and gets the same observations as a fresh run."""
    st, ids = store
    present = [c.id for c in st.manifest.captures if st.image_path(c).exists()]
    results = {cid: D.detect_capture(st, cid) for cid in present}
    assert isinstance(results[ids["bad_rv"]], DetectionFailure)  # the reason is known at capture time
    assert not isinstance(results["p0000"], DetectionFailure)
    detected = _count_detections(monkeypatch)
    kept = detect_session(st, workers=2)
    assert not detected
    _same(kept, detect_session(st, workers=2, cache="off"))
    # a deleted capture's entry goes with the next capture's write; an unknown id is an error
    st.delete_capture("p0000")
    D.detect_capture(st, "p0001")
    assert "p0000" not in json.loads((st.folder / detect_cache.CACHE_FILE).read_text())["captures"]
    with pytest.raises(D.SessionError, match="no capture 'p0000'"):
        D.detect_capture(st, "p0000")
