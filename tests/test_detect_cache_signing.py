"""detections.json is untrusted input (it travels with the session folder). Only entries this
installation signed are used (an HMAC with its own key, calib.detection.cache); a forged or foreign
entry is detected again with one warning, and a signed entry that does not fit its capture is detected
again too, never an IndexError/TypeError later."""

import json
import os
import stat

import pytest

from calib.detection import cache as detect_cache
from calib.detection.detect import detect_session
from test_detect_cache import _count_detections, _same, store  # noqa: F401  (fixtures and helpers)
from test_detect_session import session  # noqa: F401


def _entries(st):
    return json.loads((st.folder / detect_cache.CACHE_FILE).read_text())["captures"]


@pytest.fixture
def own_key(tmp_path, monkeypatch):
    """A key file of its own for one test (the cached key of another path is not reused)."""
    path = tmp_path / "config" / "procam-station" / "cache.key"
    monkeypatch.setenv(detect_cache.KEY_ENV, str(path))
    return path


def test_a_forged_entry_is_not_used(store, monkeypatch):
    """Every projector entry's pattern points shifted by +3 px, image SHA-1s and detector kept (the
    issue's forged cache: ProjK 0.28 -> 7.68 px, exit 0): detected again, with one warning."""
    st, _ = store
    first = detect_session(st, workers=1)
    data = json.loads((st.folder / detect_cache.CACHE_FILE).read_text())
    forged = [cid for cid, e in data["captures"].items() if "pattern_px" in e["result"]]
    for cid in forged:
        e = data["captures"][cid]
        e["result"]["pattern_px"] = [[x + 3.0, y + 3.0] for x, y in e["result"]["pattern_px"]]
    (st.folder / detect_cache.CACHE_FILE).write_text(json.dumps(data))
    detected = _count_detections(monkeypatch)
    with pytest.warns(RuntimeWarning, match=f"{len(forged)} of the .* not written by this station"):
        again = detect_session(st, workers=1)
    assert set(detected) == set(forged) and len(forged) == 3
    _same(first, again)


def test_a_cache_from_another_installation_is_detected_again(store, tmp_path, monkeypatch):
    st, _ = store
    monkeypatch.setenv(detect_cache.KEY_ENV, str(tmp_path / "elsewhere.key"))
    first = detect_session(st, workers=1)  # signed on another machine
    monkeypatch.setenv(detect_cache.KEY_ENV, str(tmp_path / "here.key"))
    detected = _count_detections(monkeypatch)
    with pytest.warns(RuntimeWarning, match="not written by this station"):
        _same(first, detect_session(st, workers=1))
    assert set(detected) == set(_entries(st))
    detected.clear()
    _same(first, detect_session(st, workers=1))  # now signed with this installation's key: used
    assert not detected


def test_the_key_is_created_once_private(own_key):
    assert detect_cache.key_path() == own_key and not own_key.exists()
    key = detect_cache.installation_key()
    assert own_key.read_bytes() == key and len(key) == 32
    assert stat.S_IMODE(own_key.stat().st_mode) == 0o600
    assert stat.S_IMODE(own_key.parent.stat().st_mode) == 0o700
    detect_cache._key_at.cache_clear()
    assert detect_cache.installation_key() == key  # read again, never replaced
    assert [p.name for p in own_key.parent.iterdir()] == ["cache.key"]  # no temporary file left


@pytest.mark.parametrize("damage, why", [
    (lambda p: os.chmod(p, 0o644), "mode 644"),
    (lambda p: p.write_bytes(b"short"), "32-byte"),
    (lambda p: (p.unlink(), os.mkfifo(p)), "not a plain file"),
    (lambda p: (p.unlink(), p.symlink_to("/etc/hostname")), "Too many levels|link"),
])
def test_an_unusable_key_file_is_reported_and_not_used(own_key, damage, why):
    """A key others can read, of the wrong size, a FIFO (which must not hang) or a link: one warning naming
    the file, and a key for this run only."""
    key = detect_cache.installation_key()
    damage(own_key)
    detect_cache._key_at.cache_clear()
    with pytest.warns(RuntimeWarning, match=f"cache key {own_key} is unusable .*({why})"):
        other = detect_cache.installation_key()
    assert len(other) == 32 and other != key


def _set(path, value):
    """A function setting entries[path[0]]...[path[-1]] = value(entries)."""
    def apply(entries, ids):
        keys = [ids.get(k, k) for k in path]
        node = entries
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value(entries, ids)
    return apply


_P = ("p0000", "result")
BAD_ENTRIES = {
    "corner id 9999": _set(_P + ("board", "ids"), lambda e, i: [9999] + e["p0000"]["result"]["board"]["ids"][1:]),
    "corner id -5": _set(_P + ("board", "ids"), lambda e, i: [-5] + e["p0000"]["result"]["board"]["ids"][1:]),
    "repeated corner ids": _set(_P + ("board", "ids"), lambda e, i: [0] * len(e["p0000"]["result"]["board"]["ids"])),
    "boolean corner ids": _set(_P + ("board", "ids"), lambda e, i: [True] * len(e["p0000"]["result"]["board"]["ids"])),
    "3 pattern points": _set(_P + ("pattern_px",), lambda e, i: e["p0000"]["result"]["pattern_px"][:3]),
    "1,000,000 pattern points": _set(_P + ("pattern_px",), lambda e, i: [[10.0, 10.0]] * 1_000_000),
    "corners far outside the image": _set(_P + ("board", "corners_px"),
                                          lambda e, i: [[x + 1e6, y] for x, y in e["p0000"]["result"]["board"]["corners_px"]]),
    "board not seen in the mirror": _set(_P + ("board", "mirrored"), lambda e, i: False),
    "projector entry holding a mirror result": _set(_P, lambda e, i: e[i["rv"]]["result"]),
    "mirror entry holding a projector result": _set(("rv", "result"), lambda e, i: e["p0000"]["result"]),
    "mirror entry of another capture": _set(("rv", "result", "mirror", "capture_id"), lambda e, i: "mrv0099"),
    "mirror entry of the other mirror method": _set(("rv", "result", "mirror", "method"), lambda e, i: "mirror-real-mirror"),
    "mirror entry without its virtual board": _set(("rv", "result", "mirror", "virtual"), lambda e, i: None),
    "failure reason a number": _set(_P, lambda e, i: {"failure": 5}),
}


@pytest.mark.parametrize("name", list(BAD_ENTRIES))
def test_a_signed_entry_that_does_not_fit_its_capture_is_detected_again(store, monkeypatch, name):
    """Signed by this installation (so only a bug could write it) but not what its capture can hold:
    detected again, the other entries still used, the observations those of a fresh run."""
    st, ids = store
    first = detect_session(st, workers=1)
    entries = {k: {f: x for f, x in v.items() if f != "mac"} for k, v in _entries(st).items()}
    BAD_ENTRIES[name](entries, ids)
    detect_cache.save(st.folder, entries)
    victim = ids["rv"] if name.startswith("mirror") else "p0000"
    detected = _count_detections(monkeypatch)
    _same(first, detect_session(st, workers=1))
    assert set(detected) == {victim}
