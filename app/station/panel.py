"""The station's browser panel (viser): status for everyone, controls for whoever may operate the rig.

Shared by every browser (server.gui), top to bottom: what to do next (the current step, its progress
and instruction), the results once calibrated (summary, Download button, parameters with distortion,
worst views, the session's files), the checklist; in a window docked on the left the live camera image
with detections, verified pixels and where to hold the board next, the coverage maps and the diversity
bars with their targets, all captures with thumbnails, and a log; and the 3D view of the rig
(server.scene), where the camera image can be clicked to check a pixel once calibrated.

Per browser (client.gui): the operator's controls, organised by step (app/station/panel_controls.py's
PanelControls, given what it uses of the panel as a PanelContext).
Who may connect at all is decided before the websocket opens (app/station/access.py, hooked into viser
by app/station/_origin.py): only pages the panel served itself (their Origin), and served on a network
only browsers that gave the access code; a browser without it gets a page asking for the code.

A heartbeat element makes the page say so when the station process is gone (`DISCONNECT_TEXT`), and a
banner shows when the capture loop failed (restarted) or stopped.

Detection runs in the station's own threads; the panel only draws (app/station/panel_live.py): the live
image is redrawn from each new frame with the newest detection, up to IMAGE_RATE_HZ times a second.
Guidance: app/station/panel_guidance.py; results and downloads: app/station/panel_results.py; the status
in words (checklist, results' summary, log, banners): app/station/panel_status.py; the
projection-uncertainty heat maps: app/station/panel_uncertainty.py; the 3D view: app/station/panel_scene.py.
"""

from __future__ import annotations

import html
import logging
import threading
import time

import cv2
import numpy as np

from app.station import panel_status
from app.station._origin import start_viser_server
from app.station.access import LOOPBACK_HOSTS, WILDCARD_HOSTS, AccessGate, new_access_code  # noqa: F401
from app.station.activity import activities_text
from app.station.autocapture import PoseFeatures, diversity_bars
from app.station.frame_source import rate_of
from app.station.machine import (
    CALIBRATION,
    CAPTURE_STATES,
    DONE,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    STATE_TITLES,
    VERIFICATION,
)
from app.station.panel_controls import PanelContext, PanelControls
from app.station.panel_driver import DriverSeat
from app.station.panel_guidance import (
    camera_coverage_image,
    capture_corners_px,
    coverage_grid,
    coverage_summary,
    projector_coverage_image,
    side_by_side,
    suggest_next,
)
from app.station.panel_live import (
    LEGEND,
    draw_asked_outline,
    draw_banner,
    draw_checks,
    draw_detection,
    draw_suggestion,
    flash,
    predicted_curves,
)
from app.station.panel_results import (
    REPORT_MISSING,
    captures_html,
    files_text,
    folder_stamp,
    parameters_text,
    worst_views_text,
    write_report_if_available,
)
from app.station.panel_scene import IMAGE_PLANE_NAME, SCENE_LEGEND, camera_plane, update_rig, view_whole_rig
from app.station.panel_uncertainty import DEVICES as UNCERTAINTY_DEVICES
from app.station.panel_uncertainty import INTRO as UNCERTAINTY_INTRO
from app.station.panel_uncertainty import uncertainty_image, uncertainty_text
from calib.models.observations import STEP_PROJECTOR
from calib.quality.coverage import GRID_COLUMNS, coverage_fraction
from calib.quality.next_pose import position_area

LIVE_WIDTH = 640
IMAGE_RATE_HZ = 25.0  # most live-image updates per second (one per new camera frame)
PLANE_RATE_HZ = 4.0  # updates per second of the clickable camera image in the 3D view


def rate_text(rate: float) -> str:
    """A rate as the live line shows it: tenths below 10/s, so a slow source never reads as 0."""
    return f"{rate:.1f}" if rate < 10 else f"{rate:.0f}"


def needs_access_code(host: str) -> bool:
    return host not in LOOPBACK_HOSTS


