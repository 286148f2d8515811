"""The ``visloc`` command line: ingest, localize, evaluate, evaluate-drives, track, dashboard, bench, info.

This module only parses; ``visloc.cli.commands`` does the work. Errors in input or
parameters end the command with one line on stderr naming the file or parameter, and
exit status 2; nothing already stored is lost.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from pathlib import Path

from visloc.cli.help_text import DEFAULT_DB, DEFAULT_FAST_DB, examples
from visloc.cli.param_flags import add_param_flags, check_flag_values
from visloc.cli.stopping import interrupted_status, interrupted_text, stop_on_signal
from visloc.errors import VislocError
from visloc.params import (BENCH, BENCH_WORKERS, COMMAND_OPTIONS, FAST, PAPER_EVAL_RETRIEVAL, PAPER_FILTER,
                           PAPER_MATCH, PAPER_RETRIEVAL, PAPER_SIFT, STORE_SIFT, TRACK, BenchParams, CommandOptions,
                           FastParams, FilterParams, MatchParams, RefinedParams, RetrievalParams, SiftParams, TrackParams)
from visloc.params.methods import METHODS
from visloc.sources.imagesize import DEFAULT_MAX_IMAGE_MP, require_max_image_mp

# Parsing, --help, --version and refusing a bad argument load nothing heavy: what a command does
# (``visloc.cli.commands``, OpenCV, the store) is imported once the arguments are accepted.


def _version() -> str:
    import visloc  # its own attribute, which pyproject.toml reads: no scan of the installed packages' metadata

    return visloc.__version__


class _VersionAction(argparse.Action):
    """``--version``: the package's version, read only when asked for."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"visloc {_version()}")
        parser.exit()


def _runs(module: str, function: str):
    """What a command does: ``visloc.cli.<module>.<function>``, imported when the command runs."""
    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(f"visloc.cli.{module}"), function)(args)

    run.__qualname__ = run.__name__ = function
    return run


# -- argument groups --------------------------------------------------------------

SIFT_CONTRAST_HELP = (f"SIFT's contrast threshold (the paper's {PAPER_SIFT.contrast_threshold:g}; default: the store's, "
                      f"{STORE_SIFT.contrast_threshold:g} for a new store; the paper's method reads a store built at a "
                      "lower one with the keypoints SIFT keeps at the paper's)")


def _add_sift(p: argparse.ArgumentParser) -> None:
    add_param_flags(p.add_argument_group(
        "SIFT (the store's settings; a store built keeping every keypoint at a lower --sift-contrast serves a "
        "higher one)"), SiftParams, PAPER_SIFT, automatic={"contrast_threshold": SIFT_CONTRAST_HELP})


EXCLUSION_AUTO_HELP = ("ignore database images closer in time to the query than this, s (default: 1 when the database "
                       "holds images of the queries' own drive, any camera, so that no query is posed from its own "
                       "image or its twin; else 0. 0 turns it off, with a warning on such a database)")


def _add_method(p: argparse.ArgumentParser, retrieval: RetrievalParams, *, auto_exclusion: bool = False) -> None:
    g = p.add_argument_group("matching, retrieval and filter (defaults: the paper's Table 1)")
    add_param_flags(g, MatchParams, PAPER_MATCH)
    add_param_flags(g, RetrievalParams, retrieval,
                    automatic={"exclusion_s": EXCLUSION_AUTO_HELP} if auto_exclusion else None)
    add_param_flags(g, FilterParams, PAPER_FILTER)


def _method_presets(part: str) -> list[tuple[str, object]]:
    """(label, parameters) of ``part`` ("pose" or "shortlist") in every method that has it; the fast
    retrieval's own for ``--fast``."""
    out = [(m.name, getattr(m, part)) for m in METHODS.values() if getattr(m, part) is not None]
    return out + ([("--fast", FAST)] if part == "shortlist" else [])


def _add_mode(p: argparse.ArgumentParser, *, choose_mode: bool = True, exclude: tuple[str, ...] = ()) -> None:
    g = p.add_argument_group("method (paper: the paper's; refined: a metric pose from the database, see the README)")
    if choose_mode:  # a plain string checked by commands.method_of, so a bad value is a one-line error naming --mode
        g.add_argument("--mode", default="paper", metavar="{" + ",".join(METHODS) + "}",
                       help="paper: the best match's geotag; refined: a metric pose from the database's geometry; "
                            "refined-fast: the refined pose on the store's stored structure, at camera rate "
                            "(default %(default)s)")
    add_param_flags(p.add_argument_group("refined and refined-fast methods (default: each method's own)"),
                    RefinedParams, presets=_method_presets("pose"), exclude=exclude)
    add_param_flags(p.add_argument_group("fast retrieval: --fast and refined-fast (default: each method's own)"),
                    FastParams, presets=_method_presets("shortlist"), exclude=exclude)


