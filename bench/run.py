"""``visloc bench``: the paper's brute-force path and the fast path on the same queries, in one run.

Sections (each prints as it finishes; ``--json`` writes everything):

The drive's left gray camera gives the queries; the database is its right gray camera where
the drive has one, else the left camera itself (the 1 s exclusion keeps a query off its own image).

1. **Accuracy** over every series of the paper's protocol (1 s exclusion), one row per lever: the paper's path, the filter gate, gate + VLAD shortlist, and the
   same at SIFT image scale 0.5 (the fast path). Counts come from each store's pair-count
   cache, filled by exact matching when missing (the counts are deterministic, so cached and
   fresh counts are the same numbers); per query, whether the best match agrees with the paper's.
2. **Latency** on the same live queries (``--series`` series of six, spread over the drive)
   for every lever, everything recomputed: query SIFT from the PNG (the read itself not
   timed), retrieval, geometry (the measurement; 0 in the paper's mode), filter.
   Percentiles per stage, and the speed ratio paper / fast.
3. **Ingest**: images per second of bare OpenCV SIFT in a process pool against
   ``visloc.store.ingest`` into a fresh store, same images, same number of processes.
2b. **Refined paths** (``visloc.bench.refined``): the exact refined path and the camera-rate one,
   run as ``visloc track`` runs on the same frames: latency, speed ratio, errors.
4. **Scale**: a synthetic database of ``--synthetic-images`` images; time for a lost query
   to find its candidates, and peak memory, in a process of its own.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from visloc.bench.refined import refined_fast, refined_fast_targets
from visloc.bench.synthetic import SyntheticSpec, build_store, lost_query, peak_rss_mb
from visloc.protocols.evaluation import evaluate, series_schedule
from visloc.features.sift import extract_sift, make_sift
from visloc.errors import InputError
from visloc.geo import geodesic_distance_m
from visloc.retrieval.matching import backend_counter
from visloc.params.methods import PAPER_METHOD, features_for
from visloc.tracking.methods import build_localizer
from visloc.progress import progress_reporter
from visloc.params import (BENCH, BENCH_WORKERS, PAPER_EVAL_RETRIEVAL, PAPER_FILTER, PAPER_MATCH, PAPER_SIFT,
                           STORE_SIFT, BenchParams, FastParams, SiftParams)
from visloc.sources.queries import extract_queries
from visloc.retrieval.retrievers import build_global_index
from visloc.tracking.runs import run_queries
from visloc.sources.drives import load_gray
from visloc.sources.opening import open_source
from visloc.store.workspace import Workspace
from visloc.store.build import build_global_vectors, build_structure, ingest_sequence

LEVERS = ("paper", "faiss_nn", "gate", "gate_shortlist", "fast")


def _pct(values) -> dict:
    v = np.asarray(list(values), float)
    if v.size == 0:
        return {"p50": None, "p95": None}
    return {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95))}


def _load() -> dict:
    one, five, fifteen = os.getloadavg()
    return {"load_1min": one, "load_5min": five, "load_15min": fifteen, "cores": os.cpu_count()}


# -- stores ------------------------------------------------------------------------------------

def _cameras(root: Path | None, drive: str | None) -> tuple[str, str]:
    """(query camera, database camera): left queries against the right camera where the drive has both
    gray cameras, else queries and database from the left one (the exclusion window keeps a query off itself)."""
    try:
        open_source(root, drive=drive, camera="image_01")
    except InputError:
        return "image_00", "image_00"
    return "image_00", "image_01"


def _ensure_store(path: Path, sequences: dict, sift: SiftParams, workers: int, say) -> None:
    """Ingest what the store at ``path`` lacks, as ``visloc ingest`` would: at the store's SIFT settings, ``sift``
    for a new store."""
    ws = Workspace(path, create=True)
    sift = ws.sift_params or sift
    for seq in {s.name: s for s in sequences.values()}.values():
        if ws.stored_frame_count(seq.source, seq.camera) < len(seq):
            say(f"building {path} ({seq.name}, SIFT {sift.as_dict()})")
            ingest_sequence(ws, seq, sift, workers=workers, progress=progress_reporter(f"ingest {seq.name}", "images"),
                      vectors_progress=progress_reporter(f"global vectors {seq.name}", "images"),
                      structure_progress=progress_reporter(f"structure {seq.name}", "images"),
                      self_check_progress=progress_reporter(f"self-check {seq.name}", "images"))
        else:  # a store from before structure was kept: add what ingest now stores
            build_global_vectors(ws, seq.source, seq.camera,
                                    progress=progress_reporter(f"global vectors {seq.name}", "images"))
            build_structure(ws, seq.source, seq.camera, progress=progress_reporter(f"structure {seq.name}", "images"))


def _load_store(path: Path, sequences: dict):
    """The workspace, and the database and queries as the paper's method reads them (on a store described at a
    lower SIFT contrast, the paper's features selected)."""
    ws = Workspace(path)
    db, queries, sift = sequences["database"], sequences["queries"], features_for(PAPER_METHOD, ws.sift_params)
    return ws, ws.load_database(db.source, db.camera, sift), ws.load_queries(queries.source, queries.camera, sift)


