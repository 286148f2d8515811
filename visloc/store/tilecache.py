"""Features of a sharded store read tile by tile, when a query needs them, within a memory budget.

A sharded store's database and queries carry every image's metadata (its time, geotag, attitude)
from the store's catalogue, but their keypoints and descriptors are sequences that read an image's
tile the first time the engine asks for one of its images: the search window (or the filter's gate,
or a shortlist from the global vectors) decides which images a query looks at, so it decides which
tiles are opened. Open tiles are kept, least recently used first out, while their arrays fit the
budget; an image is always read from the tile that owns it, so a halo copy is never held twice.
"""

from __future__ import annotations

import math
import sqlite3
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from visloc.db import StoreError
from visloc.db.connection import sqlite_error_line
from visloc.db.shards import Manifest, tile_features, tile_structure_points
from visloc.errors import InputError
from visloc.features.sift import contrast_kept
from visloc.pose.structure import ViewStructure
from visloc.params import COMMAND_OPTIONS


@dataclass
class TileCacheStats:
    """What a ``TileCache`` did: tiles read (again after an eviction counts again), tiles dropped to
    stay within the budget, the distinct tiles read, the most bytes it held at once."""

    tiles_read: int = 0
    tiles_evicted: int = 0
    distinct_tiles: set = field(default_factory=set)
    peak_bytes: int = 0


class TileCache:
    """Open tiles of the sharded store ``folder``: what a query read from each, at most ``budget_mb`` of
    arrays (the part being read is kept whatever its size). Thread-safe. Per tile two parts: its
    images' features (image id -> (keypoints_f32, descriptors_u8)) and, for each structure setting
    asked, its images' structure points (image id -> variant -> (points_f64, cov_f64))."""

    def __init__(self, folder: str | Path, budget_mb: float = COMMAND_OPTIONS.tile_cache_mb):
        if not (math.isfinite(budget_mb) and budget_mb > 0):
            raise InputError(f"tile cache budget must be a number of MB above 0, got {budget_mb}")
        self.folder = Path(folder)
        self.budget_bytes = int(budget_mb * 1e6)
        with Manifest(self.folder, read_only=True) as manifest:
            self._files = {t.key: t.file for t in manifest.tiles()}
        self._owned: dict[str, set[int]] = {}  # image ids a tile serves, as datasets were asked for
        self._open: OrderedDict[tuple[str, str], dict] = OrderedDict()  # (tile, part) -> image id -> arrays
        self._bytes: dict[tuple[str, str], int] = {}
        self._lock = threading.RLock()
        self.stats = TileCacheStats()

    @property
    def n_tiles(self) -> int:
        return len(self._files)

    @property
    def held_bytes(self) -> int:
        return sum(self._bytes.values())

    def features(self, image_ids: Sequence[int], owners: dict[int, str]) -> tuple["TileFeatures", "TileFeatures"]:
        """(keypoints, descriptors) of ``image_ids`` as lazy sequences; ``owners``: image id -> its tile."""
        ids = [int(i) for i in image_ids]
        lacking = [i for i in ids if i not in owners]
        if lacking:
            raise InputError(f"{self.folder}: image {lacking[0]} is in no tile of the manifest; run 'visloc ingest' "
                             "of its drive into the store again")
        keys = [owners[i] for i in ids]
        with self._lock:
            for i, key in zip(ids, keys):
                self._owned.setdefault(key, set()).add(i)
        return TileFeatures(self, ids, keys, 0), TileFeatures(self, ids, keys, 1)

    def get(self, key: str, image_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints_f32, descriptors_u8) of ``image_id`` from the tile ``key`` that owns it."""
        return self._part(key, _FEATURES, image_id)

    def structure_points(self, key: str, image_id: int, params_json: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """variant -> (points_f64, cov_f64) of the structure of ``image_id`` made with ``params_json``, from the
        tile ``key`` that owns it."""
        return self._part(key, params_json, image_id)

    def _part(self, key: str, part: str, image_id: int):
        with self._lock:
            tile = self._open.get((key, part))
            if tile is None or image_id not in tile:
                self._owned.setdefault(key, set()).add(int(image_id))
                tile = self._read(key, part)
            self._open.move_to_end((key, part))
            if image_id not in tile:
                raise InputError(f"{self.folder / self._files[key]}: tile {key} lacks image {image_id} that the "
                                 "manifest says it owns; run 'visloc ingest' of its drive into the store again")
            return tile[image_id]

    def _read(self, key: str, part: str) -> dict:
        if key not in self._files:
            raise InputError(f"{self.folder}: tile {key} is not in the manifest; run 'visloc ingest' into the store "
                             "again")
        path = self.folder / self._files[key]
        ids = sorted(self._owned.get(key, ()))
        try:
            tile = tile_features(path, ids) if part == _FEATURES else tile_structure_points(path, ids, part)
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(sqlite_error_line(str(path), exc)) from None
        arrays = [a for v in tile.values() for a in (v if part == _FEATURES else _flat(v))]
        for array in arrays:
            array.setflags(write=False)  # shared by every caller
        self._open.pop((key, part), None)
        self._open[(key, part)] = tile
        self._bytes[(key, part)] = sum(a.nbytes for a in arrays)
        self.stats.tiles_read += 1
        self.stats.distinct_tiles.add(key)
        self.stats.peak_bytes = max(self.stats.peak_bytes, self.held_bytes)
        while self.held_bytes > self.budget_bytes and len(self._open) > 1:
            oldest = next(iter(self._open))
            del self._open[oldest], self._bytes[oldest]
            self.stats.tiles_evicted += 1
        return tile


_FEATURES = "features"  # the part of a tile holding its images' features (the others: structure, by settings)


def _flat(variants: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    return [a for pair in variants.values() for a in pair]


class TileFeatures(Sequence):
    """One part (0: keypoints_f32, 1: descriptors_u8) of the features of a list of images, read from
    their tiles through a ``TileCache`` when asked for; ``map(fn)`` gives the same sequence through ``fn``."""

    def __init__(self, cache: TileCache, image_ids: list[int], tiles: list[str], part: int,
                 fn: Callable[[np.ndarray], np.ndarray] | None = None):
        self.cache, self.image_ids, self.tiles, self.part, self.fn = cache, image_ids, tiles, part, fn

    def __len__(self) -> int:
        return len(self.image_ids)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(len(self)))]
        k = range(len(self))[int(index)]  # IndexError as a list gives it
        array = self.cache.get(self.tiles[k], self.image_ids[k])[self.part]
        return array if self.fn is None else self.fn(array)

    def map(self, fn: Callable[[np.ndarray], np.ndarray]) -> "TileFeatures":
        return TileFeatures(self.cache, self.image_ids, self.tiles, self.part, fn)

    def selected(self, target: "TileFeatures", contrast_threshold: float, n_octave_layers: int) -> "ContrastSelected":
        """``target`` (these keypoints' descriptors, say) at the rows SIFT keeps at ``contrast_threshold``."""
        return ContrastSelected(self, target, contrast_threshold, n_octave_layers)

    def tiles_of(self, indices) -> list[str]:
        """The distinct tiles the images at ``indices`` are read from, in first-use order."""
        return list(dict.fromkeys(self.tiles[int(k)] for k in indices))


class ContrastSelected(Sequence):
    """``target``'s arrays (a tile-read part: keypoints or descriptors), each only at the rows of its image's
    ``keypoints`` that SIFT keeps at ``contrast_threshold`` (``visloc.features.sift.contrast_kept``), read when
    asked for; ``map(fn)`` gives the same sequence through ``fn``."""

    def __init__(self, keypoints: TileFeatures, target: TileFeatures, contrast_threshold: float, n_octave_layers: int,
                 fn: Callable[[np.ndarray], np.ndarray] | None = None):
        self.keypoints, self.target, self.fn = keypoints, target, fn
        self.contrast_threshold, self.n_octave_layers = contrast_threshold, n_octave_layers

    def __len__(self) -> int:
        return len(self.target)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[k] for k in range(*index.indices(len(self)))]
        kept = contrast_kept(self.keypoints[index], self.contrast_threshold, self.n_octave_layers)
        array = self.target[index][kept]
        return array if self.fn is None else self.fn(array)

    def map(self, fn: Callable[[np.ndarray], np.ndarray]) -> "ContrastSelected":
        return ContrastSelected(self.keypoints, self.target, self.contrast_threshold, self.n_octave_layers, fn)

    def tiles_of(self, indices) -> list[str]:
        return self.target.tiles_of(indices)


