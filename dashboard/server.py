"""Starting and stopping the dashboard: ``serve`` runs it until stopped."""

from __future__ import annotations

import ipaddress
import sys
import threading
from pathlib import Path

import viser
import viser._messages  # viser has no API for the page title; see name_the_tab

import visloc
from visloc.dashboard.app import DashboardApp
from visloc.dashboard.state import Allowed

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


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only (localhost, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name or an interface's address: other machines may reach it
        return False


def allowed_stores(store_path: Path, allow: list[Path] | None) -> Allowed:
    """What the page may open: stores inside the folders ``allow`` (default: the store's folder), and
    the store itself. A folder named in ``allow`` that is not one is refused (``--allow``)."""
    for folder in allow or ():
        if not Path(folder).is_dir():
            raise visloc.InputError(f"--allow {folder}: " + ("not a folder" if Path(folder).exists()
                                                             else "no such folder"))
    return Allowed.of(allow if allow else [Path(store_path).parent], store_path)


def public_warning(host: str, port: int, allowed: Allowed) -> str:
    """What serving beyond this machine exposes, and the safer way to look from elsewhere."""
    folders = ", ".join(str(f) for f in allowed.folders) or "none"
    return (f"visloc dashboard: warning: serving on {host}: anyone who reaches port {port} can open the stores "
            f"under {folders}; to look from another machine, keep the default host and use an SSH tunnel "
            f"(ssh -L {port}:localhost:{port} this-machine)")


def serve(store_path: Path, *, host: str = "127.0.0.1", port: int = 8080, db_camera: str | None = "image_01",
          query_camera: str | None = "image_00", db_source: str | None = None, query_source: str | None = None,
          allow: list[Path] | None = None, tune_from: tuple[Path, visloc.LiveSettings] | None = None,
          ready: threading.Event | None = None, stop: threading.Event | None = None, announce=print,
          tiles=None, query_images: Path | None = None) -> None:
    """Serve the dashboard until ``stop`` is set (or forever). viser moves to the next free
    port when ``port`` is taken, so the URL announced is the one actually served. The page opens
    only stores inside the folders ``allow`` (default: the store's folder) and ``store_path`` itself;
    a host other than this machine's loopback is warned of on stderr. ``tune_from``: (a saved run's file, its
    settings) to start the controls from (``visloc dashboard --tune-from``). ``tiles``: a web map's tiles under
    the top-down map (``visloc.dashboard.tiles.TileSource``), None for none. ``query_images``: where the camera-rate
    mode reads the query series' images to follow points (``visloc.open_series``; None: the data root)."""
    allowed = allowed_stores(store_path, allow)  # before anything is served
    server = viser.ViserServer(host=host, port=port, label="visloc", verbose=False)
    name_the_tab(server)
    try:  # Ctrl-C or kill -INT at any moment from here on stops every thread, so the process can end
        app = DashboardApp(server, store_path, db_camera=db_camera, query_camera=query_camera,
                           db_source=db_source, query_source=query_source, allowed=allowed, tune_from=tune_from,
                           tiles=tiles, query_images=query_images)
        try:
            if not is_loopback(host):
                print(public_warning(host, server.get_port(), allowed), file=sys.stderr, flush=True)
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


def saved_run_files(runs: list[Path]) -> list[tuple[str, Path]]:
    """Every run the files given hold, in order (``evaluate-drives``' JSON: each drive's runs beside it).
    A file that is no run is refused here, in one line naming it, before anything is served."""
    files: list[tuple[str, Path]] = []
    for path in runs:
        files += visloc.run_files(path)
    if not files:
        raise visloc.InputError("--run: give at least one run file")
    return files


def serve_runs(runs: list[Path], *, host: str = "127.0.0.1", port: int = 8080, ready: threading.Event | None = None,
               stop: threading.Event | None = None, announce=print) -> None:
    """Serve the saved-run viewer on the runs in ``runs`` (the first shown, the second, if any, compared with
    it) until ``stop`` is set. It opens only those files."""
    from visloc.dashboard.runview import RunViewer

    files = saved_run_files(runs)
    visloc.load_run(files[0][1])  # a first run that cannot be read is said here, not only in the page
    compare = len(visloc.run_files(runs[0])) if len(runs) > 1 else None
    server = viser.ViserServer(host=host, port=port, label="visloc", verbose=False)
    name_the_tab(server, f"{PAGE_TITLE}: saved runs")
    try:
        viewer = RunViewer(server, files, compare=compare)
        try:
            if not is_loopback(host):
                print(f"visloc dashboard: warning: serving on {host}: anyone who reaches port {server.get_port()} "
                      "can read these runs", file=sys.stderr, flush=True)
            announce(f"visloc dashboard: http://{host}:{server.get_port()}  ({len(files)} saved run(s); "
                     "Ctrl-C stops it)")
            if ready is not None:
                ready.set()
            stop = stop or threading.Event()
            while not stop.wait(0.5):
                pass
        finally:
            viewer.close()
    finally:
        server.stop()
