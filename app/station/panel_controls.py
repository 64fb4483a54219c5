"""The operator's controls, per browser (client.gui), organised by step: the current step's folder is
shown and the others are out of the way (hidden until "Show every step's controls" is ticked). Every
action goes through the session machine, so a refusal carries its reason; refusals and successes both
show in the message line under "Next:" and as a notification that stays in view while scrolling.

Also the Download button (a zip of the results) and the click on the camera image in the 3D view that
checks a pixel. StationPanel (app/station/panel.py) owns one `PanelControls`, built with a `PanelContext`:
what the controls use of the panel, passed in, so they reach nothing of the panel's own.
"""

from __future__ import annotations

import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from app.station.activity import CHECK_RIG_NAME, DOWNLOAD_NAME, Status, activity_name
from app.station.machine import (
    CALIBRATION,
    CHECK_RIG,
    DONE,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    VERIFICATION,
    ActionRefused,
)
from app.station.panel_driver import TAKE_CONTROL, DriverSeat
from app.station.panel_guidance import unmet_targets
from app.station.panel_results import (
    EXPORTS_ALL, export_choices, export_names, results_zip, write_report_if_available,
)
from app.station.panel_scene import click_to_pixel, view_from_camera, view_whole_rig
from calib.errors import ProcamError
from calib.models.vocab import MirrorMethod

# which folder of controls each step shows (the rest stay hidden unless all are asked for)
STEP_FOLDERS = {
    CHECK_RIG: ("rig", "camera_model"),
    MIRROR_CAPTURE: ("mirror", "capture", "change"),
    PROJECTOR_CAPTURE: ("capture", "calibration", "change"),
    CALIBRATION: ("calibration", "verification", "camera_model", "change"),
    VERIFICATION: ("verification", "calibration"),
    DONE: ("verification",),
}
# the buttons whose action is an activity (app/station/activity.py): its line and notifications follow it
FOLLOWED = {"check": CHECK_RIG_NAME, "calibrate": activity_name("calibrate"), "verify": activity_name("verify"),
            "check_pixel": activity_name("check pixel"), "download": DOWNLOAD_NAME}
FOLDER_TITLES = {"rig": "Check the rig", "mirror": "Mirror method", "capture": "Capture",
                 "calibration": "Calibration", "verification": "Verification", "camera_model": "Camera model",
                 "change": "Change captures"}


@dataclass
class ClientControls:
    client: object
    unlocked: bool
    handles: dict = field(default_factory=dict)
    folders: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict)


@dataclass(frozen=True)
class PanelContext:
    """What the per-browser controls use of their panel."""

    station: object  # app.station.station.Station: its machine, actions, options and activities
    server: object  # the viser server (its scene: the views a button frames)
    seat: DriverSeat  # which browser drives; the others watch
    lock: threading.RLock  # the panel's: a browser joins between two refreshes, never during one
    report_lock: threading.Lock  # one report.html written at a time (the panel's own and the Download's)
    refresh: Callable[[], None]  # bring every status element and every browser up to date
    bars_now: Callable[[], list]  # the current step's diversity bars (panel_guidance)
    click_camera: Callable[[], object]  # the camera model of the clickable image in the 3D view


