"""The station's browser panel (viser): status for everyone, controls for whoever may operate the rig.

Shared by every browser (server.gui): what to do next, the checklist with counts, the live camera image
with detections drawn over it, the projector's coverage by the pattern positions captured, the board
pose diversity bars, results (RMS errors, uncertainties, verification verdict), the captures and a log;
and the 3D view of the rig (server.scene).

Per browser (client.gui): the operator's buttons. Who may connect at all is decided before the
websocket opens (app/station/access.py, hooked into viser by app/station/_origin.py): only pages the
panel served itself (their Origin), and served on a network only browsers that gave the access code; a
browser without it gets a page asking for the code and nothing of the session.

A heartbeat element makes the page say so when the station process is gone (`DISCONNECT_TEXT`), and a
banner shows when the capture loop failed (restarted) or stopped.

Detection runs in the station's own threads; the panel only draws: the live image is redrawn from the
newest frame and the newest detection about 12 times a second.
"""

from __future__ import annotations

import html
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.station._origin import start_viser_server
from app.station.access import LOOPBACK_HOSTS, WILDCARD_HOSTS, AccessGate, new_access_code  # noqa: F401
from app.station.autocapture import PoseFeatures, diversity_bars
from app.station.machine import (
    CALIBRATION,
    CAPTURE_STATES,
    CHECK_RIG,
    DONE,
    MIRROR_CAPTURE,
    PROJECTOR_CAPTURE,
    STATE_TITLES,
    STATES,
    VERIFICATION,
    ActionRefused,
)
from app.station.rigview import rig_scene
from calib.errors import ProcamError
from calib.observations import STEP_PROJECTOR

LIVE_WIDTH = 640
COVERAGE_WIDTH = 384


