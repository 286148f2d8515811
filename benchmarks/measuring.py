"""What every measuring script in ``benchmarks/`` shares: the repository (and its engine, first on the path),
the machine's load, the JSON a script writes and the docs section it renders from that JSON.

A script measures, writes ``docs/results/NAME.json`` and renders its section of a docs page between two HTML
comments; ``--page`` renders again from the JSON alone, so a page cannot drift from what was measured:

    from measuring import REPO, Section, load_1min

    SECTION = Section("track-following", "track_following", REPO / "docs" / "performance.md")
    ...
    SECTION.main(__doc__, measure, render)      # or the pieces: SECTION.write(result), SECTION.render_page(render)
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))  # the engine of this checkout, whatever is installed


def commit() -> str:
    """The checkout's commit, short: what a result was measured at."""
    import subprocess

    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()


def run_once(args: list, log: Path, made: Path, label: str) -> None:
    """Run ``args`` in the repository, its output appended to ``log``, unless ``made`` (what it writes) exists:
    an interrupted measurement goes on where it stopped."""
    import subprocess

    if made.is_file():
        print(f"{label}: already measured:", made.relative_to(REPO) if made.is_relative_to(REPO) else made,
              flush=True)
        return
    print(f"{label}:", " ".join(map(str, args)), flush=True)
    with log.open("a") as f:
        subprocess.run(list(map(str, args)), cwd=REPO, check=True, stdout=f, stderr=subprocess.STDOUT,
                       stdin=subprocess.DEVNULL)


def load_1min() -> float:
    """The machine's load average over the last minute (2 cores here: above 2, runs queue)."""
    return os.getloadavg()[0]


def load_line(result: dict) -> str:
    """The footer of a section: the load average before and after the measuring run (``load_1min_before``,
    ``load_1min_after`` of its JSON)."""
    return (f"Load average (1 min) {result['load_1min_before']:.1f} before, {result['load_1min_after']:.1f} after; "
            "2 cores.")


def drives_and_store_arguments(parser: argparse.ArgumentParser, root_flag: str = "--root") -> None:
    """``root_flag`` (the KITTI raw root, default the shared data) and ``--db`` (the results' store)."""
    parser.add_argument(root_flag, type=Path, default=REPO.parent / "shared" / "data" / "kitti")
    parser.add_argument("--db", type=Path, default=REPO / "out" / "results" / "visloc.sqlite",
                        help="a store holding every drive's cameras (default scripts/results.py's, "
                             "out/results/visloc.sqlite)")


def track_run(root: Path, drive: str, db: Path, flags: list[str], out: Path) -> dict:
    """``visloc track`` on every frame of ``drive``'s image_00 against its own image_00 in ``db`` with the 1 s
    exclusion window (the evaluation protocol) and ``flags``: its JSON (written to ``out``)."""
    import subprocess

    cmd = [sys.executable, "-m", "visloc", "track", str(root), "--drive", drive, "--camera", "image_00",
           "--db-camera", "image_00", "--db", str(db), "--exclusion-s", "1", *flags, "--json", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(Path(out).read_text())


def median_s(fn: Callable[[], object], repeats: int = 1) -> float:
    """The median wall time of ``repeats`` calls of ``fn``, s."""
    import statistics
    import time

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(statistics.median(times))


def replace_section(page: Path, begin: str, end: str, text: str) -> str:
    """``page``'s text with the section from ``begin`` to ``end`` replaced by ``text`` (which carries both)."""
    content = page.read_text()
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.DOTALL)
    if not pattern.search(content):
        raise SystemExit(f"{page}: no section between {begin} and {end}")
    return pattern.sub(lambda _: text, content)


@dataclass(frozen=True)
class Section:
    """A measuring script's JSON (``docs/results/<script>.json``) and its section ``marker`` of ``page``."""

    marker: str
    script: str
    page: Path

    @property
    def out(self) -> Path:
        return REPO / "docs" / "results" / f"{self.script}.json"

    @property
    def begin(self) -> str:
        return f"<!-- {self.marker}: begin (python benchmarks/{self.script}.py --page) -->"

    @property
    def end(self) -> str:
        return f"<!-- {self.marker}: end -->"

    def write(self, result: dict) -> None:
        self.out.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {self.out.relative_to(REPO)}")

    def updated_page(self, rendered: str) -> str:
        """The page's text with this section replaced by ``rendered`` (which carries its markers)."""
        return replace_section(self.page, self.begin, self.end, rendered)

    def render_page(self, render: Callable[[dict], str]) -> None:
        """Render the section from the JSON into the page."""
        self.page.write_text(self.updated_page(render(json.loads(self.out.read_text()))))
        print(f"rendered {self.page.relative_to(REPO)}")

    def main(self, doc: str, measure: Callable[[argparse.Namespace], dict], render: Callable[[dict], str],
             add_arguments: Callable[[argparse.ArgumentParser], None] | None = None) -> int:
        """The usual command line: measure (with the script's own arguments), write the JSON, render the
        page; ``--page``: only render the page from the JSON."""
        parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
        if add_arguments is not None:
            add_arguments(parser)
        parser.add_argument("--page", action="store_true", help=f"only render its section of "
                                                                f"{self.page.relative_to(REPO)} from the JSON")
        a = parser.parse_args()
        if not a.page:
            self.write(measure(a))
        self.render_page(render)
        return 0
