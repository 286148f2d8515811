"""The README's pictures of the dashboard, taken in headless Chromium from the real runs.

    python scripts/dashboard_screenshots.py [--results out/results]

Opens ``visloc dashboard --run`` on drive 0001's refined evaluation compared with its paper evaluation (the
files ``python scripts/results.py run`` writes), and saves into docs/images/: the whole drive with the Runs tab,
and the worst step of the first series zoomed to its ellipse (drawn ×100) with the timelines. Then the live
page on the results' store (``visloc dashboard --db``), in the refined mode, followed to a step with its
ellipse magnified. Needs Debian's chromium (``bash scripts/install_chromium.sh``).
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


def live(browser, store: Path) -> None:
    """The live page in the refined mode at step 5, followed, its ellipses magnified, with the step's numbers."""
    proc = DashboardProcess("--db", str(store), "--port", "8711")
    try:
        page = new_page(browser)
        page.goto(proc.url)
        page.get_by_text(re.compile(r"^Ready \(run 1,")).first.wait_for()
        dismiss_webgl_notice(page)
        choose(page, "Mode", "refined")
        page.get_by_text(re.compile(r"^Ready \(run 2, refined")).first.wait_for(timeout=600_000)
        box = control(page, "Step").locator("input:not([type=hidden])")
        box.fill("5")
        box.press("Enter")
        page.get_by_text("Step 5 of 11", exact=True).wait_for()
        page.get_by_text("3D view layers", exact=True).click()
        choose(page, "Ellipses drawn", "×100")
        control(page, "Camera follows").locator("input").first.check()
        page.mouse.move(400, 850)  # no control's hint over the picture
        settled(page.locator("canvas").first, "the view on step 5")
        page.screenshot(path=str(IMAGES / "live_refined_step.jpg"), type="jpeg", quality=80)
        page.close()
    finally:
        proc.stop()


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
            live(browser, a.results / "visloc.sqlite")
            browser.close()
    finally:
        proc.stop()
    for name in ("saved_runs_compared.jpg", "saved_run_worst_step.jpg", "live_refined_step.jpg"):
        print(f"wrote {IMAGES / name}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
