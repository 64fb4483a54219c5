"""The session state machine: every transition, refusals with reasons, retakes, going back, the
pre-calibrated camera, and resuming from the manifest. Calibration and verification are stand-ins
here (they are exercised for real in test_station_session.py)."""

import json

import numpy as np
import pytest

from app.station.machine import (
    CALIBRATION,
    CHECK_RIG,
    DONE,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    VERIFICATION,
    ActionRefused,
    Plan,
    RigCheck,
    SessionMachine,
    Target,
)
from calib.formats.session import SessionStore
from calib.models.observations import STEP_PROJECTOR, STEP_REAL_MIRROR, STEP_REAL_VIRTUAL, VIEW_DIRECT
from calib.synthetic import d455_camera
from _station_helpers import TINY, Recorder, make_store

OK = [RigCheck("camera", True, "streaming"), RigCheck("projector", True, "up")]
SMALL = Plan(poses_per_position=2, real_virtual_captures=4, real_mirror_captures=2, min_real_virtual=3,
             min_projector_captures=6)


def machine(tmp_path, view="mirror", plan=SMALL, rec=None, positions=5, verify=True):
    rec = rec or Recorder()
    store = make_store(tmp_path / "s", view, positions)
    m = SessionMachine(store, plan, calibrate_fn=rec.calibrate, verify_fn=rec.verify if verify else None)
    return m, rec


def refused(fn, *args, match=None):
    with pytest.raises(ActionRefused) as e:
        fn(*args)
    assert e.value.reason  # a reason a person can read
    if match:
        assert match in e.value.reason, e.value.reason
    return e.value.reason


def saved_state(m):
    data = json.loads((m.store.folder / "session.json").read_text())
    SessionStore.open(m.store.folder)  # the manifest always loads
    return data["state"]


def fill_mirror(m, n=None):
    for _ in range(n if n is not None else m.target and m.mirror_total - m.counts()["mirror"]):
        m.record_capture(TINY)


def fill_projector(m):
    while m.target is not None:
        m.record_capture(TINY)


def test_complete_mirror_session_walks_every_state(tmp_path):
    m, rec = machine(tmp_path)
    assert m.state == CHECK_RIG
    refused(m.start_session, match="not been checked")
    refused(m.start_session, [RigCheck("camera", False, "no frame in 3 s")], match="camera: no frame")
    refused(m.record_capture, TINY, match="Check the rig")
    refused(m.calibrate, match="after the captures")
    assert m.start_session(OK) == MIRROR_CAPTURE
    assert saved_state(m)["step"] == MIRROR_CAPTURE
    refused(m.record_capture, TINY, match="choose the mirror method")
    refused(m.proceed, match="choose the mirror method")
    m.choose_mirror_method("real-virtual")
    assert m.target == Target(STEP_REAL_VIRTUAL, None, 0)
    for i in range(2):
        m.record_capture(TINY)
    refused(m.proceed, match="at least 3")
    fill_mirror(m, 2)
    assert m.target is None and m.counts()["mirror"] == 4
    refused(m.record_capture, TINY, match="all 4 mirror captures")
    assert m.proceed() == PROJECTOR_CAPTURE
    refused(m.choose_mirror_method, "real-mirror", match="go back")
    # projector: positions in order, poses within each
    seen = []
    while m.target is not None:
        t = m.target
        seen.append((t.pattern_position, t.pose_index))
        cap = m.record_capture(TINY)
        assert cap.pattern_position == t.pattern_position and cap.meta["pose_index"] == t.pose_index
        assert np.allclose(cap.pattern_points_px, m.manifest.pattern.points_px(1920, 1080, t.pattern_position))
        if len(seen) == 3:
            refused(m.proceed, match="3 of 10")
    assert seen == [(p, k) for p in range(5) for k in range(2)]
    refused(m.verify, match="after calibration")
    refused(m.finish)
    assert m.proceed() == CALIBRATION
    refused(m.verify, match="calibrate first")
    m.calibrate()
    assert (m.store.folder / "calibration.json").exists()
    assert rec.calibrations[-1][2] == 14 and rec.calibrations[-1][1] is None
    refused(m.finish, match="verify")
    report = m.verify()
    assert m.state == VERIFICATION and report.passed
    refused(m.delete_capture, "p0000", match="go back to the calibration")
    assert m.finish() == DONE
    st = saved_state(m)
    assert st["step"] == DONE and st["calibrated"] and st["verified"] is True
    refused(m.finish, match="already complete")
    refused(m.proceed, match="complete")