# -- 1. accuracy ---------------------------------------------------------------------------------

def _accuracy(datasets: dict, indexes: dict, say) -> dict:
    rows, best_frames = {}, {}
    for lever, (store_key, fast_key) in {"paper": ("full", None), "gate": ("full", "gate"),
                                         "gate_shortlist": ("full", "gate_shortlist"),
                                         "paper_scaled": ("scaled", None), "fast": ("scaled", "fast")}.items():
        ws, db, queries = datasets[store_key]
        method = PAPER_METHOD if fast_key is None else PAPER_METHOD.replace(shortlist=indexes[fast_key][0])
        cache = ws.pair_cache(db, queries, PAPER_MATCH)
        t0 = time.perf_counter()
        try:
            ev = evaluate(queries, db, PAPER_MATCH, PAPER_EVAL_RETRIEVAL, PAPER_FILTER, method=method, cache=cache,
                          shortlist_index=None if fast_key is None else indexes[fast_key][1],
                          progress=progress_reporter(f"bench accuracy {lever}", "series"))
        finally:
            ws.save_pair_counts(cache)
        s = ev.summary()
        best_frames[lever] = [r.best_db_frame for series in ev.series for r in series]
        rows[lever] = {"final_error_m": s["final_error_m"], "measurement_error_m": s["measurement_error_m"],
                       "estimate_error_m": s["estimate_error_m"], "n_series": s["n_series"],
                       "mean_candidates_counted": float(np.mean([r.n_candidates for se in ev.series for r in se])),
                       "seconds": time.perf_counter() - t0}
        say(f"  accuracy {lever:15s} final mean {s['final_error_m']['mean']:.2f} m, measurement "
            f"{' '.join(f'{v:.2f}' for v in s['measurement_error_m'])} m, "
            f"{rows[lever]['mean_candidates_counted']:.1f} images counted per query")
    for lever in rows:
        a, b = np.array(best_frames[lever], object), np.array(best_frames["paper"], object)
        same = [x == y for x, y in zip(a, b)]
        near = [x is not None and y is not None and abs(x - y) <= 1 for x, y in zip(a, b)]
        rows[lever]["best_match_agrees_with_paper"] = float(np.mean(same))
        rows[lever]["best_match_within_1_frame_of_paper"] = float(np.mean(near))
    return rows


# -- 2. latency ----------------------------------------------------------------------------------

def _live(lever: str, datasets: dict, indexes: dict, seq_by_key: dict, starts: list[list[int]]) -> list[dict]:
    store_key = "scaled" if lever == "fast" else "full"
    ws, db, _ = datasets[store_key]
    sift = features_for(PAPER_METHOD, ws.sift_params)  # the paper's features, as the database was loaded
    counter = backend_counter("faiss", db.descriptors_u8, PAPER_MATCH) if lever == "faiss_nn" else None
    method, index = PAPER_METHOD, None
    if lever in indexes:
        (fast_params, index) = indexes[lever]
        method = PAPER_METHOD.replace(shortlist=fast_params)
    loc = build_localizer(method, db, PAPER_MATCH, PAPER_EVAL_RETRIEVAL, PAPER_FILTER, counter=counter,
                          shortlist_index=index)
    engine = make_sift(sift)
    seq = seq_by_key["queries"]
    extract_sift(load_gray(seq.frames[0].image_path), sift, sift=engine)  # warm up (imports, allocations)
    out = []
    for indices in starts:
        loc.reset()
        for k, (i, step) in enumerate(zip(indices, run_queries(loc, extract_queries(seq, indices, sift,
                                                                                     engine=engine)))):
            r, fr = step.result, seq.frames[i]
            best = r.best_index
            m_err = None
            if best is not None:
                m_err = float(geodesic_distance_m(db.lat_deg[best], db.lon_deg[best], fr.lat_deg, fr.lon_deg))
            out.append({"query_frame": fr.frame, "step": k, "sift_ms": r.query.sift_ms,
                        "retrieval_ms": r.timings.retrieval_ms, "geometry_ms": r.timings.measurement_ms,
                        "filter_ms": r.timings.filter_ms, "total_ms": r.query.sift_ms + r.timings.total_ms,
                        "n_keypoints": len(r.query.descriptors_u8), "n_counted": int(r.retrieval.candidates.size),
                        "best_db_frame": None if best is None else int(db.images[best].frame),
                        "measurement_error_m": m_err})
    return out


