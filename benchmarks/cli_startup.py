"""How soon the command line answers: ``visloc --help``, a command's help, ``--version`` and a refused argument,
against a bare Python interpreter, and a command that opens a store for comparison.

    python benchmarks/cli_startup.py [--rounds 20]
    python benchmarks/cli_startup.py --page   # its section of docs/performance.md from the JSON

Each round runs every command once, in a fresh process, in an order rotated by one each round (so that none
always runs first); each command's wall time is measured from outside (start to exit). Reported: medians, and
the median of each round's ratio to the bare interpreter (``python -c pass``) of the same round.

Writes docs/results/cli_startup.json; ``--page`` renders its section of docs/performance.md from it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


from measuring import REPO, Section, load_1min  # noqa: E402

SECTION = Section("cli-startup", "cli_startup", REPO / "docs" / "performance.md")
OUT, PAGE, BEGIN, END = SECTION.out, SECTION.page, SECTION.begin, SECTION.end

BARE = "python -c pass"


def commands(visloc: str, folder: Path) -> dict[str, list[str]]:
    """What a user types (the installed ``visloc`` command), by the label the page shows."""
    return {
        BARE: [sys.executable, "-c", "pass"],
        "visloc --help": [visloc, "--help"],
        "visloc localize --help": [visloc, "localize", "--help"],
        "visloc --version": [visloc, "--version"],
        "visloc localize x.csv --tau1 1.5 (refused)": [visloc, "localize", "x.csv", "--tau1", "1.5"],
        "visloc info --db missing.sqlite (opens a store)": [visloc, "info", "--db", str(folder / "missing.sqlite")],
    }


def measure(rounds: int) -> dict:
    visloc = str(Path(sys.executable).parent / "visloc")
    with tempfile.TemporaryDirectory() as tmp:
        cmds = commands(visloc, Path(tmp))
        labels = list(cmds)
        times: dict[str, list[float]] = {label: [] for label in labels}
        load = [load_1min()]
        for r in range(rounds + 1):  # the first round warms the file cache and is not counted
            order = labels[r % len(labels):] + labels[: r % len(labels)]
            for label in order:
                start = time.perf_counter()
                subprocess.run(cmds[label], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp)
                if r:
                    times[label].append(time.perf_counter() - start)
        load.append(load_1min())
    ratios = {label: [t / b for t, b in zip(times[label], times[BARE])] for label in labels}
    return {
        "rounds": rounds, "python": sys.version.split()[0], "cpu_count": os.cpu_count(),
        "load_1min_start_end": load,
        "commands": {label: {"median_ms": 1000 * statistics.median(times[label]),
                             "min_ms": 1000 * min(times[label]), "max_ms": 1000 * max(times[label]),
                             "median_ratio_to_bare": statistics.median(ratios[label])} for label in labels},
    }


def render(result: dict) -> str:
    rows = "\n".join(f"| `{label}` | {c['median_ms']:.0f} | {c['min_ms']:.0f}-{c['max_ms']:.0f} | "
                     f"{c['median_ratio_to_bare']:.1f}× |" for label, c in result["commands"].items())
    help_ratio = result["commands"]["visloc --help"]["median_ratio_to_bare"]
    store = result["commands"]["visloc info --db missing.sqlite (opens a store)"]["median_ratio_to_bare"]
    return f"""{BEGIN}
The command line answers its help, `--version` and an argument it refuses without loading OpenCV, numpy, faiss,
viser or the store: those load once a command runs. Measured by `python benchmarks/cli_startup.py --rounds
{result['rounds']}` (each command in a fresh process, wall time from outside; medians over the rounds, and the
median of each round's ratio to a bare interpreter in the same round; load {result['load_1min_start_end'][0]:.1f}
at the start, {result['load_1min_start_end'][1]:.1f} at the end):

| command | median (ms) | range (ms) | against `python -c pass` |
|---|---|---|---|
{rows}

`visloc --help` takes {help_ratio:.1f}× a bare interpreter; a command that opens a store takes {store:.1f}×, most of it
importing the pipeline it is about to run.
{END}"""



def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=20, help="counted rounds (default %(default)s)")
    parser.add_argument("--page", action="store_true", help="render docs/performance.md's section from the JSON")
    a = parser.parse_args()
    if a.page:
        SECTION.render_page(render)
        return 0
    result = measure(a.rounds)
    SECTION.write(result)
    print(render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
