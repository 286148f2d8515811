"""Sharded stores measured: ingest on a local Dask cluster against today's single file, and a synthetic city.

    python benchmarks/shard_scale.py [--root ../shared/data/kitti] [--frames 100] [--repeats 3] [--images 1000000]
    python benchmarks/shard_scale.py --only ingest --only city   # measure those parts, keep the JSON's others
    python benchmarks/shard_scale.py --page   # its section of docs/sharding.md from the JSON

1. Ingest, on every drive of the data root: the first ``--frames`` frames of image_00 (SIFT, global vectors,
   structure, self-check), one command after the other on this machine, each into a new store:
   ``file_1``: today's single file, ``visloc ingest --workers 1`` (OpenCV's and BLAS's threads use every
   core); ``file_1_one_core``: the same with one thread each; ``tiles_1`` and ``tiles_2``:
   ``visloc ingest --tile-m 250 --workers 1`` and ``--workers 2`` (a local cluster, whose workers share the
   cores' OpenCV threads: one worker uses both, as ``file_1`` does; two use one each). Wall time, images per
   second, and the largest resident memory of one worker process (sampled every 0.2 s).
2. A synthetic city: ``--images`` images in tiles of 250 m over a square city (metadata and a 64-float global
   vector per image in the manifest; no features). Timed in this process: picking the tiles of a gated
   query (a disc of 30 m around a random point), the lost query (the 10 nearest global vectors by exact
   inner product, and their tiles), and this process's peak memory.
3. Reading, on every drive of the data root: image_00 whole in tiles of 25 m (two workers), then the
   paper's ``visloc localize`` (one series from the middle of the drive) and ``visloc track`` (every frame,
   then the first third of the frames) on it: the tiles each read (of how many), how often, and the most memory their features and structure points held, against
   the features of every tile and the catalogue a command reads (of the drives it uses: the store's one).

Writes docs/results/shard_scale.json; ``--page`` renders its section of docs/sharding.md from it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


from measuring import REPO, Section, load_1min  # noqa: E402

SECTION = Section("shard-scale", "shard_scale", REPO / "docs" / "sharding.md")
OUT, PAGE, BEGIN, END = SECTION.out, SECTION.page, SECTION.begin, SECTION.end

VISLOC = [sys.executable, "-m", "visloc"]
RUNS = {"file_1": ["--workers", "1"], "file_1_one_core": ["--workers", "1"],
        "tiles_1": ["--tile-m", "250", "--workers", "1"], "tiles_2": ["--tile-m", "250", "--workers", "2"]}
# today's ingest with one worker runs SIFT in its own process with OpenCV's threads, and BLAS's: on this
# machine it uses both cores. Run again with one thread each, it is the one-core figure a worker compares with.
ONE_CORE = {"OPENCV_FOR_THREADS_NUM": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
PARTS = ("ingest", "city", "reads")
CITY_TILE_M = 250.0
VECTOR_DIM = 64


def _ingest(root: Path, drive: str, frames: int, store: Path, flags: list[str], env: dict | None = None) -> dict:
    """One ingest command, timed, with the largest resident memory of any one of its child processes."""
    import psutil

    cmd = [*VISLOC, "ingest", str(root), "--drive", drive, "--camera", "image_00", "--db", str(store),
           "--limit", str(frames), *flags]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **(env or {})})
    parent = psutil.Process(proc.pid)
    worker_rss, main_rss = 0, 0
    while proc.poll() is None:
        try:
            main_rss = max(main_rss, parent.memory_info().rss)
            for child in parent.children(recursive=True):
                worker_rss = max(worker_rss, child.memory_info().rss)
        except psutil.Error:
            pass
        time.sleep(0.2)
    out, err = proc.communicate()
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{err}")
    return {"seconds": seconds, "images_per_s": frames / seconds, "worker_rss_mb": worker_rss / 2**20,
            "main_rss_mb": main_rss / 2**20}


def measure_ingest(root: Path, frames: int, repeats: int) -> list[dict]:
    """Every configuration of ``RUNS`` on every drive, ``repeats`` rounds, each round running every
    configuration once (so that a change of load meets all of them), in an order rotated by one from
    round to round (so that no configuration always runs first); per configuration the median time, and
    each ratio as the median of the rounds' ratios (paths compared within the same round)."""
    from visloc.sources.drives import kitti_drives
    from visloc.sources.opening import open_source

    drives = [name.removesuffix("_sync") for name in kitti_drives(root)]
    counts = {drive: min(frames, len(open_source(root, drive=drive, camera="image_00"))) for drive in drives}
    rounds: dict[str, list[dict]] = {drive: [] for drive in drives}
    for k in range(repeats):
        for drive in drives:
            runs = {}
            with tempfile.TemporaryDirectory() as tmp:
                names = list(RUNS)
                for name in names[k % len(names):] + names[: k % len(names)]:
                    flags = RUNS[name]
                    store = Path(tmp) / (name + (".sqlite" if name.startswith("file") else ""))
                    runs[name] = _ingest(root, drive, counts[drive], store, flags,
                                         ONE_CORE if name.endswith("one_core") else None)
                    shutil.rmtree(store, ignore_errors=True) if store.is_dir() else store.unlink(missing_ok=True)
                    print(f"round {k + 1}/{repeats} {drive} {name}: {runs[name]['seconds']:.0f} s", file=sys.stderr)
            rounds[drive].append(runs)
    out = []
    for drive in drives:
        n, done = counts[drive], rounds[drive]
        runs = {}
        for name in RUNS:
            seconds = [r[name]["seconds"] for r in done]
            median_s = float(np.median(seconds))
            runs[name] = {"seconds": median_s, "seconds_each": seconds, "images_per_s": n / median_s,
                          "worker_rss_mb": max(r[name]["worker_rss_mb"] for r in done),
                          "main_rss_mb": max(r[name]["main_rss_mb"] for r in done)}

        def ratio(a: str, b: str) -> float:
            return float(np.median([r[a]["seconds"] / r[b]["seconds"] for r in done]))

        out.append({"drive": drive, "images": n, "repeats": repeats, "runs": runs,
                    "speedup_2_over_1": ratio("tiles_1", "tiles_2"),
                    "tiles_1_over_file_1": ratio("tiles_1", "file_1"),
                    "tiles_1_over_file_1_one_core": ratio("tiles_1", "file_1_one_core")})
    return out


