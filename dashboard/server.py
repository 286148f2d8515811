"""Starting and stopping the dashboard: ``serve`` runs it until stopped."""

from __future__ import annotations

import threading
from pathlib import Path

import viser
import viser._messages  # viser has no API for the page title; see name_the_tab

from visloc.dashboard.app import DashboardApp

PAGE_TITLE = "visloc"


def name_the_tab(server: viser.ViserServer, title: str = PAGE_TITLE) -> None:
    """Set the browser tab's title (viser's client says "Viser" and has no setting for it).

    viser 1.1.1 can only run a script in its client through the message it uses to load plotly.js,
    broadcast and kept for every tab that connects later; that message sets ``document.title``.
    Without that message (another viser version) the tab keeps viser's title and nothing else changes.
    """
    message = getattr(viser._messages, "RunJavascriptMessage", None)
    queue = getattr(getattr(server, "_websock_server", None), "queue_message", None)
    if message is not None and queue is not None:
        queue(message(source=f"document.title = {title!r};"))


def serve(store_path: Path, *, host: str = "127.0.0.1", port: int = 8080, db_camera: str | None = "image_01",
          query_camera: str | None = "image_00", db_source: str | None = None, query_source: str | None = None,
          ready: threading.Event | None = None,
          stop: threading.Event | None = None, announce=print) -> None:
    """Serve the dashboard until ``stop`` is set (or forever). viser moves to the next free
    port when ``port`` is taken, so the URL announced is the one actually served."""
    server = viser.ViserServer(host=host, port=port, label="visloc", verbose=False)
    name_the_tab(server)
    try:  # Ctrl-C or kill -INT at any moment from here on stops every thread, so the process can end
        app = DashboardApp(server, store_path, db_camera=db_camera, query_camera=query_camera,
                           db_source=db_source, query_source=query_source)
        try:
            announce(f"visloc dashboard: http://{host}:{server.get_port()}  (store {store_path}; Ctrl-C stops it)")
            if ready is not None:
                ready.set()
            stop = stop or threading.Event()
            while not stop.wait(0.5):  # short waits keep Ctrl-C responsive
                pass
        finally:
            app.close()
    finally:
        server.stop()