_log = logging.getLogger("procam.station")
HEARTBEAT_S = 1.0
SILENT_S = 5.0  # no heartbeat for this long: the page says the station is gone
DISCONNECT_TEXT = ("The station is not answering: its process stopped or the network connection is lost. "
                   "Restart it with procam station --resume on the session folder; every acknowledged capture "
                   "is in the session. This page reconnects by itself when the station is back.")


def heartbeat_html(beat: int) -> str:
    """A banner hidden by a CSS animation that shows it after SILENT_S seconds; every heartbeat replaces
    the element (new markup, so the animation starts over). When the station process is gone the
    heartbeats stop and the banner appears: no script needed in the page. Hidden, it takes no room."""
    return (f"<style>@keyframes procam-silent{{from{{visibility:hidden;max-height:0;padding:0}}"
            f"to{{visibility:visible;max-height:none;padding:0.6em 0.8em}}}}</style>"
            f"<div data-beat='{beat}' role='alert' style='visibility:hidden;max-height:0;overflow:hidden;padding:0;"
            f"animation:procam-silent 0s linear {SILENT_S:g}s forwards;background:#a51111;color:#fff;"
            f"font-weight:bold;border-radius:4px;opacity:1'>{html.escape(DISCONNECT_TEXT)}</div>")


class StationPanel:
    def __init__(self, station, host: str = "127.0.0.1", port: int = 8080, access_code: str | None = None,
                 rig_note: str = "", verbose: bool = False, gate: AccessGate | None = None):
        self.station = station
        self.machine = station.machine
        self.host = host
        self.access_code = access_code
        self.rig_note = rig_note
        self.gate = gate or AccessGate(host, access_code)
        self.gate.log = self._access_log
        # the gate answers every request before viser does (Origin, access code, throttle)
        self.server = start_viser_server(self.gate, host=host, port=port, label="procam station", verbose=verbose)
        self.port = self.server.get_port()
        self.seat = DriverSeat(self.machine.log)  # one browser drives, the others watch
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._scene_key = None
        self._global_cache: dict = {}
        self.image_updates = 0  # live images sent (the test and the caption read the rate)
        self.frames_shown = 0  # of which showed a camera frame not shown before (the rest: a new detection)
        self._image_times: list[float] = []
        self._last_image_key = None
        self._beat = 0
        self._loop_errors_seen = 0
        self._thumbs: dict = {}  # capture id -> thumbnail data URL
        self._predicted: dict = {}  # id(report or pixel check) -> {check index: predicted curve}
        self.suggestion = None  # where to hold the board next (panel_guidance.Suggestion)
        self._plane_key = None
        self.h_plane = None  # the clickable camera image in the 3D view (once calibrated)
        self._plane_s = 0.0
        self._report_key = None
        self.report_lock = threading.Lock()  # one report.html written at a time (auto and Download)
        self.controls = PanelControls(PanelContext(station, self.server, self.seat, self._lock, self.report_lock,
                                                   self.refresh, self.bars_now, self.click_camera))
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        self.server.gui.main_panel.dock_right()  # viser 1.1's replacement of control_layout="fixed"
        self.server.scene.set_up_direction("-y")
        ic = self.server.initial_camera  # behind and above the camera, looking at the rig (metres)
        ic.up = (0.0, -1.0, 0.0)
        ic.position = (-1.0, -1.6, -1.1)
        ic.look_at = (0.35, 0.1, 0.5)
        self._build_global()
        self.server.on_client_connect(self.controls.on_connect)
        self.server.on_client_disconnect(self.controls.on_disconnect)

    def _access_log(self, text: str) -> None:
        """Refused origins and wrong codes: the panel's log tab and the process log."""
        self.machine.log(text)
        _log.warning("procam station: %s", text)

    @property
    def url(self) -> str:
        """The panel's address from this machine (with the access code when one is needed)."""
        host = "127.0.0.1" if self.host in WILDCARD_HOSTS else self.host
        if ":" in host:
            host = f"[{host}]"
        base = f"http://{host}:{self.port}"
        return base + "/code/" + self.access_code if self.access_code is not None else base

    def network_urls(self) -> list[str]:
        """Addresses a tablet on the network may open (bound to all interfaces: this machine's IPv4s)."""
        if self.access_code is None:
            return []
        if self.host not in WILDCARD_HOSTS:
            return [self.url]
        hosts = sorted(h for h in self.gate.allowed_hosts
                       if h.count(".") == 3 and h.replace(".", "").isdigit() and not h.startswith("127."))
        return [f"http://{h}:{self.port}/code/{self.access_code}" for h in hosts]

    # ---- shared status ---------------------------------------------------------------------------
    def _build_global(self) -> None:
        g = self.server.gui
        self.h_alive = g.add_html(heartbeat_html(0), order=-1)
        self.h_alert = g.add_markdown("", order=-0.5, visible=False)
        self.h_title = g.add_markdown(self._title(), order=0)
        self.h_next = g.add_markdown("", order=1)
        self.h_activity = g.add_markdown("", order=1.1, visible=False)  # what runs, what the last actions came to
        # results at the top once calibrated (the Download button, per browser, sits just above)
        self.h_results_folder = g.add_folder("Results", order=2, visible=False)
        with self.h_results_folder:
            self.h_progress = g.add_progress_bar(0.0, animated=True, visible=False)
            self.h_results = g.add_markdown("No calibration yet.")
            with g.add_folder("Parameters and distortion"):
                self.h_params = g.add_markdown("")
            with g.add_folder("Projection uncertainty (1 sigma over the image)"):
                g.add_markdown(UNCERTAINTY_INTRO)
                self.h_unc = {dev: (g.add_markdown(""), g.add_image(np.zeros((8, 8, 3), np.uint8), format="png",
                                                                      label=f"{dev} projection uncertainty",
                                                                      visible=False))
                              for dev in UNCERTAINTY_DEVICES}
            with g.add_folder("Worst views (reprojection RMS)", expand_by_default=False):
                self.h_worst = g.add_markdown("")
            with g.add_folder("Files written", expand_by_default=False):
                self.h_files = g.add_markdown("")
        self.h_check = g.add_markdown("", order=5)
        with g.add_folder("3D view", order=7, expand_by_default=False):
            g.add_markdown(SCENE_LEGEND)
            self.h_view_rig = g.add_button("View the whole rig")
        self.h_view_rig.on_click(lambda event: view_whole_rig(self.server, event.client))
        # a second window, docked on the left of the 3D view: what the camera sees and what is covered
        self.live_panel = g.add_panel()
        with self.live_panel.add_tab("Live camera"):
            self.h_image = g.add_image(np.zeros((400, LIVE_WIDTH, 3), np.uint8), format="jpeg", jpeg_quality=70)
            self.h_live = g.add_markdown("")
            self.h_checks = g.add_markdown("")
            self.h_cov_text = g.add_markdown("")
            self.h_cov = g.add_image(np.zeros((8, 8, 3), np.uint8), format="png")
            self.h_bars_title = g.add_markdown("")
            self.h_bars = []
            for name in ("position x", "position y", "size", "tilt"):
                label = g.add_markdown(f"{name}")
                bar = g.add_progress_bar(0.0, color="orange")
                self.h_bars.append((label, bar))
        with self.live_panel.add_tab("Captures"):
            self.h_caps = g.add_html("")
        with self.live_panel.add_tab("Log"):
            self.h_log = g.add_markdown("")
        self.live_panel.dock_left()
        self.live_panel.set_width(LIVE_WIDTH + 40)

    def _title(self) -> str:
        folder = self.machine.store.folder
        lock = ""
        if self.access_code is not None:
            lock = " Served on the network: only browsers that gave the access code see this panel."
        return f"{self.rig_note} Session: `{folder}`.{lock}"

    def _set(self, handle, attr: str, value, key=None) -> None:
        """Set a handle's property only when it changed (every change is a message to every browser)."""
        key = key or (id(handle), attr)
        if self._global_cache.get(key) != value:
            self._global_cache[key] = value
            setattr(handle, attr, value)

    # ---- text (app/station/panel_status.py) ---------------------------------------------------------
    def checklist(self) -> str:
        return panel_status.checklist(self.machine)

    def log_text(self, n: int = panel_status.LOG_EVENTS) -> str:
        return panel_status.log_text(self.machine, n)

    def captures_html(self) -> str:
        m = self.machine
        per_view = {}
        if m.result is not None:
            for pv in m.result.per_view:
                if isinstance(pv, dict) and "capture_id" in pv:
                    per_view[pv["capture_id"]] = pv.get("rms_px")
        return captures_html(m.manifest.captures, m.store, per_view, self._thumbs)

    # ---- guidance ---------------------------------------------------------------------------------
    def step_features(self) -> list:
        m = self.machine
        step_caps = m.mirror_captures() if m.state == MIRROR_CAPTURE else m.captures_of(STEP_PROJECTOR)
        return [f for c in step_caps if isinstance(c.meta.get("pose"), dict)
                for f in [PoseFeatures.from_dict(c.meta["pose"])] if f is not None]

    def bars_now(self) -> list:
        return diversity_bars(self.step_features())

    def _update_guidance(self) -> None:
        """Coverage maps, bars with their targets and the next-pose suggestion (when the captures changed)."""
        m = self.machine
        best = m.next_placement
        asked = m.asked_pose
        key = (tuple(c.id for c in m.manifest.captures), m.state, m.target, best, id(asked))
        if self._global_cache.get("guidance") == key:
            return
        self._global_cache["guidance"] = key
        caps = m.manifest.captures
        cam_size = tuple(m.manifest.rig.camera_size)
        corners = capture_corners_px(caps)
        counts = coverage_grid(corners, cam_size)
        feats = self.step_features()
        bars = diversity_bars(feats)
        sugg = suggest_next(counts, feats, bars) if m.state in CAPTURE_STATES and m.target is not None else None
        self.suggestion = sugg
        tgt = m.target if m.state == PROJECTOR_CAPTURE else None
        dashed = best.position if best is not None else asked.position if asked is not None else None
        cam_img = camera_coverage_image(corners, cam_size, counts, sugg)
        proj_img = projector_coverage_image(m.manifest.pattern, tuple(m.manifest.rig.projector_size),
                                            m.position_counts(), m.plan.poses_per_position,
                                            None if tgt is None else tgt.pattern_position,
                                            None if dashed is None else position_area(
                                                m.manifest.pattern, *m.manifest.rig.projector_size, dashed))
        self.h_cov.image = side_by_side(cam_img, proj_img)
        step = "mirror" if m.state == MIRROR_CAPTURE else "projector"
        self._set(self.h_cov_text, "content",
                  f"**Coverage** (share of each image's {GRID_COLUMNS}-column grid cells holding a point). Camera: "
                  f"{coverage_summary(counts)}. Projector: coverage **{self.coverage_fraction() * 100:.0f}%** "
                  f"(pattern points captured; {m.counts()['positions_done']} of "
                  f"{m.positions} positions complete)." + (f"\n\n**Next:** {sugg.text}" if sugg else "")
                  + (f"\n\n**Next projector placement:** {best.reason()} (dashed on the projector map)."
                     if best is not None else "")
                  + (f"\n\n**Asked pose:** {asked.reason()} (its outline dashed on the camera image)."
                     if asked is not None else ""))
        self._set(self.h_bars_title, "content", f"**Board pose diversity** of the {step} captures (a full bar "
                                                "meets its target):")
        for (label, bar), b in zip(self.h_bars, bars):
            mark = "✔ target met" if b.met else f"target: a range of {b.target}"
            self._set(label, "content", f"{b.name}: {b.fraction * 100:.0f}% ({b.detail}; {mark})")
            self._set(bar, "value", float(round(b.fraction * 100.0, 1)))
            self._set(bar, "color", "green" if b.met else "orange")

    def coverages(self) -> dict[str, float]:
        """Coverage (calib.quality.coverage) of the camera by the board corners captured and of the
        projector by the pattern points captured."""
        m = self.machine
        return {"camera": float((coverage_grid(capture_corners_px(m.manifest.captures),
                                               tuple(m.manifest.rig.camera_size)) > 0).mean()),
                "projector": self.coverage_fraction()}

    def coverage_fraction(self) -> float:
        """Projector coverage (calib.quality.coverage) by the pattern points of the positions captured."""
        m = self.machine
        W, H = m.manifest.rig.projector_size
        pts = [m.manifest.pattern.points_px(W, H, p) for p, n in enumerate(m.position_counts()) if n > 0]
        return coverage_fraction(np.concatenate(pts) if pts else np.zeros((0, 2)), W, H)

    # ---- the live image -----------------------------------------------------------------------------
    def live_image(self, unless_key=None) -> tuple[np.ndarray, tuple] | None:
        """The newest frame, downscaled, with the newest detection, the verified pixels and the next-pose
        box drawn over it (RGB), and a key that changes when any of them does; None when there is no
        frame yet or the key is `unless_key` (nothing new to draw)."""
        st = self.station
        frame = st.frames.preview
        live = st.live
        if frame is None and live is None:
            return None
        if frame is None or (live is not None and live.frame_number > frame.frame_number):
            image, number = live.image, live.frame_number
        else:
            image, number = frame.image, frame.frame_number
        m = self.machine
        verifying = m.state in (CALIBRATION, VERIFICATION, DONE)
        rep = m.report if verifying and getattr(m.report, "checks", None) else None
        pc = st.pixel_check if verifying else None
        asked = m.asked_pose if m.state in CAPTURE_STATES else None
        key = (number, None if live is None else live.frame_number, m.state, id(self.suggestion), id(asked),
               id(rep), len(self._predicted.get(id(rep), {})), id(pc), len(self._predicted.get(id(pc), {})))
        if key == unless_key:
            return None
        det = live.detection if live is not None else None
        dec = live.decision if live is not None else None
        H, W = image.shape[:2]
        s = LIVE_WIDTH / W
        small = cv2.resize(image, (LIVE_WIDTH, int(round(H * s))), interpolation=cv2.INTER_AREA)
        if small.ndim == 2:
            small = cv2.cvtColor(small, cv2.COLOR_GRAY2BGR)
        draw_detection(small, det, s)
        if m.state in CAPTURE_STATES:
            draw_suggestion(small, self.suggestion)
            draw_asked_outline(small, asked)
        footer = ""
        if rep is not None or pc is not None:
            thr, factor = panel_status.verdict_threshold(m.report)
            if rep is not None:
                draw_checks(small, rep.checks, s, thr, factor, self._predicted.get(id(rep)))
            if pc is not None:
                draw_checks(small, [pc], s, thr, factor, self._predicted.get(id(pc)))
                footer = "pixel check " + panel_status.pixel_check_verdict(m.report, pc).replace("**", "")
        draw_banner(small, self._banner(det, dec), (80, 230, 80) if dec is not None and dec.capture else (240, 240, 240))
        draw_banner(small, footer, (240, 240, 240), top=False)
        if time.monotonic() - st.last_capture_s < 0.8:  # flash green: captured
            flash(small)
        return small[:, :, ::-1].copy(), key

    def _update_predicted(self) -> None:
        """Predicted curves for the verified pixels that carry none (from the calibration and the board's
        pose in the newest frame), once per report or pixel check."""
        m, st = self.machine, self.station
        if m.result is None or m.busy:
            return
        frame = st.frames.preview
        for obj, checks in ((m.report, getattr(m.report, "checks", None)), (st.pixel_check, None)):
            if obj is None or id(obj) in self._predicted:
                continue
            checks = list(checks) if checks is not None else [obj]
            self._predicted[id(obj)] = predicted_curves(m.result, checks, None if frame is None else frame.image,
                                                        m.manifest.projector_board)
        live_ids = {id(m.report), id(st.pixel_check)}
        for k in [k for k in self._predicted if k not in live_ids]:
            del self._predicted[k]

    def _banner(self, det, dec) -> str:
        m = self.machine
        if m.state not in CAPTURE_STATES:
            return STATE_TITLES[m.state]
        if det is None:
            return "no frame with the board detected yet"
        if dec is None:
            return det.failure or "waiting for the board to settle"
        if dec.capture:
            return "captured"
        parts = []
        if det.board is not None:
            parts.append(f"board {len(det.board.ids)} corners")
        if det.virtual is not None:
            parts.append(f"mirror image {len(det.virtual.ids)}")
        if det.pattern_px is not None:
            parts.append("pattern ok")
        return " | ".join(parts + [dec.message])

    # ---- 3D view -----------------------------------------------------------------------------------
    def click_camera(self):
        """The camera model the clickable image plane uses: the calibrated one, else the approximate one."""
        r = self.machine.result
        return r.camera if r is not None else self.station.camera_model

    def update_scene(self, force: bool = False) -> None:
        m = self.machine
        key = (tuple(c.id for c in m.manifest.captures), id(m.result))
        if key == self._scene_key and not force:
            return
        self._scene_key = key
        update_rig(self.server, m.manifest, m.result, self.station.camera_model)
        if m.result is not None and self._plane_key != id(m.result):
            self._plane_key = id(m.result)
            for ctl in list(self.controls.clients.values()):  # calibrated: show every browser the rig as it is now
                try:
                    view_whole_rig(self.server, ctl.client)
                except Exception:  # a browser that went away
                    pass
            centre, w, h, wxyz = camera_plane(m.result.camera)
            self.h_plane = self.server.scene.add_image(IMAGE_PLANE_NAME, np.zeros((8, 8, 3), np.uint8), w, h,
                                                       format="jpeg", jpeg_quality=70, position=tuple(centre),
                                                       wxyz=wxyz, cast_shadow=False)
            self.h_plane.on_click(self.controls.on_image_click)

    # ---- refresh loops --------------------------------------------------------------------------------
    def step_line(self) -> str:
        """The current step, its progress and what to do: the first thing an operator reads."""
        return panel_status.step_line(self.machine, self.station.instruction())

    def refresh(self) -> None:
        """Bring every status element (and every browser's controls) up to date."""
        with self._lock:
            m, st = self.machine, self.station
            self._set(self.h_next, "content", self.step_line())
            acts = activities_text(st.activities.all(), ended=0)  # outcomes: the line of whoever started it
            self._set(self.h_activity, "content", acts or " ")
            self._set(self.h_activity, "visible", bool(acts))
            self._set(self.h_check, "content", self.checklist())
            r = m.result
            self._set(self.h_results_folder, "visible", r is not None or bool(m.calibration_error)
                      or m.busy == "calibrating")
            self._set(self.h_results, "content", panel_status.results_summary(m, st.pixel_check))
            self._set(self.h_params, "content", parameters_text(r, bool(m.camera_intrinsics)) if r else "")
            self._set(self.h_worst, "content", worst_views_text(r) if r else "")
            self._update_uncertainty(r)
            files_key = folder_stamp(m.store.folder)
            if self._global_cache.get("files") != files_key:
                self._global_cache["files"] = files_key
                self._set(self.h_files, "content", files_text(m.store.folder))
            caps_key = (tuple(c.id for c in m.manifest.captures), id(r))
            if self._global_cache.get("caps") != caps_key:
                self._global_cache["caps"] = caps_key
                self._set(self.h_caps, "content", self.captures_html())
            self._set(self.h_log, "content", self.log_text())
            alert = panel_status.alert_text(st.frames)
            self._set(self.h_alert, "content", alert or " ")
            self._set(self.h_alert, "visible", bool(alert))
            self._notify_loop_errors()
            prog = st.progress if m.busy == "calibrating" else None
            self._set(self.h_progress, "visible", prog is not None)
            if prog is not None and prog[1] > 0:
                self._set(self.h_progress, "value", float(min(100.0, 100.0 * prog[0] / prog[1])))
            self._update_guidance()
            self._update_predicted()
            self._auto_report()
            if m.retake_target is None and st.autocap.avoided:  # the retaken slot is filled: the rule is spent
                st.autocap.forget_avoided()
            self._set(self.h_checks, "content", panel_status.checks_text(m, st.pixel_check))
            self.controls.refresh_all()
            self.update_scene()

    def _update_uncertainty(self, r) -> None:
        """The projection-uncertainty heat maps and their numbers, redrawn once per calibration."""
        if "uncertainty" in self._global_cache and self._global_cache["uncertainty"] is r:  # (not id: reusable)
            return
        self._global_cache["uncertainty"] = r
        images = {dev: uncertainty_image(r, dev) if r is not None else None for dev in self.h_unc}
        cov = self.coverages()
        for dev, (text, image) in self.h_unc.items():
            if images[dev] is not None:
                image.image = images[dev]
            image.visible = images[dev] is not None
            text.content = uncertainty_text(r, dev, cov.get(dev)) if r is not None else ""

    def _auto_report(self) -> None:
        """After each calibration and each verification: report.html in the session (app.report, when
        installed), written in the background; the log says where, or why not."""
        m = self.machine
        key = (id(m.result), id(m.report))
        if m.result is None or m.result_stale or m.busy or key == self._report_key:
            return
        self._report_key = key

        def work():
            with self.report_lock:
                path, why = write_report_if_available(m.store.folder)
            if path is not None:
                m.log(f"report written: {path}")
            elif why != REPORT_MISSING:
                m.log(f"report.html not written: {why}")

        threading.Thread(target=work, name="panel-report", daemon=True).start()

    def _notify_loop_errors(self) -> None:
        """A toast in every browser for each unexpected error of the capture loop."""
        errors = list(self.station.frames.loop_errors)
        new, self._loop_errors_seen = errors[self._loop_errors_seen:], len(errors)
        for e in new[-3:]:
            for ctl in list(self.controls.clients.values()):
                try:
                    ctl.client.add_notification("Capture loop failed", f"{e.summary}. It restarts; the "
                                                "traceback is in the Log tab.", auto_close_seconds=10.0, color="red")
                except Exception:  # a browser that went away; the banner says the same
                    pass

    def heartbeat(self) -> None:
        self._beat += 1
        self.h_alive.content = heartbeat_html(self._beat)

    def _heartbeat_loop(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                self.heartbeat()
            except Exception:  # the server is stopping
                pass

    def _status_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.refresh()
            except Exception as e:  # keep the panel alive; the log shows what went wrong
                self.machine.log(f"panel refresh failed: {e!r}")
            self._stop.wait(0.25)

    def _image_loop(self, rate_hz: float = IMAGE_RATE_HZ) -> None:
        period = 1.0 / rate_hz
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                out = self.live_image(unless_key=self._last_image_key)
                if out is not None:
                    img, key = out
                    if key != self._last_image_key:
                        if self._last_image_key is None or key[0] != self._last_image_key[0]:
                            self.frames_shown += 1
                        self._last_image_key = key
                        self.h_image.image = img
                        self.image_updates += 1
                        self._image_times.append(time.monotonic())
                        del self._image_times[:-60]
                        frames = self.station.frames
                        self._set(self.h_live, "content",
                                  f"Live: {rate_text(self.image_rate)} updates/s, camera {rate_text(frames.preview_fps)} "
                                  f"frames/s, detection {rate_text(frames.detection_fps)}/s. {LEGEND}")
                        if self.h_plane is not None and t0 - self._plane_s >= 1.0 / PLANE_RATE_HZ:
                            self._plane_s = t0
                            self.h_plane.image = img
            except Exception as e:  # keep drawing; the log shows what went wrong
                self.machine.log(f"live image failed: {e!r}")
                time.sleep(0.5)
            time.sleep(max(0.0, period - (time.monotonic() - t0)))

    @property
    def image_rate(self) -> float:
        """Live images sent per second over the last two seconds."""
        return rate_of(self._image_times)

    def start(self) -> None:
        self.refresh()
        for target, name in ((self._status_loop, "panel-status"), (self._image_loop, "panel-image"),
                             (self._heartbeat_loop, "panel-heartbeat")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(3.0)
        self.server.stop()