SOURCE_HELP = ("a drive: a vehicle's log (a ROS 1 .bag, an .mcap file or a rosbag2 folder), a KITTI raw root "
               "(default $VISLOC_DATA or ../shared/data/kitti) or a CSV of geotagged images")


def _add_source(p: argparse.ArgumentParser, camera_help: str, camera_default: str, *, multiple: bool = False) -> None:
    # --camera defaults to None, resolved by the command: given for a CSV drive it is an error
    p.add_argument("source", nargs="?", type=Path, default=None, help=SOURCE_HELP)
    p.add_argument("--drive", default=None, help="KITTI drive, e.g. 2011_09_26_drive_0001 (needed if the root holds several)")
    p.add_argument("--camera", action="append" if multiple else "store", default=None,
                   help=camera_help + f"{' (repeatable)' if multiple else ''}: a KITTI camera (default "
                        f"{camera_default}) or a log's image topic (default its only one); a CSV drive has one camera")
    _add_log_topics(p)


def _add_log_topics(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("a log's topics (default: the log's only one of each kind)")
    g.add_argument("--fix-topic", default=None, metavar="TOPIC", help="sensor_msgs/NavSatFix topic of the geotags")
    g.add_argument("--camera-info-topic", default=None, metavar="TOPIC",
                   help="sensor_msgs/CameraInfo topic of the images (default: the one beside the image topic)")
    g.add_argument("--imu-topic", default=None, metavar="TOPIC",
                   help="sensor_msgs/Imu topic whose orientation gives the attitude (the refined mode needs it)")
    _add_options(g, "max_fix_gap_s")


def _add_sampling(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sampling", choices=("stride", "time"), default="stride",
                   help="stride: every round(dt/frame interval)-th frame, as the paper (every 10th on KITTI); "
                        "time: the frame nearest to each multiple of dt (default %(default)s)")


def _add_bad_frames(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("ingest: bad frames and limits")
    g.add_argument("--skip-bad-frames", action="store_true",
                   help="skip frames that cannot be described (unreadable, too large, no keypoints) instead of "
                        "stopping; the store records which and why ('visloc info' lists them)")
    g.add_argument("--max-image-mp", type=float, default=DEFAULT_MAX_IMAGE_MP,
                   help="refuse images larger than this many megapixels, checked before decoding; SIFT needs "
                        "about 230 bytes per pixel in each worker (default %(default)s)")


def _add_db(p: argparse.ArgumentParser, *, tile_cache: bool = False) -> None:
    p.add_argument("--db", type=Path, default=Path(DEFAULT_DB), help="store file (default %(default)s)")
    if tile_cache:
        _add_options(p, "tile_cache_mb")


def _add_options(p, *names: str, preset: CommandOptions = COMMAND_OPTIONS) -> None:
    """The commands' own options ``names`` (``visloc.params.options``), with ``preset``'s defaults."""
    add_param_flags(p, CommandOptions, preset, only=names)


def _add_database_choice(p: argparse.ArgumentParser, camera_help: str,
                         source_help: str = "database drive/dataset in the store (default: the store's only one, "
                                            "else the queries' own)") -> None:
    """--db-camera and --db-source: which of the store's drives and cameras is the database."""
    p.add_argument("--db-camera", default=None, help=camera_help)
    p.add_argument("--db-source", default=None, help=source_help)


def _add_json(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--json", type=Path, default=None, help=f"write {what} as JSON")


def _add_outputs(p: argparse.ArgumentParser, what: str) -> None:
    """--json (``what`` it writes) and the trajectory files."""
    _add_json(p, what)
    _add_exports(p)


def _add_exports(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("trajectory files (truth, measurements, estimates with covariance)")
    g.add_argument("--geojson", type=Path, default=None, metavar="FILE",
                   help="write them as GeoJSON for GIS tools (FILE ends in .geojson or .json)")
    g.add_argument("--csv", type=Path, default=None, metavar="FILE", help="write them as CSV, one row per step")
    g.add_argument("--mcap", type=Path, default=None, metavar="FILE",
                   help="write the run as MCAP for Foxglove (FILE ends in .mcap): location fixes with their "
                        "covariance, the tracks and ellipses as 3D scene entities, each step's figures")
    g.add_argument("--mcap-images", action="store_true",
                   help="with --mcap: also each query's image and its best match's (a larger file)")


class _HelpFormatter(argparse.HelpFormatter):
    """Descriptions wrapped to the terminal as usual; the examples (text with line breaks) kept as written."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if "\n" in text:
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)


def _command(sub, name: str, help: str, description: str, module: str = "commands") -> argparse.ArgumentParser:
    """The subcommand ``name``; what it does is ``visloc.cli.<module>.cmd_<name>``, loaded when it runs."""
    p = sub.add_parser(name, help=help, description=description, epilog=examples(name),
                       formatter_class=_HelpFormatter)
    p.set_defaults(func=_runs(module, "cmd_" + name.replace("-", "_")))
    return p



# -- parser ----------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="visloc",
        description="Localize a vehicle from one camera against a database of geotagged images (SIFT + Kalman filter).",
        epilog=examples(), formatter_class=_HelpFormatter)
    parser.add_argument("--version", action=_VersionAction, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = _command(sub, "ingest", help="build or extend a store: SIFT features and geotags of every image",
                       description="Extract SIFT from every image of a drive (or CSV) and store features and geotags. "
                                   "Re-running skips what is stored; an interruption loses nothing committed.")
    _add_source(p, "KITTI camera to store", "image_01, or image_00 on a drive without it", multiple=True)
    _add_db(p)
    _add_options(p, "workers", "limit")
    p.add_argument("--features-only", action="store_true",
                   help="store SIFT features and geotags only, for a camera used only for queries: no global "
                        "vectors, structure or self-check, which a database camera needs (a later ingest without "
                        "this flag adds them)")
    _add_options(p, "tile_m", "halo_m")
    p.add_argument("--address", default=None, metavar="HOST:PORT",
                   help="sharded store: ingest on the Dask scheduler at this address (default: a local cluster "
                        "of --workers processes)")
    _add_bad_frames(p)
    _add_sift(p)

    p = _command(sub, "localize", help="localize one query series against a store; print the paper's Tables 2 and 3",
                       description="Run one series of queries (one every --dt-s seconds) against the database and "
                                   "print the paper's Tables 2 and 3 for it.")
    _add_source(p, "query camera", "image_00")
    _add_db(p, tile_cache=True)
    _add_database_choice(p, "database camera in the store (default: the database drive's only camera; with several, "
                            "image_01 for image_00 queries, as the paper)")
    p.add_argument("--start-frame", type=int, default=0, help="query frame of the first step, t-5 (default %(default)s)")
    _add_options(p, "steps")
    _add_sampling(p)
    _add_outputs(p, "the steps")
    _add_method(p, PAPER_RETRIEVAL, auto_exclusion=True)
    _add_mode(p)
    _add_sift(p)

    p = _command(sub, "evaluate", help="the paper's evaluation protocol on a drive (KITTI or CSV)",
                       description="Every series of --steps queries one --dt-s apart that fits in the drive; "
                                   "per-step mean measurement and estimate errors (Figure 4), final error, latency. "
                                   "Ingests both cameras into --db first (skipping what is stored).")
    p.add_argument("root", nargs="?", type=Path, default=None, help=SOURCE_HELP)
    p.add_argument("--drive", default=None, help="KITTI drive, e.g. 2011_09_26_drive_0001")
    _add_db(p, tile_cache=True)
    p.add_argument("--query-camera", default=None, help="camera of the queries: KITTI's (default image_00, left "
                                                        "gray) or a log's image topic (default its only one)")
    _add_log_topics(p)
    _add_database_choice(p, "KITTI camera of the database (default image_01, right gray; the query camera on a drive "
                            "without image_01); with --db-source, a camera in the store",
                         "evaluate against this drive/dataset already in the store (e.g. another CSV drive ingested "
                         "before) instead of the query drive's own cameras")
    _add_options(p, "steps")
    p.add_argument("--start-frames", default=None, help="only series starting at these query frames, e.g. 0,20,40")
    _add_sampling(p)
    _add_json(p, "the results")
    p.add_argument("--plot", type=Path, default=None, help="error plot PNG (default: the JSON path with .png)")
    _add_exports(p)
    _add_options(p, "workers")
    p.add_argument("--smooth", action="store_true",
                   help="also run the RTS smoother over each series and report its per-step errors")
    p.add_argument("--fast", action="store_true",
                   help="the fast retrieval: the filter gates the candidates, VLAD vectors shortlist "
                        "8 of them, exact counts on those only (default: the paper's window, every candidate)")
    _add_method(p, PAPER_EVAL_RETRIEVAL)
    _add_mode(p)
    _add_sift(p)
    _add_bad_frames(p)

    p = _command(sub, "evaluate-drives", help="the evaluation on every drive of a data root, every protocol and mode",
                       description="Every KITTI drive under ROOT (a drive dropped into the folder is picked up), "
                                   "with each protocol it supports: a stereo drive's left queries against its right "
                                   "camera's database, and every drive's queries against its own camera's database "
                                   "with the --exclusion-s window; each in every --modes method. Prints one table per "
                                   "drive and a pooled line per method; writes OUT_DIR/drives.json and one "
                                   "evaluation JSON per drive, protocol and method.")
    p.add_argument("root", nargs="?", type=Path, default=None, help="KITTI raw root (default $VISLOC_DATA or ../shared/data/kitti)")
    _add_db(p)
    p.add_argument("--out-dir", type=Path, default=Path("out/drives"), help="where the JSON goes (default %(default)s)")
    p.add_argument("--modes", default="paper,refined", help="comma-separated methods (default %(default)s)")
    _add_options(p, "steps")
    _add_sampling(p)
    _add_options(p, "workers")
    p.add_argument("--smooth", action="store_true", help="also run the RTS smoother over each series")
    _add_method(p, PAPER_EVAL_RETRIEVAL)
    _add_mode(p, choose_mode=False)
    _add_sift(p)
    _add_bad_frames(p)

    p = _command(sub, "dashboard", help="browser dashboard: scrub through a drive, tune the method live",
                       description="Serve the viser dashboard for a store built by 'visloc ingest' or 'visloc "
                                   "evaluate'. Prints the URL actually served (viser moves to the next free port "
                                   "when --port is taken). A missing or bad store is reported in the page. With "
                                   "--run it shows saved runs instead, without their store.", module="serving")
    _add_db(p)
    p.add_argument("--run", action="append", type=Path, default=None, metavar="JSON",
                   help="open a run that evaluate, evaluate-drives or track wrote (its --json, or drives.json); "
                        "a second --run is drawn beside the first to compare")
    p.add_argument("--tune-from", type=Path, default=None, metavar="JSON",
                   help="tune a saved run live: the page on --db starts from that run's mode, query rate, "
                        "parameters, database and queries")
    p.add_argument("--host", default="127.0.0.1", help="interface to serve on (default %(default)s, this machine only)")
    _add_options(p, "port")
    p.add_argument("--allow", action="append", type=Path, default=None, metavar="DIR",
                   help="a folder whose stores the page may open (repeatable; default: the store's folder)")
    _add_database_choice(p, "database camera to show first (default: the store's only camera, else image_01)",
                         "database drive/dataset to show first, e.g. a CSV drive's folder name (default: the first)")
    p.add_argument("--query-camera", default=None,
                   help="query camera to show first (default: the store's only camera, else image_00)")
    p.add_argument("--query-source", default=None,
                   help="query drive/dataset to show first (default: the database's drive, or another drive "
                        "when the store holds several and the cameras do not tell)")
    p.add_argument("--tiles", default=None, metavar="URL",
                   help="draw a web map under the top-down map: an XYZ tile URL with {z}, {x} and {y}, or 'osm' for "
                        "OpenStreetMap's (mind its tile usage policy: a person viewing, no bulk downloads); "
                        "tiles are kept on disk (default: no tiles)")
    p.add_argument("--tiles-attribution", default=None, metavar="TEXT",
                   help="the tiles' attribution, drawn on the map (default: OpenStreetMap's for 'osm', else the "
                        "server's name)")
    p.add_argument("--query-images", type=Path, default=None, metavar="PATH",
                   help="where the camera-rate mode reads the query series' images to follow points as 'visloc "
                        "track' does: a KITTI raw root that holds the drive, or the CSV or log it was stored from "
                        "(default: the data root, $VISLOC_DATA or ../shared/data/kitti); where they cannot be read, "
                        "every frame is localized in full on its stored features and the page says why")

    p = _command(sub, "bench", help="time the paper's brute-force path against the fast path",
                       description="Run the paper's path and the fast path (filter gate, VLAD shortlist, faiss, "
                                   "SIFT at a smaller image scale) on the same queries of a KITTI drive: accuracy, "
                                   "latency per stage, ingest throughput against bare SIFT, and a synthetic "
                                   "database's lost-query time and peak memory. Builds the stores it lacks.")
    p.add_argument("root", nargs="?", type=Path, default=None,
                   help="KITTI raw root (default $VISLOC_DATA or ../shared/data/kitti)")
    p.add_argument("--drive", default="2011_09_26_drive_0001", help="KITTI drive (default %(default)s)")
    p.add_argument("--db", type=Path, default=Path(DEFAULT_DB), help="store of the paper's path (default %(default)s)")
    p.add_argument("--fast-db", type=Path, default=Path(DEFAULT_FAST_DB),
                   help="store of the fast path, SIFT at --fast-scale (default %(default)s)")
    add_param_flags(p, BenchParams, BENCH)
    _add_options(p, "workers", preset=COMMAND_OPTIONS.replace(workers=BENCH_WORKERS))
    _add_json(p, "every number")

    p = _command(sub, "track", help="localize every frame of a drive in order, at the camera's rate",
                       description="Localize every frame of a drive in order, as a vehicle would: SIFT, retrieval, "
                                   "the refined measurement and the filter (its time step the frame interval). By "
                                   "default the camera-rate path: the database's stored structure and global "
                                   "vectors, the filter's gate, matching against 3D points only. Ingests the "
                                   "database camera into --db first when the store lacks it. Prints latency per "
                                   "frame, sustained rate and errors against the frames' geotags.")
    _add_source(p, "camera of the frames", "image_00")
    _add_db(p, tile_cache=True)
    _add_database_choice(p, "database camera (default: --camera; with --db-source, that source's only camera in the "
                            "store)", "database drive/dataset in the store (default: the frames' own drive, ingested "
                                      "first)")
    p.add_argument("--exact", action="store_true",
                   help="the exact refined path (the paper's retrieval, every candidate verified; seconds per frame)")
    _add_options(p, "frames")
    add_param_flags(p.add_argument_group("the run"), TrackParams, TRACK, automatic={"exclusion_s": EXCLUSION_AUTO_HELP})
    _add_options(p, "workers")
    _add_outputs(p, "the summary and every frame")
    add_param_flags(p.add_argument_group("filter (its time step: the frame interval)"), FilterParams, PAPER_FILTER,
                    exclude=("dt_s",))
    _add_mode(p, choose_mode=False)
    _add_sift(p)
    _add_bad_frames(p)

    p = _command(sub, "upgrade", help="migrate a store of an older schema version in place",
                       description="Bring a store written by an older visloc to this version's schema, keeping every "
                                   "image and cached count. Reading commands (info, dashboard) never migrate; ingest "
                                   "and the other commands that write do it on their own.", module="store_commands")
    _add_db(p)

    p = _command(sub, "info", help="what a store holds, or what visloc reads from a drive",
                 description="Images, drives, cameras and SIFT settings of a store. Given a drive (a log, a KITTI "
                             "root or a CSV), what visloc reads from it instead: its frames, geotags, calibration "
                             "and attitudes, and for a log its topics, the ones chosen and the largest gap between "
                             "the fixes a geotag was interpolated from.", module="store_commands")
    _add_source(p, "camera", "image_01")
    _add_db(p)

    p = _command(sub, "check", help="is a store whole? (exit 0 when it is, 2 when not)",
                 description="Check a store without changing it: SQLite's own integrity check, every table and column "
                             "this version needs, and every stored array (features, structure, global vectors) "
                             "against the checksum written with it and the size its row states. Prints one line per "
                             "damaged image (drive, camera, frame, what is wrong) and a summary. Re-running 'visloc "
                             "ingest' of a drive repairs its damaged images.", module="store_commands")
    _add_db(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    # Ctrl-C and `kill -INT` stop a command cleanly (what it committed is kept) even when it was
    # started in the background, where Python would otherwise inherit SIGINT as ignored
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, stop_on_signal)  # `kill` stops it as cleanly as Ctrl-C
    parser = build_parser()
    args = parser.parse_args(argv)
    try:  # values refused on their own, before any command is loaded or creates a file
        check_flag_values(args)
        if getattr(args, "max_image_mp", None) is not None:
            require_max_image_mp(args.max_image_mp)
    except VislocError as exc:
        print(f"visloc: error: {exc}", file=sys.stderr)
        return 2
    return _run(args)


def _run(args: argparse.Namespace) -> int:
    import sqlite3

    from visloc.db import StoreError
    from visloc.db.connection import sqlite_error_line

    try:
        status = args.func(args)
        sys.stdout.flush()  # here, so that a reader gone away (| head) is met below, not at exit
        return status
    except BrokenPipeError:
        # the reader of the output went away (| head): stop quietly, as the shell's own tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except (VislocError, StoreError) as exc:
        print(f"visloc: error: {exc}", file=sys.stderr)
        return 2
    except sqlite3.Error as exc:  # locked, read-only or damaged store file
        print(f"visloc: error: {sqlite_error_line(str(getattr(args, 'db', 'database')), exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"visloc: {interrupted_text(exc)}", file=sys.stderr)
        return interrupted_status(exc)


if __name__ == "__main__":
    sys.exit(main())
