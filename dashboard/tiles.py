"""Web-map tiles under the top-down map: an XYZ tile server (``{z}/{x}/{y}`` in its URL, Web Mercator,
256 px tiles), fetched once and kept on disk.

Off unless ``visloc dashboard --tiles URL`` (``--tiles osm``: OpenStreetMap's standard tiles, whose usage
policy asks for a valid User-Agent, caching, and modest use: a person looking at a run, never bulk
downloads; the attribution is drawn on the map). A tile that cannot be fetched is left blank, and while the
server is unreachable (no network) the map says so and is drawn as before, without tiles; the server is
asked again after ``RETRY_S``. Tiles are fetched beside the page, never while it draws: the map is drawn again
when they come.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np

import visloc

OSM_URL = "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
OSM_ATTRIBUTION = "(c) OpenStreetMap contributors"
TILE_PX = 256
MAX_ZOOM = 19
RETRY_S = 30.0
MAX_TILES_PER_VIEW = 30
WASH = 0.35  # the tiles blended toward white, so that the run's lines stay readable on them
EARTH_CIRCUMFERENCE_M = 40_075_016.686


def tile_url(url: str) -> str:
    """``url`` checked: http(s) with ``{z}``, ``{x}`` and ``{y}``; ``osm`` is OpenStreetMap's."""
    url = OSM_URL if url == "osm" else url
    if not url.startswith(("http://", "https://")) or not all(k in url for k in ("{z}", "{x}", "{y}")):
        raise visloc.InputError(f"--tiles {url[:80]!r}: expected 'osm' or an http(s) URL with {{z}}, {{x}} and {{y}}")
    return url


def global_px(lat_deg, lon_deg, zoom: int) -> np.ndarray:
    """(..., 2) Web Mercator pixel coordinates (x right, y down) at ``zoom``."""
    lat = np.radians(np.clip(np.asarray(lat_deg, float), -85.0511, 85.0511))
    n = TILE_PX * 2.0 ** zoom
    x = (np.asarray(lon_deg, float) + 180.0) / 360.0 * n
    y = (1.0 - np.log(np.tan(lat) + 1.0 / np.cos(lat)) / math.pi) / 2.0 * n
    return np.stack([x, y], axis=-1)


def zoom_for(px_per_m: float, lat_deg: float) -> int:
    """The tile zoom whose pixels are closest to (not coarser than half) ``px_per_m`` at ``lat_deg``."""
    m_per_px_z0 = EARTH_CIRCUMFERENCE_M * math.cos(math.radians(lat_deg)) / TILE_PX
    return int(np.clip(math.ceil(math.log2(max(px_per_m * m_per_px_z0, 1.0))), 0, MAX_ZOOM))


class TileSource:
    """Tiles of one server: in memory, on disk under ``cache_dir``, and fetched when missing by a thread of its
    own, never by the drawing that asked (a slow or absent network never holds the page up). ``on_fetched`` is
    called from that thread once the tiles asked for have come, or the server could not be reached."""

    def __init__(self, url: str, cache_dir: Path, *, attribution: str | None = None, timeout_s: float = 4.0):
        self.url = tile_url(url)
        self.attribution = attribution or (OSM_ATTRIBUTION if self.url == OSM_URL else
                                           f"map tiles: {self.url.split('/')[2][:60]}")
        self.folder = Path(cache_dir) / hashlib.sha256(self.url.encode()).hexdigest()[:16]
        self.timeout_s = timeout_s
        self.problem: str | None = None  # why the server could not be reached, while it cannot
        self.on_fetched = None
        self._failed_at = -math.inf
        self._memory: dict[tuple[int, int, int], np.ndarray | None] = {}
        self._wanted: list[tuple[int, int, int]] = []  # asked for, not fetched yet, in the order asked
        self._fetching = False
        self._lock = threading.Lock()

    def _path(self, z: int, x: int, y: int) -> Path:
        return self.folder / str(z) / str(x) / f"{y}.png"

    def tile(self, z: int, x: int, y: int) -> np.ndarray | None:
        """The RGB tile, or None when it is not here yet (then it is fetched, unless the server was unreachable
        less than ``RETRY_S`` ago)."""
        key = (z, x, y)
        with self._lock:
            if key in self._memory:
                return self._memory[key]
            path = self._path(*key)
            if path.is_file():
                return self._keep(key, path.read_bytes())
            if time.monotonic() - self._failed_at >= RETRY_S and key not in self._wanted:
                self._wanted.append(key)
                if not self._fetching:
                    self._fetching = True
                    threading.Thread(target=self._fetch_wanted, name="visloc-dashboard-tiles", daemon=True).start()
            return None

    def _keep(self, key: tuple[int, int, int], data: bytes) -> np.ndarray | None:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        rgb = None if image is None or image.shape[:2] != (TILE_PX, TILE_PX) else image[:, :, ::-1].copy()
        self._memory[key] = rgb
        return rgb

    def _fetch_wanted(self) -> None:
        while True:
            with self._lock:
                if not self._wanted:
                    self._fetching = False
                    break
                key = self._wanted.pop(0)
            data = self._fetch(*key)
            with self._lock:
                if data is not None:
                    path = self._path(*key)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    tmp = path.with_name(f".{key[2]}.{os.getpid()}.tmp")
                    tmp.write_bytes(data)
                    os.replace(tmp, path)
                    self._keep(key, data)
                elif time.monotonic() - self._failed_at < RETRY_S:
                    self._wanted.clear()  # the network is down: asked again after RETRY_S
        if self.on_fetched is not None:
            self.on_fetched()

    def _fetch(self, z: int, x: int, y: int) -> bytes | None:
        url = self.url.format(z=z, x=x, y=y)
        request = urllib.request.Request(url, headers={"User-Agent": f"visloc/{visloc.__version__} (dashboard)"})
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                data = response.read()
            self.problem = None
            return data
        except urllib.error.HTTPError as exc:  # the server answered: this tile is missing, not the network
            with self._lock:
                self._memory[(z, x, y)] = None
            self.problem = None if exc.code == 404 else f"tile server answered {exc.code}"
            return None
        except (OSError, ValueError) as exc:
            self._failed_at = time.monotonic()
            reason = getattr(exc, "reason", exc)
            self.problem = f"map tiles unreachable ({str(reason)[:60]}): drawn without them"
            return None


