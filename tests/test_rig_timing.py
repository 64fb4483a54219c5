"""The simulated rig behaves like the hardware (projector latency, the camera's own frame clock, blended
frames, auto exposure, flicker, the IR emitter), and the station and the verification only use frames
that show what they asked for: checked against the simulator's own record of what was on the
projector during each frame's exposure (SimRig.frame_truth)."""

import subprocess
import sys

import numpy as np
import pytest

from _station_helpers import tick_until_projector_captures
from app.station.machine import Plan
from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
from app.station.station import Station, StationOptions
from app.verification import Grabber, verify
from calib.models.observations import STEP_PROJECTOR
from drivers.exposure import MAX_FRAMES, search_exposure
from drivers.settle import apply_timing
from drivers.sim.hardware import REFERENCE_EXPOSURE_US
from drivers.sim.render import decode_gamma
from drivers.sim.rig import open_sim_rig

PERIOD_US = 1e6 / 60.0
QUIET = dict(read_noise_dn=0.0, electrons_per_dn=0.0)  # no noise: pixel differences are the model's


def _white(rig):
    W, H = rig.projector.size
    return np.full((H, W), 255, np.uint8)


def _frames(rig, n, after=None):
    f = rig.camera.get_frame(newer_than=after)
    out = [f]
    for _ in range(n - 1):
        f = rig.camera.get_frame(newer_than=f.frame_number)
        out.append(f)
    return out


def _lag_s(rig) -> float:
    """How long after a change of exposure or gain the frames still show the old settings."""
    return rig.hardware.settings_lag_frames * rig.hardware.period_s


def _pure(rig, frame_number, ticket) -> bool:
    """The frame saw only the image of `ticket`, for its whole exposure."""
    return rig.frame_truth[frame_number] == ((int(ticket), 1.0),)


# ---- the devices ------------------------------------------------------------------------------------
def test_frames_follow_the_camera_clock_and_never_come_from_the_future():
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0)
    rig.camera.start()
    f = rig.camera.get_frame()
    for _ in range(5):
        g = rig.camera.get_frame(newer_than=f.frame_number)
        returned = rig.clock.now()
        assert g.frame_number > f.frame_number
        # frame n is exposed from t0 + n / 30 s and delivered a frame period later, not before
        assert g.exposure_start_s - f.exposure_start_s == pytest.approx((g.frame_number - f.frame_number) / 30.0)
        assert g.exposure_start_s + 1 / 30.0 <= returned + 1e-6
        f = g
    far = rig.camera.get_frame(newer_than=f.frame_number + 5)  # waits for that frame's time
    assert far.frame_number == f.frame_number + 6 and far.exposure_start_s + 1 / 30.0 <= rig.clock.now() + 1e-6
    rig.camera.stop()
    rig.camera.start()  # a restarted clock goes on numbering: a frame number is never handed out twice
    again = rig.camera.get_frame()
    assert again.frame_number > far.frame_number and again.exposure_start_s > far.exposure_start_s


def test_the_projector_shows_an_image_only_after_its_latency_and_frames_blend_the_change(monkeypatch):
    import drivers.sim.rig as R

    monkeypatch.setattr(R, "FRAME_QUEUE", 1000)  # a driver that queues every frame: none is skipped
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=100.0, ambient=0.2, projector_gain=0.2, **QUIET)
    cam, proj = rig.camera, rig.projector
    cam.start()
    cam.set_manual_exposure(2 * PERIOD_US, 1.0)  # long exposures: one of them spans the change
    cam.set_emitter(False)
    rig.operator.request_pose("verification", None, 0)
    _frames(rig, 3)  # the settings apply from the next frames on
    assert proj.refresh_hz == 60.0
    t_req = rig.clock.now()
    ticket = proj.show(_white(rig))
    swap = proj.wait_presented(ticket)  # settle_s 0: the presentation (vsync), not the visibility
    visible = proj.true_visible_s(ticket)
    assert t_req <= swap < t_req + 1 / 60.0 + 1e-3 and 0.096 <= visible - swap <= 0.104
    seen = _frames(rig, 10, after=rig.camera.get_frame().frame_number)
    before = [f for f in seen if f.exposure_start_s + 2 * PERIOD_US * 1e-6 <= visible]
    after = [f for f in seen if f.exposure_start_s >= visible]
    done = {f.frame_number for f in before + after}
    spanning = [f for f in seen if f.frame_number not in done]
    assert before and after and spanning
    assert all(rig.frame_truth[f.frame_number] == ((0, 1.0),) for f in before)
    assert all(_pure(rig, f.frame_number, ticket) for f in after)
    for f in spanning:  # the fractions are the parts of the exposure each image was visible
        (t0, a), (t1, b) = rig.frame_truth[f.frame_number]
        assert (t0, t1) == (0, ticket) and a + b == pytest.approx(1.0)
        exposure_s = f.meta["exposure_us"] * 1e-6
        assert b == pytest.approx((f.exposure_start_s + exposure_s - visible) / exposure_s)
        dark, lit = before[-1].image.astype(float).mean(), after[0].image.astype(float).mean()
        assert lit - dark > 2 and max(f.image.max(), after[0].image.max()) < 254  # nothing clipped
        assert f.image.astype(float).mean() == pytest.approx(a * dark + b * lit, abs=0.3)