def measure_city(n_images: int, folder: Path) -> dict:
    """A synthetic city in ``folder``: a manifest of ``n_images`` images in 250 m tiles, then the reads."""
    from visloc.db.shards import Manifest, TileRecord
    from visloc.store.tiles import cell_bounds_m, owner_cells, tile_key

    rng = np.random.default_rng(3)
    side_m = CITY_TILE_M * np.ceil(np.sqrt(max(n_images / 900, 1000)))  # >= 1000 tiles, ~900 images each
    east_north = rng.uniform(0, side_m, size=(n_images, 2)) + [500_000.0, 5_400_000.0]
    cells = owner_cells(east_north, CITY_TILE_M)
    keys = [tile_key(*c) for c in cells.tolist()]
    start = time.perf_counter()
    with Manifest(folder, create=True) as manifest:
        from visloc.db.shards import Grid

        manifest.require_grid(Grid(32632, CITY_TILE_M, 50.0))
        unique, counts = np.unique(cells, axis=0, return_counts=True)
        for (ix, iy), n in zip(unique.tolist(), counts.tolist()):
            manifest.publish(TileRecord(tile_key(ix, iy), ix, iy, cell_bounds_m(ix, iy, CITY_TILE_M),
                                        f"tiles/{tile_key(ix, iy)}.sqlite", int(n), int(n), "", ""))
        for start_row in range(0, n_images, 200_000):  # written in parts: the vectors are made as they go
            rows = range(start_row, min(start_row + 200_000, n_images))
            vectors = rng.normal(size=(len(rows), VECTOR_DIM)).astype(np.float32)
            vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
            manifest.add_global_index([(k + 1, "city", "camera", k, float(k), float(east_north[k, 0]),
                                        float(east_north[k, 1]), keys[k]) for k in rows], "synthetic", vectors)
    write_s = time.perf_counter() - start
    read = subprocess.run([sys.executable, __file__, "--read-city", str(folder), "--images", str(n_images)],
                          capture_output=True, text=True, check=True)  # a fresh process: its memory is the query's
    return {"images": n_images, "tiles": len(unique), "tile_m": CITY_TILE_M, "vector_dim": VECTOR_DIM,
            "manifest_mb": (folder / "manifest.sqlite").stat().st_size / 2**20, "write_s": write_s,
            **json.loads(read.stdout)}