def _latency(datasets: dict, indexes: dict, seq_by_key: dict, n_series: int, say) -> dict:
    seq = seq_by_key["queries"]
    schedule = series_schedule(seq.timestamps_s, PAPER_FILTER.dt_s, 6)
    picks = np.unique(np.linspace(0, len(schedule) - 1, n_series).round().astype(int))
    starts = [schedule[p] for p in picks]
    out = {"start_frames": [seq.frames[s[0]].frame for s in starts], "levers": {}}
    progress = progress_reporter("bench latency", "levers")
    progress(0, len(LEVERS))
    for n, lever in enumerate(LEVERS, 1):
        rows = _live(lever, datasets, indexes, seq_by_key, starts)
        progress(n, len(LEVERS))
        stages = {k: _pct(r[k] for r in rows) for k in ("sift_ms", "retrieval_ms", "geometry_ms", "filter_ms",
                                                        "total_ms")}
        out["levers"][lever] = {"stages_ms": stages, "queries": rows,
                                "mean_counted": float(np.mean([r["n_counted"] for r in rows])),
                                "median_keypoints": float(np.median([r["n_keypoints"] for r in rows]))}
        say(f"  latency {lever:15s} total p50 {stages['total_ms']['p50']:8.1f} ms  p95 {stages['total_ms']['p95']:8.1f}"
            f" ms  (SIFT {stages['sift_ms']['p50']:.0f}, retrieval {stages['retrieval_ms']['p50']:.1f}, "
            f"filter {stages['filter_ms']['p50']:.2f}; {out['levers'][lever]['mean_counted']:.1f} images counted)")
    paper, fast = out["levers"]["paper"]["queries"], out["levers"]["fast"]["queries"]
    ratio = [p["total_ms"] / f["total_ms"] for p, f in zip(paper, fast)]
    out["speed_ratio_paper_over_fast"] = {"p50": float(np.median(ratio)), "min": float(np.min(ratio)),
                                          "max": float(np.max(ratio))}
    for lever in LEVERS:
        rows = out["levers"][lever]["queries"]
        out["levers"][lever]["best_match_agrees_with_paper"] = float(np.mean(
            [r["best_db_frame"] == p["best_db_frame"] for r, p in zip(rows, paper)]))
    return out


# -- 3. ingest -----------------------------------------------------------------------------------

_bare_sift = None


def _bare_init(sift_dict: dict) -> None:
    global _bare_sift
    cv2.setNumThreads(1)
    _bare_sift = make_sift(SiftParams(**sift_dict))


def _bare_one(path: str) -> int:
    gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    keypoints, _ = _bare_sift.detectAndCompute(gray, None)
    return len(keypoints)


