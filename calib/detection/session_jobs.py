"""Detection of a whole session folder: entry `detect_session(store)` -> SessionObservations (its results
kept in detections.json: calib.detection.cache), and `detect_capture(store, capture_id)` for one capture
as the station takes it. Images are read and detected in threads; which detector a capture needs is
decided in one place, `_detect_job`.
"""

from __future__ import annotations

import json
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np

from calib.detection import cache as detect_cache
from calib.detection import structured_session
from calib.detection.charuco import detect_board
from calib.detection.mirror_views import detect_real_mirror, detect_real_virtual
from calib.detection.pattern import detect_pattern
from calib.detection.response import CameraResponse, recorded_response
from calib.errors import SessionError
from calib.formats.fileio import read_regular
from calib.formats.session import image_header_problem, image_max_bytes
from calib.models.boards import CharucoSpec
from calib.models.observations import (
    STEP_PROJECTOR,
    STEP_REAL_MIRROR,
    STEP_REAL_VIRTUAL,
    VIEW_MIRROR,
    DetectionFailure,
    MirrorView,
    ProjectorView,
    SessionObservations,
    Skipped,
)
from calib.models.pattern import PatternSpec


@dataclass(frozen=True)
class _Job:
    capture_id: str
    image_path: str
    step: str
    mirrored: bool
    board: CharucoSpec
    pattern: PatternSpec | None
    camera_size: tuple[int, int]
    cached: dict | None = None  # this capture's detections.json entry, if any (calib.detection.cache)
    refused: str | None = None  # why the image is not read at all (its path leads out of the session folder)
    response: CameraResponse | None = None  # the camera's tone curve the session recorded, if any


def _read_file(path: str, camera_size: tuple[int, int]) -> np.ndarray:
    """An image file's bytes (the one place detect_session reads images): a regular file no larger than
    a PNG of the camera can be (calib.formats.fileio.read_regular); its header is checked before decoding."""
    return np.frombuffer(read_regular(path, image_max_bytes(camera_size), "image"), np.uint8)


def _run_job(job: _Job, seen: dict | None = None):
    """(capture_id, result, image SHA-1 or None) with result a BoardObservation/pattern tuple, MirrorView
    or DetectionFailure. The file is read once and hashed, then decoded and detected unless `job.cached`
    holds a valid result for exactly these bytes, or `seen` ({(SHA-1, step, mirrored): result}, shared
    by the jobs of one run) holds the result of a byte-identical image detected for the same step."""
    if isinstance(job, structured_session.StructuredJob):
        return job.run()
    digest = None
    if job.refused is not None:
        return job.capture_id, DetectionFailure(job.refused), None
    try:
        try:
            data = _read_file(job.image_path, job.camera_size)
        except FileNotFoundError:
            return job.capture_id, DetectionFailure(f"image missing: {job.image_path}"), None
        except SessionError as e:  # a link, FIFO, device or huge file: never read
            return job.capture_id, DetectionFailure(str(e)), None
        digest = detect_cache.image_digest(data)
        same = (digest, job.step, job.mirrored)
        if seen is not None and same in seen:
            res = seen[same]
            if isinstance(res, MirrorView):  # a mirror result names its capture
                res = replace(res, capture_id=job.capture_id)
            return job.capture_id, res, digest
        res = _cached_result(job, digest)
        if res is None:
            res = _detect_job(job, data)
        if seen is not None:
            seen.setdefault(same, res)
        return job.capture_id, res, digest
    except Exception as e:  # noqa: BLE001 - a pathological image must not stop the whole session
        lines = str(e).strip().splitlines()
        msg = lines[-1] if lines else ""
        why = f"detection failed ({e.__class__.__name__}): {msg}".rstrip(": ")
        return job.capture_id, DetectionFailure(why), digest


def _cached_result(job: _Job, digest: str):
    """The result `job.cached` holds for an image with this SHA-1, or None (no entry, another image, or
    an entry that does not fit the capture: detect again)."""
    if job.cached is None or job.cached.get("image_sha1") != digest:
        return None
    try:
        return detect_cache.decode_result(job.cached.get("result"), job.capture_id, job.step, job.mirrored,
                                          job.board, job.pattern, job.camera_size)
    except ValueError:
        return None