def test_direct_rig_skips_the_mirror_step(tmp_path):
    m, _ = machine(tmp_path, view=VIEW_DIRECT)
    refused(m.choose_mirror_method, "real-virtual", match="no mirror")
    assert m.start_session(OK) == PROJECTOR_CAPTURE
    assert m.target == Target(STEP_PROJECTOR, 0, 0)
    assert m.go_back() == CHECK_RIG
    m.start_session()
    fill_projector(m)
    m.calibrate()  # from the capture step directly
    assert m.state == CALIBRATION and m.result is not None


def test_back_from_every_state(tmp_path):
    m, _ = machine(tmp_path)
    refused(m.go_back, match="first step")
    m.start_session(OK)
    m.choose_mirror_method("real-mirror")
    fill_mirror(m, 2)
    m.proceed()
    fill_projector(m)
    m.calibrate()
    m.verify()
    m.finish()
    path = []
    while True:
        try:
            path.append(m.go_back())
        except ActionRefused:
            break
    assert path == [VERIFICATION, CALIBRATION, PROJECTOR_CAPTURE, MIRROR_CAPTURE, CHECK_RIG]
    # without verification, done goes back to calibration
    m2, _ = machine(tmp_path / "b", verify=False)
    m2.start_session(OK)
    m2.choose_mirror_method("real-mirror")
    fill_mirror(m2, 2)
    m2.proceed()
    fill_projector(m2)
    m2.calibrate()
    refused(m2.verify, match="not available")
    m2.finish()
    assert m2.state == DONE and m2.go_back() == CALIBRATION


def test_retake_and_delete(tmp_path):
    m, rec = machine(tmp_path)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    fill_mirror(m, 4)
    m.proceed()
    fill_projector(m)
    m.calibrate()
    m.verify()
    # retake a projector capture from the verification step: refused, from calibration: allowed
    refused(m.retake, "p0005", match="go back to the calibration")
    m.go_back()
    cap = next(c for c in m.manifest.captures if c.id == "p0005")
    tgt = m.retake("p0005")
    assert m.state == PROJECTOR_CAPTURE
    assert tgt == Target(STEP_PROJECTOR, cap.pattern_position, cap.meta["pose_index"]) == m.target
    assert not (m.store.folder / cap.image).exists()
    assert m.result_stale and m.report is None
    st = saved_state(m)
    assert st["retake"] == tgt.to_dict() and st["result_stale"]
    new = m.record_capture(TINY)
    assert new.pattern_position == cap.pattern_position and new.meta["pose_index"] == cap.meta["pose_index"]
    assert new.meta.get("retake") is True and m.target is None
    # the stale result must be recalibrated before verifying
    m.proceed()
    refused(m.verify, match="calibrate again")
    m.calibrate()
    assert len(rec.calibrations) == 2
    # retaking a mirror capture goes back to the mirror step
    m.retake("mrv0001")
    assert m.state == MIRROR_CAPTURE and m.target == Target(STEP_REAL_VIRTUAL, None, 1)
    m.record_capture(TINY)
    # deleting leaves a hole that the target fills first
    m.delete_capture("mrv0002")
    assert m.target == Target(STEP_REAL_VIRTUAL, None, 2)
    refused(m.delete_capture, "nope", match="no capture 'nope'")
    refused(m.choose_mirror_method, "real-mirror", match="delete them first")
    for c in list(m.mirror_captures()):
        m.delete_capture(c.id)
    m.choose_mirror_method("real-mirror")
    assert m.target == Target(STEP_REAL_MIRROR, None, 0)
    assert json.loads((m.store.folder / "session.json").read_text())["mirror_method"] == "real-mirror"


