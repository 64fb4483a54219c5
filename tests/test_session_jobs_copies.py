"""A capture that repeats another (byte-identical image, or identical detections for its step)
adds no information and is counted once (calib.detection.detect), for the calibration and the quality
gate, and named as a copy in `procam calibrate`'s output and calibration.json's diagnostics. Padded with
copies, a thin session stays LOW QUALITY; a mirror step of one image repeated is one placement."""

import json
import shutil

import cv2
import pytest

from app.cli import main
from calib.detection.detect import detect_session
from calib.formats.session import SessionStore

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

#: 6 projector captures spread over the plan (as tests/test_quality_gate.py's thin session)
THIN = {"p0000", "p0002", "p0005", "p0007", "p0010", "p0012"}


def _simulate(folder, mirror_count):
    assert main(["simulate", "nonoverlap-136", "--out", str(folder), "--per-position", "1", "--mirror-count",
                 str(mirror_count), "--quality", "live", "--workers", "1", "--no-progress"]) == 0
    return folder


@pytest.fixture(scope="module")
def thin(tmp_path_factory):
    """3 mirror and 6 projector captures: LOW QUALITY (exit 3) on their own."""
    folder = _simulate(tmp_path_factory.mktemp("dup") / "thin", 3)
    man = json.loads((folder / "session.json").read_text())
    man["captures"] = [c for c in man["captures"] if c["step"] != "projector" or c["id"] in THIN]
    (folder / "session.json").write_text(json.dumps(man))
    return folder


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst, json.loads((dst / "session.json").read_text())


def _add_copies(folder, man, n):
    """n byte-identical copies of every capture, under new ids; {copy id: original id}."""
    originals, copies = list(man["captures"]), {}
    for k in range(n):
        for c in originals:
            new = dict(c, id=f"{c['id']}c{k:02d}", image=f"images/{c['id']}c{k:02d}.png")
            shutil.copyfile(folder / c["image"], folder / new["image"])
            man["captures"].append(new)
            copies[new["id"]] = c["id"]
    (folder / "session.json").write_text(json.dumps(man))
    return copies


def _calibrate(folder, capsys):
    capsys.readouterr()
    code = main(["calibrate", str(folder), "--no-progress", "--workers", "1"])
    out = capsys.readouterr()
    return code, out.out + out.err, json.loads((folder / "calibration.json").read_text())


def test_a_thin_session_padded_with_copies_stays_low_quality_and_names_them(thin, tmp_path, capsys):
    """The issue's case: 11 byte-identical copies of each of the 9 captures took it to exit 0 with a
    1-sigma below the true error."""
    folder, man = _copy(thin, tmp_path / "padded")
    copies = _add_copies(folder, man, 11)
    code, out, saved = _calibrate(folder, capsys)
    assert code == 3 and "LOW QUALITY calibration" in out
    assert "p0012c07 is a copy of p0012 (the same image bytes)" in out
    assert "mrv0001c10 is a copy of mrv0001" in out
    assert saved["diagnostics"]["copies"] == copies and len(copies) == 99
    skipped = {s["capture_id"]: s for s in saved["skipped"]}
    assert {cid for cid, s in skipped.items() if s.get("copy_of")} == set(copies)
    assert not THIN & set(skipped) and not {"mrv0000", "mrv0001", "mrv0002"} & set(skipped)  # the firsts count


def test_a_mirror_step_of_one_image_repeated_is_one_placement(tmp_path, capsys):
    """All 14 mirror images equal to the first were taken as 14 placements (exit 0)."""
    folder = _simulate(tmp_path / "mirror14", 14)
    first = (folder / "images" / "mrv0000.png").read_bytes()
    for k in range(1, 14):
        (folder / "images" / f"mrv{k:04d}.png").write_bytes(first)
    obs = detect_session(SessionStore.open(folder), workers=1, cache="off")
    assert [v.capture_id for v in obs.mirror_views] == ["mrv0000"] and len(obs.projector_views) == 13
    code, out, saved = _calibrate(folder, capsys)
    assert code == 3 and "[quality_mirror_normal]" in out
    assert saved["diagnostics"]["copies"] == {f"mrv{k:04d}": "mrv0000" for k in range(1, 14)}


def test_the_same_pixels_in_other_bytes_are_a_copy_too(thin, tmp_path):
    """A re-encoded image (other PNG bytes, the same pixels) gives identical detections: a copy of its
    first, said so; a capture that differs from every other is never one."""
    folder, man = _copy(thin, tmp_path / "reencoded")
    pixels = cv2.imread(str(folder / "images" / "p0005.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(folder / "images" / "again.png"), pixels, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    assert (folder / "images" / "again.png").read_bytes() != (folder / "images" / "p0005.png").read_bytes()
    man["captures"].insert(0, dict(next(c for c in man["captures"] if c["id"] == "p0005"), id="p0099",
                                   image="images/again.png"))
    (folder / "session.json").write_text(json.dumps(man))
    obs = detect_session(SessionStore.open(folder), workers=2, cache="off")
    # the earlier capture in the session's order is the one kept
    assert [s.capture_id for s in obs.skipped] == ["p0005"] and obs.skipped[0].copy_of == "p0099"
    assert obs.skipped[0].reason == "p0005 is a copy of p0099 (the same detections): counted once"
    assert sorted(v.capture_id for v in obs.projector_views) == sorted(THIN - {"p0005"} | {"p0099"})
