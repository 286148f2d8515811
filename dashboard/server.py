"""Starting and stopping the dashboard: ``serve`` runs it until stopped."""

from __future__ import annotations

import threading
from pathlib import Path

import viser

from visloc.dashboard.app import DashboardApp


def serve(store_path: Path, *, host: str = "127.0.0.1", port: int = 8080, db_camera: str = "image_01",
          query_camera: str = "image_00", ready: threading.Event | None = None,
          stop: threading.Event | None = None, announce=print) -> None:
    """Serve the dashboard until ``stop`` is set (or forever). viser moves to the next free
    port when ``port`` is taken, so the URL announced is the one actually served."""
    server = viser.ViserServer(host=host, port=port, label="visloc", verbose=False)
    try:  # Ctrl-C or kill -INT at any moment from here on stops every thread, so the process can end
        app = DashboardApp(server, store_path, db_camera=db_camera, query_camera=query_camera)
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
