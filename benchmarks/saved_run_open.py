"""How long a saved run takes to open in the dashboard (``visloc dashboard --run FILE``), measured.

    python benchmarks/saved_run_open.py [--results out/results]
    python benchmarks/saved_run_open.py --page    # the performance page from docs/results/saved_run_open.json

For every run file the results hold (``track_*.json`` and each drive's ``evaluate`` JSON named in
``drives.json``), medians of 5 in this process: reading it (``visloc.load_run``) and the viewer's
first screen on a viser server (its first series and first step drawn: tracks, ellipses, grid,
timelines, tables), then the command itself: from starting ``visloc dashboard --run FILE`` to the
URL it prints (Python and its libraries starting included; the page is served from then on), median
of 3. Writes docs/results/saved_run_open.json; ``--page`` renders its section of docs/performance.md from it.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


import viser  # noqa: E402

import visloc  # noqa: E402
from measuring import REPO, Section, median_s  # noqa: E402

SECTION = Section("saved-run-open", "saved_run_open", REPO / "docs" / "performance.md")
OUT, PAGE, BEGIN, END = SECTION.out, SECTION.page, SECTION.begin, SECTION.end
from visloc.dashboard.runview import RunViewer  # noqa: E402

URL = re.compile(r"visloc dashboard: http://\S+")


def run_paths(results: Path) -> list[Path]:
    tracks = sorted(results.glob("track_*.json"))
    drives = results / "drives.json"
    evaluations = [p for _, p in visloc.run_files(drives)] if drives.exists() else []
    return tracks + evaluations



def command_to_url_s(path: Path, port: int) -> float:
    """Seconds from starting ``visloc dashboard --run path`` to the URL it prints."""
    start = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "visloc", "dashboard", "--run", str(path), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        for line in proc.stdout:
            if URL.search(line):
                return time.perf_counter() - start
        raise SystemExit(f"visloc dashboard --run {path}: printed no URL (exit {proc.wait()})")
    finally:
        proc.terminate()
        proc.wait(30)


def measure(results: Path) -> dict:
    server = viser.ViserServer(port=8697, verbose=False)
    runs = []
    try:
        for path in run_paths(results):
            run = visloc.load_run(path)
            load_s = median_s(lambda: visloc.load_run(path), 5)

            def first_screen():
                RunViewer(server, [(path.stem, path)]).close()

            first_screen_s = median_s(first_screen, 5)
            to_url_s = float(np.median([command_to_url_s(path, 8698) for _ in range(3)]))
            runs.append({"file": os.path.relpath(path, REPO), "kind": run.kind, "steps": run.n_steps,
                         "series": len(run.series), "megabytes": path.stat().st_size / 1e6, "load_s": load_s,
                         "first_screen_s": first_screen_s, "command_to_url_s": to_url_s})
            print(f"{path.name}: load {load_s:.2f} s, first screen {first_screen_s:.2f} s, command to URL "
                  f"{to_url_s:.1f} s", file=sys.stderr)
    finally:
        server.stop()
    shown = os.path.relpath(results, REPO) if results.resolve().is_relative_to(REPO) else str(results)
    return {"command": f"python benchmarks/saved_run_open.py --results {shown}", "runs": runs}


def render(result: dict) -> str:
    rows = ["| run file | steps (series) | size (MB) | read (s) | first screen drawn (s) | command to URL (s) |",
            "|---|---|---|---|---|---|"]
    for r in result["runs"]:
        rows.append(f"| {Path(r['file']).name} | {r['steps']} ({r['series']}) | {r['megabytes']:.1f} | "
                    f"{r['load_s']:.2f} | {r['first_screen_s']:.2f} | {r['command_to_url_s']:.1f} |")
    tracks = [r for r in result["runs"] if r["kind"] == "track"]
    worst_track = max((r["command_to_url_s"] + r["first_screen_s"] for r in tracks), default=float("nan"))
    return "\n".join([
        BEGIN,
        f"Opening a saved run (`visloc dashboard --run FILE`), measured by `{result['command']}` (medians, this "
        "machine): reading the file, drawing the first screen (the first series, its first step, the timelines and "
        "tables), and the command from its start to the URL it prints (Python and its libraries starting):",
        "",
        *rows,
        "",
        f"A `track` run of every frame of a drive is on screen at most {worst_track:.1f} s after the command starts "
        "(command to URL, then the first screen).",
        END,
    ])



def main() -> int:
    def arguments(parser):
        parser.add_argument("--results", type=Path, default=REPO / "out" / "results")

    return SECTION.main(__doc__, lambda a: measure(a.results), render, arguments)


if __name__ == "__main__":
    sys.exit(main())
