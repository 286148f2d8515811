"""The map's web-map tiles (``visloc dashboard --tiles``), from a tile server this test starts on loopback, in
the session's headless Chromium: the tiles under the run and their attribution, kept on disk; with the
server unreachable, the page says so and the map is drawn without them. Screenshots go to
``out/screenshots/tiles_*.png``."""

from __future__ import annotations

import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest
from helpers import SERVER_WORK_S, DashboardProcess, open_page, screenshot, wait_for

TILE_BGR = (90, 200, 250)  # a warm yellow, which nothing else on the map is drawn in


def tile_png(path: str) -> bytes:
    tile = np.full((256, 256, 3), TILE_BGR, np.uint8)
    cv2.rectangle(tile, (0, 0), (255, 255), (60, 120, 160), 2)
    cv2.putText(tile, path[:20], (8, 128), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 80, 120), 1, cv2.LINE_AA)
    return cv2.imencode(".png", tile)[1].tobytes()


def start_tile_server() -> tuple[ThreadingHTTPServer, list[str]]:
    asked: list[str] = []

    class Tiles(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            asked.append(self.path)
            body = tile_png(self.path)
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Tiles)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, asked


def map_tab(page):
    page.get_by_role("tab", name="Map").click()
    return page.get_by_text("top-down map (north up, east right)", exact=True).locator("xpath=..").locator("img")


def tile_share(path) -> float:
    """The share of the map picture's pixels in the tiles' colour, washed toward white as the map draws it."""
    shot = cv2.imread(str(path))
    washed = np.array(TILE_BGR) * 0.65 + 255 * 0.35
    return float(np.mean(np.all(np.abs(shot.astype(float) - washed) < 12, axis=2)))


@pytest.mark.slow
def test_the_map_draws_web_map_tiles_and_says_when_the_server_is_unreachable(csv_pair, browser, tmp_path,
                                                                              monkeypatch):
    monkeypatch.setenv("VISLOC_CACHE", str(tmp_path / "cache"))  # the dashboard's tiles on disk, this test's own
    server, asked = start_tile_server()
    url = f"http://127.0.0.1:{server.server_address[1]}/{{z}}/{{x}}/{{y}}.png"
    proc = DashboardProcess("--db", str(csv_pair.store), "--port", "8450", "--tiles", url)
    try:
        page = open_page(browser, proc.url)
        picture = map_tab(page)
        page.get_by_text(f"map tiles: 127.0.0.1:{server.server_address[1]}").wait_for()
        wait_for(lambda: asked, SERVER_WORK_S, "the dashboard to ask the tile server")
        shot = tmp_path / "map.png"

        def tiles_drawn() -> bool:  # fetched beside the page, the tiles come into the map once they are here
            picture.first.screenshot(path=str(shot))
            return tile_share(shot) > 0.3

        wait_for(tiles_drawn, SERVER_WORK_S, "the tiles under the map", poll_s=1.0)
        screenshot(page, "tiles_map.png")
        assert all(p.endswith(".png") and p.count("/") == 3 for p in asked)
        assert list((tmp_path / "cache" / "tiles").rglob("*.png")), "tiles are kept on disk"
        page.close()
    finally:
        proc.stop()
        server.shutdown()
    with socket.socket() as s:  # a port nothing listens on: the server is unreachable
        s.bind(("127.0.0.1", 0))
        closed = s.getsockname()[1]
    monkeypatch.setenv("VISLOC_CACHE", str(tmp_path / "empty_cache"))
    proc = DashboardProcess("--db", str(csv_pair.store), "--port", "8451", "--tiles",
                            f"http://127.0.0.1:{closed}/{{z}}/{{x}}/{{y}}.png")
    try:
        page = open_page(browser, proc.url)
        picture = map_tab(page)
        page.get_by_text("map tiles unreachable", exact=False).first.wait_for()
        shot = tmp_path / "offline.png"
        picture.first.screenshot(path=str(shot))
        screenshot(page, "tiles_offline.png")
        assert tile_share(shot) < 0.01  # drawn as without tiles: white under the run
        page.close()
    finally:
        proc.stop()