def _detect_job(job: _Job, data: np.ndarray):
    problem = image_header_problem(data, job.camera_size, job.image_path)
    if problem is not None:  # another size (a lying header too) is never decoded
        return DetectionFailure(problem)
    gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
    if gray is None:
        return DetectionFailure(f"image unreadable: {job.image_path} cannot be decoded")
    h, w = gray.shape
    if (w, h) != tuple(job.camera_size):
        return DetectionFailure(f"image is {w}x{h}, the session's camera is {job.camera_size[0]}x{job.camera_size[1]}")
    if job.step == STEP_REAL_VIRTUAL:
        return detect_real_virtual(gray, job.board, job.capture_id, response=job.response)
    if job.step == STEP_REAL_MIRROR:
        return detect_real_mirror(gray, job.board, job.capture_id, response=job.response)
    board = detect_board(gray, job.board, job.mirrored, response=job.response)
    if isinstance(board, DetectionFailure):
        return board
    pts = detect_pattern(gray, job.pattern, job.mirrored, board, job.board, job.response)
    if isinstance(pts, DetectionFailure):
        return pts
    return board, pts


#: serialises detections.json read-modify-writes within one process (the station detects each capture in
#: the background while it captures the next; calibration may run detect_session on the same folder)
_CACHE_LOCK = threading.Lock()


def _job_for(store, c, old: dict, cache_on: bool):
    """(_Job, job key or None) of capture `c` of a SessionStore; `old` its detections.json entries."""
    if c.structured:
        return structured_session.job_for(store, c), None
    m = store.manifest
    board = m.projector_board if c.step == STEP_PROJECTOR else (m.mirror_board or m.projector_board)
    flip = m.rig.view == VIEW_MIRROR and c.step == STEP_PROJECTOR
    pattern = m.pattern if c.step == STEP_PROJECTOR else None
    response = recorded_response(m.rig.camera_settings)
    key = detect_cache.job_key(c.step, flip, board, pattern, m.rig.camera_size, response) if cache_on else None
    entry = old.get(c.id)
    cached = entry if entry is not None and entry.get("job") == key else None
    try:
        path, refused = str(store.image_path(c)), None
    except SessionError as e:  # never read, hashed or named: the reason does not tell whether it exists
        path, refused = "", str(e)
    return _Job(c.id, path, c.step, flip, board, pattern, tuple(m.rig.camera_size), cached,
                refused=refused, response=response), key


def detect_capture(store, capture_id: str):
    """Detect one capture of a SessionStore now and put the result in the session's detections.json,
    so that a later detect_session (calibration) finds it there instead of decoding and detecting the
    image again. The station calls this in the background right after each capture: by the time the
    operator presses Calibrate every image has been detected, once, from the bytes on disk (so the
    result is bit for bit what detect_session would compute). Returns the result: a DetectionFailure
    (with the reason calibration will skip this capture for), (board, pattern points) or a MirrorView.
    Raises SessionError for an unknown capture id."""
    c = next((c for c in store.manifest.captures if c.id == capture_id), None)
    if c is None:
        raise SessionError(f"no capture '{capture_id}' in this session")
    job, key = _job_for(store, c, {}, True)  # detected now: the capture is new, it has no entry yet
    cid, result, digest = _run_job(job)
    if digest is not None:
        with _CACHE_LOCK:
            entries = detect_cache.load(store.folder)
            live = {x.id for x in store.manifest.captures} | {cid}
            entries = {k: v for k, v in entries.items() if k in live}
            entries[cid] = {"image_sha1": digest, "job": key, "result": detect_cache.encode_result(result)}
            detect_cache.save(store.folder, entries)
    return result


