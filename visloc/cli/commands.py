"""What each ``visloc`` command does, given its parsed arguments (``visloc.cli.parser`` parses them).

Errors in input or parameters raise ``VislocError`` naming the file or parameter; the command
line prints them on one line and exits with status 2. Nothing already stored is lost.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from visloc.bench.run import run_bench
from visloc.cli.choices import (PAPER_DATABASE_CAMERA, log_options, require_exports, write_exports, choose_database, exclusion_for, kitti_camera, kitti_only_camera,
                            make_folder_of, refuse_camera_for_csv, require_output, start_indices, store_for_writing)
from visloc.errors import InputError, ParameterError
from visloc.protocols.evaluation import evaluate, series_schedule
from visloc.params.methods import METHODS, REFINED_FAST_METHOD, REFINED_METHOD, Method, features_for, method_named
from visloc.tracking.methods import build_localizer
from visloc.cli.outputs import require_output_folder, require_writable_output
from visloc.cli.param_flags import params_from_flags
from visloc.params import (BENCH, FAST, PAPER_FILTER, PAPER_MATCH, PAPER_RETRIEVAL, PAPER_SIFT, REFINED, STORE_SIFT,
                           TRACK, FilterParams, MatchParams, RetrievalParams, SiftParams)
from visloc.sources.queries import extract_queries
from visloc.progress import progress_reporter
from visloc.protocols.records import QueryTruth, records_of
from visloc.results.report import (evaluation_json, is_paper_protocol, record_json, save_error_plot, series_tables,
                           summary_text, track_text, write_json)
from visloc.tracking.runs import run_queries
from visloc.sources.drives import Drive, default_data_root
from visloc.sources.opening import open_source
from visloc.protocols.suite import database_row, drive_protocols, drives_of, pooled_rows, protocol_row, table_text
from visloc.protocols.track import run_track, track_filter, track_localizer
from visloc.store.workspace import Workspace
from visloc.store.build import ingest_sequence
from visloc.cli.sharding import ingest_sharded, print_tiles_read, require_stored
from visloc.cli.stopping import interrupted_status, interrupted_text
from visloc.db.shards import is_sharded


# -- arguments -> parameters ------------------------------------------------------------------

def sift_params(a: argparse.Namespace, store: SiftParams | None = None, method: Method | None = None) -> SiftParams:
    """The SIFT settings from the flags. Without ``--sift-contrast``, the contrast threshold is the store's
    (``store``; ``STORE_SIFT``'s for a new store), as ``method`` reads it (``features_for``)."""
    sift = params_from_flags(a, PAPER_SIFT)
    if getattr(a, "sift_contrast", None) is not None:
        return sift
    sift = sift.replace(contrast_threshold=(store or STORE_SIFT).contrast_threshold)
    return sift if method is None else features_for(method, sift)


def method_params(a: argparse.Namespace) -> tuple[MatchParams, RetrievalParams, FilterParams]:
    """The method's parameters from the flags; an automatic ``--exclusion-s`` (None) is 0 here, until
    ``exclusion_for`` has seen the database."""
    return (params_from_flags(a, PAPER_MATCH), params_from_flags(a, PAPER_RETRIEVAL),
            params_from_flags(a, PAPER_FILTER))


def with_method_flags(a: argparse.Namespace, method: Method, init_var: float) -> Method:
    """``method`` with the refined and fast-retrieval flags the user gave. Flags of a part the method
    lacks are still checked, so a bad value is refused in any mode. A geotag accuracy of 0 needs P0 > 0
    (see ``FilterParams``)."""
    pose = params_from_flags(a, method.pose or REFINED)
    shortlist = params_from_flags(a, method.shortlist or FAST)
    if pose.geotag_sigma_m == 0 and init_var == 0:
        raise ParameterError("--geotag-sigma-m 0 with --init-var 0: a geotag fallback's measurement variance R = 0 "
                             "on P0 = 0 makes the innovation covariance S = P + R singular; give either a value > 0")
    return method.replace(pose=pose if method.pose is not None else None,
                          shortlist=shortlist if method.shortlist is not None else None)


def method_of(a: argparse.Namespace, mode: str | None = None) -> Method:
    """The method ``--mode`` (or ``mode``) names, with the refined flags applied (and the fast retrieval
    if ``--fast``)."""
    name = a.mode if mode is None else mode
    try:
        method = method_named(name)
    except ParameterError:
        raise InputError(f"--mode {name!r}: must be one of {', '.join(METHODS)}") from None
    if getattr(a, "fast", False) and not method.camera_rate:
        method = method.replace(shortlist=FAST)
    return with_method_flags(a, method, a.init_var)


def stored_for(ws: Workspace, db, method: Method) -> dict:
    """What a refined method reads from the store: its structure (the camera-rate path's global vectors too;
    nothing for the paper's)."""
    if method.pose is None:
        return {}
    if not method.camera_rate:
        return {"stored": ws.load_structure(db, method.pose)}
    return {"stored": ws.load_structure(db, method.pose),
            "shortlist_index": ws.global_vectors.load_database_index(db, method.shortlist)}


def _ingest(ws: Workspace, seq: Drive, sift: SiftParams, a: argparse.Namespace, limit: int | None = None,
            structure: bool = True, repair: bool = False, cluster=None):
    if ws.sharded:  # read by this command, never written: it holds the drive, or says how to add it
        return require_stored(ws, seq)
    report = ingest_sequence(ws, seq, sift, workers=a.workers, limit=limit, structure=structure, cluster=cluster,
                             progress=progress_reporter(f"ingest {seq.name}", "images"),
                             vectors_progress=progress_reporter(f"global vectors {seq.name}", "images"),
                             structure_progress=progress_reporter(f"structure {seq.name}", "images"),
                             self_check_progress=progress_reporter(f"self-check {seq.name}", "images"),
                             camera_rate_check_progress=progress_reporter(f"camera-rate self-check {seq.name}",
                                                                          "images"),
                             skip_bad_frames=a.skip_bad_frames, max_image_mp=a.max_image_mp, repair=repair)
    if not repair and report.n_source_changed:  # ingest itself prints its whole report
        n = report.n_source_changed
        print(f"visloc: {a.db}: {seq.name}: {n} image{'s' if n != 1 else ''} described again (their image file "
              "changed since they were stored)", file=sys.stderr)
    return report


_NOTES_SHOWN: set[str] = set()


def _open_source(*args, **kwargs) -> Drive:
    """``open_source``, telling the user once what reading it changed (e.g. intrinsics scaled to the images)."""
    seq = open_source(*args, **kwargs)
    for note in seq.notes:
        if note not in _NOTES_SHOWN:
            _NOTES_SHOWN.add(note)
            print(f"visloc: {note}", file=sys.stderr)
    return seq


# -- commands -----------------------------------------------------------------------------------

def cmd_ingest(a: argparse.Namespace) -> int:
    sift_params(a)  # bad SIFT flags are refused before any source is opened
    refuse_camera_for_csv(a.source, "--camera", a.camera)
    cameras = a.camera or [kitti_camera(a.source, a.drive, None)]
    sequences = [_open_source(a.source, drive=a.drive, camera=camera, **log_options(a)) for camera in cameras]
    if a.tile_m is not None or is_sharded(a.db):
        return ingest_sharded(a, sequences, lambda ws, seq, cluster: _print_ingest(
            a, seq, _ingest(ws, seq, sift_params(a, ws.sift_params), a, a.limit, structure=not a.features_only,
                            repair=True, cluster=cluster)))
    if a.halo_m is not None or a.address is not None:
        raise InputError(f"{'--halo-m' if a.halo_m is not None else '--address'}: only for a sharded store "
                         "(give --tile-m)")
    seq, ws = sequences[0], None
    try:
        # only once every source opened: a bad source creates no store file; a store this command
        # created is removed again if it fails before storing any image
        with store_for_writing(a.db):
            ws = Workspace(a.db, create=True)
            sift = sift_params(a, ws.sift_params)  # the store's contrast unless the flag says otherwise
            for seq in sequences:
                _print_ingest(a, seq, _ingest(ws, seq, sift, a, a.limit, structure=not a.features_only, repair=True))
    except KeyboardInterrupt as exc:
        n = ws.stored_frame_count(seq.source, seq.camera) if ws is not None and Path(a.db).exists() else 0
        print(f"visloc: {interrupted_text(exc)}; {a.db} keeps {n} images of {seq.name} (run the same command again "
              "to go on)", file=sys.stderr)
        return interrupted_status(exc)
    return 0


def _print_ingest(a: argparse.Namespace, seq: Drive, report) -> None:
    filled = f", attitude filled in for {report.n_attitudes_filled}" if report.n_attitudes_filled else ""
    bad = report.n_bad_skipped
    bad = f", {bad} bad frame{'s' if bad > 1 else ''} skipped (visloc info lists them)" if bad else ""
    redone = report.n_repaired + report.n_source_changed
    again = "".join(text for n, text in (
        (report.n_repaired, f", {report.n_repaired} repaired (their features failed their checksum)"),
        (report.n_source_changed, f", {report.n_source_changed} described again (their image file changed)"),
        (report.n_derived_repaired, f", {report.n_derived_repaired} damaged rows of structure or global vectors "
                                    "rebuilt"),
        (report.n_sources_recorded, f", {report.n_sources_recorded} checked against their image files"),
        (report.n_geotags_moved, f", {report.n_geotags_moved} geotags taken again from the source (structure "
                                 "rebuilt)")) if n)
    print(f"{a.db}: {seq.name}: {report.n_added} added, {report.n_skipped - redone} already stored{again}, "
          f"{len(seq)} frames{bad} ({report.images_per_s:.1f} images/s){filled}")


def cmd_localize(a: argparse.Namespace) -> int:
    match, retrieval, filt = method_params(a)
    method = method_of(a)
    require_writable_output(a.json, "--json")
    require_exports(a)
    seq = _open_source(a.source, drive=a.drive, camera=kitti_only_camera(a.source, "--camera", a.camera, "image_00"),
                       **log_options(a))
    ws = Workspace(a.db, tile_cache_mb=a.tile_cache_mb)  # reading: a missing store is an error, never created
    sift = sift_params(a, ws.sift_params, method)
    db = ws.load_database(*choose_database(ws, seq.source, db_source=a.db_source, db_camera=a.db_camera,
                                           prefer=PAPER_DATABASE_CAMERA.get(seq.camera, ())), sift)
    times = seq.timestamps_s
    start = next((i for i, f in enumerate(seq.frames) if f.frame == a.start_frame), None)
    if start is None:
        frames = sorted(f.frame for f in seq.frames)
        raise InputError(f"--start-frame {a.start_frame}: {seq.name} has frames {frames[0]}..{frames[-1]}")
    schedule = [s for s in series_schedule(times[start:], filt.dt_s, a.steps, a.sampling) if s[0] == 0]
    if not schedule:
        raise InputError(f"--start-frame {a.start_frame}: {a.steps} queries {filt.dt_s} s apart do not fit in the "
                         f"{times[-1] - times[start]:.1f} s left of {seq.name}")
    indices = [start + i for i in schedule[0]]
    retrieval = retrieval.replace(exclusion_s=exclusion_for(a.exclusion_s, db, seq.timestamps_s, seq.lat_deg,
                                                            seq.lon_deg, seq.name))
    localizer = build_localizer(method, db, match, retrieval, filt, query_camera=seq.camera_model, query_what=seq.name,
                                **stored_for(ws, db, method))
    progress = progress_reporter(f"localize {seq.name}", "queries")
    progress(0, len(indices))
    steps = run_queries(localizer, extract_queries(seq, indices, sift),
                        progress=lambda done: progress(done, len(indices)))
    records = records_of([s.result for s in steps], [s.latency_ms for s in steps], indices,
                         QueryTruth.of_drive(seq, db, method.geotag_sigma_m), db, keep_counts=True)
    print(f"queries: {seq.name} frames {[seq.frames[i].frame for i in indices]}   "
          f"database: {db.source}/{db.camera} ({len(db)} images)   exclusion {retrieval.exclusion_s} s   "
          f"mode {method.name}")
    print()
    print(series_tables(records, db.frame))
    print_tiles_read(ws)
    if a.json:
        write_json(a.json, {"queries": seq.name, "database": f"{db.source}/{db.camera}", "mode": method.name,
                            "steps": [record_json(r, db.frame) for r in records],
                            "params": {"match": match.as_dict(), "retrieval": retrieval.as_dict(),
                                       "filter": filt.as_dict(), "sift": sift.as_dict(), "mode": method.name,
                                       "refined": None if method.pose is None else method.pose.as_dict()}})
        print(f"\nwrote {a.json}")
    write_exports(a, [records], db.frame, f"{seq.name} against {db.source}/{db.camera}, mode {method.name}",
                  queries=seq, db=db)
    return 0


def _evaluate_sources(a: argparse.Namespace, ws: Workspace, db_seq: Drive | None, query_seq: Drive,
                      methods: list[Method], *, wanted: set[int] | None = None, label: str = "",
                      db_key: tuple[str, str] | None = None):
    """Ingest both sources (skipping what is stored), evaluate each method on them, keep the counts.

    Returns ([evaluation per method], [the SIFT settings of the features each read], database, queries). Counts are saved after every series: a stop
    loses one at most. ``wanted``: only series starting at these query frames. ``db_key``: (source,
    camera) of a database the store already holds, in place of ``db_seq``.
    """
    match, retrieval, filt = method_params(a)
    for seq in {s.name: s for s in (db_seq, query_seq) if s is not None}.values():
        # queries need only their SIFT: the structure and self-check are the database's
        _ingest(ws, seq, sift_params(a, ws.sift_params), a, structure=db_seq is not None and seq.name == db_seq.name)
    loaded: dict[SiftParams, tuple] = {}  # the features each method reads (the paper's may be a selection)
    results, sifts = [], []
    for method in methods:
        sift = sift_params(a, ws.sift_params, method)
        if sift not in loaded:
            db = ws.load_database(*(db_key or (db_seq.source, db_seq.camera)), sift)
            queries = ws.load_queries(query_seq.source, query_seq.camera, sift)
            exclusion_for(a.exclusion_s, db, queries.timestamps_s, queries.lat_deg, queries.lon_deg,
                          queries.name)  # warns
            # counts earlier runs computed with the same tau1, tau2
            loaded[sift] = db, queries, ws.pair_cache(db, queries, match)
        db, queries, cache = loaded[sift]
        starts = None if wanted is None else [i for i, f in enumerate(queries.frames) if f in wanted]
        bar = progress_reporter(f"evaluate {label}{method.name}", "series")

        def progress(done: int, total: int, bar=bar, cache=cache) -> None:
            bar(done, total)
            ws.save_pair_counts(cache)

        try:
            results.append(evaluate(queries, db, match, retrieval, filt, method=method, n_steps=a.steps,
                                    sampling=a.sampling, start_indices=starts, cache=cache, progress=progress,
                                    smooth=a.smooth, **stored_for(ws, db, method)))
        finally:
            ws.save_pair_counts(cache)
        sifts.append(sift)
    return results, sifts, db, queries


def _summary(result, sift: SiftParams) -> dict:
    summary = result.summary()
    summary["params"]["sift"] = sift.as_dict()
    return summary


def cmd_evaluate(a: argparse.Namespace) -> int:
    match, retrieval, filt = method_params(a)
    method = method_of(a)
    plot = a.plot or (Path(a.json).with_suffix(".png") if a.json else None)
    require_output(a.json, "--json", a.db)  # a file in the store's folder: made with it
    require_output(plot, "--plot" if a.plot else "--json (its plot, .png)", a.db)
    require_exports(a, a.db)
    query_camera = kitti_only_camera(a.root, "--query-camera", a.query_camera, "image_00")
    db_seq = None  # with --db-source, the database is one the store holds
    if a.db_source is None:
        refuse_camera_for_csv(a.root, "--db-camera", a.db_camera)
        # the paper's protocol (right database for left queries) where the drive has both, else the query camera
        db_camera = kitti_camera(a.root, a.drive, a.db_camera, (*PAPER_DATABASE_CAMERA.get(query_camera, ()),
                                                               query_camera)) or query_camera
        db_seq = _open_source(a.root, drive=a.drive, camera=db_camera, camera_flag="--db-camera", **log_options(a))
    query_seq = _open_source(a.root, drive=a.drive, camera=query_camera, camera_flag="--query-camera",
                             **log_options(a))
    # check the series before any slow work
    schedule = series_schedule(query_seq.timestamps_s, filt.dt_s, a.steps, a.sampling)
    if not schedule:
        raise InputError(f"{query_seq.name}: too short for {a.steps} queries {filt.dt_s} s apart")
    wanted = start_indices(a, query_seq, schedule)
    with store_for_writing(a.db):
        ws = Workspace(a.db, create=True, tile_cache_mb=a.tile_cache_mb)
        db_key = None if db_seq else choose_database(ws, query_seq.source, db_source=a.db_source,
                                                     db_camera=a.db_camera)
        [result], [sift], db, queries = _evaluate_sources(a, ws, db_seq, query_seq, [method], wanted=wanted,
                                                          db_key=db_key)
    summary = _summary(result, sift)
    print(summary_text(summary))
    print_tiles_read(ws)
    if a.json:
        write_json(a.json, evaluation_json(result, summary))
        print(f"wrote {a.json}")
    if plot:
        title = (f"{db.source}: queries {queries.camera}, database {db.camera}, exclusion "
                 f"{retrieval.exclusion_s:g} s, {summary['n_series']} series, mode {method.name}")
        save_error_plot(summary, plot, title, paper=is_paper_protocol(summary))
        print(f"wrote {plot}")
    write_exports(a, result.series, result.frame, f"{queries.source}/{queries.camera} against "
                                                   f"{db.source}/{db.camera}, mode {method.name}", queries=query_seq,
                  db=db)
    return 0


def cmd_evaluate_drives(a: argparse.Namespace) -> int:
    match, retrieval, filt = method_params(a)
    modes = [m.strip() for m in a.modes.split(",") if m.strip()]
    methods = [method_of(a, m) for m in modes]
    if not methods:
        raise InputError(f"--modes {a.modes!r}: name at least one of paper, refined")
    out_dir = Path(a.out_dir)
    require_output_folder(out_dir, "--out-dir", files=("drives.json",))
    root = a.root if a.root is not None else default_data_root()
    folders = drives_of(root)
    if not folders:
        raise InputError(f"{root}: no KITTI drives (folders named *_drive_*_sync under a date folder)")
    out_dir.mkdir(exist_ok=True)
    make_folder_of(a.db, "--db")
    ws = Workspace(a.db, create=True)
    sift = sift_params(a, ws.sift_params)  # the store's features; each evaluation's JSON says what it read
    everything, report = [], {"root": str(root), "drives": {}, "params": {
        "match": match.as_dict(), "retrieval": retrieval.as_dict(), "filter": filt.as_dict(), "sift": sift.as_dict(),
        "methods": [m.as_dict() for m in methods], "steps": a.steps, "sampling": a.sampling}}
    for folder in folders:
        drive = folder.name.removesuffix("_sync")
        rows = []
        for protocol in drive_protocols(folder):
            db_seq = _open_source(root, drive=drive, camera=protocol.db_camera)
            query_seq = _open_source(root, drive=drive, camera=protocol.query_camera)
            results, sifts, db, _ = _evaluate_sources(a, ws, db_seq, query_seq, methods,
                                                      label=f"{drive} {protocol.key} ")
            for method, result, sift in zip(methods, results, sifts):
                summary = _summary(result, sift)
                name = f"{drive}_{protocol.key}_{method.name}"
                write_json(out_dir / f"{name}.json", evaluation_json(result, summary))
                row = {**protocol_row(result), "protocol": protocol.key, "protocol_label": protocol.label,
                       "file": f"{name}.json", "database": database_row(db)}
                report["drives"].setdefault(drive, []).append(row)
                rows.append((f"{protocol.key} ({protocol.label[:11]}), {method.name}", row))
                everything.append(result)
        print(table_text(drive, rows) + "\n", flush=True)
    report["pooled"] = pooled_rows(everything)
    print(table_text(f"pooled over {len(folders)} drive(s), every protocol",
                     [(f"all, {r['mode']}", r) for r in report["pooled"]]))
    write_json(out_dir / "drives.json", report)
    print(f"wrote {out_dir / 'drives.json'} and one JSON per drive, protocol and method beside it")
    return 0


def cmd_bench(a: argparse.Namespace) -> int:
    params = params_from_flags(a, BENCH)
    require_output(a.json, "--json", a.db)
    for flag, path in (("--db", a.db), ("--fast-db", a.fast_db)):
        require_output(path, flag, path)  # its missing folder (as out/) is made
    _open_source(a.root, drive=a.drive, camera="image_00")  # a missing drive fails here, before any slow work
    for flag, path in (("--db", a.db), ("--fast-db", a.fast_db)):
        make_folder_of(path, flag)
    result = run_bench(a.root, a.drive, Path(a.db), Path(a.fast_db), params, a.workers,
                       say=lambda t: print(t, flush=True))
    if a.json:
        write_json(a.json, result)
        print(f"wrote {a.json}")
    return 0


def cmd_track(a: argparse.Namespace) -> int:
    params = params_from_flags(a, TRACK.replace(fast=not a.exact), exclude=("exclusion_s",))
    base = params_from_flags(a, PAPER_FILTER, exclude=("dt_s",))
    method = with_method_flags(a, REFINED_METHOD if a.exact else REFINED_FAST_METHOD, base.init_var)
    require_output(a.json, "--json", a.db)
    require_exports(a, a.db)
    seq = _open_source(a.source, drive=a.drive, camera=kitti_only_camera(a.source, "--camera", a.camera, "image_00"),
                       **log_options(a))
    filt = track_filter(seq, params, base)
    indices = list(range(0, len(seq), params.stride))
    if a.frames is not None:
        indices = indices[: a.frames]
    with store_for_writing(a.db):
        ws = Workspace(a.db, create=True, tile_cache_mb=a.tile_cache_mb)
        sift = sift_params(a, ws.sift_params, method)
        if a.db_source is None:  # the database is the frames' own drive: store it first if the store lacks it
            db_camera = kitti_only_camera(a.source, "--db-camera", a.db_camera, seq.camera) or seq.camera
            _ingest(ws, _open_source(a.source, drive=a.drive, camera=db_camera, camera_flag="--db-camera",
                                     **log_options(a)), sift, a)
            source = seq.source
        else:
            source, db_camera = choose_database(ws, seq.source, db_source=a.db_source, db_camera=a.db_camera,
                                                prefer=(seq.camera,))
    db = ws.load_database(source, db_camera, sift)
    params = params.replace(exclusion_s=exclusion_for(a.exclusion_s, db, seq.timestamps_s, seq.lat_deg, seq.lon_deg,
                                                      seq.name))
    localizer, query_sift = track_localizer(ws, db, seq.camera_model, filt, params, method, query_what=seq.name)
    progress = progress_reporter(f"track {seq.name}", "frames")
    progress(0, len(indices))
    run = run_track(localizer, seq, query_sift, db, params, indices=indices, progress=progress,
                    path_params={"method": method.as_dict()}, pose=method.pose)
    print(track_text(run.summary()))
    print_tiles_read(ws)
    if a.json:
        write_json(a.json, run.as_json())
        print(f"wrote {a.json}")
    write_exports(a, run.frames, db.frame, f"{seq.name} against {db.source}/{db.camera}, track", queries=seq, db=db)
    return 0
