"""Structured-light captures in a session folder (docs/FORMATS.md "Structured-light captures"): a frame
that is missing, damaged, or a link leading out of the folder skips that capture alone with its reason;
a frame path outside the images folder or a bad sequence spec in session.json is refused with a message
naming it; the captures calibrate (`procam calibrate`'s pipeline) from the folder."""

import json
import os
import shutil
from dataclasses import replace

import pytest

from calib.detection.detect import detect_session
from calib.errors import FormatError
from calib.formats.session import SessionStore

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


@pytest.fixture(scope="module")
def structured_session(tmp_path_factory):
    from app.commands.simulate import simulate_session
    from drivers.sim.scenarios import get_scenario

    sc = replace(get_scenario("nonoverlap-136", 0), mirror_count=4)
    out = tmp_path_factory.mktemp("structured") / "s"
    simulate_session(sc, out, quality="live", workers=1, progress=False, structured_placements=4)
    return out


@pytest.fixture
def folder(structured_session, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(structured_session, dst)
    return dst


def _structured(store):
    return [c for c in store.manifest.captures if c.structured]


def _skipped(folder):
    obs = detect_session(SessionStore.open(folder), workers=1, cache="off")
    return obs, {s.capture_id: s.reason for s in obs.skipped}


def test_an_intact_session_detects_every_placement(folder):
    store = SessionStore.open(folder)
    caps = _structured(store)
    assert len(caps) == 4 and all(len(c.frames) == 47 for c in caps)
    assert len({c.placement for c in store.manifest.captures}) == len(store.manifest.captures)
    obs, skipped = _skipped(folder)
    assert not skipped and len(obs.projector_views) == 4
    assert all(len(v.pattern_cam_px) > 50 for v in obs.projector_views)


@pytest.mark.parametrize("damage", ["missing", "truncated", "not-png", "link-out"])
def test_a_damaged_frame_skips_only_its_capture(folder, damage, tmp_path):
    store = SessionStore.open(folder)
    victim = _structured(store)[1]
    frame = folder / victim.frames[10]
    if damage == "missing":
        frame.unlink()
    elif damage == "truncated":
        frame.write_bytes(frame.read_bytes()[:200])
    elif damage == "not-png":
        frame.write_bytes(b"GIF89a" + b"\0" * 100)
    else:
        outside = tmp_path / "outside.png"
        shutil.copy(frame, outside)
        frame.unlink()
        os.symlink(outside, frame)
    obs, skipped = _skipped(folder)
    assert set(skipped) == {victim.id}, skipped
    reason = skipped[victim.id]
    assert "capture this placement again" in reason, reason
    if damage == "link-out":  # refused before anything is read, naming the frame
        assert f"{victim.frames[10]} is a link leading out of the session folder" in reason, reason
        assert outside.exists()
    else:
        assert "frame 11 of 47" in reason, reason
    if damage == "missing":
        assert "missing" in reason
    assert len(obs.projector_views) == 3  # the others kept
    assert frame.name in os.listdir(folder / "images") or damage == "missing"  # nothing deleted


def _edit_manifest(folder, edit):
    p = folder / "session.json"
    d = json.loads(p.read_text())
    cap = next(c for c in d["captures"] if c.get("pattern_kind") == "structured")
    edit(cap)
    p.write_text(json.dumps(d))
    return cap["id"]


@pytest.mark.parametrize("path", ["../outside.png", "images/../../x.png", "/etc/passwd", "images/sub/x.png"])
def test_a_frame_path_outside_the_images_folder_is_refused(folder, path):
    cid = _edit_manifest(folder, lambda c: c["frames"].__setitem__(3, path))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert cid in str(e.value) or "frames" in str(e.value), str(e.value)


@pytest.mark.parametrize("spec, words", [({"period_px": 7, "phase_steps": 8}, "period_px"),
                                         ({"period_px": 32, "phase_steps": 2}, "phase_steps"),
                                         ({"period_px": "32", "phase_steps": 8}, "period_px"),
                                         ("gray", "structured_light")])
def test_a_bad_sequence_spec_is_refused_with_its_field(folder, spec, words):
    _edit_manifest(folder, lambda c: c.__setitem__("structured_light", spec))
    with pytest.raises(FormatError) as e:
        SessionStore.open(folder)
    assert words in str(e.value), str(e.value)


def test_a_frame_list_that_is_not_the_sequence_skips_the_capture(folder):
    cid = _edit_manifest(folder, lambda c: c.__setitem__("frames", c["frames"][:40]))
    obs, skipped = _skipped(folder)
    assert set(skipped) == {cid} and "40 frames, its sequence has 47" in skipped[cid]
