"""The commands' own options, declared as the method parameters are (``visloc.params.declare``): how much
of a drive a command runs, how many processes it uses, the sharded store's tiles, the dashboard's port,
and what ``visloc bench`` runs. Their flags, ranges, ``--help`` lines and refusals come from here, like
every parameter's; a command takes the ones it has (``add_param_flags(..., only=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass

from visloc.params.declare import Params, param

COMMANDS = ("commands",)  # used by the command line, not by a method
BENCH_ONLY = ("bench",)


@dataclass(frozen=True)
class CommandOptions(Params):
    """Options of the commands that are not a method's parameters. A default of None is chosen by the
    command (the number of cores, the whole drive, ...), as its help says."""

    steps: int = param(6, "queries per series", kind="integer", low=1, methods=COMMANDS)
    workers: int | None = param(None, "processes for ingest: SIFT, structure and self-check", kind="integer", low=1,
                                when_unset="number of cores", methods=COMMANDS)
    limit: int | None = param(None, "stop after this many new images", kind="integer", low=1,
                              when_unset="every image", methods=COMMANDS)
    frames: int | None = param(None, "stop after this many frames", kind="integer", low=1,
                               when_unset="the whole drive", methods=COMMANDS)
    tile_m: float | None = param(None, "write a sharded store: --db is a folder of square tiles this many metres "
                                       "wide, one store each, ingested on a Dask cluster (pip install "
                                       "'visloc[cluster]'); every command reads it like a file",
                                 unit="m", low=0, open_low=True, when_unset="a plain store file; extending a sharded "
                                                                            "store, its own", methods=COMMANDS)
    halo_m: float | None = param(None, "sharded store: copy into each tile the images this close to its border",
                                 unit="m", low=0, when_unset="50, or the sharded store's own", methods=COMMANDS)
    tile_cache_mb: float = param(512.0, "sharded store: the most memory the open tiles' features and structure "
                                        "points may hold; the least recently used tile is dropped first",
                                 unit="MB", low=0, open_low=True, methods=COMMANDS)
    port: int = param(8080, "port to try first", kind="integer", low=1, high=65535, methods=COMMANDS)
    max_fix_gap_s: float | None = param(None, "a log: an image's geotag is interpolated between the fixes around it "
                                              "when they are at most this far apart; an image further from any fix is "
                                              "left out", unit="s", low=0, when_unset="1", methods=COMMANDS)


COMMAND_OPTIONS = CommandOptions()


@dataclass(frozen=True)
class BenchParams(Params):
    """What ``visloc bench`` runs: the paper's path against the fast path on the same queries, ingest
    throughput, a synthetic database and the refined paths. Its processes are ``--workers`` (2 here)."""

    series: int = param(2, "live series of 6 queries timed per lever", kind="integer", low=1, methods=BENCH_ONLY)
    shortlist_size: int = param(8, "images matched exactly per query by the fast path (the fast retrieval's "
                                   "shortlist)", kind="integer", low=1, flag="--shortlist", methods=BENCH_ONLY)
    fast_scale: float = param(0.5, "fast path's SIFT image scale", low=0.1, high=1, methods=BENCH_ONLY)
    ingest_images: int = param(40, "images timed for ingest", kind="integer", low=2,
                               methods=BENCH_ONLY)
    synthetic_images: int = param(100_000, "synthetic database size", kind="integer", low=1000,
                                  methods=BENCH_ONLY)
    synthetic_descriptors: int = param(64, "descriptors per synthetic image", kind="integer", low=8, methods=BENCH_ONLY)
    synthetic_queries: int = param(20, "lost queries on it", kind="integer", low=1,
                                   methods=BENCH_ONLY)
    skip_synthetic: bool = param(False, "leave out the synthetic database test", kind="bool", methods=BENCH_ONLY)
    skip_accuracy: bool = param(False, "leave out the accuracy over every series", kind="bool", methods=BENCH_ONLY)
    refined_stride: int = param(2, "refined paths: time every stride-th frame of the drive with each",
                                kind="integer", low=1, methods=BENCH_ONLY)
    skip_refined: bool = param(False, "leave out the exact and camera-rate refined paths", kind="bool",
                               methods=BENCH_ONLY)


BENCH = BenchParams()
BENCH_WORKERS = 2  # the bench's --workers: two processes, on every machine, so its figures compare
