"""The shared session made visible: how many tabs are open, and who changed what last.

Every browser tab shows the same run (one shared state, see ``visloc.dashboard.app``); this
keeps the tabs' numbers (in the order they connected) and the last change made in one of
them, and says it in one line every tab sees.
"""

from __future__ import annotations

import threading
import time

from visloc.dashboard.panels import session_html


class SessionLog:
    def __init__(self, clock=time.localtime):
        self._lock = threading.Lock()
        self._tab_of: dict[int, int] = {}  # viser client id -> tab number, 1 for the first to connect
        self._tabs_ever = 0
        self._last: tuple[str, str, int | None, str] | None = None  # (control, value, tab, time)
        self._clock = clock

    def connected(self, client_id: int) -> int:
        """Count a new tab; returns its number."""
        with self._lock:
            self._tabs_ever += 1
            self._tab_of[client_id] = self._tabs_ever
            return self._tabs_ever

    def disconnected(self, client_id: int) -> None:
        with self._lock:
            self._tab_of.pop(client_id, None)

    def tab(self, client_id: int | None) -> int | None:
        with self._lock:
            return self._tab_of.get(client_id) if client_id is not None else None

    def changed(self, client_id: int | None, control: str, value: str) -> bool:
        """Record a change a tab made (``client_id`` None: made by the page itself, not recorded).
        Returns whether it was recorded."""
        if client_id is None:
            return False
        with self._lock:
            tab = self._tab_of.get(client_id)
            self._last = (control, value, tab, time.strftime("%H:%M:%S", self._clock()))
        return True

    def line(self) -> str:
        """E.g. "Shared by 2 open tabs · last change: τ1 → 0.85 from tab 2 at 14:02:11"."""
        with self._lock:
            n, last = len(self._tab_of), self._last
        shared = "Open in 1 tab" if n == 1 else f"Shared by {n} open tabs"
        if last is None:
            return shared + " · no change made yet"
        control, value, tab, when = last
        who = f" from tab {tab}" if tab is not None else ""
        return f"{shared} · last change: {control} → {value}{who} at {when}"


class SessionView:
    """The session line every tab shows, and each tab's own "This is tab N" under it (viser handles)."""

    def __init__(self, line, html=session_html):
        self.log, self.line, self._html = SessionLog(), line, html
        self._tab_lines: dict[int, object] = {}  # each tab's own line

    def opened(self, client) -> None:
        tab = self.log.connected(client.client_id)
        self._tab_lines[client.client_id] = client.gui.add_html(self._html(f"This is tab {tab}"),
                                                                order=self.line.order + 0.001)
        self.show()

    def closed(self, client) -> None:
        self.log.disconnected(client.client_id)
        self._tab_lines.pop(client.client_id, None)
        self.show()

    def changed(self, event, label: str, value) -> None:
        """A tab changed a control: every tab is told which and from where (the page's own moves are not)."""
        shown = ("on" if value else "off") if isinstance(value, bool) else \
            f"{value:g}" if isinstance(value, float) else str(value)
        if self.log.changed(event.client_id, label, shown):
            self.show()

    def show(self) -> None:
        self.line.content = self._html(self.log.line())
