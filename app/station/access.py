"""Who may use the station's panel: the websocket's Origin, the access code, and a throttle on wrong codes.

The rules (docs/STATION.md, "Security"):

- A websocket handshake whose `Origin` is not the panel's own (http(s)://<a name of this station>:<its
  port>) is refused with 403, so a web page the operator happens to visit cannot drive the rig.
  Browsers always send Origin; a client without one (a script) must present the per-start secret in
  the address (`ws://host:port/code/<secret>`) or is refused too.
- Served on the network, every client needs the access code: a browser without it gets a page asking
  for it and nothing of the session (no websocket, so no live image, log, paths or results).
- The access code is 80 random bits. Wrong codes are throttled per client address and per station with
  an exponential back-off (a try during the back-off is refused unchecked, HTTP 429), and every failure
  is logged.

This module is the policy only (no sockets); app/station/_origin.py hooks it into viser's server.
"""

from __future__ import annotations

import base64
import hmac
import html
import secrets
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable
from urllib.parse import parse_qs, quote, unquote, urlsplit

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
CODE_PREFIX = "/code/"
UNLOCK_PATH = "/unlock"


def new_access_code() -> str:
    """80 random bits as 16 base32 letters and digits in groups of four (easy to read out and type)."""
    raw = base64.b32encode(secrets.token_bytes(10)).decode("ascii").lower()
    return "-".join(raw[i:i + 4] for i in range(0, len(raw), 4))


def normalize_code(text: str) -> str:
    """What is compared: letters and digits, lower case (dashes, spaces and case do not matter)."""
    return "".join(ch for ch in str(text).lower() if ch.isascii() and ch.isalnum())


# ---- throttle --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Backoff:
    """`free_tries` failures are allowed, then each further failure doubles the wait before the next
    try: base_s, 2 base_s, 4 base_s, ... at most max_s."""

    free_tries: int
    base_s: float
    max_s: float

    def wait_after(self, failures: int) -> float:
        if failures < self.free_tries:
            return 0.0
        return float(min(self.max_s, self.base_s * 2.0 ** (failures - self.free_tries)))


class Throttle:
    """Failures and the back-off they earn, per key (a client address, or one key for the station)."""

    def __init__(self, backoff: Backoff, clock: Callable[[], float]):
        self.backoff = backoff
        self.clock = clock
        self._failures: dict[str, int] = {}
        self._until: dict[str, float] = {}

    def wait_s(self, key: str) -> float:
        return max(0.0, self._until.get(key, 0.0) - self.clock())

    def failures(self, key: str) -> int:
        return self._failures.get(key, 0)

    def failed(self, key: str) -> float:
        n = self._failures.get(key, 0) + 1
        self._failures[key] = n
        wait = self.backoff.wait_after(n)
        self._until[key] = self.clock() + wait
        if len(self._failures) > 10_000:  # many addresses: forget the ones whose back-off ran out
            now = self.clock()
            for k in [k for k, t in self._until.items() if t <= now][:5_000]:
                self._failures.pop(k, None)
                self._until.pop(k, None)
        return wait

    def succeeded(self, key: str) -> None:
        self._failures.pop(key, None)
        self._until.pop(key, None)


# ---- the gate -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Verdict:
    """What to do with one HTTP request or websocket handshake: pass it on (status 0, maybe with the
    path rewritten), or answer it with `status` and `body` (text, or the code page when `page`)."""

    status: int = 0
    body: str = ""
    page: bool = False
    path: str | None = None
    location: str | None = None
    retry_after_s: float = 0.0

    @property
    def allowed(self) -> bool:
        return self.status == 0


def machine_hosts() -> set[str]:
    """Names and addresses this machine may be reached by (for a panel bound to 0.0.0.0): its host name
    (and .local), the addresses it resolves to, and the addresses of its network interfaces."""
    out: set[str] = set()
    try:
        name = socket.gethostname()
    except OSError:
        name = ""
    if name:
        out |= {name.lower(), name.lower() + ".local"}
        try:
            out |= {ai[4][0] for ai in socket.getaddrinfo(name, None)}
        except OSError:
            pass
    out |= _interface_addresses()
    return {h.split("%")[0] for h in out if h}