def read_city(folder: Path, n_images: int) -> dict:
    """In a query process of its own: open the city's tile index and global index, then time the reads."""
    from visloc.db.shards import Manifest
    from visloc.store.sharded import GlobalSearch, TileIndex

    rng = np.random.default_rng(4)
    start = time.perf_counter()
    tiles = TileIndex.from_manifest(folder)
    open_tiles_s = time.perf_counter() - start
    start = time.perf_counter()
    with Manifest(folder, read_only=True) as manifest:
        columns, vectors = manifest.global_index()
    search = GlobalSearch(vectors, columns["tile"])
    del vectors
    open_index_s = time.perf_counter() - start

    gate_ms = []
    for centre in np.c_[columns["east_m"], columns["north_m"]][rng.integers(0, n_images, 2000)]:
        t = time.perf_counter()
        picked = tiles.for_gate(centre, 30.0)
        gate_ms.append((time.perf_counter() - t) * 1000)
        assert picked
    lost_ms = []
    queries = rng.normal(size=(40, VECTOR_DIM)).astype(np.float32)
    for q in queries:
        t = time.perf_counter()
        search.tiles_for(q / np.linalg.norm(q), k=10)
        lost_ms.append((time.perf_counter() - t) * 1000)
    return {"open_tile_index_s": open_tiles_s, "open_global_index_s": open_index_s,
            "gate_tiles_ms_p50": float(np.median(gate_ms)), "gate_tiles_ms_p95": float(np.percentile(gate_ms, 95)),
            "lost_query_ms_p50": float(np.median(lost_ms)), "lost_query_ms_p95": float(np.percentile(lost_ms, 95)),
            "process_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


READ_TILE_M = 25.0
TILES_LINE = re.compile(r"tiles read: (\d+) of (\d+) \((\d+) reads.*?, (\d+) dropped .* at most ([\d.]+) MB")


def _tiles_read(cmd: list[str]) -> dict:
    """Run a reading command; its "tiles read" line as numbers."""
    done = subprocess.run([*VISLOC, *cmd], capture_output=True, text=True)
    found = TILES_LINE.search(done.stdout)
    if done.returncode != 0 or found is None:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    distinct, total, reads, dropped, peak = found.groups()
    return {"tiles_read": int(distinct), "tiles": int(total), "reads": int(reads), "dropped": int(dropped),
            "peak_mb": float(peak)}


def measure_reads(root: Path) -> list[dict]:
    from visloc.sources.drives import kitti_drives
    from visloc.sources.opening import open_source
    from visloc.db.shards import table_bytes
    from visloc.store.sharded import merged_store

    out = []
    for drive in [name.removesuffix("_sync") for name in kitti_drives(root)]:
        n = len(open_source(root, drive=drive, camera="image_00"))
        with tempfile.TemporaryDirectory() as tmp:
            city = Path(tmp) / "city"
            made = _ingest(root, drive, n, city, ["--tile-m", str(READ_TILE_M), "--workers", "2"])
            where = [str(root), "--drive", drive, "--db", str(city)]
            localize = _tiles_read(["localize", *where, "--start-frame", str(n // 2)])
            track = _tiles_read(["track", *where, "--no-follow-points"])
            track_third = _tiles_read(["track", *where, "--no-follow-points", "--frames", str(n // 3)])
            tiles_mb = sum(f.stat().st_size for f in (city / "tiles").glob("*.sqlite")) / 1e6
            catalogue = merged_store(city, features=False)
            catalogue_mb = catalogue.stat().st_size / 1e6
            catalogue_tables_mb = {k: v / 1e6 for k, v in table_bytes(catalogue).items()}
        print(f"{drive} reads: localize {localize}, track {track}", file=sys.stderr)
        out.append({"drive": drive, "images": n, "tile_m": READ_TILE_M, "ingest_s": made["seconds"], "tiles_mb": tiles_mb,
                    "catalogue_mb": catalogue_mb,
                    "catalogue_tables_mb": catalogue_tables_mb, "localize": localize, "track": track,
                    "track_first_third": track_third})
    return out


def _render_reads(reads: list[dict]) -> list[str]:
    lines = ["", f"Reading, image_00 of each drive whole in tiles of {reads[0]['tile_m']:g} m: the tiles a command "
             "read (of the store's), how many reads (a tile dropped from the cache and read again counts again) "
             "and the most memory the open tiles' features and structure points held; the catalogue a command reads "
             "(of the drives it uses: here the store's one drive).", "",
             "| drive | images | tile files | catalogue (its structure, its global vectors) | localize, paper mode, one series | track, every frame | "
             "track, first third of the frames |", "|---|---|---|---|---|---|---|"]
    for d in reads:
        cell = {k: f"{d[k]['tiles_read']} of {d[k]['tiles']} tiles, {d[k]['reads']} reads, {d[k]['peak_mb']:.0f} MB"
                for k in ("localize", "track", "track_first_third")}
        t = d.get("catalogue_tables_mb", {})
        lines.append(f"| {d['drive']} | {d['images']} | {d['tiles_mb']:.0f} MB | {d['catalogue_mb']:.0f} MB "
                     f"({t.get('structures', 0):.0f} MB, {t.get('global_vectors', 0):.1f} MB) | "
                     f"{cell['localize']} | {cell['track']} | {cell['track_first_third']} |")
    return lines


def render(result: dict) -> str:
    repeats = result["ingest"][0].get("repeats", 1)
    lines = [BEGIN, "", "Ingest, first frames of image_00 of each drive (wall time, images per second, the largest "
             "worker process's resident memory; " + (f"the median of {repeats} rounds, each running every "
             "configuration once, in an order rotated from round to round, and each ratio the median of the rounds' ratios" if repeats > 1 else "one run")
             + "):", "",
             "| drive | images | one file, 1 process | one file, 1 process, 1 thread | tiles, 1 worker | "
             "tiles, 2 workers | 2 workers / 1 | tiles 1 worker / one file (1 thread) |",
             "|---|---|---|---|---|---|---|---|"]
    for d in result["ingest"]:
        r = d["runs"]
        cell = {k: f"{v['seconds']:.0f} s, {v['images_per_s']:.2f}/s" for k, v in r.items()}
        for k in ("tiles_1", "tiles_2"):
            cell[k] += f", {r[k]['worker_rss_mb']:.0f} MB"
        lines.append(f"| {d['drive']} | {d['images']} | {cell['file_1']} | {cell['file_1_one_core']} | "
                     f"{cell['tiles_1']} | {cell['tiles_2']} | {d['speedup_2_over_1']:.2f}× | "
                     f"{d['tiles_1_over_file_1']:.2f}× ({d['tiles_1_over_file_1_one_core']:.2f}×) |")
    lines += _load_line(result, "ingest_load_1min", "while ingesting")
    per_core_h = 3600 * float(np.median([d["runs"]["tiles_1"]["images_per_s"] for d in result["ingest"]]))
    lines += ["", f"On paper, from the median one-worker rate ({per_core_h:.0f} images per core-hour, the whole "
              "ingest: SIFT, global vectors, structure, self-check, tiles), if every core kept it:", "",
              "| cluster | images per hour | 1,000,000 images in |", "|---|---|---|"]
    for nodes, cores in ((1, 2), (10, 16), (100, 16)):
        rate = per_core_h * nodes * cores
        lines.append(f"| {nodes} node{'s' if nodes > 1 else ''} × {cores} cores | {rate:,.0f} | "
                     f"{1e6 / rate:.1f} h |")
    c = result["city"]
    lines += ["", f"Synthetic city: {c['images']:,} images in {c['tiles']:,} tiles of {c['tile_m']:g} m, a "
              f"{c['vector_dim']}-float global vector each; manifest {c['manifest_mb']:.0f} MB.", "",
              "| what | p50 | p95 |", "|---|---|---|",
              f"| tiles of a gated query (30 m disc) | {c['gate_tiles_ms_p50']:.3f} ms | {c['gate_tiles_ms_p95']:.3f} ms |",
              f"| lost query: 10 nearest of {c['images']:,} global vectors, their tiles | {c['lost_query_ms_p50']:.0f} ms "
              f"| {c['lost_query_ms_p95']:.0f} ms |", "",
              f"Opening: the tile index {c['open_tile_index_s']:.2f} s, the global index {c['open_global_index_s']:.1f} s "
              f"(once per query process). The query process's peak memory: {c['process_peak_mb']:.0f} MB.",
              *_load_line(result, "city_load_1min", "while timing the city"),
              *(_render_reads(result["reads"]) if result.get("reads") else []),
              *_load_line(result, "reads_load_1min", "while reading", " (the figures are counts, not times)"),
              END]
    return "\n".join(lines)


def _load_line(result: dict, key: str, what: str, tail: str = "") -> list[str]:
    if key not in result:
        return []
    before, after = result[key]
    return ["", f"Load average (1 min) {what}: {before:.1f} before, {after:.1f} after, on {result['cores']} cores{tail}."]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "kitti")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--images", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3, help="rounds of the ingest measurement (medians are quoted)")
    ap.add_argument("--only", action="append", choices=PARTS,
                    help="measure this part only (again for another), keeping the JSON's other figures")
    ap.add_argument("--page", action="store_true", help="only render docs/sharding.md's section from the JSON")
    ap.add_argument("--read-city", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.read_city:
        print(json.dumps(read_city(a.read_city, a.images)))
        return 0
    if not a.page:
        old = json.loads(OUT.read_text()) if OUT.exists() else {}
        result = dict(old)
        parts = a.only or PARTS
        if "ingest" in parts:
            before = load_1min()
            result["ingest"] = measure_ingest(a.root, a.frames, a.repeats)
            result["ingest_load_1min"] = [before, load_1min()]
        if "city" in parts:
            before = load_1min()
            with tempfile.TemporaryDirectory() as tmp:
                result["city"] = measure_city(a.images, Path(tmp) / "city")
            result["city_load_1min"] = [before, load_1min()]
        if "reads" in parts:
            before = load_1min()
            result["reads"] = measure_reads(a.root)
            result["reads_load_1min"] = [before, load_1min()]
        if {"ingest", "city"} <= set(parts):
            result.pop("load_1min_before", None), result.pop("load_1min_after", None)  # measured over both, once
        result["cores"] = os.cpu_count()
        SECTION.write(result)
    SECTION.render_page(render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
