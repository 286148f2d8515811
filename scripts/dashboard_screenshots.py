"""The README's pictures of the dashboard's saved-run viewer, taken in headless Chromium from the real runs.

    python scripts/dashboard_screenshots.py [--results out/results]

Opens ``visloc dashboard --run`` on drive 0001's refined evaluation compared with its paper evaluation (the
files ``python scripts/results.py run`` writes), and saves into docs/images/: the whole drive with the Runs tab,
and the worst step of the first series zoomed to its ellipse (drawn ×100) with the timelines.
Needs Debian's chromium (``bash scripts/install_chromium.sh``).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

from helpers import DashboardProcess, choose, control, dismiss_webgl_notice, new_page, settled  # noqa: E402

import visloc  # noqa: E402
from visloc.dashboard import runpanels  # noqa: E402

IMAGES = REPO / "docs" / "images"
CHROMIUM = "/usr/bin/chromium"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=REPO / "out" / "results")
    a = parser.parse_args()
    refined = a.results / "2011_09_26_drive_0001_stereo_refined.json"
    paper = a.results / "2011_09_26_drive_0001_stereo_paper.json"
    for path in (refined, paper):
        if not path.is_file():
            raise SystemExit(f"{path}: missing (python scripts/results.py run writes it)")
    from playwright.sync_api import sync_playwright

    IMAGES.mkdir(parents=True, exist_ok=True)
    proc = DashboardProcess("--run", str(refined), "--run", str(paper), "--port", "8710")
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                                        args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = new_page(browser)
            page.goto(proc.url)
            page.get_by_text(re.compile(r"steps in \d+ series; compared with")).first.wait_for()
            dismiss_webgl_notice(page)
            canvas = page.locator("canvas").first
            page.get_by_role("tab", name="Runs").click()
            page.get_by_text("Parameters that differ", exact=True).wait_for()
            settled(canvas, "the whole drive")
            page.screenshot(path=str(IMAGES / "saved_runs_compared.jpg"), type="jpeg", quality=80)
            series = visloc.load_run(refined).series[0]
            worst = runpanels.jump_choices(series)[0]
            choose(page, "Jump to", worst)
            choose(page, "Ellipses drawn", "×100")
            control(page, "Camera follows").locator("input").first.check()
            page.get_by_role("tab", name="Timelines").click()
            page.get_by_text("Error per step (m) and the estimate's 2σ", exact=True).wait_for()
            settled(canvas, "the view on the worst step")
            page.screenshot(path=str(IMAGES / "saved_run_worst_step.jpg"), type="jpeg", quality=80)
            browser.close()
    finally:
        proc.stop()
    for name in ("saved_runs_compared.jpg", "saved_run_worst_step.jpg"):
        print(f"wrote {IMAGES / name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
