"""`procam report SESSION`: one self-contained HTML file with the calibration's numbers, its figures and
the verification, opened in Debian's chromium."""

from __future__ import annotations

import json
import math
import re
import shutil

import numpy as np
import pytest
from calib.errors import FormatError

from app.cli import main
from _station_helpers import launch_chromium, make_store, run_procam

SECTIONS = ("summary", "parameters", "distortion", "residuals", "per-view", "coverage", "rig", "verification",
            "exports")


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A small simulated session (13 projector views, 4 mirror views), calibrated (joint) and verified."""
    folder = tmp_path_factory.mktemp("report") / "session"
    assert main(["simulate", "nonoverlap-136", "--out", str(folder), "--quality", "live", "--per-position", "1",
                 "--mirror-count", "4", "--no-progress"]) == 0
    assert main(["calibrate", str(folder), "--no-progress"]) == 0
    assert main(["verify", str(folder), "--rig", "sim", "--grid", "3x2"]) == 0
    return folder


@pytest.fixture(scope="module")
def report(calibrated, tmp_path_factory):
    out = tmp_path_factory.mktemp("out") / "report.html"
    r = run_procam("report", str(calibrated), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"wrote {out}" in r.stdout
    return out


def _cells(html: str) -> dict:
    """data-key -> (data-value, visible text) of every tagged number."""
    out = {}
    for m in re.finditer(r'data-key="([^"]+)" data-value="([^"]*)">(.*?)</(?:td|span)>', html):
        out[m.group(1)] = (m.group(2), re.sub(r"<[^>]+>", "", m.group(3)))
    return out


def _shown_matches(text: str, value: float, sigma: float | None = None) -> bool:
    """The visible 'v ± s unit' rounds value (and sigma) to the printed decimals."""
    nums = re.findall(r"-?\d+\.?\d*(?:e-?\d+)?", text)
    v = nums[0]
    dec = len(v.split(".")[1]) if "." in v and "e" not in v else None
    tol = 0.5 * 10 ** -dec + 1e-12 if dec is not None else abs(value) * 1e-5
    ok = abs(float(v) - value) <= tol
    if sigma is not None:
        ok &= "±" in text and abs(float(nums[1]) - sigma) <= tol
    return ok


@pytest.mark.slow
def test_report_is_self_contained_and_shows_the_calibration(calibrated, report):
    html = report.read_text()
    cal = json.loads((calibrated / "calibration.json").read_text())
    unc = cal["uncertainty"]
    # self-contained: nothing fetched from elsewhere, every image inline
    assert not re.search(r'(?:src|href)\s*=\s*["\']?\s*(?:https?:)?//', html, re.I)
    assert not re.search(r"<script|<link|@import|url\(", html, re.I)
    imgs = re.findall(r'<img[^>]*src="([^"]*)"', html)
    assert len(imgs) >= 9 and all(s.startswith(("data:image/png;base64,", "data:image/jpeg;base64,")) for s in imgs)
    for sid in SECTIONS:
        assert f'id="{sid}"' in html, sid
    cells = _cells(html)
    # the parameters and their 1-sigma, as calibration.json has them
    for dev in ("camera", "projector"):
        K = cal[dev]["K"]
        for key, val in (("fx", K[0][0]), ("fy", K[1][1]), ("cx", K[0][2]), ("cy", K[1][2])):
            raw, text = cells[f"{dev}.{key}"]
            assert float(raw) == val and _shown_matches(text, val, unc[dev][key]) and text.endswith("px"), (dev, key, text)
        for i, val in enumerate(cal[dev]["dist"]):
            raw, text = cells[f"{dev}.dist{i}"]
            assert float(raw) == val
            if unc[dev]["dist"][i] == 0.0:  # held fixed by the selected model: says so
                assert "fixed" in text and "±" not in text
            else:
                assert _shown_matches(text, val, unc[dev]["dist"][i]), text
    assert all(float(s) > 0 for s in re.findall(r"± (\d+\.?\d*)", html))  # never "± 0.00"
    T = np.array(cal["T_cam_proj"])
    for i, a in enumerate("xyz"):
        raw, text = cells[f"T_cam_proj.t{a}"]
        assert float(raw) == T[i, 3] and _shown_matches(text, T[i, 3], unc["T_cam_proj"]["t"][i]) and cal["units"] in text
    raw, text = cells["mirror.d"]
    assert float(raw) == cal["mirror"]["d"] and _shown_matches(text, cal["mirror"]["d"], unc["mirror"]["d"])
    assert float(cells["mirror.normal_deg"][0]) == unc["mirror"]["normal_deg"] and "deg" in cells["mirror.normal_deg"][1]
    assert float(cells["rms.joint"][0]) == cal["rms"]["joint"]
    # the projection-uncertainty heat maps, with calibration.json's median and max per device
    assert 'id="projection-uncertainty"' in html and 'alt="projection uncertainty over the camera' in html
    for dev in ("camera", "projector"):
        g = cal["projection_uncertainty"][dev]
        assert f"{dev} projection uncertainty (1 sigma over the image): median {g['median_px']:.3f} px" in html
    # the recomputed residuals reproduce the calibration's RMS (same points, same model, same poses)
    shown = float(re.search(r'id="recomputed-rms">([\d.]+) px', html).group(1))
    assert abs(shown - cal["rms"]["joint"]) <= 6e-5
    # the worst views with their RMS and a thumbnail each
    worst = cal["diagnostics"]["worst_views"]
    assert worst
    for w in worst:
        assert float(cells[f"worst.{w['capture_id']}"][0]) == w["rms_px"]
        assert f'alt="capture {w["capture_id"]} with its residuals"' in html
    # the verification: verdict and every check's distance
    ver = json.loads((calibrated / "verification.json").read_text())
    assert re.search(r'id="verification-status"><span class="pass">PASS', html)
    for i, c in enumerate(ver["checks"], 1):
        assert float(cells[f"check{i}.distance_proj_px"][0]) == c["distance_proj_px"]
        assert float(cells[f"check{i}.distance_px"][0]) == c["distance_px"]
    for key in ("mean_proj_px", "worst_proj_px", "mean_camera_px", "worst_camera_px"):
        raw, text = cells[f"verification.{key}"]
        assert float(raw) == ver[key] and _shown_matches(text, ver[key]), key
    assert 'alt="verification curves on the camera image"' in html


@pytest.mark.slow
def test_report_names_the_exports_and_which_the_session_holds(calibrated, report):
    from calib.export.registry import EXPORTERS

    html = report.read_text()
    section = html[html.index('id="exports"'):]
    rows = {m.group(1): m.group(2) for m in re.finditer(r'<tr><td class="l"><code>(\w+)</code></td>(.*?)</tr>', section)}
    assert set(rows) == set(EXPORTERS)
    for name, e in EXPORTERS.items():
        for p in e.paths(calibrated, "calibration"):
            assert f"<code>{p.name}</code>" in rows[name], (name, p.name)
    # procam calibrate writes the default (OpenCV YAML) beside calibration.json; the others on request
    assert "in the session" in rows["opencv"] and "not written yet" in rows["mrcal"]
    assert f"procam export {calibrated} --format all --out DIR" in section


def test_recomputed_residuals_match_every_view_of_the_calibration(calibrated):
    from app.report.data import gather

    d = gather(calibrated)
    res = d.residuals
    assert res.poses_source == "calibration.json"
    stored = {pv["capture_id"]: pv for pv in d.calibration["per_view"]}
    got = res.view_rms()
    assert set(got) == set(stored)
    for cid, pv in stored.items():
        assert math.isclose(got[cid], pv["rms_px"], rel_tol=1e-3), cid
        # and point by point, the norms calibration.json keeps (inliers, corners then pattern points)
        v = res.views.index(cid)
        sel = (res.cam_view == v) & ~res.cam_rejected
        norms = np.sort(np.linalg.norm(res.cam_res[sel], axis=1))
        assert np.allclose(norms, np.sort(pv["point_residuals_px"]), atol=2e-4)
    # the projector side: pattern points mapped into the projector, finite and of sub-pixel size
    ok = ~res.proj_rejected
    assert np.isfinite(res.proj_res[ok]).all() and np.abs(res.proj_res[ok]).max() < 2.0


@pytest.mark.slow
@pytest.mark.browser
def test_report_renders_in_chromium_offline(report, tmp_path):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = launch_chromium(p)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            errors, requests = [], []
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("request", lambda r: requests.append(r.url))
            page.goto(report.as_uri(), wait_until="load")
            widths = page.evaluate("Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth])")
            assert len(widths) >= 9
            for alt, complete, w in widths:
                assert complete and w > 0, alt
            assert page.locator("h2").count() == len(SECTIONS)
            page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
        finally:
            browser.close()
    assert errors == []
    assert all(u.startswith(("file:", "data:")) for u in requests), requests


@pytest.mark.slow
def test_a_session_without_verification_still_reports(calibrated, tmp_path):
    from app.report import write_report

    folder = tmp_path / "s"
    shutil.copytree(calibrated, folder)
    (folder / "verification.json").unlink()
    out = write_report(folder)
    assert out == folder / "report.html"
    html = out.read_text()
    section = html[html.index('id="verification"'):]
    assert "<b>not verified</b>" in section and "<img" not in section
    assert 'id="verification-verdict">not verified<' in html
    # a verification of another calibration (it records the file's SHA-256) is not shown as this one's
    shutil.copy(calibrated / "verification.json", folder / "verification.json")
    cal = json.loads((folder / "calibration.json").read_text())
    (folder / "calibration-other.json").write_text(json.dumps(cal))
    assert main(["report", str(folder), "--calibration", str(folder / "calibration-other.json")]) == 0
    html = (folder / "report-other.html").read_text()
    section = html[html.index('id="verification"'):]
    assert "<b>not verified</b>" in section and "verified another calibration" in section and "<img" not in section
    assert "PASS" not in html
    # an unreadable verification.json is said so, and the rest is still reported
    (folder / "verification.json").write_text("{not json")
    html = write_report(folder, tmp_path / "r.html").read_text()
    assert "not verified: verification.json cannot be read" in html and 'id="rig"' in html


@pytest.mark.slow
def test_odd_optional_fields_of_calibration_json_do_not_break_the_report(calibrated, tmp_path):
    """calibration.json is untrusted: optional parts of the wrong type are left out, text is escaped."""
    from app.report import write_report

    folder = tmp_path / "s"
    shutil.copytree(calibrated, folder)
    cal = json.loads((folder / "calibration.json").read_text())
    cal["units"] = "<b>mm</b>"  # text where a unit belongs: refused by the calibration file's reader, naming it
    (folder / "calibration.json").write_text(json.dumps(cal))
    with pytest.raises(FormatError) as e:
        write_report(folder)
    assert e.value.field == "units"
    cal["units"] = "mm"
    cal["method"] = "<b>joint</b>"  # free text from the file is escaped
    cal["uncertainty"]["camera"] = {"fx": "big", "dist": 3}
    cal["uncertainty"]["T_cam_proj"] = [1, 2]
    cal["diagnostics"]["worst_views"] = [{"capture_id": 7}, "x", {"capture_id": "p0003", "rms_px": "high"}]
    cal["diagnostics"]["rejected"] = 5
    cal["diagnostics"]["board_poses"]["p0000"] = "not a pose"
    cal["per_view"] = [{"capture_id": "p0001", "rms_px": None}]  # (entries that are not objects: refused by the reader)
    cal["rms"] = {"joint": None, "board": 0.05}
    (folder / "calibration.json").write_text(json.dumps(cal))
    html = write_report(folder).read_text()
    assert "<b>joint</b>" not in html and "&lt;b&gt;joint&lt;/b&gt;" in html
    assert 'data-key="camera.fx" data-value="' in html and 'id="recomputed-rms"' in html
    assert "board poses from PnP (calibration.json&#x27;s board poses are unreadable)" in html
    assert 'data-key="worst.p0003" data-value="None">n/a<' in html


def test_a_session_without_calibration_is_a_one_line_error(tmp_path, capsys):
    folder = tmp_path / "s"
    make_store(folder)
    assert main(["report", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "no calibration.json" in err and "procam calibrate" in err
    assert not (folder / "report.html").exists()
    # a malformed calibration.json names the file and the field
    (folder / "calibration.json").write_text('{"camera": 3}')
    assert main(["report", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "calibration.json" in err and "field" in err
    # no session at all; an output that is not an .html file; an output folder that does not exist
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["report", str(folder), "--out", str(folder / "session.json")]) == 2
    assert ".html" in capsys.readouterr().err
    assert main(["report", str(folder), "--out", str(folder / "images" / "r.html")]) == 2
    assert "images folder" in capsys.readouterr().err
    assert json.loads((folder / "session.json").read_text())["format"] == "procam-session"