def rate_of(times, window_s: float = 2.0) -> float:
    """Events per second over the last `window_s` seconds of a list of time.monotonic() stamps."""
    now = time.monotonic()
    return sum(1 for t in list(times) if now - t <= window_s) / window_s


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
    heartbeats stop and the banner appears: no script needed in the page."""
    return (f"<style>@keyframes procam-silent{{from{{visibility:hidden}}to{{visibility:visible}}}}</style>"
            f"<div data-beat='{beat}' role='alert' style='visibility:hidden;animation:procam-silent 0s linear "
            f"{SILENT_S:g}s forwards;background:#a51111;color:#fff;font-weight:bold;padding:0.6em 0.8em;"
            f"border-radius:4px;opacity:1'>{html.escape(DISCONNECT_TEXT)}</div>")


@dataclass
class ClientControls:
    client: object
    unlocked: bool
    handles: dict = field(default_factory=dict)
    cache: dict = field(default_factory=dict)


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
        self._clients: dict[int, ClientControls] = {}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._scene_key = None
        self._global_cache: dict = {}
        self.image_updates = 0  # live images sent (the test and the caption read the rate)
        self._image_times: list[float] = []
        self._last_image_key = None
        self._beat = 0
        self._loop_errors_seen = 0
        self.server.gui.configure_theme(control_width="large", control_layout="fixed", show_share_button=False)
        self.server.scene.set_up_direction("-y")
        ic = self.server.initial_camera  # behind and above the camera, looking at the rig (metres)
        ic.up = (0.0, -1.0, 0.0)
        ic.position = (-1.0, -1.6, -1.1)
        ic.look_at = (0.35, 0.1, 0.5)
        self._build_global()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)

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
        self.h_check = g.add_markdown("", order=2)
        with g.add_folder("Results", order=6):
            self.h_progress = g.add_progress_bar(0.0, animated=True, visible=False)
            self.h_results = g.add_markdown("No calibration yet.")
        # a second window, docked on the left of the 3D view: what the camera sees and what is covered
        self.live_panel = g.add_panel()
        with self.live_panel.add_tab("Live camera"):
            self.h_image = g.add_image(np.zeros((400, LIVE_WIDTH, 3), np.uint8), format="jpeg", jpeg_quality=75)
            self.h_live = g.add_markdown("")
            self.h_cov_text = g.add_markdown("")
            self.h_cov = g.add_image(self._coverage_image(), format="png")
            self.h_bars = []
            for name in ("position x", "position y", "size", "tilt"):
                label = g.add_markdown(f"{name}")
                bar = g.add_progress_bar(0.0, color="teal")
                self.h_bars.append((label, bar))
        with self.live_panel.add_tab("Captures"):
            self.h_caps = g.add_markdown("")
        with self.live_panel.add_tab("Log"):
            self.h_log = g.add_markdown("")
        self.live_panel.dock_left()
        self.live_panel.set_width(LIVE_WIDTH + 40)

    def _title(self) -> str:
        folder = self.machine.store.folder
        lock = ""
        if self.access_code is not None:
            lock = " Served on the network: only browsers that gave the access code see this panel."
        return f"### procam station\n{self.rig_note}\n\nSession: `{folder}`.{lock}"

    def _set(self, handle, attr: str, value, key=None) -> None:
        """Set a handle's property only when it changed (every change is a message to every browser)."""
        key = key or (id(handle), attr)
        if self._global_cache.get(key) != value:
            self._global_cache[key] = value
            setattr(handle, attr, value)

    # ---- text -------------------------------------------------------------------------------------
    def checklist(self) -> str:
        m = self.machine
        s = m.state
        idx = STATES.index(s)
        c = m.counts()

        def mark(state):
            i = STATES.index(state)
            if state == CALIBRATION and m.result is not None and not m.result_stale and s != CALIBRATION:
                return "✔"
            if i < idx:
                return "✔"
            return "▶" if i == idx else "○"

        checks = "; ".join(f"{ch.name} {'ok' if ch.ok else 'FAILED: ' + ch.detail}" for ch in m.rig_checks)
        lines = ["**Checklist**", ""]
        lines.append(f"- {mark(CHECK_RIG)} **Check the rig**" + (f": {checks}" if checks else ": not checked yet"))
        if m.direct:
            lines.append("- ✔ **Mirror capture**: none needed (direct view)")
        else:
            method = m.mirror_method or "method not chosen"
            lines.append(f"- {mark(MIRROR_CAPTURE)} **Mirror capture** ({method}): "
                         f"**{c['mirror']} / {c['mirror_total'] or '?'}** captures")
        lines.append(f"- {mark(PROJECTOR_CAPTURE)} **Projector capture**: **{c['projector']} / {c['projector_total']}** "
                     f"captures, {c['positions_done']} / {c['positions']} pattern positions complete")
        cam = (f"camera from `{Path(m.camera_intrinsics).name}` (given)" if m.camera_intrinsics
               else "camera from the captures")
        cal = "done" if m.result is not None and not m.result_stale else (
            "out of date: re-run" if m.result is not None else "not run")
        if m.busy == "calibrating":
            cal = "running"
        lines.append(f"- {mark(CALIBRATION)} **Calibration** ({cam}, mirror, projector): {cal}")
        ver = "not run"
        if m.busy == "verifying":
            ver = "running"
        elif m.report is not None:
            ver = "passed" if getattr(m.report, "passed", False) else "FAILED"
        elif m.why_not("verify") == "verification is not available in this installation":
            ver = "not available"
        lines.append(f"- {mark(VERIFICATION)} **Verification**: {ver}")
        lines.append(f"- {mark(DONE)} **Done**")
        return "\n".join(lines)

    def results_text(self) -> str:
        m = self.machine
        r = m.result
        if r is None:
            if m.calibration_error:
                return f"**Calibration failed:** {m.calibration_error}"
            return "No calibration yet."
        u = r.uncertainty or {}

        def pm(group, key, digits=2):
            v = (u.get(group) or {}).get(key) if isinstance(u.get(group), dict) else None
            return f" ± {v:.{digits}f}" if isinstance(v, (int, float)) else ""

        lines = []
        if m.result_stale:
            lines.append("**Out of date:** the captures or the camera model changed; re-run the calibration.\n")
        rms = ", ".join(f"{k} {v:.3f} px" for k, v in r.rms.items() if isinstance(v, (int, float)))
        lines.append(f"**Calibration** ({r.method}, units {r.units}). RMS: {rms}")
        lines.append("")
        lines.append("| device | fx | fy | cx | cy |")
        lines.append("|---|---|---|---|---|")
        for name, cam, grp in (("camera", r.camera, "camera"), ("projector", r.projector, "projector")):
            lines.append(f"| {name} | {cam.fx:.2f}{pm(grp, 'fx')} | {cam.fy:.2f}{pm(grp, 'fy')} | "
                         f"{cam.cx:.2f}{pm(grp, 'cx')} | {cam.cy:.2f}{pm(grp, 'cy')} |")
        lines.append("")
        t = r.T_cam_proj[:3, 3]
        ang = float(np.degrees(np.arccos(np.clip((np.trace(r.T_cam_proj[:3, :3]) - 1) / 2, -1, 1))))
        tu = (u.get("T_cam_proj") or {}) if isinstance(u.get("T_cam_proj"), dict) else {}
        t_pm = f" (± {tu['t_total']:.2f})" if isinstance(tu.get("t_total"), (int, float)) else ""
        r_pm = f" (± {tu['rot_total_deg']:.3f} deg)" if isinstance(tu.get("rot_total_deg"), (int, float)) else ""
        lines.append(f"Projector in the camera frame: [{t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}] {r.units}{t_pm}, "
                     f"rotated {ang:.2f} deg{r_pm}")
        if r.mirror is not None:
            n = r.mirror.normal
            mu = u.get("mirror") if isinstance(u.get("mirror"), dict) else {}
            extra = ""
            if isinstance(mu.get("d"), (int, float)) and isinstance(mu.get("normal_deg"), (int, float)):
                extra = f" (± {mu['d']:.2f} {r.units}, normal ± {mu['normal_deg']:.3f} deg)"
            lines.append(f"\nMirror: normal [{n[0]:.4f}, {n[1]:.4f}, {n[2]:.4f}], d {r.mirror.d:.2f} {r.units}{extra}")
        if r.skipped:
            lines.append(f"\nSkipped {len(r.skipped)} capture(s): " + "; ".join(
                f"{s.get('capture_id', '?')}: {s.get('reason', '')}" for s in list(r.skipped)[:5]))
        rep = m.report
        if rep is not None:
            verdict = "PASSED" if getattr(rep, "passed", False) else "FAILED"
            summary = rep.summary() if hasattr(rep, "summary") else ""
            lines.append(f"\n**Verification {verdict}** (threshold {getattr(rep, 'threshold_px', float('nan')):.2f} "
                         f"projector px): {summary}")
        elif m.verification_error:
            lines.append(f"\n**Verification could not run:** {m.verification_error}")
        return "\n".join(lines)

    def captures_text(self, limit: int = 12) -> str:
        m = self.machine
        caps = list(m.manifest.captures)
        if not caps:
            return "No captures yet."
        per_view = {}
        if m.result is not None:
            for pv in m.result.per_view:
                if isinstance(pv, dict) and "capture_id" in pv:
                    per_view[pv["capture_id"]] = pv.get("rms_px")
        lines = [f"{len(caps)} captures (newest first):", "", "| id | step | position | pose | how | RMS px |",
                 "|---|---|---|---|---|---|"]
        for c in reversed(caps[-limit:]):
            pos = "" if c.pattern_position is None else str(c.pattern_position + 1)
            rms = per_view.get(c.id)
            lines.append(f"| {c.id} | {c.step} | {pos} | {c.meta.get('pose_index', 0) + 1} | {c.meta.get('how', '')} | "
                         f"{'' if rms is None else f'{rms:.3f}'} |")
        return "\n".join(lines)

    def log_text(self, n: int = 10) -> str:
        evs = self.machine.events[-n:]
        if not evs:
            return "Nothing yet."
        lines = []
        for e in reversed(evs):
            head, _, rest = e.text.partition("\n")
            lines.append(f"- {time.strftime('%H:%M:%S', time.localtime(e.time_s))} {head}")
            if rest.strip():  # a traceback: kept as it is, in a code block under its line
                lines.append("")
                lines.append("  ```")
                lines += ["  " + ln for ln in rest.rstrip().splitlines()]
                lines.append("  ```")
        return "\n".join(lines)

    def alert_text(self) -> str:
        """The banner over the panel when the capture loop failed: restarted, or stopped for good."""
        st = self.station
        stopped = getattr(st, "loop_stopped", None)
        if stopped:
            return f"**The capture loop stopped.** {stopped}"
        errors = getattr(st, "loop_errors", [])
        if errors and time.monotonic() - errors[-1].time_s < 20.0:
            e = errors[-1]
            return (f"**The capture loop failed and was restarted** ({e.summary}). The traceback is in the Log "
                    "tab; if it keeps failing, restart the station with --resume.")
        return ""

    # ---- images -----------------------------------------------------------------------------------
    def _coverage_image(self) -> np.ndarray:
        """The projector image with the pattern positions: green complete, orange started, grey not yet,
        the one shown now outlined in white."""
        m = self.machine
        W, H = m.manifest.rig.projector_size
        s = COVERAGE_WIDTH / W
        h = int(round(H * s))
        img = np.full((h, COVERAGE_WIDTH, 3), 40, np.uint8)
        pat = m.manifest.pattern
        counts = m.position_counts()
        ppp = m.plan.poses_per_position
        tgt = m.target if m.state == PROJECTOR_CAPTURE else None
        pad = pat.radius_px if pat.kind == "circles" else pat.spacing_px
        for p in range(pat.positions):
            pts = pat.points_px(W, H, p)
            x0, y0 = (pts.min(axis=0) - pad) * s
            x1, y1 = (pts.max(axis=0) + pad) * s
            p0, p1 = (int(x0), int(y0)), (int(x1), int(y1))
            if counts[p] >= ppp:
                colour = (90, 190, 60)
            elif counts[p] > 0:
                colour = (40, 150, 240)
            else:
                colour = None
            if colour is not None:
                over = img.copy()
                cv2.rectangle(over, p0, p1, colour, -1)
                img = cv2.addWeighted(over, 0.55, img, 0.45, 0)
            cv2.rectangle(img, p0, p1, (150, 150, 150), 1)
            cv2.putText(img, str(p + 1), (p0[0] + 3, p0[1] + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (230, 230, 230), 1,
                        cv2.LINE_AA)
            if tgt is not None and tgt.pattern_position == p:
                cv2.rectangle(img, p0, p1, (255, 255, 255), 2)
        return img[:, :, ::-1].copy()  # RGB

    def coverage_fraction(self) -> float:
        m = self.machine
        W, H = m.manifest.rig.projector_size
        s = 0.1
        mask = np.zeros((int(H * s) + 1, int(W * s) + 1), np.uint8)
        pat = m.manifest.pattern
        pad = pat.radius_px if pat.kind == "circles" else pat.spacing_px
        for p, n in enumerate(m.position_counts()):
            if n > 0:
                pts = pat.points_px(W, H, p)
                x0, y0 = ((pts.min(axis=0) - pad) * s).astype(int)
                x1, y1 = ((pts.max(axis=0) + pad) * s).astype(int)
                mask[max(y0, 0):y1 + 1, max(x0, 0):x1 + 1] = 1
        return float(mask.mean())

    def live_image(self) -> tuple[np.ndarray, tuple] | None:
        """The newest frame, downscaled, with the newest detection drawn over it (RGB)."""
        st = self.station
        frame = st.preview
        live = st.live
        if frame is None and live is None:
            return None
        if frame is None or (live is not None and live.frame_number > frame.frame_number):
            image, number = live.image, live.frame_number
        else:
            image, number = frame.image, frame.frame_number
        det = live.detection if live is not None else None
        dec = live.decision if live is not None else None
        key = (number, None if live is None else live.frame_number)
        H, W = image.shape[:2]
        s = LIVE_WIDTH / W
        small = cv2.resize(image, (LIVE_WIDTH, int(round(H * s))), interpolation=cv2.INTER_AREA)
        if small.ndim == 2:
            small = cv2.cvtColor(small, cv2.COLOR_GRAY2BGR)
        if det is not None:
            if det.board is not None:
                for x, y in det.board.corners_px * s:
                    cv2.circle(small, (int(round(x)), int(round(y))), 2, (60, 220, 60), -1, cv2.LINE_AA)
            if det.virtual is not None:
                for x, y in det.virtual.corners_px * s:
                    cv2.circle(small, (int(round(x)), int(round(y))), 2, (230, 200, 40), -1, cv2.LINE_AA)
            if det.pattern_px is not None:
                pts = np.round(det.pattern_px * s).astype(np.int32)
                cv2.polylines(small, [pts.reshape(-1, 1, 2)], False, (200, 60, 220), 1, cv2.LINE_AA)
                for x, y in pts:
                    cv2.circle(small, (int(x), int(y)), 3, (220, 80, 240), 1, cv2.LINE_AA)
        pc = st.pixel_check
        if pc is not None and self.machine.state in (CALIBRATION, VERIFICATION, DONE):
            ov = pc.overlay()
            if ov.get("predicted") is not None and len(ov["predicted"]) > 1:
                pts = np.round(np.asarray(ov["predicted"]) * s).astype(np.int32)
                cv2.polylines(small, [pts.reshape(-1, 1, 2)], False, (40, 200, 240), 1, cv2.LINE_AA)
            if ov.get("detected") is not None and len(ov["detected"]) > 1:
                pts = np.round(np.asarray(ov["detected"]) * s).astype(np.int32)
                cv2.polylines(small, [pts.reshape(-1, 1, 2)], False, (240, 220, 60), 2, cv2.LINE_AA)
            px, py = (int(round(v * s)) for v in ov["pixel"])
            cv2.drawMarker(small, (px, py), (40, 40, 240), cv2.MARKER_CROSS, 14, 2)
            hh = small.shape[0]
            cv2.rectangle(small, (0, hh - 22), (LIVE_WIDTH, hh), (0, 0, 0), -1)
            cv2.putText(small, str(ov.get("label", ""))[:95], (6, hh - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                        (240, 240, 240), 1, cv2.LINE_AA)
            key = key + (id(pc),)
        banner = self._banner(det, dec)
        if banner:
            cv2.rectangle(small, (0, 0), (LIVE_WIDTH, 22), (0, 0, 0), -1)
            colour = (80, 230, 80) if dec is not None and dec.capture else (240, 240, 240)
            cv2.putText(small, banner[:90], (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
        if time.monotonic() - self.station.last_capture_s < 0.8:  # flash green: captured
            cv2.rectangle(small, (0, 0), (small.shape[1] - 1, small.shape[0] - 1), (60, 230, 60), 4)
        return small[:, :, ::-1].copy(), key

    def _banner(self, det, dec) -> str:
        m = self.machine
        if m.state not in CAPTURE_STATES:
            return STATE_TITLES[m.state]
        if det is None:
            return "waiting for a frame"
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
    def update_scene(self, force: bool = False) -> None:
        m = self.machine
        key = (tuple(c.id for c in m.manifest.captures), id(m.result))
        if key == self._scene_key and not force:
            return
        self._scene_key = key
        sc = rig_scene(m.manifest, m.result, self.station.camera_model)
        k = sc.to_m
        scene = self.server.scene
        from viser import transforms as vtf

        def pose(T):
            return vtf.SO3.from_matrix(np.asarray(T[:3, :3])).wxyz, np.asarray(T[:3, 3]) * k

        scene.add_frame("/rig", show_axes=False)
        q, p = pose(sc.camera.T_cam_dev)
        scene.add_camera_frustum("/rig/camera", sc.camera.fov_v_rad, sc.camera.aspect, scale=0.08,
                                 color=(40, 110, 230), wxyz=q, position=p)
        scene.add_label("/rig/camera/label", "camera", position=(0, -0.08, 0))
        if sc.virtual_camera is not None:
            q, p = pose(sc.virtual_camera.T_cam_dev)
            scene.add_camera_frustum("/rig/virtual_camera", sc.virtual_camera.fov_v_rad, sc.virtual_camera.aspect,
                                     scale=0.08, color=(150, 150, 150), wxyz=q, position=p)
            scene.add_label("/rig/virtual_camera/label", "virtual camera", position=(0, -0.08, 0))
        if sc.mirror_quad is not None:
            v = sc.mirror_quad * k
            scene.add_mesh_simple("/rig/mirror", v.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
                                  color=(150, 200, 240), opacity=0.45, side="double")
        if sc.projector is not None:
            q, p = pose(sc.projector.T_cam_dev)
            scene.add_camera_frustum("/rig/projector", sc.projector.fov_v_rad, sc.projector.aspect, scale=0.1,
                                     color=(240, 140, 30), wxyz=q, position=p)
            scene.add_label("/rig/projector/label", "projector", position=(0, -0.1, 0))
        if len(sc.rays):
            scene.add_line_segments("/rig/rays", (sc.rays * k).astype(np.float32), (250, 170, 60), thickness=0.002)
        else:
            try:
                scene.remove_by_name("/rig/rays")
            except Exception:
                pass
        groups = {"mirror step": ((60, 200, 90), []), "projector step": ((240, 150, 40), []),
                  "seen in the mirror": ((170, 170, 170), [])}
        for b in sc.boards:
            key = "mirror step" if b.step != STEP_PROJECTOR else ("seen in the mirror" if b.virtual else "projector step")
            groups[key][1].append(b.outline * k)
        for key, (col, quads) in groups.items():
            name = "/rig/boards/" + key.replace(" ", "_")
            if not quads:
                try:
                    scene.remove_by_name(name)
                except Exception:
                    pass
                continue
            v = np.concatenate(quads).astype(np.float32)
            f = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i for i in range(len(quads))]).astype(np.uint32)
            scene.add_mesh_simple(name, v, f, color=col, opacity=0.35, side="double")
            segs = np.array([[q[i], q[(i + 1) % 4]] for q in quads for i in range(4)], np.float32)
            scene.add_line_segments(name + "_edges", segs, col, thickness=0.002)
        # frame the rig for browsers that connect from now on
        pts = [np.zeros(3)] + [b.outline.mean(axis=0) * k for b in sc.boards]
        if sc.mirror_quad is not None:
            pts.append(sc.mirror_quad.mean(axis=0) * k)
        if sc.projector is not None:
            pts.append(sc.projector.T_cam_dev[:3, 3] * k)
        pts = np.array(pts)
        centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
        extent = float(max(np.ptp(pts, axis=0).max(), 0.6))
        ic = self.server.initial_camera
        ic.look_at = tuple(centre)
        ic.position = tuple(centre + extent * np.array([-0.9, -1.1, -1.0]))

    # ---- per-browser controls ------------------------------------------------------------------------
    def _on_connect(self, client) -> None:
        # every websocket reaching here passed the gate: the panel's own Origin (or the secret), and the
        # access code when one is needed; a browser without the code never gets this far
        ctl = ClientControls(client, unlocked=True)
        with self._lock:
            self._clients[client.client_id] = ctl
        self._build_controls(ctl)

    def _on_disconnect(self, client) -> None:
        with self._lock:
            self._clients.pop(client.client_id, None)

    def _build_controls(self, ctl: ClientControls) -> None:
        g = ctl.client.gui
        h = ctl.handles
        sim = self.station.is_sim
        with g.add_folder("Operate the rig", order=3):
            h["message"] = g.add_markdown("")
            with g.add_folder("Session", expand_by_default=True):
                h["check"] = g.add_button("Check rig")
                h["start"] = g.add_button("Start")
                h["next"] = g.add_button("Next step")
                h["back"] = g.add_button("Back")
            with g.add_folder("Mirror method"):
                h["real-virtual"] = g.add_button("Mirror: real-virtual")
                h["real-mirror"] = g.add_button("Mirror: real-mirror")
                h["thickness"] = g.add_number(f"Board thickness ({self.machine.manifest.units})",
                                              float(self.machine.manifest.board_thickness), min=0.0, step=0.1,
                                              hint="real-mirror: height of the printed face above the mirror")
                h["set_thickness"] = g.add_button("Set thickness")
            with g.add_folder("Capture"):
                h["capture"] = g.add_button("Capture")
                if sim:
                    h["move"] = g.add_button("Move board", hint="asks the simulated operator for the pose the station needs")
                h["retake_last"] = g.add_button("Retake last")
                h["auto_capture"] = g.add_checkbox("Auto-capture", self.station.options.auto_capture,
                                                   hint="capture when the board is still and in a new pose")
                if sim:
                    h["follow"] = g.add_checkbox("Simulated operator moves the board by itself",
                                                 bool(self.station.options.follow_operator))
                ids = self._capture_ids()
                h["which"] = g.add_dropdown("Capture to change", ids or ["(none)"], initial_value=(ids or ["(none)"])[0])
                h["retake"] = g.add_button("Retake selected")
                h["delete"] = g.add_button("Delete selected")
            with g.add_folder("Calibration"):
                h["calibrate"] = g.add_button("Calibrate")
                h["intrinsics"] = g.add_text("Intrinsics file", "", hint="calibration.json or OpenCV YAML of a "
                                                                        "pre-calibrated camera")
                h["skip_camera"] = g.add_button("Skip camera step")
                h["use_camera"] = g.add_button("Calibrate camera from captures")
                h["verify"] = g.add_button("Verify")
                h["finish"] = g.add_button("Finish")
            with g.add_folder("Check one pixel"):
                W, H = self.machine.manifest.rig.camera_size
                h["pixel_x"] = g.add_number("Pixel x", float(W // 2), min=0.0, max=float(W - 1), step=0.5)
                h["pixel_y"] = g.add_number("Pixel y", float(H // 2), min=0.0, max=float(H - 1), step=0.5)
                h["check_pixel"] = g.add_button("Check pixel", hint="the projector draws this camera pixel's "
                                                                    "epipolar curve; the camera measures how far it passes")
        st, m = self.station, self.machine
        actions = {
            "check": lambda: self._check(),
            "start": lambda: m.start_session(),
            "next": lambda: m.proceed(),
            "back": lambda: m.go_back(),
            "real-virtual": lambda: m.choose_mirror_method("real-virtual"),
            "real-mirror": lambda: m.choose_mirror_method("real-mirror"),
            "capture": lambda: st.capture_now(),
            "move": lambda: st.request_pose(),
            "retake_last": lambda: self._retake(None, ctl),
            "retake": lambda: self._retake(h["which"].value, ctl),
            "delete": lambda: m.delete_capture(self._selected(h["which"].value)),
            "calibrate": lambda: st.run_long("calibrate", st.calibrate),
            "skip_camera": lambda: m.skip_camera(h["intrinsics"].value.strip()),
            "use_camera": lambda: m.use_camera_calibration(),
            "set_thickness": lambda: m.set_board_thickness(h["thickness"].value),
            "verify": lambda: st.run_long("verify", st.verify),
            "finish": lambda: m.finish(),
            "check_pixel": lambda: self._check_pixel(h),
        }
        for name, fn in actions.items():
            if name in h:
                h[name].on_click(self._handler(ctl, name, fn))

        @h["auto_capture"].on_update
        def _(event):
            if self._allowed(ctl, event):
                st.options.auto_capture = bool(h["auto_capture"].value)

        if "follow" in h:
            @h["follow"].on_update
            def _(event):
                if self._allowed(ctl, event):
                    st.options.follow_operator = bool(h["follow"].value)
                    st._requested = None

        self._refresh_controls(ctl)

    def _allowed(self, ctl: ClientControls, event) -> bool:
        return ctl.unlocked and event.client_id == ctl.client.client_id

    def _selected(self, value):
        if not value or value == "(none)":
            raise ActionRefused("change a capture", "there are no captures yet")
        return value

    def _retake(self, capture_id, ctl):
        tgt = self.machine.retake(None if capture_id is None else self._selected(capture_id))
        if self.station.is_sim and not self.station.options.follow_operator:
            return f"asked for the same pose again: press Move board to put the board back (pose {tgt.pose_index + 1})"
        return tgt

    def _check_pixel(self, h):
        if self.machine.result is None:
            raise ActionRefused("check a pixel", "calibrate first")
        x, y = float(h["pixel_x"].value), float(h["pixel_y"].value)
        self.station.run_long("check pixel", lambda: self.station.check_pixel(x, y))
        return f"checking pixel ({x:.1f}, {y:.1f}); the result appears on the live image and in the log"

    def _check(self):
        checks = self.station.check_rig()
        bad = [c for c in checks if not c.ok]
        if bad:
            raise ActionRefused("check the rig", "; ".join(f"{c.name}: {c.detail}" for c in bad))
        return "the rig is ready"

    def _handler(self, ctl: ClientControls, name: str, fn):
        def on_click(event):
            if not self._allowed(ctl, event):
                return
            label = ctl.handles[name].label
            try:
                out = fn()
            except ActionRefused as e:
                self._message(ctl, f"**Refused: {label}.** {e.reason[:1].upper() + e.reason[1:]}.", error=True)
            except ProcamError as e:
                self._message(ctl, f"**{label} failed:** {e}", error=True)
            else:
                text = self._describe_outcome(name, out)
                self._message(ctl, f"**{label}:** {text}")
            self.refresh()

        return on_click

    def _describe_outcome(self, name, out) -> str:
        if name == "capture" and out is not None:
            return f"{out.id} written to the session"
        if name in ("calibrate", "verify"):
            return "running; the results appear below when it is done"
        if name == "move" and isinstance(out, str):
            return out
        if isinstance(out, str):
            return out.replace("_", " ")
        return "done"

    def _message(self, ctl: ClientControls, text: str, error: bool = False) -> None:
        h = ctl.handles.get("message")
        if h is not None:
            h.content = text
        if error:
            try:
                ctl.client.add_notification("Not possible now", text.replace("**", ""), auto_close_seconds=6.0,
                                            color="red")
            except Exception:  # a notification is a nicety; the message above says the same
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
                return {"real-virtual"}
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
            return {"verify"} if m.why_not("verify") is None else {"finish"}
        if s == VERIFICATION:
            return {"finish"} if m.report is not None else {"verify"}
        return set()

    def _refusals(self) -> dict[str, str | None]:
        m, st = self.machine, self.station
        last = m.last_capture.id if m.last_capture is not None else (m.manifest.captures[-1].id if m.manifest.captures else None)
        r = {
            "check": None if m.state == CHECK_RIG and not m.busy else "the rig is checked in the first step; go back to it",
            "start": m.why_not("start"),
            "next": m.why_not("proceed"),
            "back": m.why_not("back"),
            "real-virtual": m.why_not("choose_mirror_method", "real-virtual"),
            "real-mirror": m.why_not("choose_mirror_method", "real-mirror"),
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
            "check_pixel": ("calibrate first" if m.result is None else
                            f"the station is busy ({m.busy})" if m.busy else
                            None if m.state in (CALIBRATION, VERIFICATION, DONE) else
                            "pixels are checked after calibration"),
        }
        return r

    def _refresh_controls(self, ctl: ClientControls) -> None:
        h = ctl.handles
        if not h:
            return
        refusals = self._refusals()
        rec = self._recommended()
        m = self.machine
        for name, reason in refusals.items():
            b = h.get(name)
            if b is None:
                continue
            colour = "green" if name in rec and reason is None else ("gray" if reason else "blue")
            hint = reason[:1].upper() + reason[1:] if reason else None
            if ctl.cache.get((name, "color")) != colour:
                ctl.cache[(name, "color")] = colour
                b.color = colour
            if ctl.cache.get((name, "hint")) != hint:
                ctl.cache[(name, "hint")] = hint
                b.hint = hint
        label = "Re-run calibration" if m.result is not None else "Calibrate"
        if ctl.cache.get("cal_label") != label:
            ctl.cache["cal_label"] = label
            h["calibrate"].label = label
        ids = self._capture_ids() or ["(none)"]
        if ctl.cache.get("ids") != ids:
            ctl.cache["ids"] = ids
            cur = h["which"].value
            h["which"].options = ids
            h["which"].value = cur if cur in ids else ids[0]
        if "follow" in h and ctl.cache.get("follow") != bool(self.station.options.follow_operator):
            ctl.cache["follow"] = bool(self.station.options.follow_operator)
            h["follow"].value = ctl.cache["follow"]

    # ---- refresh loops --------------------------------------------------------------------------------
    def refresh(self) -> None:
        """Bring every status element (and every browser's controls) up to date."""
        with self._lock:
            m, st = self.machine, self.station
            self._set(self.h_next, "content", "**Next:** " + st.instruction())
            self._set(self.h_check, "content", self.checklist())
            self._set(self.h_results, "content", self.results_text())
            self._set(self.h_caps, "content", self.captures_text())
            self._set(self.h_log, "content", self.log_text())
            alert = self.alert_text()
            self._set(self.h_alert, "content", alert or " ")
            self._set(self.h_alert, "visible", bool(alert))
            self._notify_loop_errors()
            prog = st.progress if m.busy == "calibrating" else None
            self._set(self.h_progress, "visible", prog is not None)
            if prog is not None and prog[1] > 0:
                self._set(self.h_progress, "value", float(min(100.0, 100.0 * prog[0] / prog[1])))
            cov_key = (tuple(m.position_counts()), m.target, m.state)
            if self._global_cache.get("cov") != cov_key:
                self._global_cache["cov"] = cov_key
                self.h_cov.image = self._coverage_image()
            self._set(self.h_cov_text, "content",
                      f"Projector image covered by the pattern positions captured: **{self.coverage_fraction() * 100:.0f}%** "
                      f"({m.counts()['positions_done']} of {m.positions} positions complete). Board pose diversity of "
                      f"the {'mirror' if m.state == MIRROR_CAPTURE else 'projector'} captures:")
            step_caps = m.mirror_captures() if m.state == MIRROR_CAPTURE else m.captures_of(STEP_PROJECTOR)
            feats = [f for c in step_caps if isinstance(c.meta.get("pose"), dict)
                     for f in [PoseFeatures.from_dict(c.meta["pose"])] if f is not None]
            for (label, bar), b in zip(self.h_bars, diversity_bars(feats)):
                self._set(label, "content", f"{b.name}: {b.fraction * 100:.0f}% ({b.detail})")
                self._set(bar, "value", float(round(b.fraction * 100.0, 1)))
            for ctl in list(self._clients.values()):
                if ctl.unlocked:
                    try:
                        self._refresh_controls(ctl)
                    except Exception:  # a browser that went away mid-update
                        pass
            self.update_scene()

    def _notify_loop_errors(self) -> None:
        """A toast in every browser for each unexpected error of the capture loop."""
        errors = list(getattr(self.station, "loop_errors", []))
        new, self._loop_errors_seen = errors[self._loop_errors_seen:], len(errors)
        for e in new[-3:]:
            for ctl in list(self._clients.values()):
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

    def _image_loop(self, rate_hz: float = 12.0) -> None:
        period = 1.0 / rate_hz
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                out = self.live_image()
                if out is not None:
                    img, key = out
                    if key != self._last_image_key:
                        self._last_image_key = key
                        self.h_image.image = img
                        self.image_updates += 1
                        self._image_times.append(time.monotonic())
                        del self._image_times[:-60]
                        rate = self.image_rate
                        self._set(self.h_live, "content",
                                  f"Live: {rate:.0f} updates/s, camera {self.station.preview_fps:.0f} fps, "
                                  f"detection {self.station.detection_fps:.0f}/s. Green: board "
                                  "corners; yellow: board in the mirror; violet: projected pattern.")
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