def _detect_threaded(jobs, workers: int, done) -> None:
    """Run jobs in `workers` threads. OpenCV releases the GIL in decoding and in every detector, which
    is nearly all of the time, so threads scale like processes here (1.9x on 2 cores) without the
    half second a process pool takes to start. OpenCV's own thread pool is set to one thread per
    stream while the jobs run (one detection stream per core) and restored after."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ThreadPoolExecutor(max_workers=workers) as ex:
            for out in ex.map(partial(_run_job, seen={}), jobs):  # in job order; `done` runs in this thread only
                done(*out)
    finally:
        cv2.setNumThreads(threads)


def detect_session(store, workers: int = 2, progress=None, cache: str = "use") -> SessionObservations:
    """Detect every capture of a session (SessionStore) -> SessionObservations.

    Each image is read once; detection runs in `workers` threads (1 = inline). A capture whose image
    is missing or unreadable, or whose board/pattern is not found, is listed in `skipped` with the
    reason. `progress(done, total, capture_id)` is called after each capture. A capture that repeats
    an earlier one (_copies) is detected once and skipped as a copy of it (Skipped.copy_of).

    `cache`: "use" takes the results of earlier runs from the session's detections.json for captures
    whose image, job and detector are unchanged (calib.detection.cache) and writes the file back;
    "refresh" detects every image and writes the file; "off" neither reads nor writes it."""
    if cache not in ("use", "refresh", "off"):
        raise ValueError(f"cache must be 'use', 'refresh' or 'off', not {cache!r}")
    m = store.manifest
    if cache == "use":
        with _CACHE_LOCK:
            old = detect_cache.load(store.folder)
    else:
        old = {}
    jobs, keys = [], {}
    for c in m.captures:
        job, keys[c.id] = _job_for(store, c, old, cache != "off")
        jobs.append(job)
    results: dict[str, object] = {}
    digests: dict[str, str | None] = {}
    total = len(jobs)

    def done(cid, res, digest):
        results[cid] = res
        digests[cid] = digest
        if progress is not None:
            progress(len(results), total, cid)

    if workers > 1 and total > 1:
        _detect_threaded(jobs, min(workers, total), done)
    else:
        seen = {}
        for job in jobs:
            done(*_run_job(job, seen))

    if cache != "off":
        entries = {cid: {"image_sha1": digests[cid], "job": keys[cid],
                         "result": detect_cache.encode_result(results[cid])}
                   for cid in results if digests.get(cid)}
        if entries != old:
            with _CACHE_LOCK:
                detect_cache.save(store.folder, entries)

    copies = _copies(m.captures, results, digests)
    pviews, mviews, skipped = [], [], []
    for c in m.captures:
        res = results[c.id]
        if c.id in copies:
            skipped.append(copies[c.id])
        elif isinstance(res, DetectionFailure):
            skipped.append(Skipped(c.id, c.image, res.reason))
        elif c.step == STEP_PROJECTOR:
            board, pts = res
            pviews.append(structured_session.projector_view(c, board, pts) if c.structured else
                          ProjectorView(c.id, board, pts, c.pattern_points_px, c.pattern_position))
        else:
            mviews.append(res)
    return SessionObservations(
        camera_size=tuple(m.rig.camera_size), projector_size=tuple(m.rig.projector_size), view=m.rig.view,
        projector_board=m.projector_board, pattern=m.pattern, projector_views=tuple(pviews),
        mirror_board=m.mirror_board, mirror_views=tuple(mviews), board_thickness=m.board_thickness,
        skipped=tuple(skipped),
    )


def _copies(captures, results: dict, digests: dict) -> dict[str, Skipped]:
    """{capture id: why it is skipped} for the captures that repeat an earlier one: a byte-identical image
    (same SHA-1) or, for the same step, identical detections. A copy adds no information, so it is counted
    once: kept, it would shrink the uncertainty and defeat the quality gate (calib.quality.trust)."""
    first_image: dict[str, str] = {}
    first_found: dict[tuple, str] = {}
    out = {}
    for c in captures:
        res = results[c.id]
        if isinstance(res, DetectionFailure):
            continue
        found = (c.step, _detections_key(res))
        orig, what = first_image.get(digests.get(c.id)), "the same image bytes"
        if orig is None:
            orig, what = first_found.get(found), "the same detections"
        if orig is not None:
            out[c.id] = Skipped(c.id, c.image, f"{c.id} is a copy of {orig} ({what}): counted once", copy_of=orig)
            continue
        if digests.get(c.id):
            first_image[digests[c.id]] = c.id
        first_found[found] = c.id
    return out


def _detections_key(result) -> str:
    """A detection result's points as text, whichever capture it belongs to."""
    enc = detect_cache.encode_result(result)
    if "mirror" in enc:
        enc["mirror"] = dict(enc["mirror"], capture_id=None)
    return json.dumps(enc, sort_keys=True)