def test_auto_exposure_drifts_until_locked():
    # the board clamped still: locked frames are compared pixel for pixel (a stand's microns of vibration
    # would change pixels)
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0, hold="still", **QUIET)
    rig.camera.start()
    rig.camera.set_emitter(False)
    rig.operator.request_pose("verification", None, 0)
    drifting = _frames(rig, 6)
    assert all(f.meta["auto_exposure"] for f in drifting)
    assert len({round(f.meta["exposure_us"]) for f in drifting}) >= 3  # it keeps moving
    assert len({round(float(f.image.mean()), 2) for f in drifting}) >= 3
    t = rig.clock.now()
    applied = rig.camera.set_manual_exposure(PERIOD_US, 1.0)
    assert applied == {"exposure_us": round(PERIOD_US), "gain": 1.0}
    locked = [f for f in _frames(rig, 10) if f.exposure_start_s >= t + _lag_s(rig)]
    assert len(locked) >= 3
    assert {f.meta["exposure_us"] for f in locked} == {round(PERIOD_US)} and not any(f.meta["auto_exposure"] for f in locked)
    assert all(np.array_equal(locked[0].image, f.image) for f in locked[1:])  # no drift any more


@pytest.mark.parametrize("faults", [(), ("flicker",)])
def test_global_shutter_flicker_for_an_exposure_off_the_refresh_period_only(faults):
    """The D455's colour sensor has a global shutter: an exposure off a whole number of refresh periods
    makes the whole frame's projector light brighter or darker, from frame to frame (the flicker's phase
    drifts slowly; under the flicker fault any phase at any frame), never bands across the image."""
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0, ambient=0.2, projector_gain=0.2, faults=faults,
                       hold="still", **QUIET)  # still: the frames' light is compared pixel for pixel
    cam = rig.camera
    cam.start()
    cam.set_emitter(False)
    rig.operator.request_pose("verification", None, 0)

    def frames_at(exposure_us, image, n=6):
        rig.projector.show(image)
        t = rig.clock.now()
        cam.set_manual_exposure(exposure_us, 1.0)
        fs = [f for f in _frames(rig, n + 6) if f.exposure_start_s >= t + _lag_s(rig)][-n:]
        # ratios of light: undo the camera's tone curve (docs/SIMULATOR.md)
        return [255.0 * decode_gamma(f.image[:, :, 0].astype(np.float64) / 255.0, rig.settings.camera_gamma)
                for f in fs], fs

    W, H = rig.projector.size
    dark = frames_at(PERIOD_US, np.zeros((H, W), np.uint8))[0][-1]  # the room's light alone
    lit_ref = frames_at(PERIOD_US, _white(rig))[0][-1]
    proj = lit_ref - dark  # the projector's light at one period
    lit = proj > 0.3 * proj.max()
    rows = lit.sum(axis=1) > 20
    assert lit.sum() > 2000

    def row_factors(img, periods):
        """Per row: the share of the projector's light the frame caught, relative to one period's."""
        k = np.where(lit, (img - periods * dark) / (periods * np.maximum(proj, 1e-6)), np.nan)
        return np.nanmean(k[rows], axis=1)

    whole, whole_frames = frames_at(2 * PERIOD_US, _white(rig))
    off, off_frames = frames_at(1.5 * PERIOD_US, _white(rig))
    assert whole_frames[0].meta["flicker_amplitude"] == 0.0 and off_frames[0].meta["flicker_amplitude"] > 0.05
    # every row of a frame catches the same share (no bands), at any exposure
    for img, periods in [(i, 2.0) for i in whole] + [(i, 1.5) for i in off]:
        assert np.ptp(row_factors(img, periods)) < 0.03
    # a whole number of periods: the same light in every frame
    assert all(np.array_equal(whole_frames[0].image, f.image) for f in whole_frames[1:])
    caught = [float(np.median(row_factors(img, 1.5))) for img in off]
    assert caught == pytest.approx([f.meta["flicker_factor"] for f in off_frames], abs=0.02)
    if faults:  # off a whole number: frame to frame the frame catches another share
        assert max(caught) - min(caught) > 0.1
    else:  # a slow drift (the clocks beat by 0.06 Hz): a steady offset over a few frames
        assert max(caught) - min(caught) < 0.02