class PanelControls:
    """The per-browser half of the panel: every browser's controls (`clients`), and a mode's own
    controls in place of the steps' when one is set (`mode`, app/station/panel_recal.py)."""

    def __init__(self, ctx: PanelContext):
        self.ctx = ctx
        self.station = ctx.station
        self.machine = ctx.station.machine
        self.seat = ctx.seat
        self.clients: dict[int, ClientControls] = {}
        self.mode = None
        # viser runs each click's callback in a thread pool: without this, a click handled while the one
        # before it is still running sees the state before it (Move board refused just after the mirror
        # method was chosen) and the earlier action's "done" overwrites the later one's line
        self.action_lock = threading.Lock()

    def refresh_all(self) -> None:
        """Every connected browser's controls up to date (the panel's refresh, under its lock)."""
        for ctl in list(self.clients.values()):
            if ctl.unlocked:
                try:
                    self.refresh_controls(ctl)
                except Exception:  # a browser that went away mid-update
                    pass

    def on_connect(self, client) -> None:
        # every websocket reaching here passed the gate: the panel's own Origin (or the secret), and the
        # access code when one is needed; a browser without the code never gets this far
        ctl = ClientControls(client, unlocked=True)
        view_whole_rig(self.ctx.server, client)  # framed from the start, not only once calibrated
        self.seat.join(client.client_id)
        self._build_controls(ctl)
        # the refresh loop sees a browser only once all its controls exist: a refresh of half-built controls
        # would disable (for a watching browser) only those built so far and remember it as done
        with self.ctx.lock:
            if self.seat.connected(client.client_id):  # not gone while its controls were being built
                self.clients[client.client_id] = ctl

    def on_disconnect(self, client) -> None:
        self.seat.leave(client.client_id)  # first: a browser still being built then never joins _clients
        with self.ctx.lock:
            self.clients.pop(client.client_id, None)

    def _build_controls(self, ctl: ClientControls) -> None:
        g = ctl.client.gui
        h, f = ctl.handles, ctl.folders
        sim = self.station.is_sim
        m = self.machine
        h["who"] = g.add_markdown(self.seat.roster(ctl.client.client_id), order=1.1)
        h["take"] = g.add_button(TAKE_CONTROL, order=1.15, color="green", visible=False)
        h["take"].on_click(lambda event: self._take_control(ctl, event))
        h["message"] = g.add_markdown("", order=1.2)
        h["download"] = g.add_button("Download results (zip)", order=1.5, color="teal", visible=False,
                                     hint="calibration.json, calibration.yaml, verification.json, report.html and "
                                          "recalibration.json, those that exist, and the exports chosen below")
        h["exports"] = g.add_dropdown("Exports in the zip", export_choices(), initial_value=EXPORTS_ALL, order=1.55,
                                      visible=False, hint="ROS camera_info, mrcal, OpenGL, Unity, three.js, OpenCV: "
                                                          "under exports/ in the zip (docs/FORMATS.md)")
        with g.add_folder("Step controls", order=3) as h["steps"]:
            with g.add_folder(FOLDER_TITLES["rig"]) as f["rig"]:
                h["check"] = g.add_button("Check rig")
                h["start"] = g.add_button("Start")
            with g.add_folder(FOLDER_TITLES["mirror"]) as f["mirror"]:
                h[MirrorMethod.REAL_VIRTUAL] = g.add_button("Mirror: real-virtual")
                h[MirrorMethod.REAL_MIRROR] = g.add_button("Mirror: real-mirror")
                h["thickness"] = g.add_number(f"Board thickness ({m.manifest.units})", float(m.manifest.board_thickness),
                                              min=0.0, step=0.1,
                                              hint="real-mirror: height of the printed face above the mirror")
                h["set_thickness"] = g.add_button("Set thickness")
            with g.add_folder(FOLDER_TITLES["capture"]) as f["capture"]:
                h["capture"] = g.add_button("Capture")
                if sim:
                    h["move"] = g.add_button("Move board", hint="asks the simulated operator for the pose the station needs")
                h["retake_last"] = g.add_button("Retake last", hint="deletes the last capture; the next one must be "
                                                                    "a new pose (move the board)")
                h["auto_capture"] = g.add_checkbox("Auto-capture", self.station.options.auto_capture,
                                                   hint="capture when the board is still and in a new pose")
                if sim:
                    h["follow"] = g.add_checkbox("Simulated operator moves the board by itself",
                                                 bool(self.station.options.follow_operator))
            with g.add_folder(FOLDER_TITLES["calibration"]) as f["calibration"]:
                h["calibrate"] = g.add_button("Calibrate")
                # viser 1.1 shows no tooltip on buttons: what Calibrate would say is written under it
                h["calibrate_note"] = g.add_markdown("")
            with g.add_folder(FOLDER_TITLES["verification"]) as f["verification"]:
                h["verify"] = g.add_button("Verify")
                h["pick_hint"] = g.add_markdown("Check one pixel: **click on the camera image in the 3D view** "
                                                "(or type it here).")
                h["view_camera"] = g.add_button("View from the camera",
                                                hint="puts the 3D view at the camera: the live image fills it")
                W, H = m.manifest.rig.camera_size
                h["pixel_x"] = g.add_number("Pixel x (camera px)", float(W // 2), min=0.0, max=float(W - 1), step=0.5)
                h["pixel_y"] = g.add_number("Pixel y (camera px)", float(H // 2), min=0.0, max=float(H - 1), step=0.5)
                h["check_pixel"] = g.add_button("Check pixel", hint="the projector draws this camera pixel's "
                                                                    "epipolar curve; the camera measures how far it passes")
                h["finish"] = g.add_button("Finish")
            with g.add_folder(FOLDER_TITLES["camera_model"]) as f["camera_model"]:
                h["intrinsics"] = g.add_text("Intrinsics file", "", hint="calibration.json or OpenCV YAML of a "
                                                                        "pre-calibrated camera")
                h["skip_camera"] = g.add_button("Skip camera step")
                h["use_camera"] = g.add_button("Calibrate camera from captures")
            with g.add_folder(FOLDER_TITLES["change"], expand_by_default=False) as f["change"]:
                ids = self._capture_ids()
                h["which"] = g.add_dropdown("Capture to change", ids or ["(none)"], initial_value=(ids or ["(none)"])[0])
                h["retake"] = g.add_button("Retake selected")
                h["delete"] = g.add_button("Delete selected")
            h["next"] = g.add_button("Next step")
            h["back"] = g.add_button("Back")
            h["show_all"] = g.add_checkbox("Show every step's controls", False)
        st = self.station
        actions = {
            "check": lambda: self._check(),
            "start": lambda: m.start_session(),
            "next": lambda: m.proceed(),
            "back": lambda: m.go_back(),
            MirrorMethod.REAL_VIRTUAL: lambda: m.choose_mirror_method(MirrorMethod.REAL_VIRTUAL),
            MirrorMethod.REAL_MIRROR: lambda: m.choose_mirror_method(MirrorMethod.REAL_MIRROR),
            "capture": lambda: st.capture_now(),
            "move": lambda: st.request_pose(),
            "retake_last": lambda: self._retake(None),
            "retake": lambda: self._retake(h["which"].value),
            "delete": lambda: m.delete_capture(self._selected(h["which"].value)),
            "calibrate": lambda: st.run_long("calibrate", st.calibrate),
            "skip_camera": lambda: m.skip_camera(h["intrinsics"].value.strip()),
            "use_camera": lambda: m.use_camera_calibration(),
            "set_thickness": lambda: m.set_board_thickness(h["thickness"].value),
            "verify": lambda: st.run_long("verify", st.verify),
            "finish": lambda: m.finish(),
            "check_pixel": lambda: self._check_pixel(float(h["pixel_x"].value), float(h["pixel_y"].value)),
            "download": lambda: self._download(ctl),
            "view_camera": lambda: self._view(ctl, True),
        }
        for name, fn in actions.items():
            if name in h:
                h[name].on_click(self.handler(ctl, name, fn))

        @h["auto_capture"].on_update
        def _(event):
            if self._allowed(ctl, event):
                st.options.auto_capture = bool(h["auto_capture"].value)
                self._log_action(ctl, f"set Auto-capture {'on' if st.options.auto_capture else 'off'}")

        @h["show_all"].on_update
        def _(event):
            if self._allowed(ctl, event):
                self.refresh_controls(ctl)

        if "follow" in h:
            @h["follow"].on_update
            def _(event):
                if self._allowed(ctl, event):
                    st.options.follow_operator = bool(h["follow"].value)
                    st.operator.forget()
                    self._log_action(ctl, f"set the simulated operator {'on' if h['follow'].value else 'off'}")

        if self.mode is not None:
            self.mode.build(ctl)
        self.refresh_controls(ctl)

    def _allowed(self, ctl: ClientControls, event) -> bool:
        """Only the driving browser acts (the others' controls are disabled; this catches a stale click)."""
        return ctl.unlocked and event.client_id == ctl.client.client_id and self.seat.drives(event.client_id)

    def _log_action(self, ctl: ClientControls, what: str) -> None:
        self.machine.log(f"{self.seat.name(ctl.client.client_id)}: {what}")

    def _take_control(self, ctl: ClientControls, event) -> None:
        if event.client_id != ctl.client.client_id:
            return
        self._message(ctl, f"**{TAKE_CONTROL}:** {self.seat.take(event.client_id)}")
        self.ctx.refresh()

    def _selected(self, value):
        if not value or value == "(none)":
            raise ActionRefused("change a capture", "there are no captures yet")
        return value

    def _retake(self, capture_id):
        """Delete a capture and ask for its slot again; the next capture must be a new pose, so a board
        left where it was is not captured again at once."""
        m = self.machine
        cid = capture_id if capture_id is None else self._selected(capture_id)
        if cid is None:
            cid = m.last_capture.id if m.last_capture is not None else (
                m.manifest.captures[-1].id if m.manifest.captures else None)
        old = next((c for c in m.manifest.captures if c.id == cid), None)
        tgt = m.retake(cid)
        from app.station.autocapture import PoseFeatures

        feats = PoseFeatures.from_dict(old.meta.get("pose")) if old is not None and isinstance(
            old.meta.get("pose"), dict) else None
        said = self.station.retake_pose(tgt, feats, f"{cid} (deleted)")
        if said:
            return f"{cid} deleted; the simulated operator holds the board in another pose for the same slot"
        return f"{cid} deleted; move the board to a new pose: the same pose is not captured again"

    def _check_pixel(self, x: float, y: float):
        if self.machine.result is None:
            raise ActionRefused("check a pixel", "calibrate first")
        self.station.run_long("check pixel", lambda: self.station.check_pixel(x, y))
        return f"checking pixel ({x:.1f}, {y:.1f}) camera px; its curve and verdict appear on the live image"

    def _check(self):
        checks = self.station.check_rig()
        bad = [c for c in checks if not c.ok]
        if bad:
            raise ActionRefused("check the rig", "; ".join(f"{c.name}: {c.detail}" for c in bad))
        return "the rig is ready"

    def _download(self, ctl: ClientControls) -> str:
        m = self.machine
        if m.result is None:
            raise ActionRefused("download the results", "there is no calibration yet; calibrate first")
        if m.busy:
            raise ActionRefused("download the results", f"the station is busy ({m.busy}); wait until it finishes")
        acts = self.station.activities
        with acts.running(DOWNLOAD_NAME, "writing report.html") as act:
            folder = Path(m.store.folder)
            with self.ctx.report_lock:
                _, why = write_report_if_available(folder)
            note = f" (no report.html: {why})" if why else ""
            acts.progress(DOWNLOAD_NAME, "packing the result files", log=False)
            data, names = results_zip(folder, export_names(ctl.handles["exports"].value))
            name = f"{folder.name}-results.zip"
            acts.progress(DOWNLOAD_NAME, f"sending {name} ({len(data) / 1024:.0f} kB) to this browser", log=False)
            ctl.client.send_file_download(name, data, save_immediately=True)
            m.log(f"results sent to a browser as {name}: {', '.join(names)}")
            act.outcome = f"{name} sent ({len(data) / 1024:.0f} kB): {', '.join(names)}{note}"
        return act.outcome

    def _view(self, ctl: ClientControls, camera: bool) -> str:
        view_from_camera(ctl.client, self.ctx.click_camera())
        return "the 3D view looks from the camera; click on the image to check a pixel"

    def on_image_click(self, event) -> None:
        """A click on the camera image in the 3D view: check that pixel (operators only)."""
        ctl = self.clients.get(event.client_id)
        if ctl is None or not ctl.unlocked or not self.seat.drives(event.client_id):
            return
        px = click_to_pixel(self.ctx.click_camera(), event)
        if px is None:
            self._message(ctl, "**Check pixel:** the click is outside the camera image", error=True)
            return
        h = ctl.handles
        try:
            h["pixel_x"].value, h["pixel_y"].value = round(px[0], 1), round(px[1], 1)
            out = self._check_pixel(*px)
        except ActionRefused as e:
            self._message(ctl, f"**Refused: Check pixel.** {e.reason[:1].upper() + e.reason[1:]}.", error=True)
        except ProcamError as e:
            self._message(ctl, f"**Check pixel failed:** {e}", error=True)
        else:
            self._message(ctl, f"**Check pixel:** {out}")
        self.ctx.refresh()

    def handler(self, ctl: ClientControls, name: str, fn):
        def on_click(event):
            with self.action_lock:  # one action at a time, in the order the browser sent them
                run(event)

        def run(event):
            if not self._allowed(ctl, event):
                return
            label = ctl.handles[name].label
            acts = self.station.activities
            act_name = FOLLOWED.get(name)
            before = acts.get(act_name) if act_name else None
            ctl.cache.pop("busy_refusal", None)
            self._log_action(ctl, f"pressed {label}")
            try:
                out = fn()
            except ActionRefused as e:
                self._message(ctl, f"**Refused: {label}.** {e.reason[:1].upper() + e.reason[1:]}.", error=True)
                ctl.cache["busy_refusal"] = bool(self.machine.busy)  # said while busy: gone once it is not
            except ProcamError as e:
                self._message(ctl, f"**{label} failed:** {e}", error=True)
            except Exception as e:  # a bug must not leave the old line standing: said here, traceback in the log
                self.machine.log(f"{label} failed unexpectedly: {e!r}\n{traceback.format_exc()}")
                self._message(ctl, f"**{label} failed:** {type(e).__name__}: {e} (details in the Log tab)", error=True)
            else:
                if act_name is None:
                    self._message(ctl, f"**{label}:** {self._describe_outcome(name, out)}")
            after = acts.get(act_name) if act_name else None
            if after is not None and (before is None or after.seq > before.seq):
                # the line and the notifications follow the action to its end (refresh)
                ctl.cache["follow"] = (act_name, self._describe_extra(name))
                ctl.cache.pop("followed", None)
                self._follow(ctl)
            self.ctx.refresh()

        return on_click

    def _follow(self, ctl: ClientControls) -> None:
        """The message line of an action this browser started, as it is now; "Started" once while it runs
        and "Done" or "Failed" once when it ended. A refusal said because the station was busy goes
        when it no longer is."""
        if ctl.cache.get("busy_refusal") and not self.machine.busy:
            ctl.cache.pop("busy_refusal")
            ctl.handles["message"].content = ""
        follow = ctl.cache.get("follow")
        if follow is None:
            return
        act = self.station.activities.get(follow[0])
        if act is None:
            return
        running = act.status is Status.RUNNING
        text = act.text() + (follow[1] if running else "")
        if self.cached(ctl, "follow_text", text):
            ctl.handles["message"].content = text
        said = ctl.cache.get("followed")
        if said == (act.seq, act.status) or (running and said is not None):
            return
        ctl.cache["followed"] = (act.seq, act.status)
        title = {Status.RUNNING: "Started", Status.DONE: "Done", Status.FAILED: "Failed"}[act.status]
        self._notify(ctl, title, text, act.status)

    def _describe_extra(self, name) -> str:
        """What to know while a long action runs (said with its "running" line only)."""
        if name == "calibrate":
            unmet = [b for b in self.ctx.bars_now() if not b.met]
            return (" Diversity targets not met yet: " + ", ".join(f"{b.name} ({b.fraction * 100:.0f}%)" for b in unmet)
                    + " (the note under the button says more).") if unmet else ""
        if name == "verify":
            return " The verified pixels appear on the live image and the verdict at the top."
        return ""

    def _describe_outcome(self, name, out) -> str:
        if name == "capture" and out is not None:
            similar = out.meta.get("similar_to") if isinstance(out.meta, dict) else None
            note = (f" (auto-capture had not taken this pose: it is close to {similar}; taken as you asked)"
                    if similar else "")
            return f"{out.id} written to the session{note}"
        if isinstance(out, str):
            return out.replace("_", " ") if name not in ("download", "move") else out
        return "done"

    def _message(self, ctl: ClientControls, text: str, error: bool = False) -> None:
        """The message line under "Next:" and a notification (refusals red, successes green); it no longer
        follows an earlier action."""
        ctl.cache.pop("follow", None)
        ctl.cache.pop("follow_text", None)
        h = ctl.handles.get("message")
        if h is not None:
            h.content = text
        self._notify(ctl, "Not possible now" if error else "Done", text, Status.FAILED if error else Status.DONE)

    def _notify(self, ctl: ClientControls, title: str, text: str, status) -> None:
        colour = {Status.RUNNING: "blue", Status.DONE: "green", Status.FAILED: "red"}[status]
        try:
            ctl.client.add_notification(title, text.replace("**", ""), auto_close_seconds=
                                        6.0 if status is Status.FAILED else 3.5, color=colour)
        except Exception:  # a notification is a nicety; the message line says the same
            pass

    def _capture_ids(self) -> list[str]:
        return [c.id for c in reversed(self.machine.manifest.captures)]

    def _recommended(self) -> set[str]:
        m, st = self.machine, self.station
        s = m.state
        if m.busy:
            return set()
        if s == CHECK_RIG:
            return {"start"} if m.rig_checks and m.why_not("start") is None else {"check"}
        if s == MIRROR_CAPTURE:
            if m.mirror_method is None:
                return {MirrorMethod.REAL_VIRTUAL}
            if m.target is None:
                return {"next"}
            return {"capture", "move"} if st.is_sim and not st.options.follow_operator else {"capture"}
        if s == PROJECTOR_CAPTURE:
            if m.target is None:
                return {"calibrate"}
            return {"capture", "move"} if st.is_sim and not st.options.follow_operator else {"capture"}
        if s == CALIBRATION:
            if m.result is None or m.result_stale:
                return {"calibrate"}
            return {"verify"} if m.why_not("verify") is None else {"finish", "download"}
        if s == VERIFICATION:
            return {"finish", "download"} if m.report is not None else {"verify"}
        return {"download"}

    def _refusals(self) -> dict[str, str | None]:
        m = self.machine
        last = m.last_capture.id if m.last_capture is not None else (m.manifest.captures[-1].id if m.manifest.captures else None)
        pixel = ("calibrate first" if m.result is None else
                 f"the station is busy ({m.busy})" if m.busy else
                 None if m.state in (CALIBRATION, VERIFICATION, DONE) else "pixels are checked after calibration")
        return {
            "check": None if m.state == CHECK_RIG and not m.busy else "the rig is checked in the first step; go back to it",
            "start": m.why_not("start"),
            "next": m.why_not("proceed"),
            "back": m.why_not("back"),
            MirrorMethod.REAL_VIRTUAL: m.why_not("choose_mirror_method", MirrorMethod.REAL_VIRTUAL),
            MirrorMethod.REAL_MIRROR: m.why_not("choose_mirror_method", MirrorMethod.REAL_MIRROR),
            "capture": m.why_not("capture"),
            "move": None if m.target is not None else "no capture is asked for now",
            "retake_last": m.why_not("retake", last),
            "retake": m.why_not("retake", last) if last else "there are no captures yet",
            "delete": m.why_not("delete", last) if last else "there are no captures yet",
            "calibrate": m.why_not("calibrate"),
            "skip_camera": (m.why_not("back") if m.busy else None) or (
                "the camera model cannot change now; go back to the calibration step first"
                if m.state in (VERIFICATION, DONE) else None),
            "use_camera": m.why_not("use_camera_calibration"),
            "set_thickness": m.why_not("set_board_thickness"),
            "verify": m.why_not("verify"),
            "finish": m.why_not("finish"),
            "check_pixel": pixel,
            "download": ("there is no calibration yet" if m.result is None else
                         f"the station is busy ({m.busy})" if m.busy else None),
            "view_camera": None if m.result is not None else "the camera image is clickable once calibrated",
        }

    def cached(self, ctl: ClientControls, key, value) -> bool:
        """True when `value` differs from the last one sent to this browser under `key` (and remember it)."""
        if ctl.cache.get(key) == value:
            return False
        ctl.cache[key] = value
        return True

    def refresh_controls(self, ctl: ClientControls) -> None:
        h = ctl.handles
        if not h:
            return
        m = self.machine
        self._refresh_seat(ctl)
        refusals = self._refusals()
        rec = self._recommended() if self.mode is None else self.mode.recommended()
        unmet = unmet_targets(self.ctx.bars_now()) if m.state in (PROJECTOR_CAPTURE, CALIBRATION) else []
        for name, reason in refusals.items():
            b = h.get(name)
            if b is None:
                continue
            colour = "green" if name in rec and reason is None else ("gray" if reason else "blue")
            if name == "download" and reason is None:
                colour = "teal" if name not in rec else "green"
            hint = reason[:1].upper() + reason[1:] if reason else None
            if name == "calibrate" and unmet:
                hint = ((hint + ". ") if hint else "Possible now. ") + "Targets not met yet: " + "; ".join(unmet)
            if self.cached(ctl, (name, "color"), colour):
                b.color = colour
            if self.cached(ctl, (name, "hint"), hint):
                b.hint = hint
        note = ""
        if refusals["calibrate"]:
            note = f"Not possible now: {refusals['calibrate']}."
        elif unmet:
            note = "Possible now. Diversity targets not met yet: " + "; ".join(unmet) + "."
        if self.cached(ctl, "calibrate_note", note):
            h["calibrate_note"].content = note
        if self.cached(ctl, "download_visible", m.result is not None):
            h["download"].visible = h["exports"].visible = m.result is not None
        if self.cached(ctl, "cal_label", "Re-run calibration" if m.result is not None else "Calibrate"):
            h["calibrate"].label = ctl.cache["cal_label"]
        shown = set(STEP_FOLDERS.get(m.state, ())) if not h["show_all"].value else set(ctl.folders)
        for key, folder in ctl.folders.items():
            if self.cached(ctl, ("folder", key), key in shown):
                folder.visible = key in shown
        ids = self._capture_ids() or ["(none)"]
        old = ctl.cache.get("ids")
        if self.cached(ctl, "ids", ids):
            cur = h["which"].value
            h["which"].options = ids
            # the newest capture unless the operator picked another one that still exists
            keep = cur in ids and old is not None and cur != old[0]
            h["which"].value = cur if keep else ids[0]
        if "follow" in h and self.cached(ctl, "follow_operator", bool(self.station.options.follow_operator)):
            h["follow"].value = ctl.cache["follow_operator"]
        self._follow(ctl)
        if self.mode is not None:
            self.mode.refresh(ctl)

    def _refresh_seat(self, ctl: ClientControls) -> None:
        """Who is connected; a watching browser's controls disabled, with Take control shown instead."""
        h, cid = ctl.handles, ctl.client.client_id
        drives = self.seat.drives(cid)
        if self.cached(ctl, "who", self.seat.roster(cid)):
            h["who"].content = ctl.cache["who"]
        if self.cached(ctl, "drives", (drives, len(h))):  # controls added later get the same state
            h["take"].visible = not drives
            for name, handle in list(h.items()):
                if name != "take" and hasattr(handle, "disabled"):
                    handle.disabled = not drives
