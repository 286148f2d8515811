"""The README's bring-your-own-drive walk-through, run exactly as written: the fenced block after
its marker goes to bash from the checkout's root, as a user pastes it, and the dashboard it ends
with is opened in headless Chromium.

It writes into ``out/byod/`` of the checkout (its paths are the README's), removed first. Only
the data root changes, and only when ``VISLOC_DATA`` points elsewhere than the README's
``../shared/data/kitti``.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import threading

import geojson
import pytest
from helpers import control, dismiss_webgl_notice, new_page, run_number, screenshot, wait_for

from conftest import REPO

pytestmark = [pytest.mark.kitti, pytest.mark.slow, pytest.mark.browser]

MARKER = "<!-- the walk-through: tests/test_walkthrough.py runs this block as it is -->"
README_ROOT = "../shared/data/kitti"
OUT = REPO / "out" / "byod"
URL_LINE = re.compile(r"visloc dashboard: (http://\S+)")
WALK_S = 3600  # everything before the dashboard: two CSV drives, an ingest, a series, an evaluation


def walkthrough_block() -> str:
    readme = (REPO / "README.md").read_text()
    assert MARKER in readme, "the README lost its walk-through marker"
    after = readme.split(MARKER, 1)[1]
    assert after.lstrip().startswith("```bash\n")
    return after.split("```bash\n", 1)[1].split("```", 1)[0]


def test_the_readme_walkthrough_runs_as_written(kitti_root, browser):
    script = walkthrough_block()
    commands = [line for line in script.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert commands[-1].startswith("visloc dashboard"), "the walk-through ends by opening the dashboard"
    if kitti_root.resolve() != (REPO / README_ROOT).resolve():
        script = script.replace(README_ROOT, str(kitti_root))
    shutil.rmtree(OUT, ignore_errors=True)
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", script], cwd=REPO, stdout=subprocess.PIPE,
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
        series = geojson.loads((OUT / "series_40.geojson").read_text())
        assert series.is_valid, series.errors()
        kinds = {f["properties"]["kind"] for f in series["features"]}
        assert {"truth track", "measurement track", "estimate track", "estimate"} <= kinds
        assert len([f for f in series["features"] if f["properties"]["kind"] == "estimate"]) == 6
        evaluation = json.loads((OUT / "evaluation.json").read_text())
        assert evaluation["n_series"] == len(evaluation["series"]) == 3
        rows = list(csv.DictReader((OUT / "evaluation.csv").open()))
        assert len(rows) == sum(len(s) for s in evaluation["series"])
        assert "1.85" not in log  # the paper's figure for its own drive is not a comparison for this one
        # the dashboard shows the query drive against the database drive and fills in a run
        url = URL_LINE.search(log).group(1)
        page = new_page(browser)
        try:
            page.goto(url)
            page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()
            wait_for(lambda: run_number(page) > 0, 600, "the first run to be ready")
            page.get_by_text("Data", exact=True).click()
            assert control(page, "Database").locator("input").first.input_value() == "database/camera"
            queries = page.get_by_text("Queries", exact=True).last  # the Data fold's, after the fold named so
            assert queries.locator("xpath=../../..").locator("input").first.input_value() == "queries/camera"
            dismiss_webgl_notice(page)
            screenshot(page, "walkthrough_dashboard.png")
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
