"""A one-file ingest on every core: structure and the self-check in worker processes, against the same steps
in one process (how a one-file ingest built them before), on drive 0001's two gray cameras.

    python benchmarks/ingest_cores.py [--root ../shared/data/kitti] [--drive 2011_09_26_drive_0001] [--rounds 3]
    python benchmarks/ingest_cores.py --page   # its section of docs/performance.md from the JSON

Each round ingests the drive's cameras into a new store twice, in a fresh process each, in an order that
alternates from round to round:

* ``one_process``: SIFT in worker processes (as always), then the global vectors, the structure and the
  self-check of each camera in the ingesting process (``build_structure``/``build_self_check`` without
  workers: what ``ingest_sequence`` did before);
* ``every_core``: ``ingest_sequence`` as the command line runs it (structure and self-check in one worker
  process per core).

Both stores are then compared table by table, row by row (every column but the timings and file paths): the
speed-up must not change a bit of what is stored. Reported: each phase's time, the whole ingest's medians and
the median of the rounds' paired ratios.

Writes docs/results/ingest_cores.json; ``--page`` renders its section of docs/performance.md from it.
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


from measuring import REPO, Section, load_1min  # noqa: E402

SECTION = Section("ingest-cores", "ingest_cores", REPO / "docs" / "performance.md")
OUT, PAGE, BEGIN, END = SECTION.out, SECTION.page, SECTION.begin, SECTION.end

CONFIGS = ("one_process", "every_core")
PHASES = ("sift", "global_vectors", "structure", "self_check")
TIMING_COLUMNS = {"sift_ms", "created_at", "build_ms", "checked_at", "path", "skipped_at"}


def ingest_once(config: str, root: Path, drive: str, cameras: list[str], db: Path, workers: int) -> dict:
    """One ingest of ``cameras`` into the new store ``db`` in this process; seconds per phase and in all."""
    from visloc import PAPER_SIFT, Workspace, open_kitti
    from visloc.store.build import build_global_vectors, build_self_check, build_structure, ingest_sequence

    ws = Workspace(db, create=True)
    phases = {phase: 0.0 for phase in PHASES}
    start = time.perf_counter()
    for camera in cameras:
        seq = open_kitti(root, drive, camera)
        if config == "one_process":
            for phase, step in (("sift", lambda: ws.add_features(seq, PAPER_SIFT, workers=workers)),
                                ("global_vectors", lambda: build_global_vectors(ws, seq.source, seq.camera)),
                                ("structure", lambda: build_structure(ws, seq.source, seq.camera)),
                                ("self_check", lambda: build_self_check(ws, seq.source, seq.camera))):
                t = time.perf_counter()
                step()
                phases[phase] += time.perf_counter() - t
        else:
            marks: dict[str, list[float]] = {phase: [] for phase in PHASES}

            def mark(phase: str):
                return lambda done, total: marks[phase].append(time.perf_counter())

            t = time.perf_counter()
            ingest_sequence(ws, seq, PAPER_SIFT, workers=workers, progress=mark("sift"),
                            vectors_progress=mark("global_vectors"), structure_progress=mark("structure"),
                            self_check_progress=mark("self_check"))
            # a phase runs from its first report (its start) to the next phase's first report
            starts = [t] + [marks[p][0] if marks[p] else None for p in PHASES[1:]] + [time.perf_counter()]
            for k, phase in enumerate(PHASES):
                begin = starts[k]
                end = next(s for s in starts[k + 1:] if s is not None)
                phases[phase] += end - begin if begin is not None else 0.0
    return {"seconds": time.perf_counter() - start, "phases_s": phases}


def table_rows(store: Path) -> dict[str, list]:
    """What a store holds, row by row, without the columns that say when, how fast or from which path."""
    conn = sqlite3.connect(store)
    tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
    out = {}
    for table in tables:
        columns = [r[1] for r in conn.execute(f"PRAGMA table_info({table})") if r[1] not in TIMING_COLUMNS]
        out[table] = sorted(conn.execute(f"SELECT {', '.join(columns)} FROM {table}").fetchall(), key=repr)
    conn.close()
    return out


def measure(root: Path, drive: str, cameras: list[str], rounds: int, workers: int) -> dict:
    runs: dict[str, list[dict]] = {c: [] for c in CONFIGS}
    identical = []
    load = [load_1min()]
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            order = CONFIGS if r % 2 == 0 else CONFIGS[::-1]
            stores = {}
            for config in order:
                stores[config] = Path(tmp) / f"{config}_{r}.sqlite"
                out = subprocess.run([sys.executable, __file__, "--run", config, "--root", str(root), "--drive", drive,
                                      "--cameras", ",".join(cameras), "--db", str(stores[config]),
                                      "--workers", str(workers)], capture_output=True, text=True, check=True)
                runs[config].append(json.loads(out.stdout.strip().splitlines()[-1]))
                print(f"round {r + 1}: {config} {runs[config][-1]['seconds']:.1f} s", file=sys.stderr)
            a, b = (table_rows(stores[c]) for c in CONFIGS)
            identical.append(a == b)
            for path in stores.values():
                path.unlink()
    load.append(load_1min())
    seconds = {c: [run["seconds"] for run in runs[c]] for c in CONFIGS}
    ratios = [one / every for one, every in zip(seconds["one_process"], seconds["every_core"])]
    return {
        "drive": drive, "cameras": cameras, "rounds": rounds, "workers": workers, "cpu_count": os.cpu_count(),
        "load_1min_start_end": load, "runs": runs,
        "median_s": {c: statistics.median(seconds[c]) for c in CONFIGS},
        "median_phase_s": {c: {p: statistics.median(run["phases_s"][p] for run in runs[c]) for p in PHASES}
                           for c in CONFIGS},
        "median_speedup": statistics.median(ratios), "speedups": ratios,
        "identical_stores": all(identical), "identical_per_round": identical,
    }


def render(result: dict) -> str:
    names = {"one_process": "structure and self-check in one process (before)",
             "every_core": "structure and self-check on every core (now)"}
    rows = "\n".join(
        f"| {names[c]} | " + " | ".join(f"{result['median_phase_s'][c][p]:.0f}" for p in PHASES)
        + f" | {result['median_s'][c]:.0f} |" for c in CONFIGS)
    same = ("identical, table by table and row by row (timings and paths aside), in every round"
            if result["identical_stores"] else "NOT identical: see identical_per_round in the JSON")
    ratios = ", ".join(f"{r:.2f}" for r in result["speedups"])
    return f"""{BEGIN}
