"""The rig check: camera streaming at the session's size, the projector window presenting, the camera's
exposure searched and its response measured, the projector's latency measured, the boards and the
pattern usable. One `RigChecker(station).run()` per check; its findings go to the session machine.

The checker works on the station's devices and its frame bookkeeping (which frames count after a
change), so it is given the station, and it is the only module besides the station that moves them.
"""

from __future__ import annotations

import logging

import numpy as np

from app.station.activity import CHECK_RIG_NAME
from app.station.machine import RigCheck
from calib.errors import ProcamError, SpecError
from calib.models.observations import VIEW_MIRROR
from drivers.errors import DeviceError, ExposureUnsupported, StreamReset
from calib.models.vocab import Step

_log = logging.getLogger("procam.station")

#: where the rig check keeps the frames it used, at reduced size, with their metadata (drivers/evidence.py)
RIG_CHECK_FOLDER = "rig_check"


def stream_findings(camera) -> str | None:
    """What the rig check says of a camera's stream: frames lost on the way (gaps in the device's frame
    numbers: USB drops) and stalled streams reset; None for a camera that does not count them."""
    try:
        frames = (camera.settings() or {}).get("frames")
    except (DeviceError, ProcamError):
        return None
    if not isinstance(frames, dict) or "gaps" not in frames:
        return None
    text = f"{frames.get('accepted', 0)} frames"
    if frames["gaps"]:
        gaps = frames["gaps"]
        text += (f", {frames.get('missing', 0)} lost in {gaps} gap{'s' if gaps != 1 else ''} of the frame numbers "
                 "(USB drops: a shorter cable, a USB 3 port without a hub)")
    else:
        text += ", no frame lost"
    if frames.get("resets"):
        text += f", the stream stalled and was reset ({frames['resets']}x)"
    return text



