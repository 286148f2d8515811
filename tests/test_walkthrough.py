"""The README's bring-your-own-drive walk-through, run exactly as written: the fenced block after
its marker goes to bash from the checkout's root, as a user pastes it, and the dashboard it ends
with is opened in headless Chromium.

It runs in a temporary folder that stands for the checkout (its ``.venv`` and ``scripts`` linked
in), so the README's paths (``out/byod/...``) are the temporary folder's and a user's own results
in the checkout's ``out/byod/`` are never touched. Only the data root changes: the README's
``../shared/data/kitti`` becomes the drive folder the tests use, by its absolute path.
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import threading

import geojson
import pytest
from helpers import control, dismiss_webgl_notice, new_page, read_back_mcap, run_number, visit, wait_for

from helpers import REPO

pytestmark = [pytest.mark.slow, pytest.mark.longest]

MARKER = "<!-- the walk-through: tests/test_walkthrough.py runs this block as it is -->"
README_ROOT = "../shared/data/kitti"
URL_LINE = re.compile(r"visloc dashboard: (http://\S+)")
WALK_S = 3600  # everything before the dashboard: a log, an ingest, a series, an evaluation


def walkthrough_block() -> str:
    readme = (REPO / "README.md").read_text()
    assert MARKER in readme, "the README lost its walk-through marker"
    after = readme.split(MARKER, 1)[1]
    assert after.lstrip().startswith("```bash\n")
    return after.split("```bash\n", 1)[1].split("```", 1)[0]


def checkout_stand_in(folder):
    """A folder where the README's commands run as in the checkout: its .venv and scripts linked in."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in (".venv", "scripts"):
        (folder / name).symlink_to(REPO / name, target_is_directory=True)
    return folder


def test_the_readme_walkthrough_runs_as_written(kitti_root, browser, tmp_path):
    script = walkthrough_block()
    commands = [line for line in script.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert commands[-1].startswith("visloc dashboard"), "the walk-through ends by opening the dashboard"
    script = script.replace(README_ROOT, str(kitti_root.resolve()))
    here = checkout_stand_in(tmp_path / "checkout")
    user_results = REPO / "out" / "byod"
    before = sorted(p.relative_to(user_results) for p in user_results.rglob("*")) if user_results.exists() else None
    out = here / "out" / "byod"
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=here, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    output: list[str] = []
    found = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            output.append(line)
            if URL_LINE.search(line):
                found.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        wait_for(lambda: found.is_set() or proc.poll() is not None, WALK_S, "the walk-through's dashboard URL")
        log = "".join(output)
        assert found.is_set(), f"the walk-through stopped (exit {proc.returncode}) before the dashboard:\n{log}"
        # what the commands before the dashboard wrote
        series = geojson.loads((out / "series_0.geojson").read_text())
        assert series.is_valid, series.errors()
        kinds = {f["properties"]["kind"] for f in series["features"]}
        assert {"truth track", "measurement track", "estimate track", "estimate"} <= kinds
        assert len([f for f in series["features"] if f["properties"]["kind"] == "estimate"]) == 3
        evaluation = json.loads((out / "evaluation.json").read_text())
        assert evaluation["n_series"] == len(evaluation["series"]) == 2
        rows = list(csv.DictReader((out / "evaluation.csv").open()))
        assert len(rows) == sum(len(s) for s in evaluation["series"])
        read_back_mcap(out / "evaluation.mcap", [{**step, "series": k} for k, s in enumerate(evaluation["series"])
                                                 for step in s], images=False)
        assert "/kitti/image_00/image_raw: sensor_msgs/Image, 21 messages" in log  # visloc info on the log
        # the paper's figures for its own drive are not a comparison for this one (a figure of this run may read 1.85)
        assert "the paper on this drive" not in log and "final estimate 1.85 m" not in log
        # the dashboard shows the query drive against the database drive and fills in a run
        url = URL_LINE.search(log).group(1)
        page = new_page(browser)
        try:
            visit(page, url)
            page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()
            wait_for(lambda: run_number(page) > 0, 600, "the first run to be ready")
            page.get_by_text("Step 1 of 3", exact=True).wait_for()  # one query a second over the 21 frames
            page.get_by_text("Data", exact=True).click()
            assert control(page, "Database").locator("input").first.input_value() == "drive/image_01"
            queries = page.get_by_text("Queries", exact=True).last  # the Data fold's, after the fold named so
            assert queries.locator("xpath=../../..").locator("input").first.input_value() == "drive/image_00"
            dismiss_webgl_notice(page)
            page.screenshot(path=str(tmp_path / "walkthrough_dashboard.png"))
        finally:
            page.close()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, as the README says
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    after = sorted(p.relative_to(user_results) for p in user_results.rglob("*")) if user_results.exists() else None
    assert after == before, "the walk-through touched the checkout's out/byod/"