def _interface_addresses() -> set[str]:
    out: set[str] = set()
    try:  # IPv4: SIOCGIFADDR on every interface (Linux)
        import fcntl
        import struct

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _, ifname in socket.if_nameindex():
                try:
                    req = struct.pack("256s", ifname.encode()[:15])
                    res = fcntl.ioctl(s.fileno(), 0x8915, req)
                    out.add(socket.inet_ntoa(res[20:24]))
                except OSError:
                    continue
    except (ImportError, OSError, AttributeError):
        pass
    try:  # IPv6: /proc/net/if_inet6 (32 hex digits per address)
        with open("/proc/net/if_inet6") as f:
            for line in f:
                h = line.split()[0]
                out.add(socket.inet_ntop(socket.AF_INET6, bytes.fromhex(h)))
    except (OSError, ValueError, IndexError):
        pass
    return out


def _bare_host(host: str) -> str:
    host = (host or "").strip().lower()
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host


class AccessGate:
    """The policy for one station. `code`: required from every client (served on the network), or None
    (loopback: browsers of the panel's own origin need no code). `secret` is what a client without an
    Origin header presents (the code when there is one, else drawn here)."""

    def __init__(self, host: str, code: str | None = None, *, clock: Callable[[], float] = time.monotonic,
                 per_client: Backoff = Backoff(5, 1.0, 60.0), per_station: Backoff = Backoff(20, 1.0, 60.0),
                 log: Callable[[str], None] | None = None, extra_hosts: tuple[str, ...] = ()):
        self.host = _bare_host(host)
        self.code = code
        self.secret = code if code is not None else new_access_code()
        self.clock = clock
        self.clients = Throttle(per_client, clock)
        self.station = Throttle(per_station, clock)
        self.log = log or (lambda text: None)
        hosts = set(LOOPBACK_HOSTS) | {_bare_host(h) for h in extra_hosts}
        if self.host in WILDCARD_HOSTS:
            hosts |= machine_hosts()
        elif self.host:
            hosts.add(self.host)
        self.allowed_hosts = frozenset(h.lower() for h in hosts)
        self.failed_tries = 0  # every wrong code and every try refused during a back-off
        self.refused_origins = 0
        self._lock = threading.Lock()
        self._throttled_logged: dict[str, float] = {}
        self._refusals_logged: dict = {}

    @property
    def code_required(self) -> bool:
        return self.code is not None

    # ---- origin -----------------------------------------------------------------------------------
    def origin_allowed(self, origin: str, port: int) -> bool:
        try:
            u = urlsplit(origin.strip())
            default = {"http": 80, "https": 443}.get(u.scheme)
            origin_port = u.port or default
        except ValueError:
            return False
        if default is None or u.hostname is None or u.path not in ("", "/") or u.username or u.query:
            return False
        return u.hostname.lower() in self.allowed_hosts and origin_port == int(port)

    # ---- codes ------------------------------------------------------------------------------------
    def try_code(self, given: str, client: str) -> Verdict:
        """Check a code from `client` (its address), with the throttle; logs every failure."""
        with self._lock:
            wait = max(self.clients.wait_s(client), self.station.wait_s("station"))
            if wait > 0:
                self.failed_tries += 1
                last = self._throttled_logged.get(client, -1e18)
                if self.clock() - last >= min(wait, 10.0):  # one line per back-off period, at most every 10 s
                    self._throttled_logged[client] = self.clock()
                    self.log(f"access code try from {client} refused unchecked: too many wrong codes, next try "
                             f"in {wait:.0f} s")
                return Verdict(429, f"Too many wrong access codes; try again in {wait:.0f} s.", retry_after_s=wait)
            if hmac.compare_digest(normalize_code(given).encode(), normalize_code(self.secret).encode()):
                self.clients.succeeded(client)
                self.station.succeeded("station")
                return Verdict()
            self.failed_tries += 1
            w1 = self.clients.failed(client)
            w2 = self.station.failed("station")
            wait = max(w1, w2)
            self.log(f"wrong access code from {client} ({self.clients.failures(client)} from this address, "
                     f"{self.station.failures('station')} on the station)"
                     + (f"; next try allowed in {wait:.0f} s" if wait > 0 else ""))
            return Verdict(403, "Wrong access code.")

    def _log_refusal(self, key, text: str) -> None:
        """Each refused handshake is logged, but the same one repeated (a page retrying every second) at
        most every 10 s, with how many were not written."""
        with self._lock:
            last, skipped = self._refusals_logged.get(key, (-1e18, 0))
            now = self.clock()
            if now - last < 10.0:
                self._refusals_logged[key] = (last, skipped + 1)
                return
            self._refusals_logged[key] = (now, 0)
            if len(self._refusals_logged) > 1000:
                self._refusals_logged.clear()
        self.log(text + (f" ({skipped} more like it since the last line)" if skipped else ""))

    # ---- requests ---------------------------------------------------------------------------------
    def check(self, path: str, headers, client: str, port: int) -> Verdict:
        """One HTTP request or websocket handshake (`headers`: a mapping with .get, and .get_all when a
        header may be repeated)."""
        upgrade = ",".join(_header_values(headers, "Upgrade")).lower()
        if "websocket" in upgrade:
            return self._check_websocket(path, headers, client, port)
        return self._check_page(path, client)

    def _check_websocket(self, path: str, headers, client: str, port: int) -> Verdict:
        origins = _header_values(headers, "Origin")
        if len(origins) > 1:  # no browser sends two; one of them could be anybody's
            self._log_refusal((client, "several"), f"refused a websocket from {client}: {len(origins)} Origin headers")
            return Verdict(403, "Forbidden: more than one Origin header.")
        origin = origins[0] if origins else None
        if origin is not None and not self.origin_allowed(origin, port):
            with self._lock:
                self.refused_origins += 1
            self._log_refusal((client, origin[:80]), f"refused a websocket from {client}: Origin {origin[:80]!r} "
                                                     "is not the panel's own")
            return Verdict(403, "Forbidden: this panel only answers pages it served itself.")
        code = _code_in_path(path)
        if code is not None:
            v = self.try_code(code, client)
            if not v.allowed:
                return v
            return Verdict()
        if origin is None:
            self._log_refusal((client, None), f"refused a websocket from {client}: no Origin header and no secret "
                                              "in the address")
            return Verdict(403, "Forbidden: a client without an Origin header must give the station's secret.")
        if self.code_required:
            return Verdict(403, "Forbidden: this panel needs the access code.")
        return Verdict()

    def _check_page(self, path: str, client: str) -> Verdict:
        split = urlsplit(path)
        if split.path == UNLOCK_PATH:  # the code page's form
            given = (parse_qs(split.query).get("code") or [""])[0]
            v = self.try_code(given, client)
            if not v.allowed:
                return Verdict(v.status, v.body, page=True, retry_after_s=v.retry_after_s)
            return Verdict(303, "", location=CODE_PREFIX + quote(normalize_code(given)))
        code = _code_in_path(path)
        if code is not None:
            v = self.try_code(code, client)
            if not v.allowed:
                return Verdict(v.status, v.body, page=True, retry_after_s=v.retry_after_s)
            rest = split.path[len(CODE_PREFIX):].partition("/")[2]
            return Verdict(path="/" + rest)
        if self.code_required:
            return Verdict(200, "", page=True)
        return Verdict()

    def code_page(self, message: str = "") -> str:
        """The page a browser without the code gets: a prompt for it, nothing of the session."""
        note = f'<p class="err">{html.escape(message)}</p>' if message else ""
        return (
            "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
            "<meta name='viewport' content='width=device-width, initial-scale=1'><title>procam station</title>"
            "<style>body{font-family:sans-serif;max-width:28em;margin:4em auto;padding:0 1em}"
            "input{font-size:1.2em;width:100%;box-sizing:border-box;padding:.3em;letter-spacing:.1em}"
            "button{font-size:1.1em;margin-top:.8em;padding:.3em 1.2em}.err{color:#b00;font-weight:bold}</style>"
            "</head><body><h2>procam station</h2>"
            "<p>This station is served on the network. Enter the access code printed in the station's "
            "terminal at start (or open the address printed there, which carries it).</p>"
            f"{note}<form method='get' action='{UNLOCK_PATH}'><label for='code'>Access code</label>"
            "<input id='code' name='code' autocomplete='off' autocapitalize='none' spellcheck='false' autofocus>"
            "<button type='submit'>Open the panel</button></form></body></html>"
        )


def _header_values(headers, name: str) -> list[str]:
    """Every value of header `name` (websockets' Headers raise on .get of a repeated one)."""
    get_all = getattr(headers, "get_all", None)
    if get_all is not None:
        return list(get_all(name))
    value = headers.get(name)
    return [] if value is None else [value]


def _code_in_path(path: str) -> str | None:
    p = urlsplit(path).path
    if not p.startswith(CODE_PREFIX):
        return None
    return unquote(p[len(CODE_PREFIX):].partition("/")[0])
