"""The projector step's 1-sigmas against their targets in the panel, in a real Chromium (Debian's, through
playwright): a simulated station stopping on confidence (--stop-on-confidence, --auto, one pose per
pattern position, 3 mirror captures, --ask-pose) judges the step after each detected projector capture
and says the pose it asks for next; once the
step has ended and the session is calibrated, the panel's checklist shows every quantity the step
constrains with a measured 1-sigma and its target, which must be calib.quality.confidence's targets and
the 1-sigmas of the calibration of the same captures (calibration.json); the mirror step's normal the
same way, and the board placements session.json records."""

import re

import pytest
from playwright.sync_api import expect, sync_playwright

from calib.formats.session import SessionStore
from calib.formats.session_captures import placements
from calib.formats.session_files import CALIBRATION
from calib.models.result import CalibrationResult
from calib.models.vocab import Step
from calib.quality.confidence import confidence_of, targets
from _station_helpers import StationProcess, launch_chromium

pytestmark = [pytest.mark.browser, pytest.mark.slow]

#: one checklist line of a quantity with a measured 1-sigma: label, sigma, unit, target, " not yet"?
LINE = r"({label}): ([0-9][0-9.e+-]*) ({unit}) \(target ([0-9.e+-]+)\)( not yet)?"
#: (label, unit) of the projector step's quantities, as calib.quality.confidence names them
QUANTITIES = {"t_mm": ("projector position", "mm"), "rot_deg": ("projector orientation", "deg"),
              "projector_intrinsics_px": ("projector fx, fy, cx, cy", "px"),
              "camera_intrinsics_px": ("camera fx, fy, cx, cy", "px"),
              "projection_projector_max_px": ("projector over its image", "px"),
              "projection_camera_max_px": ("camera over its image", "px")}


def test_the_panel_shows_each_1_sigma_of_the_projector_step_against_its_target(tmp_path):
    folder = tmp_path / "session"
    st = StationProcess("--rig", "sim", "--auto", "--stop-on-confidence", "--ask-pose", "--poses-per-position", "1",
                        "--mirror-captures", "3", "--session", str(folder))
    goal = targets(Step.PROJECTOR)
    try:
        with sync_playwright() as p:
            browser = launch_chromium(p)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(st.url)
            # the checklist says the plan's count is a maximum
            expect(page.get_by_text(re.compile(r"at most: ends when confident")).first).to_be_visible()
            # wait on state: a measured (numeric) 1-sigma of the projector's position, i.e. a confidence
            # computed from a calibration of the captures so far (before the minimum there is only "-")
            first = LINE.format(label=QUANTITIES["t_mm"][0], unit="mm")
            expect(page.get_by_text(re.compile(first)).first).to_be_visible()
            # with a calibration of the captures so far known, the whole pose asked for next is said (its
            # outline dashed on the camera image, its position on the projector's map) until the step ends
            asked = r"Asked pose: a board at pattern position ([0-9]+), held at the pose shown, leaves the worst predicted"
            node = page.get_by_text(re.compile(asked)).first
            expect(node).to_be_visible()
            chosen = int(re.search(asked, node.inner_text()).group(1)) - 1
            # then the step's end: the captures are calibrated (the last judgement is of every capture)
            expect(page.get_by_text(re.compile(r"Calibration.*: done")).first).to_be_visible()
            shown = {}
            for key, (label, unit) in QUANTITIES.items():
                pattern = LINE.format(label=re.escape(label), unit=unit)
                node = page.get_by_text(re.compile(pattern)).first
                expect(node).to_be_visible()
                m = re.search(pattern, node.inner_text())
                shown[key] = m.groups()
            # the mirror step's own quantity, judged by the same calibrations, and the board placements
            mirror_pattern = LINE.format(label="mirror normal", unit="deg")
            node = page.get_by_text(re.compile(mirror_pattern)).first
            expect(node).to_be_visible()
            shown_mirror = re.search(mirror_pattern, node.inner_text()).groups()
            node = page.get_by_text(re.compile(r"Board placements so far: [0-9]+")).first
            expect(node).to_be_visible()
            shown_placements = int(re.search(r"Board placements so far: ([0-9]+)", node.inner_text()).group(1))
            page.screenshot(path=str(tmp_path / "confidence.png"))
            browser.close()
    finally:
        st.stop()
    for key, (label, sigma, unit, target, not_yet) in shown.items():
        # the target is calib.quality.confidence's, as the checklist formats it
        assert target == f"{goal[key]:.3g}", (key, target, goal[key])
        # met or "not yet" follows the numbers shown
        assert (not_yet is None) == (float(sigma) <= float(target)), (key, sigma, target, not_yet)
    # the numbers are the station's own: those of the calibration of the step's captures
    result = CalibrationResult.load_json(folder / CALIBRATION)
    expected = {q.key: q.line() for q in confidence_of(result, Step.PROJECTOR).quantities}
    for key, (label, sigma, unit, target, not_yet) in shown.items():
        assert expected[key] == f"{label}: {sigma} {unit} (target {target}){not_yet or ''}", (key, expected[key])
    label, sigma, unit, target, not_yet = shown_mirror
    mirror = confidence_of(result, Step.REAL_VIRTUAL).quantities[0]
    assert mirror.line() == f"{label}: {sigma} {unit} (target {target}){not_yet or ''}", mirror.line()
    # one placement per capture of this circle session: the count session.json's captures give
    store = SessionStore.open(folder)
    assert shown_placements == placements(store.manifest.captures) == len(store.manifest.captures)
    # the asked pose's position shown was captured, after the plan's first ones (no calibration before them)
    proj = [c.pattern_position for c in store.manifest.captures if c.step == Step.PROJECTOR]
    assert chosen in proj[6:], (chosen, proj)