class TileStructures(Mapping):
    """The stored structure of a database read from a sharded store: database index -> variant ->
    ``ViewStructure``, as ``Workspace.load_structure`` gives it for a store file. What each view has
    (variants, neighbours, keypoint rows) comes from the catalogue (``views``: structures without their
    points); its points and covariances are read from the tile that owns the view, through the
    ``TileCache``, when the view is asked for."""

    def __init__(self, cache: TileCache, params_json: str, views: dict[int, dict[str, ViewStructure]],
                 image_ids: dict[int, int], tiles: dict[int, str]):
        self.cache, self.params_json = cache, params_json
        self._views, self._image_ids, self._tiles = views, image_ids, tiles

    def __len__(self) -> int:
        return len(self._views)

    def __iter__(self):
        return iter(self._views)

    def __contains__(self, view: object) -> bool:
        return view in self._views

    def __getitem__(self, view: int) -> dict[str, ViewStructure]:
        variants = self._views[view]
        points = (self.cache.structure_points(self._tiles[view], self._image_ids[view], self.params_json)
                  if any(len(s) for s in variants.values()) else {})
        out = {}
        for variant, s in variants.items():
            if len(s) and variant not in points:
                raise InputError(f"{self.cache.folder}: tile {self._tiles[view]} lacks the {variant} structure of "
                                 f"image {self._image_ids[view]}; run 'visloc ingest' of its drive again")
            X, S = points[variant] if len(s) else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
            out[variant] = replace(s, points_world=X, cov_world=S)
        return out
