"""One browser drives the station at a time; every other one watches.

Each browser that connects gets a short name ("browser 1", "browser 2", ... in the order they connected,
never reused while the station runs). The first one connected drives; the others see who is connected,
"watching", and a *Take control* button, and their controls are disabled until they take control. When
the driving browser goes away, the one connected longest drives. The log names the browser of every
action (app/station/panel_controls.py). Who may connect at all is app/station/access.py's decision;
this only orders the browsers that got in.
"""

from __future__ import annotations

import threading

TAKE_CONTROL = "Take control"


class DriverSeat:
    """Who is connected (client id -> short name) and who drives; `log(text)` records every change."""

    def __init__(self, log):
        self._log = log
        self._lock = threading.Lock()
        self._names: dict[int, str] = {}  # in the order of connection
        self._count = 0
        self.driver: int | None = None

    def join(self, client_id: int) -> str:
        with self._lock:
            self._count += 1
            name = self._names[client_id] = f"browser {self._count}"
            drives = self.driver is None
            if drives:
                self.driver = client_id
        self._log(f"{name} connected" + (" and drives the station" if drives else "; it watches"))
        return name

    def leave(self, client_id: int) -> None:
        with self._lock:
            name = self._names.pop(client_id, None)
            handed = None
            if self.driver == client_id:
                self.driver = next(iter(self._names), None)
                handed = self._names.get(self.driver)
        if name is not None:
            self._log(f"{name} disconnected" + (f"; {handed} drives now" if handed else ""))

    def take(self, client_id: int) -> str:
        """`client_id` drives from now on; what happened, in words."""
        with self._lock:
            if client_id not in self._names:
                return "this browser is not connected"
            old, self.driver = self.driver, client_id
            name, was = self._names[client_id], self._names.get(old)
        if old == client_id:
            return f"{name} drives already"
        self._log(f"{name} took control" + (f" from {was}" if was else ""))
        return f"{name} drives now" + (f"; {was} watches" if was else "")

    def connected(self, client_id: int) -> bool:
        with self._lock:
            return client_id in self._names

    def drives(self, client_id: int) -> bool:
        return self.driver == client_id

    def name(self, client_id: int) -> str:
        return self._names.get(client_id, "a browser")

    def roster(self, client_id: int) -> str:
        """Who is connected, as this browser's line of the panel."""
        with self._lock:
            names = dict(self._names)
            driver = self.driver
        who = ", ".join(f"{n}{' (drives)' if c == driver else ''}{' = this browser' if c == client_id else ''}"
                        for c, n in names.items())
        if client_id == driver:
            return f"**Connected:** {who}. This browser drives the station."
        return (f"**Connected:** {who}. This browser is **watching**: its controls are disabled; press "
                f"*{TAKE_CONTROL}* to drive.")
