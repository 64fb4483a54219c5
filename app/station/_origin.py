"""Start viser's server with the station's access gate (app/station/access.py) in its HTTP handshake.

Why this module exists: viser 1.1 runs its own `websockets` server and offers no hook for the opening
handshake, so a web page on any other site could open a websocket to the panel and drive the rig. The
`websockets` library lets a server answer a request before the handshake (`process_request`); viser
passes its own (it serves the client's files that way). While a ViserServer is being constructed, and
only then, `websockets.asyncio.server.serve` is replaced by a wrapper that puts the gate in front of
viser's `process_request`: viser calls `serve` from its server thread while its constructor waits for
the server to be up, so the wrapper is in place for exactly that call and for no other server. If a
future viser starts its server some other way the wrapper is never called, and the station refuses to
start rather than run unprotected.

Before viser is asked, the address is bound once here (`check_bind`): viser retries the next port on any
bind failure and waits forever for a server that never comes up, so a host that is not this machine's
would hang the station; here it is one line naming --host or --port.

Responses the gate adds: 403 for a foreign Origin or a wrong code, 429 during a back-off, the page
asking for the access code, and `X-Frame-Options: DENY` on everything served (no framing of the panel
by another site).
"""

from __future__ import annotations

import dataclasses
import errno
import http
import socket
import threading

from app.station.access import AccessGate
from calib.errors import OptionError

_construct_lock = threading.Lock()


class OriginCheckUnavailable(RuntimeError):
    """viser did not start its server through websockets' serve(): the gate could not be installed."""


def _headers(content_type: str | None, length: int, extra: dict | None = None):
    from websockets.datastructures import Headers

    h = Headers()
    if content_type is not None:
        h["Content-Type"] = content_type
    h["Content-Length"] = str(length)
    h["Cache-Control"] = "no-store"
    h["X-Frame-Options"] = "DENY"
    h["Referrer-Policy"] = "no-referrer"
    for k, v in (extra or {}).items():
        h[k] = v
    return h


def gated_process_request(gate: AccessGate, inner):
    """A websockets `process_request` putting `gate` in front of `inner` (viser's file server)."""
    from websockets.http11 import Response

    def process_request(connection, request):
        client = str((connection.remote_address or ("?",))[0])
        port = int(connection.local_address[1])
        v = gate.check(request.path, request.headers, client, port)
        if v.location is not None:
            return Response(http.HTTPStatus.SEE_OTHER, "See Other", _headers(None, 0, {"Location": v.location}), b"")
        if not v.allowed:
            extra = {"Retry-After": str(int(v.retry_after_s + 0.999))} if v.status == 429 else None
            status = http.HTTPStatus(v.status)
            if v.page:
                body = gate.code_page(v.body).encode()
                ctype = "text/html; charset=utf-8"
            else:
                body = (v.body + "\n").encode()
                ctype = "text/plain; charset=utf-8"
            return Response(status, status.phrase, _headers(ctype, len(body), extra), body)
        if v.path is not None and v.path != request.path:
            request = dataclasses.replace(request, path=v.path)
        if inner is None:
            return None
        response = inner(connection, request)
        if response is not None:
            response.headers["X-Frame-Options"] = "DENY"
            response.headers["Referrer-Policy"] = "no-referrer"
            response.headers["Cache-Control"] = "no-store"
        return response

    return process_request


def check_bind(host: str, port: int) -> None:
    """An OptionError naming --host or --port unless a server can listen on (host, port). A port in use
    passes: viser then serves on the next free one (the panel prints the address it got)."""
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                          flags=socket.AI_PASSIVE)[0]
    except (socket.gaierror, UnicodeError, OverflowError) as e:
        raise OptionError(f"--host {host}: not a host name or address this machine can serve on "
                          f"({getattr(e, 'strerror', None) or e}); use 127.0.0.1, or 0.0.0.0 for the network") from None
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
        try:
            s.bind(addr)
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return
            if e.errno == errno.EADDRNOTAVAIL:
                raise OptionError(f"--host {host} is not an address of this machine; use 127.0.0.1, 0.0.0.0 "
                                  "(every network interface) or one of this machine's addresses") from None
            if e.errno == errno.EACCES:
                raise OptionError(f"--port {port}: not allowed to serve on it (ports below 1024 need "
                                  "administrator rights); choose a port from 1024 to 65535") from None
            raise OptionError(f"cannot serve on --host {host} --port {port}: {e.strerror or e}") from None


def guarded_handler(gate: AccessGate, handler):
    """viser's websocket `handler`, with an error it raises (a malformed message from a client: random
    bytes, a text frame, an unknown type, msgpack nested too deep) logged as one line through the gate's
    log and the connection closed, instead of the full traceback websockets prints for each."""
    from app.cli import terminal_safe

    async def handle(connection):
        try:
            await handler(connection)
        except Exception as e:  # noqa: BLE001  (anything a client sends; the station itself is not affected)
            client = str((connection.remote_address or ("?",))[0])
            text = (str(e).strip().splitlines() or [""])[0][:120]
            gate.log(terminal_safe(f"closed the websocket of {client}: a malformed message ({type(e).__name__}"
                                   + (f": {text}" if text else "") + ")"))
            await connection.close(1007, "malformed message")

    return handle


def start_viser_server(gate: AccessGate, **viser_kwargs):
    """`viser.ViserServer(**viser_kwargs)` with `gate` answering every request first."""
    import viser
    import websockets.asyncio.server as ws_server

    check_bind(viser_kwargs.get("host", "0.0.0.0"), viser_kwargs.get("port", 8080))

    installed = []
    original = ws_server.serve

    def serve(handler, *args, process_request=None, **kwargs):
        installed.append(True)
        return original(guarded_handler(gate, handler), *args,
                        process_request=gated_process_request(gate, process_request), **kwargs)

    with _construct_lock:
        ws_server.serve = serve
        try:
            server = viser.ViserServer(**viser_kwargs)
        finally:
            ws_server.serve = original
    if not installed:
        server.stop()
        raise OriginCheckUnavailable(
            f"viser {getattr(viser, '__version__', '?')} does not start its server through websockets' serve(); "
            "the panel's Origin check cannot be installed (app/station/_origin.py)")
    return server
