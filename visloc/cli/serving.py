"""``visloc dashboard``: the browser app on a store (live), or on saved runs (``--run``)."""

from __future__ import annotations

import argparse

from visloc.cli.choices import only_camera
from visloc.errors import InputError


def cmd_dashboard(a: argparse.Namespace) -> int:
    # --port is checked against its declaration (visloc.params.options) by the parser
    from visloc.dashboard import serve, serve_runs  # on demand: the browser app (viser) is only needed here

    if a.run and a.tune_from:
        raise InputError("--run and --tune-from: give one (--run shows saved runs, --tune-from tunes one live)")
    if a.query_images is not None and a.run:
        raise InputError("--query-images: for a store's live page; --run shows saved runs, which need no images")
    if a.query_images is not None and not a.query_images.exists():
        raise InputError(f"--query-images {a.query_images}: not found (a KITTI raw root, a CSV or a log)")
    if a.run:  # saved runs: no store is opened
        serve_runs(a.run, host=a.host, port=a.port, announce=lambda text: print(text, flush=True))
        return 0
    tune = None
    if a.tune_from is not None:  # a file that is no run is refused here, in one line naming it
        from visloc.results.saved import live_settings, load_run, run_files

        tune = (a.tune_from, live_settings(load_run(run_files(a.tune_from)[0][1])))
    db_source, db_camera = _split(tune[1].database if tune else None)
    q_source, q_camera = _split(tune[1].queries if tune else None)
    tiles = None
    if a.tiles is not None:  # a bad URL is refused here, before anything is served
        from visloc.dashboard.tiles import TileSource
        from visloc.sources.log_cache import cache_root

        tiles = TileSource(a.tiles, cache_root() / "tiles", attribution=a.tiles_attribution)
    elif a.tiles_attribution is not None:
        raise InputError("--tiles-attribution: give the tiles with --tiles")
    only = only_camera(a.db)  # a store of one camera shows it first; a missing or bad store is reported in the page
    serve(a.db, host=a.host, port=a.port, db_camera=a.db_camera or db_camera or only or "image_01",
          query_camera=a.query_camera or q_camera or only or "image_00", db_source=a.db_source or db_source,
          query_source=a.query_source or q_source, allow=a.allow, tune_from=tune,
          announce=lambda text: print(text, flush=True), tiles=tiles, query_images=a.query_images)
    return 0


def _split(dataset: str | None) -> tuple[str | None, str | None]:
    """A dataset's name as the store lists it ("<drive>/<camera>") as (drive, camera); (None, None) when not given."""
    if not dataset or "/" not in dataset:
        return None, None
    source, camera = dataset.rsplit("/", 1)
    return source, camera