def test_the_exposure_search_meters_the_brightest_of_flickering_frames():
    """A projector so bright that even one refresh period saturates at the lowest gain: the search must
    go below a period, where the frames flicker at any phase; the frames after it must not saturate."""
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0, ambient=0.05, projector_gain=6.0,
                       faults=("flicker",))
    cam = rig.camera
    cam.start()
    cam.set_emitter(False)
    rig.operator.request_pose("projector", 6, 0)
    W, H = rig.projector.size
    rig.projector.show(rig.scenario.pattern.render(W, H, 6)[0])
    rig.clock.sleep(0.3)
    c = search_exposure(cam, rig.projector.refresh_hz)
    assert not c.whole_periods and c.periods < 1 and c.flicker > 0.03, c
    fs = _frames(rig, 30)
    assert len({round(f.meta["flicker_factor"], 3) for f in fs}) > 10  # they do flicker
    tops = [float(np.percentile(f.image.max(axis=2), 99.99)) for f in fs]
    assert max(tops) <= 250 and min(tops) >= 100, (min(tops), max(tops))


def test_the_emitter_adds_dots_until_turned_off():
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0, **QUIET)
    cam = rig.camera
    cam.start()
    cam.set_manual_exposure(PERIOD_US, 1.0)
    t = rig.clock.now()
    on = [f for f in _frames(rig, 7) if f.exposure_start_s >= t + _lag_s(rig)][-1]
    assert on.meta["emitter_enabled"] is True
    t = rig.clock.now()
    cam.set_emitter(False)
    off = [f for f in _frames(rig, 7) if f.exposure_start_s >= t + _lag_s(rig)][-1]
    assert off.meta["emitter_enabled"] is False
    d = on.image[:, :, 0].astype(int) - off.image[:, :, 0].astype(int)
    assert (d > 15).sum() > 1000 and (d < -2).sum() == 0  # bright specks only, all over the image
    ys, xs = np.nonzero(d > 15)
    assert np.ptp(xs) > 1000 and np.ptp(ys) > 600


# ---- the exposure search ------------------------------------------------------------------------------
@pytest.mark.parametrize("light", [1.0, 0.2])
def test_exposure_search_converges_on_whole_refresh_periods(light):
    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=80.0, ambient=0.5 * light, projector_gain=0.5 * light)
    cam = rig.camera
    cam.start()
    cam.set_emitter(False)
    rig.operator.request_pose("projector", 6, 0)
    W, H = rig.projector.size
    rig.projector.show(rig.scenario.pattern.render(W, H, 6)[0])
    rig.clock.sleep(0.3)  # the pattern is visible
    c = search_exposure(cam, rig.projector.refresh_hz)
    assert c.frames <= MAX_FRAMES
    assert c.whole_periods and abs(c.periods - round(c.periods)) < 1e-3 and round(c.periods) >= 1
    assert c.exposure_us == pytest.approx(round(c.periods) * PERIOD_US, abs=1.0)
    f = _frames(rig, 4)[-1]
    assert f.meta["auto_exposure"] is False and f.meta["exposure_us"] == c.exposure_us
    top = np.percentile(f.image[:, :, 1], 99.99)
    assert 120 <= top <= 245 and (f.image >= 254).mean() < 1e-4  # the lit board bright, not saturated
    if light == 1.0:
        assert c.gain == 1.0  # no gain when the light suffices
    else:
        # dim: the longest whole-period exposure, and only then gain
        assert c.exposure_us * c.gain > REFERENCE_EXPOSURE_US


# ---- the station and the verification use only frames showing what they asked for ---------------------
SMALL = Plan(poses_per_position=1, real_virtual_captures=2, min_real_virtual=2, min_projector_captures=3)


