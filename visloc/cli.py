"""The ``visloc`` command line: ingest, localize, evaluate, info.

Errors in input or parameters end the command with one line on stderr naming
the file or parameter, and exit status 2; nothing already stored is lost.
"""

from __future__ import annotations

import argparse
import os
import sqlite3
import sys
import time
from pathlib import Path


from db import FeatureStore, StoreError
from visloc.errors import InputError, VislocError
from visloc.params import (
    PAPER_EVAL_RETRIEVAL,
    PAPER_FILTER,
    PAPER_MATCH,
    PAPER_RETRIEVAL,
    PAPER_SIFT,
    REFINED,
    FilterParams,
    MatchParams,
    RefinedParams,
    RetrievalParams,
    SiftParams,
    check_mode,
)

DEFAULT_DB = "visloc.sqlite"


def default_data_root() -> Path:
    """$VISLOC_DATA, else ../shared/data/kitti beside the checkout, else relative to the working folder."""
    env = os.environ.get("VISLOC_DATA")
    if env:
        return Path(env)
    beside_checkout = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "kitti"
    return beside_checkout if beside_checkout.is_dir() else Path("../shared/data/kitti")


# -- argument groups --------------------------------------------------------------

def _add_sift(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("SIFT (must equal the store's settings)")
    d = PAPER_SIFT
    g.add_argument("--sift-features", type=int, default=d.n_features, help="keypoints kept per image, 0 = all (default %(default)s)")
    g.add_argument("--sift-octave-layers", type=int, default=d.n_octave_layers, help="default %(default)s")
    g.add_argument("--sift-contrast", type=float, default=d.contrast_threshold, help="contrast threshold (default %(default)s)")
    g.add_argument("--sift-edge", type=float, default=d.edge_threshold, help="edge threshold (default %(default)s)")
    g.add_argument("--sift-sigma", type=float, default=d.sigma, help="default %(default)s")
    g.add_argument("--sift-scale", type=float, default=d.image_scale,
                   help="run SIFT on the image resized by this factor in [0.1, 1]; keypoints stay in full-resolution "
                        "pixels (default %(default)s)")


def _sift(a: argparse.Namespace) -> SiftParams:
    return SiftParams(n_features=a.sift_features, n_octave_layers=a.sift_octave_layers,
                      contrast_threshold=a.sift_contrast, edge_threshold=a.sift_edge, sigma=a.sift_sigma,
                      image_scale=a.sift_scale)


def _add_method(p: argparse.ArgumentParser, retrieval: RetrievalParams) -> None:
    g = p.add_argument_group("matching, retrieval and filter (defaults: the paper's Table 1)")
    g.add_argument("--tau1", type=float, default=PAPER_MATCH.tau1, help="Lowe ratio threshold, eq. (1), in (0, 1] (default %(default)s)")
    g.add_argument("--tau2", type=float, default=PAPER_MATCH.tau2, help="cosine similarity threshold, eq. (2), in [-1, 1] (default %(default)s)")
    g.add_argument("--window-s", type=float, default=retrieval.window_s, help="search +-this around the previous best match, s (default %(default)s)")
    g.add_argument("--exclusion-s", type=float, default=retrieval.exclusion_s,
                   help="ignore database images closer in time to the query than this, s (default %(default)s)")
    f = PAPER_FILTER
    g.add_argument("--dt-s", type=float, default=f.dt_s, help="time between queries, s (default %(default)s)")
    g.add_argument("--meas-var-m2", type=float, default=f.meas_var_m2, help="R: measurement variance, m^2 (default %(default).1f = (0.0001 deg)^2)")
    g.add_argument("--accel-var-m2-s4", type=float, default=f.accel_var_m2_s4, help="Q: white acceleration variance, m^2/s^4 (default %(default)s)")
    g.add_argument("--init-var", type=float, default=f.init_var, help="P0 = this * I, m^2 and m^2/s^2 (default %(default)s)")


def _method(a: argparse.Namespace) -> tuple[MatchParams, RetrievalParams, FilterParams]:
    return (MatchParams(tau1=a.tau1, tau2=a.tau2),
            RetrievalParams(window_s=a.window_s, exclusion_s=a.exclusion_s),
            FilterParams(dt_s=a.dt_s, meas_var_m2=a.meas_var_m2, accel_var_m2_s4=a.accel_var_m2_s4, init_var=a.init_var))


def _add_mode(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("mode (paper: the paper's method; refined: metric pose from the database, see README)")
    # a plain string checked by check_mode, so a bad value is a one-line error naming --mode
    g.add_argument("--mode", default="paper", help="paper or refined (default %(default)s)")
    r = REFINED
    g.add_argument("--top-k", type=int, default=r.top_k,
                   help="refined: candidates re-ranked by essential-matrix inliers (default %(default)s)")
    g.add_argument("--sigma-floor-m", type=float, default=r.sigma_floor_m,
                   help="refined: added in quadrature to each pose's covariance, m (default %(default)s)")
    g.add_argument("--gate-chi2", type=float, default=r.gate_chi2,
                   help="refined: Mahalanobis gate on y' S^-1 y, 2 dof; 0 = off (default %(default)s = 99.9%%)")
    g.add_argument("--seed", type=int, default=r.seed, help="refined: RANSAC seed (default %(default)s)")


def _mode(a: argparse.Namespace) -> tuple[str, RefinedParams]:
    try:
        mode = check_mode(a.mode)
    except VislocError:
        raise InputError(f"--mode {a.mode!r}: must be paper or refined") from None
    return mode, REFINED.replace(top_k=a.top_k, sigma_floor_m=a.sigma_floor_m, gate_chi2=a.gate_chi2, seed=a.seed)


def _add_source(p: argparse.ArgumentParser, camera_help: str, camera_default: str, *, multiple: bool = False) -> None:
    p.add_argument("source", nargs="?", type=Path, default=None,
                   help="KITTI raw root (default $VISLOC_DATA or ../shared/data/kitti) or a CSV of geotagged images")
    p.add_argument("--drive", default=None, help="KITTI drive, e.g. 2011_09_26_drive_0001 (needed if the root holds several)")
    if multiple:
        p.add_argument("--camera", action="append", default=None, help=camera_help + f" (repeatable; default {camera_default})")
    else:
        p.add_argument("--camera", default=camera_default, help=camera_help + " (default %(default)s)")


def _add_sampling(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sampling", choices=("stride", "time"), default="stride",
                   help="stride: every round(dt/frame interval)-th frame, as the paper (every 10th on KITTI); "
                        "time: the frame nearest to each multiple of dt (default %(default)s)")


def _add_db(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", type=Path, default=Path(DEFAULT_DB), help="store file (default %(default)s)")


def _open_sequence(source: Path | None, drive: str | None, camera: str):
    from visloc.sources import open_source

    return open_source(source or default_data_root(), drive=drive, camera=camera)


def _progress(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="img", disable=None, file=sys.stderr, leave=False)


def _ingest_sequence(store: FeatureStore, seq, sift: SiftParams, workers: int | None, limit: int | None = None):
    from visloc.ingest import ingest

    todo = len(seq) - len(store.stored_frames(seq.source, seq.camera))
    with _progress(todo if limit is None else min(todo, limit), f"SIFT {seq.source}/{seq.camera}") as bar:
        return ingest(store, seq, sift, workers=workers, progress=bar.update, limit=limit)


# -- commands ------------------------------------------------------------------------

def cmd_ingest(a: argparse.Namespace) -> int:
    sift = _sift(a)
    with FeatureStore(a.db, create=True) as store:
        for camera in a.camera or ["image_01"]:
            seq = _open_sequence(a.source, a.drive, camera)
            try:
                report = _ingest_sequence(store, seq, sift, a.workers, a.limit)
            except KeyboardInterrupt:
                n = store.image_count(seq.source, seq.camera)
                print(f"visloc: interrupted; {a.db} keeps {n} images of {seq.source}/{seq.camera}", file=sys.stderr)
                return 130
            filled = f", attitude filled in for {report.n_attitudes_filled}" if report.n_attitudes_filled else ""
            print(f"{a.db}: {seq.source}/{seq.camera}: {report.n_added} added, {report.n_skipped} already stored, "
                  f"{len(seq)} frames ({report.images_per_s:.1f} images/s){filled}")
    return 0


def _choose_database(store: FeatureStore, query_source: str, db_source: str | None, db_camera: str) -> str:
    sources = store.sources()
    if db_source:
        return db_source
    if any(s["source"] == query_source and s["camera"] == db_camera for s in sources):
        return query_source
    with_camera = sorted({s["source"] for s in sources if s["camera"] == db_camera})
    if len(with_camera) == 1:
        return with_camera[0]
    have = ", ".join(f"{s['source']}/{s['camera']}" for s in sources) or "nothing"
    raise InputError(f"{store.label}: choose the database with --db-source (it holds {have})")


def cmd_localize(a: argparse.Namespace) -> int:
    from visloc.database import load_database
    from visloc.evaluation import series_schedule, step_record
    from visloc.features import extract_sift, make_sift
    from visloc.localizer import Localizer, Query
    from visloc.report import series_tables, write_json
    from visloc.sources import load_gray

    from visloc.geometry import CameraModel

    sift = _sift(a)
    match, retrieval, filt = _method(a)
    mode, refined = _mode(a)
    seq = _open_sequence(a.source, a.drive, a.camera)
    with FeatureStore(a.db) as store:
        db = load_database(store, _choose_database(store, seq.source, a.db_source, a.db_camera), a.db_camera, sift)
    times = seq.timestamps_s
    start = next((i for i, f in enumerate(seq.frames) if f.frame == a.start_frame), None)
    if start is None:
        frames = sorted(f.frame for f in seq.frames)
        raise InputError(f"--start-frame {a.start_frame}: {seq.source}/{seq.camera} has frames {frames[0]}..{frames[-1]}")
    schedule = [s for s in series_schedule(times[start:], filt.dt_s, a.steps, a.sampling) if s[0] == 0]
    if not schedule:
        raise InputError(f"--start-frame {a.start_frame}: {a.steps} queries {filt.dt_s} s apart do not fit in the "
                         f"{times[-1] - times[start]:.1f} s left of {seq.source}/{seq.camera}")
    indices = [start + i for i in schedule[0]]
    query_camera = None
    if seq.P_rect is not None and seq.T_camera_imu is not None:
        query_camera = CameraModel.from_projection(seq.P_rect, seq.T_camera_imu)
    localizer = Localizer(db.timestamps_s, db.east_north_m, db.descriptors_u8, match, retrieval, filt, mode=mode,
                          refined_params=refined, geometry=db.geometry() if mode == "refined" else None,
                          query_camera=query_camera)
    sift_engine = make_sift(sift)
    records = []
    for k, i in enumerate(indices):
        fr = seq.frames[i]
        gray = load_gray(fr.image_path)
        t0 = time.perf_counter()
        feats = extract_sift(gray, sift, sift=sift_engine, name=str(fr.image_path))
        sift_ms = (time.perf_counter() - t0) * 1000.0
        result = localizer.step(Query(feats.descriptors_u8, fr.timestamp_s, keypoints_f32=feats.keypoints_f32))
        records.append(step_record(k, result, db, query_frame=fr.frame, truth_lat_deg=fr.lat_deg,
                                   truth_lon_deg=fr.lon_deg, latency_ms=sift_ms + result.compute_ms, keep_counts=True))
    print(f"queries: {seq.source}/{seq.camera} frames {[seq.frames[i].frame for i in indices]}   "
          f"database: {db.source}/{db.camera} ({len(db)} images)   exclusion {retrieval.exclusion_s} s   "
          f"mode {mode}\n")
    print(series_tables(records))
    if a.json:
        write_json(a.json, {"queries": f"{seq.source}/{seq.camera}", "database": f"{db.source}/{db.camera}",
                            "mode": mode, "steps": records,
                            "params": {"match": match.as_dict(), "retrieval": retrieval.as_dict(),
                                       "filter": filt.as_dict(), "sift": sift.as_dict(), "mode": mode,
                                       "refined": refined.as_dict() if mode == "refined" else None}})
        print(f"\nwrote {a.json}")
    return 0


def cmd_evaluate(a: argparse.Namespace) -> int:
    from visloc.database import load_database, load_query_set
    from visloc.evaluation import evaluate, series_schedule
    from visloc.localizer import PairCountCache
    from visloc.report import save_error_plot, summary_text, write_json

    sift = _sift(a)
    match, retrieval, filt = _method(a)
    mode, refined = _mode(a)
    root = a.root or default_data_root()
    for path in (a.json, a.plot):
        if path is not None and not Path(path).resolve().parent.is_dir():
            raise InputError(f"{path}: folder does not exist")
    db_seq = _open_sequence(root, a.drive, a.db_camera)
    query_seq = _open_sequence(root, a.drive, a.query_camera)
    # check the series before any slow work
    schedule = series_schedule(query_seq.timestamps_s, filt.dt_s, a.steps, a.sampling)
    if not schedule:
        raise InputError(f"{query_seq.source}/{query_seq.camera}: too short for {a.steps} queries {filt.dt_s} s apart")
    wanted = None
    if a.start_frames:
        try:
            wanted = {int(v) for v in a.start_frames.split(",")}
        except ValueError:
            raise InputError(f"--start-frames {a.start_frames!r}: expected comma-separated frame numbers") from None
        allowed = {query_seq.frames[s[0]].frame for s in schedule}
        if wanted - allowed:
            raise InputError(f"--start-frames {a.start_frames}: no series of {a.steps} queries starts at "
                             f"{sorted(wanted - allowed)[:5]} (allowed start frames: {min(allowed)}..{max(allowed)})")
    store = FeatureStore(a.db, create=True)
    try:
        for seq in {(s.source, s.camera): s for s in (db_seq, query_seq)}.values():
            _ingest_sequence(store, seq, sift, a.workers)
        db = load_database(store, db_seq.source, db_seq.camera, sift)
        queries = load_query_set(store, query_seq.source, query_seq.camera, sift)
        starts = None if wanted is None else [i for i, f in enumerate(queries.frames) if f in wanted]
        fast = None
        if a.fast:  # opt-in: filter gate + VLAD shortlist + batched exact counts (visloc.fast)
            from visloc.fast import FAST, FastDatabase

            fast = FastDatabase.build(db.descriptors_u8, FAST, keypoints=db.keypoints_f32)
        # correspondence counts computed by earlier runs with the same tau1, tau2
        cache = PairCountCache(db.descriptors_u8, match, db_keys=[im.image_id for im in db.images],
                               known=store.pair_counts(queries.image_ids, match.tau1, match.tau2))

        def save_counts() -> None:
            store.add_pair_counts(cache.take_new_entries(), match.tau1, match.tau2)

        try:  # counts are saved after every series, so an interrupted run loses at most one
            with _progress(len(starts) if starts is not None else len(schedule), "series") as bar:
                result = evaluate(queries, db, match, retrieval, filt, n_steps=a.steps, sampling=a.sampling,
                                  start_indices=starts, cache=cache,
                                  progress=lambda n: (bar.update(n), save_counts()), mode=mode,
                                  refined_params=refined, smooth=a.smooth, fast=fast)
        finally:
            save_counts()
    finally:
        store.close()
    summary = result.summary()
    summary["params"]["sift"] = sift.as_dict()
    print(summary_text(summary))
    if a.json:
        write_json(a.json, {**summary, "series": result.series})
        print(f"wrote {a.json}")
    plot = a.plot or (Path(a.json).with_suffix(".png") if a.json else None)
    if plot:
        title = (f"{db.source}: queries {queries.camera}, database {db.camera}, exclusion "
                 f"{retrieval.exclusion_s:g} s, {summary['n_series']} series, mode {mode}")
        save_error_plot(summary, plot, title)
        print(f"wrote {plot}")
    return 0


def cmd_dashboard(a: argparse.Namespace) -> int:
    if not 1 <= a.port <= 65535:
        raise InputError(f"--port {a.port}: must be in 1..65535")
    from dashboard import serve

    serve(a.db, host=a.host, port=a.port, db_camera=a.db_camera, query_camera=a.query_camera,
          announce=lambda text: print(text, flush=True))
    return 0


def cmd_bench(a: argparse.Namespace) -> int:
    from bench.run import BenchParams, run_bench, write_json

    params = BenchParams(series=a.series, shortlist_size=a.shortlist, fast_scale=a.fast_scale,
                         ingest_images=a.ingest_images, workers=a.workers, synthetic_images=a.synthetic_images,
                         synthetic_descriptors=a.synthetic_descriptors, synthetic_queries=a.synthetic_queries,
                         skip_synthetic=a.skip_synthetic, skip_accuracy=a.skip_accuracy)
    root = a.root or default_data_root()
    if a.json is not None and not Path(a.json).resolve().parent.is_dir():
        raise InputError(f"--json {a.json}: folder does not exist")
    for flag, path in (("--db", a.db), ("--fast-db", a.fast_db)):
        if not Path(path).resolve().parent.is_dir():
            raise InputError(f"{flag} {path}: folder does not exist")
    _open_sequence(root, a.drive, "image_00")  # a missing drive fails here, before any slow work
    result = run_bench(root, a.drive, Path(a.db), Path(a.fast_db), params, say=lambda t: print(t, flush=True))
    if a.json:
        write_json(a.json, result)
        print(f"wrote {a.json}")
    return 0


def cmd_info(a: argparse.Namespace) -> int:
    from visloc.ingest import stored_sift_params

    with FeatureStore(a.db) as store:
        print(f"{a.db}: {store.image_count()} images")
        params = stored_sift_params(store)
        print(f"SIFT settings: {params.as_dict() if params else 'none yet'}")
        for s in store.sources():
            span = s["last_timestamp_s"] - s["first_timestamp_s"]
            cam = store.get_camera(s["source"], s["camera"])
            calib = "P_rect known" if cam and cam.P_rect is not None else "no calibration"
            calib += ", extrinsics known" if cam and cam.T_camera_imu is not None else ", no extrinsics"
            lacking = len(store.frames_without_attitude(s["source"], s["camera"]))
            calib += f", {lacking} without attitude" if lacking else ", attitudes known"
            print(f"  {s['source']}/{s['camera']}: {s['n_images']} images over {span:.1f} s, "
                  f"{s['mean_keypoints']:.0f} keypoints per image, {calib}")
    return 0


# -- parser ----------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="visloc",
        description="Localize a vehicle from one camera against a database of geotagged images (SIFT + Kalman filter).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("ingest", help="build or extend a store: SIFT features and geotags of every image",
                       description="Extract SIFT from every image of a drive (or CSV) and store features and geotags. "
                                   "Re-running skips what is stored; an interruption loses nothing committed.")
    _add_source(p, "KITTI camera to store", "image_01", multiple=True)
    _add_db(p)
    p.add_argument("--workers", type=int, default=None, help="SIFT processes (default: number of cores)")
    p.add_argument("--limit", type=int, default=None, help="stop after this many new images")
    _add_sift(p)
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("localize", help="localize one query series against a store; print the paper's Tables 2 and 3",
                       description="Run one series of queries (one every --dt-s seconds) against the database and "
                                   "print the paper's Tables 2 and 3 for it.")
    _add_source(p, "query camera", "image_00")
    _add_db(p)
    p.add_argument("--db-camera", default="image_01", help="database camera in the store (default %(default)s)")
    p.add_argument("--db-source", default=None, help="database drive/dataset in the store (default: the query's drive)")
    p.add_argument("--start-frame", type=int, default=0, help="query frame of the first step, t-5 (default %(default)s)")
    p.add_argument("--steps", type=int, default=6, help="number of queries (default %(default)s)")
    _add_sampling(p)
    p.add_argument("--json", type=Path, default=None, help="also write the steps as JSON")
    _add_method(p, PAPER_RETRIEVAL)
    _add_mode(p)
    _add_sift(p)
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("evaluate", help="the paper's evaluation protocol on a KITTI drive",
                       description="Every series of --steps queries one --dt-s apart that fits in the drive; "
                                   "per-step mean measurement and estimate errors (Figure 4), final error, latency. "
                                   "Ingests both cameras into --db first (skipping what is stored).")
    p.add_argument("root", nargs="?", type=Path, default=None, help="KITTI raw root (default $VISLOC_DATA or ../shared/data/kitti)")
    p.add_argument("--drive", default=None, help="KITTI drive, e.g. 2011_09_26_drive_0001")
    _add_db(p)
    p.add_argument("--query-camera", default="image_00", help="queries (default %(default)s, left gray)")
    p.add_argument("--db-camera", default="image_01", help="database (default %(default)s, right gray)")
    p.add_argument("--steps", type=int, default=6, help="queries per series (default %(default)s)")
    p.add_argument("--start-frames", default=None, help="only series starting at these query frames, e.g. 0,20,40")
    _add_sampling(p)
    p.add_argument("--json", type=Path, default=None, help="write the results as JSON")
    p.add_argument("--plot", type=Path, default=None, help="error plot PNG (default: the JSON path with .png)")
    p.add_argument("--workers", type=int, default=None, help="SIFT processes for ingest (default: number of cores)")
    p.add_argument("--smooth", action="store_true",
                   help="also run the RTS smoother over each series and report its per-step errors")
    p.add_argument("--fast", action="store_true",
                   help="the fast retrieval (issue 5): the filter gates the candidates, VLAD vectors shortlist "
                        "8 of them, exact counts on those only (default: the paper's window, every candidate)")
    _add_method(p, PAPER_EVAL_RETRIEVAL)
    _add_mode(p)
    _add_sift(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("dashboard", help="browser dashboard: scrub through a drive, tune the method live",
                       description="Serve the viser dashboard for a store built by 'visloc ingest' or 'visloc "
                                   "evaluate'. Prints the URL actually served (viser moves to the next free port "
                                   "when --port is taken). A missing or bad store is reported in the page.")
    _add_db(p)
    p.add_argument("--host", default="127.0.0.1", help="interface to serve on (default %(default)s, this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port to try first (default %(default)s)")
    p.add_argument("--db-camera", default="image_01", help="database camera to show first (default %(default)s)")
    p.add_argument("--query-camera", default="image_00", help="query camera to show first (default %(default)s)")
    p.set_defaults(func=cmd_dashboard)

    p = sub.add_parser("bench", help="time the paper's brute-force path against the fast path (issue 5)",
                       description="Run the paper's path and the fast path (filter gate, VLAD shortlist, faiss, "
                                   "SIFT at a smaller image scale) on the same queries of a KITTI drive: accuracy, "
                                   "latency per stage, ingest throughput against bare SIFT, and a synthetic "
                                   "database's lost-query time and peak memory. Builds the stores it lacks.")
    p.add_argument("root", nargs="?", type=Path, default=None,
                   help="KITTI raw root (default $VISLOC_DATA or ../shared/data/kitti)")
    p.add_argument("--drive", default="2011_09_26_drive_0001", help="KITTI drive (default %(default)s)")
    p.add_argument("--db", default="out/visloc.sqlite", help="store of the paper's path (default %(default)s)")
    p.add_argument("--fast-db", default="out/visloc_s05.sqlite",
                   help="store of the fast path, SIFT at --fast-scale (default %(default)s)")
    p.add_argument("--series", type=int, default=2, help="live series of 6 queries timed per lever (default %(default)s)")
    p.add_argument("--shortlist", type=int, default=8, help="images matched exactly per query (default %(default)s)")
    p.add_argument("--fast-scale", type=float, default=0.5, help="fast path's SIFT image scale (default %(default)s)")
    p.add_argument("--ingest-images", type=int, default=40, help="images timed for ingest (default %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="processes for ingest and bare SIFT (default %(default)s)")
    p.add_argument("--synthetic-images", type=int, default=100_000, help="synthetic database size (default %(default)s)")
    p.add_argument("--synthetic-descriptors", type=int, default=64,
                   help="descriptors per synthetic image (default %(default)s)")
    p.add_argument("--synthetic-queries", type=int, default=20, help="lost queries on it (default %(default)s)")
    p.add_argument("--skip-synthetic", action="store_true", help="leave out the synthetic database test")
    p.add_argument("--skip-accuracy", action="store_true", help="leave out the accuracy over every series")
    p.add_argument("--json", type=Path, default=None, help="also write every number as JSON")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("info", help="what a store holds", description="Images, drives, cameras and SIFT settings of a store.")
    _add_db(p)
    p.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("steps", "workers", "limit"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            print(f"visloc: error: --{name} {value}: must be >= 1", file=sys.stderr)
            return 2
    try:
        return args.func(args)
    except (VislocError, StoreError) as exc:
        print(f"visloc: error: {exc}", file=sys.stderr)
        return 2
    except sqlite3.Error as exc:  # locked, read-only or damaged store file
        print(f"visloc: error: {getattr(args, 'db', 'database')}: SQLite: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("visloc: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