def _ingest_bench(seq_by_key: dict, sift: SiftParams, n_images: int, workers: int, say) -> dict:
    seq = seq_by_key["queries"]
    frames = seq.frames[:n_images]
    paths = [str(f.image_path) for f in frames]
    runs = {"bare_sift_images_per_s": [], "ingest_images_per_s": [], "structure_ms_per_image": []}
    for _ in range(3):  # interleaved, three times: the machine's load drifts
        t0 = time.perf_counter()
        with mp.get_context("spawn").Pool(workers, initializer=_bare_init, initargs=(sift.as_dict(),)) as pool:
            list(pool.imap(_bare_one, paths, chunksize=1))
        runs["bare_sift_images_per_s"].append(len(paths) / (time.perf_counter() - t0))
        with tempfile.TemporaryDirectory() as tmp:
            ws = Workspace(Path(tmp) / "ingest.sqlite", create=True)
            t0 = time.perf_counter()
            report = ingest_sequence(ws, seq, sift, workers=workers, limit=n_images, structure=False)  # SIFT and storing
            runs["ingest_images_per_s"].append(report.n_added / (time.perf_counter() - t0))
            t0 = time.perf_counter()  # then what ingest adds: global vectors and structure
            build_global_vectors(ws, seq.source, seq.camera)
            build_structure(ws, seq.source, seq.camera)
            runs["structure_ms_per_image"].append((time.perf_counter() - t0) * 1000.0 / report.n_added)
    bare, ing = float(np.median(runs["bare_sift_images_per_s"])), float(np.median(runs["ingest_images_per_s"]))
    out = {"n_images": len(paths), "workers": workers, "sift": sift.as_dict(), "runs": runs,
           "bare_sift_images_per_s": bare, "ingest_images_per_s": ing, "ingest_over_bare": ing / bare,
           "structure_ms_per_image": float(np.median(runs["structure_ms_per_image"])),
           "ingest_over_bare_per_run": [i / b for i, b in zip(runs["ingest_images_per_s"],
                                                              runs["bare_sift_images_per_s"])]}
    say(f"  ingest {ing:.2f} images/s vs bare SIFT {bare:.2f} images/s over {workers} processes: "
        f"{100 * ing / bare:.0f}% (medians of 3 interleaved runs each; per run "
        f"{', '.join(f'{100 * r:.0f}%' for r in out['ingest_over_bare_per_run'])}); then global vectors and "
        f"structure {out['structure_ms_per_image']:.0f} ms per image")
    return out


# -- 4. scale ------------------------------------------------------------------------------------

def _synthetic_build(path: str, spec_dict: dict) -> dict:
    seconds = build_store(Path(path), SyntheticSpec(**spec_dict))
    return {"build_s": seconds, "peak_rss_mb": peak_rss_mb()}


def _synthetic_query(path: str, spec_dict: dict, places: list[int], shortlist_size: int) -> dict:
    return lost_query(Path(path), SyntheticSpec(**spec_dict), places, shortlist_size)


def _scale(out_dir: Path, p: BenchParams, say) -> dict:
    spec = SyntheticSpec(n_images=p.synthetic_images, descriptors_per_image=p.synthetic_descriptors)
    path = out_dir / f"synthetic_{spec.n_images}_{spec.descriptors_per_image}.sqlite"
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx) as ex:
        build = ex.submit(_synthetic_build, str(path), spec.key()).result()
    if build["build_s"]:
        say(f"  built {path} in {build['build_s']:.0f} s")
    places = np.random.default_rng(7).choice(spec.n_images, size=p.synthetic_queries, replace=False).tolist()
    with ProcessPoolExecutor(1, mp_context=ctx) as ex:  # a fresh process: its peak memory is the query's alone
        res = ex.submit(_synthetic_query, str(path), spec.key(), places, p.shortlist_size).result()
    res["build"] = build
    say(f"  {spec.n_images} images: lost query finds its candidates and reads their structure "
        f"({res['structure_points_read_p50']:.0f} points) in p50 {res['candidates_ms']['p50']:.1f} ms, "
        f"p95 {res['candidates_ms']['p95']:.1f} ms (shortlist recall {res['recall_shortlist']:.2f}, best within 1 m "
        f"{res['best_within_1m']:.2f}); global vectors {res['global_vectors_mb']:.0f} MB of a "
        f"{res['store_mb']:.0f} MB store, peak RSS {res['peak_rss_mb']:.0f} MB, index load {res['index_load_s']:.2f} s")
    return res


# -- main ----------------------------------------------------------------------------------------

