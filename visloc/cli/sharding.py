"""``visloc ingest --tile-m``: a sharded store ingested on a Dask cluster (``visloc.store.sharded``)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from visloc.cli.stopping import interrupted_status, interrupted_text
from visloc.db.shards import is_sharded
from visloc.errors import InputError
from visloc.progress import progress_reporter
from visloc.sources.drives import Drive
from visloc.store.cluster import open_cluster
from visloc.store.sharded import DEFAULT_HALO_M, prepare_store, publish_tiles, sharded_grid, staging_path
from visloc.store.workspace import Workspace


def ingest_sharded(a: argparse.Namespace, sequences: list[Drive], ingest_one: Callable) -> int:
    """Ingest ``sequences`` into the sharded store ``a.db`` on a Dask cluster (``ingest_one(workspace,
    sequence, cluster)`` ingests one into its working store and prints its report), then cut the tiles."""
    folder = Path(a.db)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"--db {folder}: a store file; a sharded store is a folder (give a new folder, or drop "
                         "--tile-m to extend the file)")
    # --tile-m and --halo-m are checked against their declarations (visloc.params.options) by the parser
    tile_m = sharded_grid(folder).tile_m if a.tile_m is None else a.tile_m
    halo_m = DEFAULT_HALO_M if a.halo_m is None else a.halo_m
    if is_sharded(folder):  # refused before any image is described: a store keeps the grid it was made with
        have = sharded_grid(folder)
        halo_m = have.halo_m if a.halo_m is None else halo_m
        if (tile_m, halo_m) != (have.tile_m, have.halo_m):
            raise InputError(f"--db {folder}: a sharded store of {have.tile_m:g} m tiles with a {have.halo_m:g} m "
                             f"halo; asked {tile_m:g} m tiles with a {halo_m:g} m halo")
    first = sequences[0].frames[0]
    prepare_store(folder, tile_m, halo_m, first.lat_deg, first.lon_deg)
    staging = staging_path(folder)
    seq = sequences[0]
    with open_cluster(a.workers or min(os.cpu_count() or 1, 8), a.address) as cluster:
        ws = Workspace(staging, create=True)
        try:
            for seq in sequences:
                ingest_one(ws, seq, cluster)
        except KeyboardInterrupt as exc:
            print(f"visloc: {interrupted_text(exc)}; {a.db} keeps {ws.stored_frame_count(seq.source, seq.camera)} "
                  f"images of {seq.name} (run the same command again to go on)", file=sys.stderr)
            return interrupted_status(exc)
        report = publish_tiles(folder, cluster, ws.global_vectors.global_vectors_by_image(), progress=progress_reporter("tiles", "tiles"))
    print(f"{a.db}: {report.n_tiles} tiles of {tile_m:g} m ({report.n_written} written, {report.n_skipped} complete "
          f"already), {report.n_images} images, {report.n_copies / max(report.n_images, 1):.1f} copies each with "
          f"the {halo_m:g} m halo")
    return 0


def print_tiles_read(ws: Workspace) -> None:
    """For a sharded store, one line on the tiles the command read and the memory they held."""
    stats = ws.tile_cache_stats
    if stats is not None:
        print(f"tiles read: {len(stats.distinct_tiles)} of {ws.tile_count()} ({stats.tiles_read} reads of features "
              f"or structure points, {stats.tiles_evicted} dropped to stay within the cache, at most "
              f"{stats.peak_bytes / 1e6:.1f} MB held)")


def require_stored(ws: Workspace, seq: Drive) -> None:
    """A reading command's drive must be in the sharded store whole (its frames stored, or skipped as
    unreadable at ingest): a sharded store is extended by 'visloc ingest --db FOLDER' only."""
    skipped = len(ws.skipped_frames(seq.source, seq.camera))
    n = ws.stored_frame_count(seq.source, seq.camera)
    if n + skipped < len(seq):
        raise InputError(f"--db {ws.path}: the sharded store holds {n} of the {len(seq)} frames of {seq.name}; add "
                         f"them with 'visloc ingest' of the drive into --db {ws.path}")
