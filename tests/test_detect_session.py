"""detect_session on a session folder written through SessionStore, with broken captures mixed in."""

from collections import Counter

import cv2
import numpy as np
import pytest

from _detect_helpers import blank_region_proj_homography, board_homography, render_board_scene
from calib.detection.detect import detect_session
from calib.formats.session import RigInfo, SessionManifest, SessionStore
from calib.models.boards import CharucoSpec
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_VIRTUAL, VIEW_MIRROR
from calib.models.pattern import PatternSpec

SPEC = CharucoSpec(8, 6, "DICT_5X5_50", 50.0, 25.0)
MSPEC = CharucoSpec(6, 5, "DICT_4X4_50", 30.0, 18.0)
W, H = 1024, 640
PROJ = (1280, 720)
PATTERN = PatternSpec.default_for(*PROJ)


def _projector_image(position, angle):
    Hb = board_homography(W, H, SPEC, angle_deg=angle, tilt=(0.2, 0.1), mirrored=True)
    Hbp = blank_region_proj_homography(SPEC, PATTERN, PROJ, position, angle_deg=4)
    return render_board_scene(W, H, SPEC, Hb, PATTERN, Hbp, PROJ, position, supersample=3)


def _real_virtual_image():
    Hr = board_homography(W, H, MSPEC, centre=(260.0, 330.0), scale_px=2.0, angle_deg=10, blank_width=0.0)
    Hv = board_homography(W, H, MSPEC, centre=(W - 1 - 760.0, 300.0), scale_px=1.6, angle_deg=-6,
                          blank_width=0.0, mirrored=True)
    a = render_board_scene(W, H, MSPEC, Hr, blank_width=0.0, background=0.0, supersample=3)
    b = render_board_scene(W, H, MSPEC, Hv, blank_width=0.0, background=0.0, supersample=3)
    return np.maximum(a.image, b.image), a.corners_px, b.corners_px


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    folder = tmp_path_factory.mktemp("det") / "session"
    manifest = SessionManifest(RigInfo((W, H), PROJ, VIEW_MIRROR, driver="test"), SPEC, PATTERN, MSPEC, "real-virtual")
    store = SessionStore.create(folder, manifest)
    truth = {}
    for k, (pos, angle) in enumerate([(0, 4.0), (4, -6.0), (8, 10.0)]):
        sc = _projector_image(pos, angle)
        img = sc.image if k != 1 else cv2.cvtColor(sc.image, cv2.COLOR_GRAY2BGR)  # colour captures too
        cap = store.add_capture(STEP_PROJECTOR, img, pos, PATTERN.points_px(*PROJ, pos))
        truth[cap.id] = sc
    missing = store.add_capture(STEP_PROJECTOR, truth["p0000"].image, 2, PATTERN.points_px(*PROJ, 2))
    store.image_path(missing).unlink()
    corrupt = store.add_capture(STEP_PROJECTOR, truth["p0000"].image, 3, PATTERN.points_px(*PROJ, 3))
    store.image_path(corrupt).write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    blank = store.add_capture(STEP_PROJECTOR, np.full((H, W), 70, np.uint8), 5, PATTERN.points_px(*PROJ, 5))
    small = store.add_capture(STEP_PROJECTOR, np.zeros((H // 2, W // 2), np.uint8), 6, PATTERN.points_px(*PROJ, 6))
    rv, real_gt, virt_gt = _real_virtual_image()
    mcap = store.add_capture(STEP_REAL_VIRTUAL, rv)
    truth[mcap.id] = (real_gt, virt_gt)
    bad_rv = store.add_capture(STEP_REAL_VIRTUAL, np.zeros((H, W), np.uint8))
    return SessionStore.open(folder), truth, dict(missing=missing.id, corrupt=corrupt.id, blank=blank.id,
                                                  small=small.id, bad_rv=bad_rv.id, rv=mcap.id)


def test_detect_session_keeps_good_captures_and_skips_bad_ones(session):
    store, truth, ids = session
    calls = []
    obs = detect_session(store, workers=2, progress=lambda d, t, c: calls.append((d, t, c)), cache="off")
    n = len(store.manifest.captures)
    assert [c[0] for c in calls] == list(range(1, n + 1)) and all(c[1] == n for c in calls)
    assert sorted(c[2] for c in calls) == sorted(c.id for c in store.manifest.captures)

    assert obs.view == VIEW_MIRROR and obs.camera_size == (W, H) and obs.projector_size == PROJ
    assert obs.projector_board == SPEC and obs.mirror_board == MSPEC and obs.pattern == PATTERN
    assert [v.capture_id for v in obs.projector_views] == ["p0000", "p0001", "p0002"]
    for v in obs.projector_views:
        sc = truth[v.capture_id]
        cap = next(c for c in store.manifest.captures if c.id == v.capture_id)
        assert v.board.mirrored and len(v.board.ids) == SPEC.n_corners
        assert np.abs(v.board.corners_px - sc.corners_px[v.board.ids]).max() < 0.15
        assert np.abs(v.pattern_cam_px - sc.pattern_px).max() < 0.1
        assert np.array_equal(v.pattern_proj_px, cap.pattern_points_px)
        assert v.pattern_position == cap.pattern_position

    assert len(obs.mirror_views) == 1
    mv = obs.mirror_views[0]
    real_gt, virt_gt = truth[ids["rv"]]
    assert mv.method == STEP_REAL_VIRTUAL and mv.capture_id == ids["rv"]
    assert np.abs(mv.real.corners_px - real_gt[mv.real.ids]).max() < 0.15
    assert np.abs(mv.virtual.corners_px - virt_gt[mv.virtual.ids]).max() < 0.15

    reasons = {s.capture_id: s.reason for s in obs.skipped}
    assert set(reasons) == {ids["missing"], ids["corrupt"], ids["blank"], ids["small"], ids["bad_rv"]}
    assert reasons[ids["missing"]].startswith("image missing")
    assert reasons[ids["corrupt"]].startswith("image unreadable")
    assert reasons[ids["blank"]] == "board not found"
    assert reasons[ids["small"]] == f"image is {W // 2}x{H // 2}, the session's camera is {W}x{H}"
    assert reasons[ids["bad_rv"]].startswith("real board: board not found")
    for s in obs.skipped:
        assert s.image == next(c.image for c in store.manifest.captures if c.id == s.capture_id)


def test_detect_session_inline_reads_each_image_once_and_matches_pool(session, monkeypatch):
    import calib.detection.session_jobs as D

    store, _, _ = session
    pooled = detect_session(store, workers=2, cache="off")
    counts = Counter()
    real_read = D._read_file

    def counting_read(path, *args):
        data = real_read(path, *args)  # a missing image raises: not a read
        counts[str(path)] += 1
        return data

    monkeypatch.setattr(D, "_read_file", counting_read)
    inline = detect_session(store, workers=1, cache="off")
    present = [str(store.image_path(c)) for c in store.manifest.captures if store.image_path(c).exists()]
    assert counts and set(counts) == set(present) and set(counts.values()) == {1}
    assert [v.capture_id for v in inline.projector_views] == [v.capture_id for v in pooled.projector_views]
    for a, b in zip(inline.projector_views, pooled.projector_views):
        assert np.array_equal(a.board.ids, b.board.ids)
        assert np.allclose(a.board.corners_px, b.board.corners_px) and np.allclose(a.pattern_cam_px, b.pattern_cam_px)
    assert inline.skipped == pooled.skipped
    assert not (store.folder / "detections.json").exists()  # cache="off" writes nothing
