"""How live the station's panel is on this machine: camera frames, detections and live-image updates
per second while the station waits for captures on the simulated rig (mirror step: two ChArUco
detections per frame; projector step: board and pattern), plus the time of a whole headless session.
A live-image update is a new camera frame or a new detection drawn over the image; "new frames shown"
counts only the first (0 when the panel does not count them).

    python benchmarks/station_live.py [--seconds 8] [--session]

Prints a table. The panel redraws the live image from the newest frame with the newest detection; the
issue asks for at least 15 updates per second. Numbers depend on the load of the machine (printed).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def measure(step: str, seconds: float) -> dict:
    from app.station.machine import Plan
    from app.station.panel import StationPanel
    from app.station.setup import RigRequest, create_session, make_machine, open_rig
    from app.station.station import Station, StationOptions

    with tempfile.TemporaryDirectory() as tmp:
        req = RigRequest("sim", "nonoverlap-136", 0)
        rig = open_rig(req)
        plan = Plan()
        store = create_session(Path(tmp) / "s", rig, req, plan)
        m = make_machine(store, rig, plan)
        st = Station(rig, m, StationOptions(auto_capture=False, follow_operator=True))
        st.check_rig()
        m.start_session()
        m.choose_mirror_method("real-virtual")
        if step == "projector":
            m.plan = Plan(real_virtual_captures=0, min_real_virtual=0)
            m.proceed()
        import socket

        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        panel = StationPanel(st, "127.0.0.1", port)
        st.start_loop()
        panel.start()
        time.sleep(2.0)  # warm up
        n0, s0, f0 = panel.image_updates, getattr(panel, "frames_shown", 0), st.preview.frame_number if st.preview else 0
        t0 = time.monotonic()
        time.sleep(seconds)
        dt = time.monotonic() - t0
        out = {
            "step": step,
            "camera fps": (st.preview.frame_number - f0) / dt if st.preview else 0.0,
            "detections/s": st.detection_fps,
            "live image updates/s": (panel.image_updates - n0) / dt,
            "new frames shown/s": (getattr(panel, "frames_shown", 0) - s0) / dt,
        }
        st.stop_loop()
        panel.stop()
        return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--session", action="store_true", help="also time `procam session --rig sim --auto`")
    args = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    rows = [measure("mirror-real-virtual", args.seconds), measure("projector", args.seconds)]
    print(f"{'step':22s} {'camera fps':>11s} {'detections/s':>13s} {'live image updates/s':>21s} "
          f"{'new frames shown/s':>19s}")
    for r in rows:
        print(f"{r['step']:22s} {r['camera fps']:11.1f} {r['detections/s']:13.1f} {r['live image updates/s']:21.1f} "
              f"{r['new frames shown/s']:19.1f}")
    if args.session:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.monotonic()
            r = subprocess.run([sys.executable, "-m", "app", "session", "--rig", "sim", "--auto", "--out",
                                str(Path(tmp) / "demo")], cwd=ROOT, capture_output=True, text=True)
            dt = time.monotonic() - t0
            tail = [ln for ln in r.stdout.splitlines() if "vs ground truth" in ln or "verification" in ln]
            print(f"procam session --rig sim --auto: exit {r.returncode}, {dt:.1f} s wall")
            for ln in tail[-2:]:
                print("  " + ln.strip())
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