def run_bench(root: Path | None, drive: str | None, db_path: Path, fast_db_path: Path, params: BenchParams = BENCH,
              workers: int = BENCH_WORKERS, say=print) -> dict:
    """Every section, on drive ``drive`` of the KITTI root ``root`` (None: the default data root); builds
    the stores of both SIFT settings at ``db_path`` and ``fast_db_path`` when they lack images, with
    ``workers`` processes."""
    result: dict = {"params": {**params.as_dict(), "workers": workers}, "load_before": _load()}
    say(f"load before: {result['load_before']}")
    query_camera, db_camera = _cameras(root, drive)
    seq_by_key = {"queries": open_source(root, drive=drive, camera=query_camera),
                  "database": open_source(root, drive=drive, camera=db_camera)}
    result.update(drive=seq_by_key["queries"].source, query_camera=query_camera, db_camera=db_camera)
    _ensure_store(db_path, seq_by_key, STORE_SIFT, workers, say)
    _ensure_store(fast_db_path, seq_by_key, PAPER_SIFT.replace(image_scale=params.fast_scale), workers, say)
    datasets = {"full": _load_store(db_path, seq_by_key), "scaled": _load_store(fast_db_path, seq_by_key)}
    fp = FastParams(shortlist_size=params.shortlist_size)
    t0 = time.perf_counter()
    # lever -> (the fast retrieval's parameters, its global vectors of the lever's database)
    indexes = {lever: (lever_params, build_global_index(datasets[key][1].descriptors_u8, lever_params))
               for lever, key, lever_params in (("gate", "full", fp.replace(shortlist_size=0)),
                                                ("gate_shortlist", "full", fp), ("fast", "scaled", fp))}
    result["fast_params"] = fp.as_dict()
    result["global_index_build_s"] = (time.perf_counter() - t0) / 3
    if not params.skip_accuracy:
        say("1. accuracy, every series of the paper's protocol (1 s exclusion):")
        result["accuracy"] = _accuracy(datasets, indexes, say)
    say(f"2. latency, {params.series} live series of 6 queries (SIFT + retrieval + geometry + filter):")
    result["latency"] = _latency(datasets, indexes, seq_by_key, params.series, say)
    r = result["latency"]["speed_ratio_paper_over_fast"]
    say(f"  speed ratio paper / fast per query: median {r['p50']:.0f}x (min {r['min']:.0f}x, max {r['max']:.0f}x)")
    if not params.skip_refined:
        say(f"2b. refined paths, every {params.refined_stride}th frame of the drive (exact, then camera-rate):")
        result["refined_fast"] = refined_fast(datasets["full"][0], seq_by_key["queries"], db_camera,
                                              params.refined_stride, say)
    result["peak_rss_mb"] = peak_rss_mb()
    say("3. ingest:")
    result["ingest"] = _ingest_bench(seq_by_key, STORE_SIFT, params.ingest_images, workers, say)
    if not params.skip_synthetic:
        say("4. scale (synthetic database, own process):")
        result["scale"] = _scale(Path(fast_db_path).parent, params, say)
    result["load_after"] = _load()
    result["targets"] = _targets(result)
    say(f"load after: {result['load_after']}")
    for k, v in result["targets"].items():
        say(f"target {k}: {'MET' if v['met'] else 'NOT MET'} ({v['value']})")
    return result


def _targets(result: dict) -> dict:
    out = {}
    st = result["latency"]["levers"]["fast"]["stages_ms"]["total_ms"]
    acc = result.get("accuracy")
    out["latency"] = {"met": st["p50"] <= 100 and st["p95"] <= 150,
                      "value": f"fast path p50 {st['p50']:.0f} ms, p95 {st['p95']:.0f} ms"}
    if acc:
        fast, paper = acc["fast"], acc["paper"]
        worse_m = [f - p for f, p in zip(fast["measurement_error_m"], paper["measurement_error_m"])]
        out["accuracy_final"] = {"met": fast["final_error_m"]["mean"] <= paper["final_error_m"]["mean"],
                                 "value": f"final mean {fast['final_error_m']['mean']:.2f} m vs paper "
                                          f"{paper['final_error_m']['mean']:.2f} m"}
        out["accuracy_measurement"] = {"met": max(worse_m) <= 0.0,
                                       "value": "measurement error minus paper's per step "
                                                + " ".join(f"{w:+.2f}" for w in worse_m) + " m"}
    if "refined_fast" in result:
        out.update(refined_fast_targets(result["refined_fast"]))
    ing = result["ingest"]
    out["ingest"] = {"met": ing["ingest_over_bare"] >= 0.9, "value": f"{100 * ing['ingest_over_bare']:.0f}% of bare SIFT"}
    if "scale" in result:
        sc = result["scale"]
        out["scale"] = {"met": sc["candidates_ms"]["max"] <= 1000 and sc["n_images"] >= 100_000,
                        "value": f"{sc['n_images']} images, max {sc['candidates_ms']['max']:.0f} ms, peak RSS "
                                 f"{sc['peak_rss_mb']:.0f} MB"}
    return out