def test_retake_last_capture_by_default(tmp_path):
    m, _ = machine(tmp_path)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    m.record_capture(TINY)
    last = m.record_capture(TINY)
    tgt = m.retake()
    assert tgt.pose_index == last.meta["pose_index"] == 1
    assert [c.id for c in m.manifest.captures] == ["mrv0000"]


def test_skip_camera_with_an_intrinsics_file(tmp_path):
    m, rec = machine(tmp_path)
    refused(m.skip_camera, str(tmp_path / "missing.json"), match="does not exist")
    wrong = tmp_path / "wrong.json"
    cam = d455_camera()
    wrong.write_text(json.dumps({"camera": dict(cam.to_dict(), width=640, height=400)}))
    refused(m.skip_camera, str(wrong), match="640x400")
    refused(m.skip_camera, "", match="give the path")
    good = tmp_path / "cam.json"
    good.write_text(json.dumps({"camera": cam.to_dict()}))
    m.skip_camera(str(good))
    # what was read is copied into the session, which records the copy (it stands alone)
    copy = m.store.folder / "given_camera.json"
    assert saved_state(m)["camera_intrinsics"] == "given_camera.json"
    assert copy.read_bytes() == good.read_bytes()
    good.unlink()
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    fill_mirror(m, 4)
    m.proceed()
    fill_projector(m)
    m.calibrate()
    assert rec.calibrations[-1][1] == str(copy)
    m.use_camera_calibration()
    assert m.result_stale
    refused(m.use_camera_calibration, match="already calibrated")
    m.calibrate()
    assert rec.calibrations[-1][1] is None


def test_the_panel_reads_only_regular_files_not_through_links(tmp_path):
    """Skip camera step with a path typed in a browser: a folder, a zip, a system file, a link and a
    binary .json are each refused with the rule they break, nothing is recorded or copied."""
    import os
    import zipfile

    m, _ = machine(tmp_path)
    good = tmp_path / "cam.json"
    good.write_text(json.dumps({"camera": d455_camera().to_dict()}))
    (tmp_path / "folder.json").mkdir()
    with zipfile.ZipFile(tmp_path / "packed.json", "w") as z:
        z.writestr("cam.json", good.read_text())
    os.symlink(good, tmp_path / "link.json")
    (tmp_path / "sub").mkdir()
    os.symlink(tmp_path / "sub", tmp_path / "linked")
    (tmp_path / "sub" / "cam.json").write_bytes(good.read_bytes())
    refused(m.skip_camera, str(tmp_path / "folder.json"), match="folder.json: is a folder")
    refused(m.skip_camera, str(tmp_path / "packed.json"), match="is not a text file (a zip?)")
    refused(m.skip_camera, "/etc/passwd", match="/etc/passwd: is not an intrinsics file")
    refused(m.skip_camera, str(tmp_path / "link.json"), match="link.json: goes through the link")
    refused(m.skip_camera, str(tmp_path / "linked" / "cam.json"), match=f"goes through the link {tmp_path / 'linked'}")
    assert m.camera_intrinsics is None and not list(m.store.folder.glob("given_camera*"))


def test_calibration_failure_is_reported_and_can_be_rerun(tmp_path):
    from calib.errors import CalibrationError

    rec = Recorder(fail_calibration="too few projector views (3 usable, need 4)")
    m, _ = machine(tmp_path, view=VIEW_DIRECT, rec=rec)
    m.start_session(OK)
    refused(m.calibrate, match="at least 6 projector captures first (0 so far)")
    fill_projector(m)
    with pytest.raises(CalibrationError):
        m.calibrate()
    assert m.state == CALIBRATION and m.result is None and "too few" in m.calibration_error
    assert m.busy is None
    refused(m.verify, match="calibrate first")
    rec.fail_calibration = None
    m.calibrate()
    assert m.result is not None and m.calibration_error is None