@pytest.mark.parametrize("latency_ms", [0.0, 50.0, 150.0])
def test_no_capture_and_no_verification_frame_shows_another_image(tmp_path, latency_ms):
    req = RigRequest("sim", "nonoverlap-136", 0)
    rig = open_requested_rig(req, latency_ms=latency_ms)
    store = create_session(tmp_path / "s", rig, req, SMALL)
    m = make_machine(store, rig, SMALL)
    st = Station(rig, m, StationOptions(auto=False, follow_operator=True, auto_capture=True))
    checks = st.check_rig()
    assert all(c.ok for c in checks), checks
    cs = m.manifest.rig.camera_settings
    assert cs["auto_exposure"] is False and cs["emitter_enabled"] is False
    assert cs["exposure_us"] == pytest.approx(PERIOD_US, abs=1.0)  # one refresh period at 60 Hz
    true_max_ms = max(rig.projector.timeline.latency_s(t) for t in range(1, rig.projector.ticket + 1)) * 1000
    assert cs["projector"]["refresh_hz"] == 60.0
    assert true_max_ms <= cs["projector"]["latency_ms"] <= true_max_ms + 90
    tick_until_projector_captures(st, m, 3)
    caps = m.manifest.captures
    assert len(m.captures_of(STEP_PROJECTOR)) >= 3
    for c in caps:
        fn, ticket = c.meta["frame_number"], c.meta["projector_ticket"]
        assert _pure(rig, fn, ticket), (c.id, rig.frame_truth[fn], ticket)
        want = st.pattern_image(c.pattern_position) if c.step == STEP_PROJECTOR else st._black()
        assert np.array_equal(rig.projector.timeline.image_of(ticket), want)
        assert c.meta["exposure_start_s"] >= rig.projector.true_visible_s(ticket)
    # the verification's frames (references and curves) each saw only the image shown for it
    rig.operator.request_pose("verification", None, 0)
    rep = verify(rig.camera, rig.projector, None, rig.ground_truth(), grid=(3, 2))
    assert rep.passed, rep.summary()
    frames = rep.settings["frames"]
    assert len(frames) == rep.settings["projector_images"] >= 3
    assert len({t for _, t in frames}) == len(frames)
    for fn, ticket in frames:
        assert _pure(rig, fn, ticket), (fn, rig.frame_truth[fn], ticket)


def test_grabber_takes_the_first_frame_after_the_image_became_visible():
    rig = open_sim_rig("nonoverlap-136", seed=1, latency_ms=120.0)
    rig.camera.start()
    rig.operator.request_pose("verification", None, 0)
    apply_timing(rig.camera, rig.projector)
    assert rig.projector.settle_s >= 0.12
    g = Grabber(rig.camera, rig.projector)
    W, H = rig.projector.size
    for v in (255, 0, 128, 255):
        g.grab(np.full((H, W), v, np.uint8))
    assert len(g.seen) == 4
    for fn, ticket in g.seen:
        assert _pure(rig, fn, ticket)
        visible_s = rig.projector.timeline.swaps[ticket] + rig.projector.settle_s  # what wait_presented said
        assert rig.camera.exposure_start_s(fn) >= visible_s


