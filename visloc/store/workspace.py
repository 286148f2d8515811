"""The one door to a store file: what it holds, building it, loading it, keeping counts.

Every caller (the command line, the dashboard, the benchmark, scripts) goes through
``Workspace``; it never hands out the store itself. Every call opens its own short-lived
connection, so one ``Workspace`` can be used from several threads. Store and SQLite
errors come out as ``InputError`` naming the file.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from visloc.store.database import GeoDatabase, QuerySet
from visloc.db.connection import sqlite_error_line
from visloc.db.integrity import clear_pair_counts
from visloc.db import (SCHEMA_VERSION, EmptyStoreError, FeatureStore, ImageRecord, SelfCheckRecord, SelfCheckTable,
                       SkippedFrame,
                       StoredImage, StoreError, StructureRecord, StructureTable)
from visloc.errors import InputError
from visloc.features.sift import at_contrast_threshold
from visloc.geo import LocalFrame
from visloc.geometry.projective import headings_deg_of
from visloc.sources.imagesize import DEFAULT_MAX_IMAGE_MP
from visloc.store.ingest import IngestReport, check_sift_settings, ingest, stored_sift_params
from visloc.store.sharded import Catalogue, held_datasets, owner_tiles
from visloc.store.tilecache import ContrastSelected, TileCache, TileCacheStats, TileStructures
from visloc.db.shards import is_sharded
from visloc.retrieval.matching import PairCountCache
from visloc.params import COMMAND_OPTIONS, REFINED, MatchParams, RefinedParams, SiftParams
from visloc.params.methods import PAPER_METHOD, features_for
from visloc.pose.selfcheck import (CAMERA_RATE_PARAMS, SelfCheckPose, lever_gain_from, record_pose,
                                    self_check_settings_json)
from visloc.sources.drives import Drive
from visloc.pose.refined import SHAPED_SPREAD_VIEWS
from visloc.pose.structure import ViewStructure, structure_settings_json
from visloc.pose.uncertainty import LeverGain
from visloc.store.globalvectors import GlobalVectors, global_vectors_name  # noqa: F401 (named here too)

STORE_SCHEMA_VERSION = SCHEMA_VERSION  # the store schema this visloc reads and writes


@dataclass(frozen=True)
class StoredDrive:
    """One (source, camera) held by a store."""

    source: str
    camera: str
    n_images: int
    duration_s: float
    mean_keypoints: float
    has_calibration: bool  # intrinsics (P_rect) known
    has_extrinsics: bool = False  # the camera's pose relative to the geotag's reference point known
    n_without_attitude: int = 0  # images whose attitude is unknown

    @property
    def name(self) -> str:
        return f"{self.source}/{self.camera}"


class Workspace:
    """A store file. ``create=True`` makes a new store when the file does not exist yet;
    ``read_only=True`` never changes the file (no migration, no cached counts saved, works on a
    read-only medium): every method that would write raises ``InputError`` instead."""

    def __init__(self, path: str | Path, *, create: bool = False, read_only: bool = False,
                 tile_cache_mb: float = COMMAND_OPTIONS.tile_cache_mb):
        self.path = Path(path)
        self.read_only = read_only
        # a sharded store (a folder of tiles, ``visloc.store.sharded``) is read from its catalogue (every
        # row but the features, of the datasets asked for) and its features from the tiles a query touches,
        # ``tile_cache_mb`` of them kept open (``visloc.store.tilecache``); extended by 'visloc ingest' only
        self.sharded = is_sharded(self.path)
        self._catalogue = Catalogue(self.path) if self.sharded else None
        self._tiles = TileCache(self.path, tile_cache_mb) if self.sharded else None
        if self.sharded:
            self.read_only, create = True, False
        with self._store(create=create) as store:  # fail now, with the file's name, if it is no store
            self._sift = stored_sift_params(store)
            # opening for writing migrates a store of an older schema version in place: from which, if it did
            self.migrated_from: int | None = store.migrated_from
            self.checksums_filled: int = store.checksums_filled  # arrays whose checksums that migration computed
        self.global_vectors = GlobalVectors(self.path, self._store, self._cover, self.drives)

    @property
    def _file(self) -> Path:
        return self.path if self._catalogue is None else self._catalogue.path

    def _cover(self, source: str, camera: str) -> None:
        """A sharded store's catalogue holds (source, camera) from here on (no-op for a store file)."""
        if self._catalogue is not None:
            self._catalogue.cover([(source, camera)])

    @property
    def catalogue_datasets(self) -> frozenset[tuple[str, str]] | None:
        """The (source, camera)s a sharded store's catalogue was merged for so far (None for a store file)."""
        return None if self._catalogue is None else self._catalogue.covered

    @property
    def tile_cache_stats(self) -> TileCacheStats | None:
        """What reading a sharded store's tiles did so far (None for a store file)."""
        return None if self._tiles is None else self._tiles.stats

    def tile_count(self) -> int:
        """How many tiles the sharded store has (0 for a store file)."""
        return 0 if self._tiles is None else self._tiles.n_tiles

    @staticmethod
    def is_sharded(path: str | Path) -> bool:
        """True when ``path`` is a sharded store (a folder of tiles) rather than a store file."""
        return is_sharded(path)

    @staticmethod
    @contextmanager
    def inspect(path: str | Path) -> Iterator[FeatureStore]:
        """The store at ``path`` read as it is, never changed, also when it lacks tables (``visloc check``)."""
        try:
            store = FeatureStore(path, read_only=True, lacking_ok=True)
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(sqlite_error_line(str(path), exc)) from None
        try:
            yield store
        finally:
            store.close()

    @contextmanager
    def _store(self, *, create: bool = False) -> Iterator[FeatureStore]:
        try:
            store = FeatureStore(self._file, create=create and not self.read_only, read_only=self.read_only)
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(sqlite_error_line(str(self.path), exc)) from None
        try:
            yield store
        except StoreError as exc:
            raise InputError(str(exc)) from None
        except sqlite3.Error as exc:
            raise InputError(sqlite_error_line(str(self.path), exc)) from None
        finally:
            store.close()

    # -- what it holds -------------------------------------------------------------------------

    @property
    def sift_params(self) -> SiftParams | None:
        """The SIFT settings the store's features were extracted with (None: no features yet)."""
        return self._sift

    def image_count(self) -> int:
        if self._catalogue is not None:
            return self._catalogue.image_count()
        with self._store() as store:
            return store.image_count()

    def drive_keys(self) -> list[tuple[str, str]]:
        """(source, camera) of every dataset the store holds, without reading their images."""
        if self._catalogue is not None:
            return held_datasets(self.path)
        with self._store() as store:
            return sorted((r["source"], r["camera"]) for r in store.sources())

    def drives(self) -> list[StoredDrive]:
        """Every dataset the store holds, summed up (for a sharded store, its whole catalogue is read)."""
        if self._catalogue is not None:
            self._catalogue.cover_all()
        with self._store() as store:
            rows = store.sources()
            cameras = {(c.source, c.camera): c for c in store.cameras()}
            lacking = {(r["source"], r["camera"]): len(store.frames_without_attitude(r["source"], r["camera"]))
                       for r in rows}
        out = []
        for r in rows:
            key = (r["source"], r["camera"])
            cam = cameras.get(key)
            out.append(StoredDrive(r["source"], r["camera"], int(r["n_images"]),
                               float(r["last_timestamp_s"] - r["first_timestamp_s"]), float(r["mean_keypoints"] or 0.0),
                               has_calibration=cam is not None and cam.P_rect is not None,
                               has_extrinsics=cam is not None and cam.T_camera_imu is not None,
                               n_without_attitude=lacking[key]))
        return out

    # -- building it ---------------------------------------------------------------------------

    def skipped_frames(self, source: str | None = None, camera: str | None = None) -> list[SkippedFrame]:
        """The frames ingest skipped because they could not be described, with the reason (of one dataset)."""
        if self._catalogue is not None:
            self._catalogue.cover(held_datasets(self.path) if source is None else [(source, camera)])
        with self._store() as store:
            return [f for f in store.skipped_frames() if source is None or (f.source, f.camera) == (source, camera)]

    def stored_frame_count(self, source: str, camera: str) -> int:
        self._cover(source, camera)
        with self._store() as store:
            return len(store.stored_frames(source, camera))

    def add_features(self, sequence: Drive, sift: SiftParams, *, workers: int | None = None,
                     limit: int | None = None, progress: Callable[[int, int], None] | None = None,
                     skip_bad_frames: bool = False, max_image_mp: float = DEFAULT_MAX_IMAGE_MP,
                     repair: bool = False, cluster=None) -> IngestReport:
        """SIFT every frame of ``sequence`` that the store lacks, into the store (``visloc.store.ingest``, also
        for ``skip_bad_frames`` and ``max_image_mp``); resumable. ``visloc.store.build.ingest_sequence`` adds
        what the refined methods need after it."""
        with self._store(create=True) as store:
            report = ingest(store, sequence, sift, workers=workers, progress=progress, limit=limit,
                            skip_bad_frames=skip_bad_frames, max_image_mp=max_image_mp, repair=repair,
                            cluster=cluster)
            self._sift = stored_sift_params(store)
        return report

    def structure_complete_ids(self, image_ids: list[int], settings_json: str, n_variants: int) -> set[int]:
        """The images among ``image_ids`` whose every structure variant made with ``settings_json`` is stored."""
        with self._store() as store:
            return set(StructureTable(store).complete_ids(image_ids, settings_json, n_variants))

    def self_checked_ids(self, image_ids: list[int], settings_json: str) -> set[int]:
        """The images among ``image_ids`` that have a self-check made with ``settings_json``."""
        with self._store() as store:
            return set(SelfCheckTable(store).get(image_ids, settings_json))

    def add_self_checks(self, records: list[SelfCheckRecord]) -> None:
        with self._store() as store:
            SelfCheckTable(store).add(records)

    def self_check_poses(self, db: GeoDatabase, params: RefinedParams = REFINED, *,
                         camera_rate: bool = False) -> list[SelfCheckPose]:
        """``db``'s stored self-check made with ``params``' settings, one pose per checked image (by database
        index, in the order stored; empty when there is none). ``camera_rate``: the camera-rate path's."""
        settings = self_check_settings_json(params, camera_rate=camera_rate)
        with self._store() as store:
            records = SelfCheckTable(store).get([im.image_id for im in db.images], settings)
        index_of, headings = {im.image_id: k for k, im in enumerate(db.images)}, headings_deg_of(db.T_world_imu())
        return [record_pose(r, index_of[r.image_id], headings[index_of[r.image_id]]) for r in records.values()]

    def lever_gain(self, db: GeoDatabase, params: RefinedParams = REFINED, *,
                   camera_rate: bool = False) -> LeverGain | None:
        """The lever gain ``db``'s stored self-check calls for (``visloc.pose.selfcheck.lever_gain_from``);
        None when the store holds no self-check of it with ``params``' settings. ``camera_rate``: the
        camera-rate path's self-check's (``params``: that path's, ``CAMERA_RATE_PARAMS``)."""
        poses = self.self_check_poses(db, params, camera_rate=camera_rate)
        if not poses:
            return None
        what = "camera-rate self-check" if camera_rate else "self-check"
        return lever_gain_from(poses, source=f"{what} of {db.source}/{db.camera} ({len(poses)} images)",
                               min_views=0 if camera_rate else SHAPED_SPREAD_VIEWS)

    def load_structure(self, db: GeoDatabase, params: RefinedParams = REFINED,
                       views: list[int] | None = None) -> Mapping[int, dict[str, ViewStructure]]:
        """Stored structure of ``db``'s images (or of the database indices ``views``): database index ->
        variant -> structure, neighbours as database indices. Images without stored structure are absent.
        A sharded store's is a mapping that reads a view's points from its tile when it is asked for."""
        if db.selected_contrast is not None:
            raise InputError(f"{self.path}: its structure indexes the features as stored, at SIFT contrast "
                             f"{self._sift.contrast_threshold:g}, not those selected at {db.selected_contrast:g} "
                             f"(--sift-contrast {self._sift.contrast_threshold:g} reads them as stored)")
        self._cover(db.source, db.camera)
        index_of = {im.image_id: k for k, im in enumerate(db.images)}
        wanted = range(len(db.images)) if views is None else views
        settings = structure_settings_json(params)
        with self._store() as store:
            records = StructureTable(store).get([db.images[k].image_id for k in wanted], settings,
                                                points=self._tiles is None)
        out: dict[int, dict[str, ViewStructure]] = {}  # a sharded store's without points: its tiles have them
        for (image_id, variant), r in records.items():
            if any(j not in index_of for j in r.neighbour_ids):
                continue
            k = index_of[image_id]
            out.setdefault(k, {})[variant] = ViewStructure(
                k, variant, tuple(index_of[j] for j in r.neighbour_ids), r.rows_i32.astype(np.int64), r.points_f64,
                r.cov_f64, r.reason, r.build_ms)
        if self._tiles is None:
            return out
        owners = owner_tiles(self.path, db.source, db.camera)
        return TileStructures(self._tiles, settings, out, {k: db.images[k].image_id for k in out},
                              {k: owners[db.images[k].image_id] for k in out})

    def save_structure(self, records: list[StructureRecord]) -> None:
        """Keep structure made elsewhere (e.g. a synthetic database), in one transaction."""
        with self._store() as store:
            StructureTable(store).add(records)

    def stored_structure(self, image_ids: list[int], settings_json: str) -> dict[tuple[int, str], StructureRecord]:
        """(image id, variant) -> the stored record, for ``image_ids`` only (large databases read what they pose)."""
        with self._store() as store:
            return StructureTable(store).get(image_ids, settings_json)

    # -- loading it ----------------------------------------------------------------------------

    def _require_features(self, sift: SiftParams | None) -> SiftParams:
        if self._sift is None:
            raise InputError(f"{self.path}: no features yet (build it with 'visloc ingest')")
        return sift or self._sift

    def _images(self, store: FeatureStore, source: str, camera: str, sift: SiftParams
                ) -> tuple[tuple[StoredImage, ...], Sequence[np.ndarray], Sequence[np.ndarray], float | None]:
        """Stored images of (source, camera) in time order with their keypoints and descriptors, and the
        contrast threshold they were selected at (None: as stored); refuses features extracted with other
        SIFT settings than ``sift``, but for a lower contrast threshold, whose features it selects."""
        selected = check_sift_settings(store, sift)
        images = tuple(store.images(source, camera))
        if not images:
            have = ", ".join(f"{s}/{c}" for s, c in self.drive_keys()) or "nothing"
            raise EmptyStoreError(f"{store.label}: no images of {source}/{camera} (it holds {have})")
        if self._tiles is not None:
            keypoints, descriptors = self._tiles.features([im.image_id for im in images],
                                                          owner_tiles(self.path, source, camera))
        else:
            features = store.features(im.image_id for im in images)
            keypoints = tuple(features[im.image_id][0] for im in images)
            descriptors = tuple(features[im.image_id][1] for im in images)
        if selected is None:
            return images, keypoints, descriptors, None
        layers = sift.n_octave_layers
        if isinstance(keypoints, tuple):
            pairs = [at_contrast_threshold(k, d, selected, layers) for k, d in zip(keypoints, descriptors)]
            return images, tuple(k for k, _ in pairs), tuple(d for _, d in pairs), selected
        return (images, ContrastSelected(keypoints, keypoints, selected, layers),
                ContrastSelected(keypoints, descriptors, selected, layers), selected)

    def load_database(self, source: str, camera: str, sift: SiftParams | None = None,
                      frame: LocalFrame | None = None) -> GeoDatabase:
        """(source, camera) as a geotagged database; its local frame is centred on its first image
        unless ``frame`` is given. ``sift`` (default: the store's) must equal the store's settings, or differ
        only by a higher contrast threshold (the store's features selected at it)."""
        sift = self._require_features(sift)
        self._cover(source, camera)
        with self._store() as store:
            images, keypoints, descriptors, selected = self._images(store, source, camera, sift)
            calibration = store.get_camera(source, camera)
        lat = np.array([im.lat_deg for im in images])
        lon = np.array([im.lon_deg for im in images])
        frame = frame or LocalFrame(float(lat[0]), float(lon[0]))
        alt = np.array([np.nan if im.alt_m is None else im.alt_m for im in images], float)
        rpy = np.array([[np.nan if v is None else v for v in (im.roll_rad, im.pitch_rad, im.yaw_rad)]
                        for im in images], float).reshape(-1, 3)
        db = GeoDatabase(
            source=source, camera=camera, images=images,
            timestamps_s=np.array([im.timestamp_s for im in images]),
            lat_deg=lat, lon_deg=lon, east_north_m=frame.to_local(lat, lon),
            keypoints_f32=keypoints, descriptors_u8=descriptors,
            calibration=calibration, frame=frame, up_m=alt - alt[0], rpy_rad=rpy, geotag_sigma_m=_sigmas(images),
            selected_contrast=selected, octave_layers=sift.n_octave_layers,
            retrieval_contrast=_retrieval_contrast(self._sift, sift),
        )
        if selected is not None:  # the self-checks measured the store's own features, which this is not
            return db
        return replace(db, lever_gain=self.lever_gain(db),
                       camera_rate_lever_gain=self.lever_gain(db, CAMERA_RATE_PARAMS, camera_rate=True))

    def load_queries(self, source: str, camera: str, sift: SiftParams | None = None) -> QuerySet:
        """(source, camera) as queries, with their geotags as ground truth."""
        sift = self._require_features(sift)
        self._cover(source, camera)
        with self._store() as store:
            images, keypoints, descriptors, selected = self._images(store, source, camera, sift)
            calibration = store.get_camera(source, camera)
        return QuerySet(
            source=source, camera=camera, frames=np.array([im.frame for im in images]),
            timestamps_s=np.array([im.timestamp_s for im in images]), lat_deg=np.array([im.lat_deg for im in images]),
            lon_deg=np.array([im.lon_deg for im in images]), descriptors_u8=descriptors,
            sift_ms=np.array([np.nan if im.sift_ms is None else im.sift_ms for im in images]),
            image_ids=tuple(im.image_id for im in images), paths=tuple(im.path for im in images),
            keypoints_f32=keypoints, calibration=calibration,
            heading_deg=np.array([np.nan if im.heading_deg is None else im.heading_deg for im in images]),
            truth_sigma_m=_sigmas(images), selected_contrast=selected,
        )

    # -- cached correspondence counts -----------------------------------------------------------

    def pair_cache(self, db: GeoDatabase, queries: QuerySet, match_params: MatchParams) -> PairCountCache:
        """A count cache keyed by store image ids, seeded with the counts the store keeps for these thresholds,
        of the features as stored or as selected at a higher contrast threshold (``GeoDatabase.selected_contrast``)."""
        db_keys = [im.image_id for im in db.images]
        counted_at = db.selected_contrast or db.retrieval_contrast  # None: the features as stored
        if db.selected_contrast != queries.selected_contrast:  # no count of such a pair is kept
            return PairCountCache(db.retrieval_descriptors_u8, match_params, db_keys=db_keys, persistent=False)
        with self._store() as store:
            known = store.pair_counts(queries.image_ids, match_params.tau1, match_params.tau2, counted_at)
        return PairCountCache(db.retrieval_descriptors_u8, match_params, db_keys=db_keys, known=known,
                              selected_contrast=counted_at)

    def save_pair_counts(self, cache: PairCountCache) -> int:
        """Persist the counts ``cache`` computed since the last save; returns how many. A read-only
        workspace writes nothing: the counts stay in ``cache`` only."""
        new = cache.take_new_entries()
        if new and cache.persistent and not self.read_only:
            with self._store() as store:
                store.add_pair_counts(new, cache.match_params.tau1, cache.match_params.tau2, cache.selected_contrast)
        return len(new)

    def clear_pair_counts(self) -> int:
        """Forget every cached image-pair count, as a store is right after ingest; returns how many."""
        if self.read_only:
            raise InputError(f"{self.path}: opened read only; its cached counts cannot be cleared")
        with self._store() as store:
            return clear_pair_counts(store)

    # -- large databases: images from elsewhere, streamed descriptors, stored global vectors --------

    def setting(self, key: str) -> object | None:
        with self._store() as store:
            return store.get_setting(key)

    def record_setting(self, key: str, value: object) -> None:
        """Record ``value`` under ``key``; refuse a store that holds another value there."""
        with self._store() as store:
            store.require_setting(key, value)

    def add_images(self, batch: list[tuple[ImageRecord, np.ndarray, np.ndarray]]) -> int:
        """Store (record, keypoints_f32 (N, 6), descriptors_u8 (N, 128)) triples made elsewhere (e.g. a
        synthetic database), in one transaction; returns how many were new."""
        with self._store(create=True) as store:
            return store.add_images(batch)

    def image_ids(self, source: str, camera: str) -> np.ndarray:
        """(N,) store ids of (source, camera)'s images in time order, without loading anything else."""
        self._cover(source, camera)
        with self._store() as store:
            return store.image_ids(source, camera)

    def iter_descriptors(self, image_ids, chunk_size: int = 256) -> Iterator[tuple[int, np.ndarray]]:
        """(image id, descriptors_u8) for ``image_ids`` in order, read ``chunk_size`` images at a time:
        memory stays bounded however large the store."""
        if self._tiles is not None:
            ids = [int(i) for i in image_ids]
            owners: dict[int, str] = {}
            for source, camera in self.drive_keys():
                owners.update(owner_tiles(self.path, source, camera))
            yield from zip(ids, self._tiles.features(ids, owners)[1])
            return
        with self._store() as store:
            yield from store.iter_descriptors(image_ids, chunk_size)

def _sigmas(images: tuple[StoredImage, ...]) -> np.ndarray:
    """(N,) stated geotag accuracy of each image, sigma per axis in metres, NaN where unknown."""
    return np.array([np.nan if im.position_accuracy_m is None else im.position_accuracy_m for im in images], float)


def _retrieval_contrast(store: SiftParams, read: SiftParams) -> float | None:
    """The contrast threshold retrieval counts features read at ``read`` from a store built with ``store`` at:
    the paper's where both are lower (``visloc.params.methods.features_for``), else None (all of them)."""
    paper = features_for(PAPER_METHOD, store).contrast_threshold
    return paper if read.contrast_threshold < paper and store.n_features == 0 else None
