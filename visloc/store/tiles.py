"""The geographic grid of a sharded store, as pure functions over numpy arrays.

The grid is fixed and metric: square tiles of ``tile_m`` metres in the UTM zone of the store's first
image (a projected CRS, so a tile is the same size everywhere in a city, the bounds are plain
numbers, and picking the tiles a gate touches is integer arithmetic; S2 or H3 cells would add a
dependency for no gain at city scale, where one UTM zone holds the whole map). An image belongs to
the tile it lies in (its owner) and is copied into every other tile whose bounds, widened by
``halo_m``, hold it: a query near a border finds in one tile the views and neighbours it would find
in one file, as long as they lie within the halo.
"""

from __future__ import annotations

import numpy as np
from pyproj import CRS, Transformer


def utm_epsg(lat_deg: float, lon_deg: float) -> int:
    """EPSG code of the WGS84 UTM zone holding (lat, lon)."""
    zone = int(np.floor((lon_deg + 180.0) / 6.0)) % 60 + 1
    return (32600 if lat_deg >= 0 else 32700) + zone


def to_grid_m(epsg: int, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """(N, 2) east, north in metres in the CRS ``epsg``."""
    transformer = Transformer.from_crs(CRS.from_epsg(4326), CRS.from_epsg(epsg), always_xy=True)
    east, north = transformer.transform(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
    return np.c_[np.atleast_1d(east), np.atleast_1d(north)]


def tile_key(ix: int, iy: int) -> str:
    """The name of tile (ix, iy): sortable, safe as a file name."""
    return f"e{ix:+07d}_n{iy:+08d}".replace("+", "p").replace("-", "m")


def owner_cells(east_north_m: np.ndarray, tile_m: float) -> np.ndarray:
    """(N, 2) integer grid cell (ix, iy) each point lies in."""
    return np.floor(np.asarray(east_north_m, float).reshape(-1, 2) / tile_m).astype(np.int64)


def cells_holding(east_north_m: np.ndarray, tile_m: float, halo_m: float) -> list[set[tuple[int, int]]]:
    """Per point, every cell whose bounds widened by ``halo_m`` hold it (its owner among them)."""
    points = np.asarray(east_north_m, float).reshape(-1, 2)
    low = np.floor((points - halo_m) / tile_m).astype(np.int64)
    high = np.floor((points + halo_m) / tile_m).astype(np.int64)
    return [{(ix, iy) for ix in range(lo[0], hi[0] + 1) for iy in range(lo[1], hi[1] + 1)} for lo, hi in zip(low, high)]


def cells_within(center_m: np.ndarray, radius_m: float, tile_m: float) -> np.ndarray:
    """(K, 2) cells whose square meets the disc of ``radius_m`` around ``center_m``: the tiles a gate of
    that radius must open (a tile's halo is not needed: each image is looked up in its owner tile)."""
    c = np.asarray(center_m, float).reshape(2)
    lo = np.floor((c - radius_m) / tile_m).astype(np.int64)
    hi = np.floor((c + radius_m) / tile_m).astype(np.int64)
    ix, iy = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
    cells = np.c_[ix.ravel(), iy.ravel()]
    nearest = np.clip(c, cells * tile_m, (cells + 1) * tile_m)  # the point of each square nearest the centre
    return cells[np.linalg.norm(nearest - c, axis=1) <= radius_m]


def cell_bounds_m(ix: int, iy: int, tile_m: float) -> tuple[float, float, float, float]:
    return float(ix * tile_m), float(iy * tile_m), float((ix + 1) * tile_m), float((iy + 1) * tile_m)


def tiles_of_images(east_north_m: np.ndarray, tile_m: float, halo_m: float) -> dict[tuple[int, int], np.ndarray]:
    """cell -> the (sorted) indices of the points the tile holds, owners and halo."""
    out: dict[tuple[int, int], list[int]] = {}
    for k, cells in enumerate(cells_holding(east_north_m, tile_m, halo_m)):
        for cell in cells:
            out.setdefault(cell, []).append(k)
    return {cell: np.array(sorted(v), np.int64) for cell, v in sorted(out.items())}