def background(source: TileSource, frame: visloc.LocalFrame, center_m, px_per_m: float, width_px: int,
               height_px: int) -> np.ndarray | None:
    """The tiles under a map view (centre in local metres, scale, size), RGB, washed toward white; None when
    none could be had."""
    corners_px = np.array([[0.0, 0.0], [width_px, 0.0], [0.0, height_px]])
    corners_m = np.c_[center_m[0] + (corners_px[:, 0] - width_px / 2) / px_per_m,
                      center_m[1] - (corners_px[:, 1] - height_px / 2) / px_per_m]
    lat, lon = frame.to_geo(corners_m)
    zoom = zoom_for(px_per_m, float(lat[0]))
    while True:
        g = global_px(lat, lon, zoom)
        far = g[0] + (g[1] - g[0]) + (g[2] - g[0])
        lo, hi = np.minimum(g.min(axis=0), far), np.maximum(g.max(axis=0), far)
        first, last = np.floor(lo / TILE_PX).astype(int), np.floor(hi / TILE_PX).astype(int)
        if np.prod(last - first + 1) <= MAX_TILES_PER_VIEW or zoom == 0:
            break
        zoom -= 1
    mosaic = np.full(((last[1] - first[1] + 1) * TILE_PX, (last[0] - first[0] + 1) * TILE_PX, 3), 255, np.uint8)
    got = 0
    limit = 2 ** zoom
    for ty in range(first[1], last[1] + 1):
        for tx in range(first[0], last[0] + 1):
            tile = source.tile(zoom, tx % limit, ty) if 0 <= ty < limit else None
            if tile is not None:
                r, c = (ty - first[1]) * TILE_PX, (tx - first[0]) * TILE_PX
                mosaic[r: r + TILE_PX, c: c + TILE_PX] = tile
                got += 1
    if not got:
        return None
    to_mosaic = cv2.getAffineTransform(corners_px.astype(np.float32), (g - first * TILE_PX).astype(np.float32))
    picture = cv2.warpAffine(mosaic, to_mosaic, (width_px, height_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                             borderValue=(255, 255, 255))
    return (picture * (1 - WASH) + 255 * WASH).astype(np.uint8)


class TileLayer:
    """A tile server under the maps of a drive whose local frame is ``frame``."""

    def __init__(self, source: TileSource, frame: visloc.LocalFrame):
        self.source, self.frame = source, frame

    def under(self, center_m, px_per_m: float, width_px: int, height_px: int) -> np.ndarray | None:
        return background(self.source, self.frame, center_m, px_per_m, width_px, height_px)

    @property
    def caption(self) -> str:
        """What the map says of its tiles: the attribution, or why there are none."""
        return self.source.problem or self.source.attribution
