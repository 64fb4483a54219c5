"""The panel's websocket seen as viser's client sees it, and a small in-process station on the simulated
rig (the origin, access-code and malformed-input tests)."""

from __future__ import annotations

import re
import socket

import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from app.station.machine import Plan
from app.station.setup import RigRequest, create_session, make_machine, open_requested_rig
from app.station.station import Station, StationOptions

PROTOCOL = [f"viser-v{viser.__version__}"]


def ws_try(url: str, origin: str | None = None, source: str | None = None):
    """Open a websocket like viser's client does; returns (status, first message bytes or body)."""
    sock = None
    if source is not None:  # another loopback address as the client's (127.0.0.x)
        host, port = re.match(r"ws://([^:/]+):(\d+)", url).groups()
        sock = socket.socket()
        sock.bind((source, 0))
        sock.connect((host, int(port)))
    try:
        with connect(url, subprotocols=PROTOCOL, sock=sock, open_timeout=10,
                     **({"origin": origin} if origin is not None else {})) as c:
            return 101, c.recv(timeout=10)
    except InvalidStatus as e:
        return e.response.status_code, bytes(e.response.body or b"")


def sim_station(tmp_path, **opts) -> Station:
    req = RigRequest("sim", "nonoverlap-136", 0)
    rig = open_requested_rig(req)
    plan = Plan(poses_per_position=1, real_virtual_captures=3, min_real_virtual=3, min_projector_captures=6)
    store = create_session(tmp_path / "s", rig, req, plan)
    m = make_machine(store, rig, plan)
    return Station(rig, m, StationOptions(**opts))