A one-file ingest builds each camera's structure and self-check in one worker process per core, as a sharded
ingest does on its cluster. Measured by `python benchmarks/ingest_cores.py --rounds {result['rounds']}`: drive
{result['drive']}, cameras {', '.join(result['cameras'])} ({result['workers']} workers on {result['cpu_count']}
cores), each configuration in a fresh process into a new store, in alternating order (medians, seconds; load
{result['load_1min_start_end'][0]:.1f} at the start, {result['load_1min_start_end'][1]:.1f} at the end):

| ingest | SIFT | global vectors | structure | self-check | whole ingest |
|---|---|---|---|---|---|
{rows}

The whole ingest is **{result['median_speedup']:.2f}×** faster (median of the rounds' paired ratios: {ratios}).
The two stores are {same}.
{END}"""



def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, default=None, help="KITTI raw root (default: the shared data)")
    parser.add_argument("--drive", default="2011_09_26_drive_0001", help="drive (default %(default)s)")
    parser.add_argument("--cameras", default="image_00,image_01", help="cameras (default %(default)s)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of both configurations (default %(default)s)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="worker processes (default: cores)")
    parser.add_argument("--page", action="store_true", help="render docs/performance.md's section from the JSON")
    parser.add_argument("--run", choices=CONFIGS, help=argparse.SUPPRESS)  # one ingest, in a fresh process
    parser.add_argument("--db", type=Path, help=argparse.SUPPRESS)
    a = parser.parse_args()
    if a.page:
        SECTION.render_page(render)
        return 0
    from visloc import default_data_root

    root = a.root or default_data_root()
    cameras = a.cameras.split(",")
    if a.run:
        print(json.dumps(ingest_once(a.run, root, a.drive, cameras, a.db, a.workers)))
        return 0
    result = measure(root, a.drive, cameras, a.rounds, a.workers)
    SECTION.write(result)
    print(render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
