"""A store file as the engine's callers see it: what it holds, loading it, keeping counts.

``Workspace`` is the way in for programs that are not the CLI (the dashboard,
scripts): it never hands out the store itself. Every call opens its own
short-lived connection, so one ``Workspace`` can be used from several threads.
Store errors come out as ``InputError`` naming the file.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from db import FeatureStore, StoreError
from visloc.database import GeoDatabase, QuerySet, load_database, load_query_set
from visloc.errors import InputError
from visloc.ingest import stored_sift_params
from visloc.localizer import PairCountCache
from visloc.params import MatchParams, SiftParams


@dataclass(frozen=True)
class Dataset:
    """One (source, camera) held by a store."""

    source: str
    camera: str
    n_images: int
    duration_s: float
    mean_keypoints: float
    has_calibration: bool

    @property
    def name(self) -> str:
        return f"{self.source}/{self.camera}"


class Workspace:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        with self._store() as store:  # fail now, with the file's name, if it is no store
            self._sift = stored_sift_params(store)

    @contextmanager
    def _store(self) -> Iterator[FeatureStore]:
        try:
            store = FeatureStore(self.path)
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(f"{self.path}: SQLite: {exc}") from None
        try:
            yield store
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(f"{self.path}: SQLite: {exc}") from None
        finally:
            store.close()

    @property
    def sift_params(self) -> SiftParams | None:
        """The SIFT settings the store's features were extracted with (None: no features yet)."""
        return self._sift

    def datasets(self) -> list[Dataset]:
        with self._store() as store:
            rows = store.sources()
            calibrated = {(c.source, c.camera) for c in store.cameras() if c.P_rect is not None}
        return [Dataset(r["source"], r["camera"], int(r["n_images"]),
                        float(r["last_timestamp_s"] - r["first_timestamp_s"]), float(r["mean_keypoints"] or 0.0),
                        (r["source"], r["camera"]) in calibrated) for r in rows]

    def _require_features(self) -> SiftParams:
        if self._sift is None:
            raise InputError(f"{self.path}: no features yet (build it with 'visloc ingest')")
        return self._sift

    def load_database(self, source: str, camera: str) -> GeoDatabase:
        sift = self._require_features()
        with self._store() as store:
            return load_database(store, source, camera, sift)

    def load_queries(self, source: str, camera: str) -> QuerySet:
        sift = self._require_features()
        with self._store() as store:
            return load_query_set(store, source, camera, sift)

    def pair_cache(self, db: GeoDatabase, queries: QuerySet, match_params: MatchParams) -> PairCountCache:
        """A count cache keyed by store image ids, seeded with the counts the store keeps for these thresholds."""
        with self._store() as store:
            known = store.pair_counts(queries.image_ids, match_params.tau1, match_params.tau2)
        return PairCountCache(db.descriptors_u8, match_params, db_keys=[im.image_id for im in db.images], known=known)

    def save_pair_counts(self, cache: PairCountCache) -> int:
        """Persist the counts ``cache`` computed since the last save; returns how many."""
        new = cache.take_new_entries()
        if new:
            with self._store() as store:
                store.add_pair_counts(new, cache.match_params.tau1, cache.match_params.tau2)
        return len(new)
