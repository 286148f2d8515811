"""Time a newcomer's first run: ``bash scripts/main.sh`` in a fresh clone, from nothing to a usable
dashboard.

    .venv/bin/python benchmarks/first_screen.py [--json out/first_screen.json] [--port 8090]

Clones this checkout's HEAD into a temporary folder (with ``../shared`` linked beside it, as on
a fresh machine), runs ``scripts/main.sh`` there with its output going to a log file, not a
terminal, and records the seconds from the start to: setup done, each progress line, the
dashboard's URL, the page showing its first step, the page's first run complete, and the
evaluation written. Uses this checkout's chromium (``scripts/install_chromium.sh``). Stops main.sh
with SIGINT at the end, as Ctrl-C does, and writes every time as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from measuring import REPO, load_1min  # noqa: E402

CHROMIUM = Path("/usr/bin/chromium")
URL_LINE = re.compile(r"visloc dashboard: (http://\S+)")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=Path, default=REPO / "out" / "first_screen.json")
    p.add_argument("--port", type=int, default=8090)
    p.add_argument("--limit-s", type=float, default=3600, help="give up after this long")
    a = p.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="visloc-first-") as tmp:
        clone = Path(tmp) / "visloc"
        subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        os.symlink(REPO.parent / "shared", Path(tmp) / "shared")
        log_path = Path(tmp) / "main.log"
        start = time.monotonic()
        events: list[tuple[float, str]] = []
        with open(log_path, "w") as log:
            proc = subprocess.Popen(["bash", "scripts/main.sh"], cwd=clone, stdout=log, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True,
                                    env={**os.environ, "VISLOC_PORT": str(a.port), "PYTHONUNBUFFERED": "1"})
        seen = 0
        url = None
        done = threading.Event()

        def follow() -> None:  # the log, line by line, as `tail -f` shows it
            nonlocal seen, url
            while not done.is_set():
                lines = log_path.read_text(errors="replace").splitlines()
                for line in lines[seen:]:
                    events.append((time.monotonic() - start, line))
                    m = URL_LINE.search(line)
                    if m and url is None:
                        url = m.group(1)
                seen = len(lines)
                time.sleep(0.5)

        threading.Thread(target=follow, daemon=True).start()

        def wait(predicate, what: str) -> float:
            while not predicate():
                if proc.poll() is not None:
                    raise SystemExit(f"main.sh ended (exit {proc.returncode}) before {what}:\n{log_path.read_text()}")
                if time.monotonic() - start > a.limit_s:
                    raise SystemExit(f"no {what} after {a.limit_s:.0f} s")
                time.sleep(0.5)
            return time.monotonic() - start

        times: dict[str, float | None] = {}
        try:
            times["setup_s"] = wait(lambda: any("setup: .venv ready" in e[1] for e in events), "setup")
            times["url_s"] = wait(lambda: url is not None, "dashboard URL")
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True,
                                             args=["--no-sandbox", "--use-angle=swiftshader",
                                                   "--enable-unsafe-swiftshader"])
                page = browser.new_page(viewport={"width": 1400, "height": 900})
                page.set_default_timeout(a.limit_s * 1000)
                page.goto(url)
                page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()
                times["page_s"] = time.monotonic() - start
                page.get_by_text(re.compile(r"^Step 1 of \d+$")).first.wait_for()
                times["first_step_s"] = time.monotonic() - start
                page.locator("text=/^Ready \\(run 1,/").first.wait_for()
                times["first_run_s"] = time.monotonic() - start
                page.screenshot(path=str(REPO / "out" / "first_screen.png"))
                browser.close()
            times["evaluation_s"] = wait(lambda: any(e[1].startswith("main: evaluation written") for e in events),
                                         "the evaluation")
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
                proc.wait(120)
            done.set()
        load = load_1min()
        report = {"times_s": times, "load_1min_end": load, "cores": os.cpu_count(),
                  "log": [{"t_s": round(t, 1), "line": line} for t, line in events]}
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(report, indent=1))
        print(json.dumps(times, indent=1))
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