class RigChecker:
    """One check of the station's rig (Station.check_rig runs it inside its activity)."""

    def __init__(self, station):
        self.station = station

    def _rig_stage(self, line: str) -> None:
        self.station.activities.progress(CHECK_RIG_NAME, line)

    def _first_frame(self):
        """The camera's first frame. A stream the driver found stalled and reset (StreamReset: it streams
        again) is asked once more, as the driver asks its callers to: a stall it recovered from is not a
        camera that fails (the stream line reports the reset)."""
        cam = self.station.rig.camera
        try:
            return cam.get_frame(timeout_s=self.station.options.frame_timeout_s)
        except StreamReset:
            return cam.get_frame(timeout_s=self.station.options.frame_timeout_s)

    def run(self) -> list[RigCheck]:
        """The findings of every stage, in order; the machine records them (set_rig_checks)."""
        man = self.station.machine.manifest
        checks = []
        try:
            f = self._first_frame()
            h, w = f.image.shape[:2]
            ok = (w, h) == tuple(man.rig.camera_size)
            checks.append(RigCheck("camera", ok, f"{w}x{h} frames streaming" if ok else
                                   f"frames are {w}x{h}, the session expects {man.rig.camera_size[0]}x"
                                   f"{man.rig.camera_size[1]}"))
            note = getattr(self.station.rig.camera, "link_note", None)  # a RealSense on USB 2, or another mode
            note = note() if callable(note) else None
            if note:
                checks.append(RigCheck("camera link", True, note))
            self.station.frames.seen(f.frame_number)
        except DeviceError as e:
            checks.append(RigCheck("camera", False, str(e)))
        try:
            self._rig_stage("projector: showing a black image")
            self.station._show(self.station._black())
            self.station._shown = ("black",)
            pw, ph = self.station.rig.projector.size
            ok = (pw, ph) == tuple(man.rig.projector_size)
            checks.append(RigCheck("projector", ok, f"{pw}x{ph} window presents images" if ok else
                                   f"window is {pw}x{ph}, the session expects {man.rig.projector_size}"))
        except (DeviceError, ProcamError) as e:
            checks.append(RigCheck("projector", False, str(e)))
        if all(c.ok for c in checks):
            checks.extend(self._check_timing())
            stream = stream_findings(self.station.rig.camera)
            if stream is not None:
                checks.append(RigCheck("camera stream", True, stream))
        checks.append(RigCheck("projector board", True, str(man.projector_board)))
        if man.rig.view == VIEW_MIRROR:
            checks.append(RigCheck("mirror board", man.mirror_board is not None,
                                   str(man.mirror_board) if man.mirror_board else "no mirror board given"))
        try:
            man.pattern.offsets(*man.rig.projector_size)
            p = man.pattern
            checks.append(RigCheck("pattern", True, f"{p.cols}x{p.rows} {p.kind}, {p.positions} positions"))
        except SpecError as e:
            checks.append(RigCheck("pattern", False, str(e)))
        self.station.machine.set_rig_checks(checks)
        return checks

    def _check_timing(self) -> list[RigCheck]:
        """Rig check, camera and projector timing: the emitter off; the exposure searched in manual mode
        while the pattern lights the board (drivers/exposure.py); the projector's latency measured
        (drivers/settle.py). Both are recorded in the manifest (rig.camera_settings) and, when recorded
        already (a resumed session), re-applied instead of measured again."""
        from dataclasses import replace as _replace

        from drivers.evidence import FrameRecorder

        man = self.station.machine.manifest
        cam, proj = FrameRecorder(self.station.rig.camera), self.station.rig.projector  # the check's frames, kept (rig_check/)
        recorded = dict(man.rig.camera_settings or {})
        timing = dict(recorded.get("projector") or {})
        checks = []
        settings = dict(recorded)
        if self.station.is_sim:  # the simulated person holds the board in the projector's light
            self.station.rig.operator.request_pose(Step.VERIFICATION, None, 0)
        try:
            return self._timing_checks(cam, proj, man, recorded, timing, settings, checks)
        finally:
            if self.station.is_sim:
                self.station.rig.operator.move_out()
            self.station._show(self.station._black())
            self.station._shown = ("black",)
            self.station.frames.changed()
            if settings != recorded:
                self.station.machine.store.update(rig=_replace(man.rig, camera_settings=settings))
            try:
                cam.write(self.station.machine.store.folder / RIG_CHECK_FOLDER)
            except OSError as e:  # the evidence is for diagnosis: its loss stops nothing
                _log.warning("the rig check's frames were not kept: %s", e)

    def _metering_image(self) -> np.ndarray:
        """What the projector shows while the exposure is searched: the brightest light the projector step
        puts on the board, so that no capture saturates. A structured step's white frame lights the whole
        board; the circle grid's dots at every position at once (one position alone meters one part of
        the board, and a brighter part, nearer or less vignetted, saturates the dots there)."""
        st = self.station
        if st.machine.structured:
            return st.sequence.white()
        image = st.pattern_image(0)
        for p in range(1, st.machine.positions):
            image = np.maximum(image, st.pattern_image(p))
        return image

    def _timing_checks(self, cam, proj, man, recorded, timing, settings, checks) -> list[RigCheck]:
        from drivers.base import ExposureControl
        from calib.detection.response import recorded_response
        from drivers.settle import recorded_exposure, recorded_latency_s

        manual = isinstance(cam, ExposureControl)
        if manual:
            try:
                cam.set_emitter(False)
                if recorded_exposure(recorded) is not None:
                    from drivers.exposure import ASSUMED_TIMING, METADATA_TIMING, apply_exposure, has_settings_metadata

                    # nothing is measured on a resume: without metadata, the longest lag allowed
                    self.station._change_timing = METADATA_TIMING if has_settings_metadata(
                        cam.get_frame(timeout_s=self.station.options.frame_timeout_s)) else ASSUMED_TIMING
                    applied, f = apply_exposure(cam, *recorded_exposure(recorded), self.station.options.frame_timeout_s,
                                                timing=self.station._change_timing)
                    self.station.frames.seen(f.frame_number)
                    detail = f"recorded {applied['exposure_us']:g} us, gain {applied['gain']:g} re-applied"
                else:
                    from drivers.exposure import search_exposure

                    self._rig_stage("camera exposure: searching while the pattern lights the board")
                    self.station._show(self._metering_image())
                    self.station.clock.sleep(0.5)  # any projector's latency (the rig's clock): the pattern lights the board now
                    choice = search_exposure(cam, float(getattr(proj, "refresh_hz", 60.0) or 60.0))
                    self.station._change_timing = choice.timing
                    applied = {"exposure_us": choice.exposure_us, "gain": choice.gain}
                    detail = (f"{choice.exposure_us:g} us ({choice.periods:.2f} refresh periods), gain {choice.gain:g}, "
                              f"lit board at level {choice.level:.0f} ({choice.frames} frames)")
                    if not choice.whole_periods:
                        detail += (f"; not a whole number of refresh periods: frames flicker by {choice.flicker:.0%} "
                                   "(a dimmer projector or a neutral-density filter allows a whole period)")
                    if choice.dim:
                        checks.append(RigCheck("camera exposure", False, detail + ": too dim at the longest "
                                               "exposure and the highest gain; bring the projector closer to "
                                               "the board, shorten the mirror path or use a brighter projector"))
                        return checks
                settings.update({"auto_exposure": False, "exposure_us": float(applied["exposure_us"]),
                                 "gain": float(applied["gain"]), "emitter_enabled": False})
                checks.append(RigCheck("camera exposure", True, detail + "; IR emitter off"))
                from drivers.exposure import camera_timing

                settings["timing"], text = camera_timing(cam.get_frame(timeout_s=self.station.options.frame_timeout_s),
                                                         self.station._change_timing)
                checks.append(RigCheck("camera timing", True, text))
            except ExposureUnsupported as e:
                # a webcam without manual exposure still calibrates: frames are gated by their times, and
                # the levels may drift with the pattern
                manual = False
                text = f"WARNING: {e}; the session continues, the camera's response is not measured"
                _log.warning(text)
                self.station.machine.log(text)
                settings.update({"auto_exposure": True, "manual_exposure": "ignored by the camera"})
                checks.append(RigCheck("camera exposure", True, text))
            except (DeviceError, ProcamError) as e:
                checks.append(RigCheck("camera exposure", False, f"could not be set: {e}"))
                return checks
        response = getattr(cam, "response", None)  # a camera that knows its tone curve (the simulated one)
        if callable(response) and recorded_response(recorded) is None:
            try:
                settings["response"] = response()
                checks.append(RigCheck("camera response", True,
                                       "tone curve {model}, gamma {gamma:g} recorded".format(**settings["response"])))
            except (DeviceError, ProcamError) as e:
                checks.append(RigCheck("camera response", False, f"could not be read: {e}"))
        if hasattr(proj, "settle_s"):
            try:
                latency_s = recorded_latency_s(recorded)
                if latency_s is not None:
                    detail = f"recorded latency {latency_s * 1000:.0f} ms re-applied"
                else:
                    from drivers.settle import measure_settle

                    self._rig_stage("projector latency: measuring (several trials)")
                    m = measure_settle(proj, cam)
                    latency_s = m.settle_s
                    jitter = "not measured" if m.jitter_s is None else f"{m.jitter_s * 1000:.0f} ms"
                    detail = (f"latency {latency_s * 1000:.0f} ms (trials "
                              + ", ".join(f"{x * 1000:.0f}" for x in m.samples_s) + f" ms, jitter {jitter})")
                    if m.jitter_s is not None:
                        timing["jitter_ms"] = round(m.jitter_s * 1000.0, 3)
                proj.settle_s = latency_s
                refresh = float(getattr(proj, "refresh_hz", 0.0) or 0.0)
                timing.update({"latency_ms": round(latency_s * 1000.0, 3), "refresh_hz": refresh})
                settings["projector"] = timing
                checks.append(RigCheck("projector latency", True, detail + (f", {refresh:g} Hz" if refresh else "")))
            except (DeviceError, ProcamError) as e:
                if manual or not isinstance(cam, ExposureControl):
                    checks.append(RigCheck("projector latency", False, f"could not be measured: {e}"))
                else:
                    # a camera's own auto exposure follows the change it should show (dark raises it until
                    # the unlit board looks lit): a latency longer than projectors' keeps frames honest
                    from drivers.settle import UNMEASURED_LATENCY_S

                    proj.settle_s = UNMEASURED_LATENCY_S
                    timing.update({"latency_ms": round(UNMEASURED_LATENCY_S * 1000.0, 3), "assumed": True,
                                   "refresh_hz": float(getattr(proj, "refresh_hz", 0.0) or 0.0)})
                    settings["projector"] = timing
                    text = ("WARNING: not measurable while the camera's own auto exposure follows the switches from "
                            f"dark to bright; {UNMEASURED_LATENCY_S * 1000:.0f} ms assumed (longer than projectors' "
                            "latency: captures wait a little longer)")
                    _log.warning("%s (the measurement said: %s)", text, e)
                    checks.append(RigCheck("projector latency", True, text))
        # the RealSense: measured, last (a full white just before the latency trials fooled the first one
        # through the emulation: 0 ms, and a settle time too short for the verification)
        if not callable(response) and manual:
            checks.append(self._measure_response(cam, proj, recorded, settings))
        return checks

    def _measure_response(self, cam, proj, recorded, settings) -> RigCheck:
        """Rig check, the tone curve of a camera that does not know it (drivers.exposure.measure_response:
        a bracket of gains while the projector's white lights the board), the searched exposure and gain
        restored after. A recorded one (a resumed session) is kept; a failed measurement is a warning:
        nothing is recorded and detection uses the levels as they are."""
        from calib.detection.response import recorded_response
        from drivers.exposure import measure_response
        from drivers.projector_images import white

        old = recorded_response(recorded)
        if old is not None:
            return RigCheck("camera response", True, f"recorded tone curve {old.model}, gamma {old.gamma:g} re-used")
        try:
            self._rig_stage("camera response: measuring a bracket of gains under the projector's white")
            self.station._show(white(self.station.projector_size))
            self.station.clock.sleep(0.5)  # any projector's latency (the rig's clock): the white lights the board now
            fit = measure_response(cam, float(getattr(proj, "refresh_hz", 60.0) or 60.0), timing=self.station._change_timing)
        except (DeviceError, ProcamError) as e:
            text = f"camera response not measured ({e}): centroids use the camera's levels uncorrected"
            _log.warning(text)
            self.station.machine.log(text)
            return RigCheck("camera response", True, text)
        finally:
            self._restore_exposure(cam, settings)
        settings.update(fit.camera_settings())
        text = (f"tone curve bt709, gamma {fit.gamma:g} measured (fit rms {fit.rms:.4f}, {fit.bins} pixel groups, "
                f"{fit.frames} frames); exposure {settings['exposure_us']:g} us, gain {settings['gain']:g} restored")
        self.station.machine.log(text)
        return RigCheck("camera response", True, text)

    def _restore_exposure(self, cam, settings) -> None:
        """Re-apply the searched exposure and gain and wait for a frame taken with them (a camera applies a
        change some frames late; drivers.exposure.frames_after_change), so no later frame has the
        response bracket's gain."""
        from drivers.exposure import apply_exposure

        try:
            _, f = apply_exposure(cam, settings["exposure_us"], settings["gain"], self.station.options.frame_timeout_s,
                                  timing=self.station._change_timing)
            self.station.frames.seen(f.frame_number)
        except (DeviceError, ProcamError, KeyError) as e:
            _log.warning("could not restore the exposure after measuring the response: %s", e)