def test_resume_restores_where_the_session_stopped(tmp_path):
    m, rec = machine(tmp_path)
    m.start_session(OK)
    m.choose_mirror_method("real-virtual")
    fill_mirror(m, 4)
    m.proceed()
    for _ in range(3):
        m.record_capture(TINY)
    before = m.target
    store = SessionStore.open(m.store.folder)
    m2 = SessionMachine.from_store(store, calibrate_fn=rec.calibrate, verify_fn=rec.verify)
    assert m2.state == PROJECTOR_CAPTURE and m2.mirror_method == "real-virtual"
    assert m2.target == before == Target(STEP_PROJECTOR, 1, 1)
    assert m2.plan == SMALL
    fill_projector(m2)
    m2.calibrate()
    m2.retake("p0002")
    m3 = SessionMachine.from_store(SessionStore.open(m.store.folder), calibrate_fn=rec.calibrate,
                                   verify_fn=rec.verify)
    assert m3.state == PROJECTOR_CAPTURE and m3.retake_target == Target(STEP_PROJECTOR, 1, 0)
    assert m3.result is not None and m3.result_stale


def test_available_actions_name_a_reason_for_each_refusal(tmp_path):
    m, _ = machine(tmp_path)
    m.start_session(OK)
    avail = m.available()
    assert avail["choose_mirror_method"] is None and avail["back"] is None
    for action in ("start", "capture", "proceed", "calibrate", "verify", "finish"):
        assert isinstance(avail[action], str) and len(avail[action]) > 10, action
    m.busy = "calibrating"
    assert "busy" in m.why_not("back")
    refused(m.go_back, match="busy")


def test_board_thickness_for_the_real_mirror_method(tmp_path):
    m, _ = machine(tmp_path)
    refused(m.set_board_thickness, -1, match="0 or more")
    refused(m.set_board_thickness, "thick", match="must be a number")
    m.start_session(OK)
    m.choose_mirror_method("real-mirror")
    m.set_board_thickness(3.0)
    assert SessionStore.open(m.store.folder).manifest.board_thickness == 3.0
    fill_mirror(m, 2)
    m.proceed()
    fill_projector(m)
    m.calibrate()
    m.set_board_thickness(2.5)  # changes the mirror plane: the calibration is out of date
    assert m.result_stale
    m.calibrate()
    m.verify()
    refused(m.set_board_thickness, 2.0, match="go back")


def test_rerun_calibration_and_verification_from_later_states(tmp_path):
    m, rec = machine(tmp_path, view=VIEW_DIRECT)
    m.start_session(OK)
    fill_projector(m)
    refused(m.finish, match="after calibration and verification")
    m.calibrate()
    refused(m.finish, match="verify the calibration first")
    m.verify()
    m.verify()  # verification again, in the verification step
    assert m.state == VERIFICATION and len(rec.verifications) == 2
    m.calibrate()  # re-run from the verification step: back to calibration, the old report is dropped
    assert m.state == CALIBRATION and m.report is None and len(rec.calibrations) == 2
    m.verify()
    m.finish()
    m.calibrate()  # and from the end of the session
    assert m.state == CALIBRATION and len(rec.calibrations) == 3
    assert saved_state(m)["verified"] is None


def test_real_mirror_needs_three_placements(tmp_path):
    """The default plan asks for at least 3 placements of the board on the mirror before going on (one
    leaves the mirror's tilt to a single board: benchmarks/real_mirror_placements.py); a plan asking for
    fewer captures in all needs only those."""
    assert Plan().min_mirror("real-mirror") == 3 and Plan().min_mirror("real-virtual") == 3
    assert Plan(real_mirror_captures=2).min_mirror("real-mirror") == 2
    m, _ = machine(tmp_path, plan=Plan(poses_per_position=2, real_mirror_captures=5, min_projector_captures=6))
    m.start_session(OK)
    m.choose_mirror_method("real-mirror")
    fill_mirror(m, 2)
    refused(m.proceed, match="take at least 3 real-mirror captures first (2 so far)")
    fill_mirror(m, 1)
    m.proceed()
    assert m.state == PROJECTOR_CAPTURE