def test_sim_latency_option_is_checked():
    out = subprocess.run([sys.executable, "-m", "app", "session", "--rig", "sim", "--auto", "--sim-latency-ms", "-5",
                          "--out", "/nonexistent/never"], capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "--sim-latency-ms must be between 0 and 2000 ms" in out.stderr + out.stdout


def test_resume_reapplies_the_recorded_exposure_and_latency(tmp_path):
    req = RigRequest("sim", "nonoverlap-136", 0)
    rig = open_requested_rig(req, latency_ms=70.0)
    store = create_session(tmp_path / "s", rig, req, SMALL)
    st = Station(rig, make_machine(store, rig, SMALL))
    assert all(c.ok for c in st.check_rig())
    rec = store.manifest.rig.camera_settings
    assert rig.projector.settle_s == pytest.approx(rec["projector"]["latency_ms"] / 1000.0, abs=1e-6)
    # a new process: fresh devices (auto exposure, emitter on, latency unknown), the session from disk
    from calib.formats.session import SessionStore

    rig2 = open_requested_rig(req, latency_ms=70.0)
    assert rig2.projector.settle_s == 0.0 and rig2.camera.settings_timeline.current["auto_exposure"]
    store2 = SessionStore.open(tmp_path / "s")
    st2 = Station(rig2, make_machine(store2, rig2, SMALL, resume=True))
    checks = {c.name: c for c in st2.check_rig()}
    assert "re-applied" in checks["camera exposure"].detail and "re-applied" in checks["projector latency"].detail
    assert rig2.projector.settle_s == pytest.approx(rec["projector"]["latency_ms"] / 1000.0, abs=1e-9)
    cur = rig2.camera.settings_timeline.current
    assert cur["auto_exposure"] is False and cur["emitter_enabled"] is False
    assert (cur["exposure_us"], cur["gain"]) == (rec["exposure_us"], rec["gain"])
    assert rig2.projector.ticket <= 2  # nothing measured again: at most black shown
    assert SessionStore.open(tmp_path / "s").manifest.rig.camera_settings == rec


def test_recorded_timing_from_a_hostile_manifest_counts_as_not_recorded():
    """rig.camera_settings comes from an untrusted session.json: an exposure, gain or latency that is not
    a finite, non-negative number is not re-applied (the station and `procam verify` search or measure
    instead) and never raises."""
    from drivers.settle import recorded_exposure, recorded_latency_s

    good = {"auto_exposure": False, "exposure_us": 16667.0, "gain": 2.0, "projector": {"latency_ms": 85.5}}
    assert recorded_exposure(good) == (16667.0, 2.0)
    assert recorded_latency_s(good) == pytest.approx(0.0855)
    assert recorded_exposure({"auto_exposure": False, "exposure_us": 8000}) == (8000.0, 1.0)  # gain defaults
    for bad in ({**good, "auto_exposure": True}, {**good, "exposure_us": "16667"}, {**good, "gain": "x"},
                {**good, "exposure_us": float("nan")}, {**good, "gain": float("inf")}, {**good, "exposure_us": -5},
                {**good, "exposure_us": True}, {}, None, "settings"):
        assert recorded_exposure(bad) is None, bad
    for bad in ({"projector": {"latency_ms": "85"}}, {"projector": {"latency_ms": -1}}, {"projector": 85},
                {"projector": {"latency_ms": float("nan")}}, {}, None, []):
        assert recorded_latency_s(bad) is None, bad


# ---- settings reach the frames late, and the waits know it ---------------------------------------------
def test_a_setting_shows_only_after_the_sensors_lag_and_the_wait_reads_it_from_the_frames(caplog):
    from drivers.exposure import apply_exposure, frames_after_change

    rig = open_sim_rig("nonoverlap-136", seed=0, latency_ms=0.0, **QUIET)
    cam = rig.camera
    cam.start()
    assert rig.hardware.settings_lag_frames >= 2  # a D455 needs a few frames
    applied, _ = apply_exposure(cam, 4000.0, 1.0)
    last = _frames(rig, 1)[0].frame_number
    t = rig.clock.now()
    new = cam.set_manual_exposure(8000.0, 2.0)
    seen = _frames(rig, 8, after=last)
    after_t = [f for f in seen if f.exposure_start_s >= t]
    old = [f for f in after_t if f.meta["exposure_us"] == applied["exposure_us"]]
    assert old and all(f.meta["gain"] == 1.0 for f in old)  # exposed after the change, taken with the old settings
    assert all(f.exposure_start_s < t + _lag_s(rig) for f in old)
    from drivers.exposure import shows_settings

    assert shows_settings(old[0], {"exposure_us": applied["exposure_us"], "gain": 1.41}) is False  # a gain step
    assert shows_settings(old[0], applied) is True
    # the wait counts only frames whose metadata shows the change, though earlier ones started after it
    last = seen[-1].frame_number
    t = rig.clock.now()
    got = cam.set_manual_exposure(2000.0, 1.0)
    f, _, counted = frames_after_change(cam, t, got, last, wait_frames=1)
    assert counted == 1 and f.meta["exposure_us"] == 2000.0 and f.exposure_start_s >= t + _lag_s(rig) - 1e-6

    class Lying:  # a camera whose metadata never reports the settings set: the frame times decide
        def __init__(self, cam):
            self.cam = cam

        def get_frame(self, timeout_s=2.0, newer_than=None):
            from dataclasses import replace

            g = self.cam.get_frame(timeout_s, newer_than)
            return replace(g, meta={**g.meta, "gain": 99.0})

    lying = Lying(cam)
    last = lying.get_frame().frame_number
    t = rig.clock.now()
    got = cam.set_manual_exposure(3000.0, 1.0)
    with caplog.at_level("WARNING"):
        f, _, counted = frames_after_change(lying, t, got, last, wait_frames=1, skip_limit=3)
    assert counted == 1 and "report settings other than those set" in caplog.text
