"""The dashboard as a person uses it: ``visloc dashboard`` in a subprocess, driven in headless
Chromium (Debian's, through playwright's ``executable_path``) on the real KITTI drive.

Screenshots go to ``out/screenshots/`` in the checkout, to be looked at.

Machines running these tests are shared and busy (load 5-10 on 2 cores), so every wait is for a
condition, with a generous timeout: ``SERVER_WORK_S`` where the server has work to do, and the
pages' default timeout for playwright's own waits and actions. The helpers that drive the page
(``DashboardProcess``, ``open_page``, ``control`` ...) are in tests/helpers.py, shared with the
other browser tests.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

import visloc
from helpers import KITTI_DRIVE, one_line_error, run_cli
from helpers import (
    RUN_S,
    SERVER_WORK_S,
    DashboardProcess,
    choose,
    control,
    dismiss_webgl_notice,
    go_to_step,
    new_page,
    open_other_store,
    open_page,
    reset,
    row,
    run_number,
    screenshot,
    settled,
    status_text,
    visit,
    wait_for,
)

# the page's runs start later than the drive for the costly ones, each at a frame the evaluation counted (frames 0, 10,
# ..., 100 from 0 s at one query a second): the paper's run from there reads its counts from the store
CAMERA_RATE_START_S = 8.2  # frame 80 on: every frame of the last three seconds, at the camera's rate
LAST_FOUR_START_S = 7.2  # frame 70 on: the drive's last four queries at one a second (the τ1 re-match, the run
# with no exclusion, the refined run: the page's costliest)


@pytest.fixture(scope="module")
def dashboard(kitti_evaluation):
    """The dashboard on the store the KITTI evaluation built (features + cached counts)."""
    tmp, _, _ = kitti_evaluation
    proc = DashboardProcess("--db", str(tmp / "kitti.sqlite"), "--port", "8340")
    yield proc
    proc.stop()


def figure(page):
    """The step's picture (Figure 3) in the panel."""
    return page.get_by_text("query (top) and best match (bottom)", exact=True).locator("xpath=..").locator("img")


def wait_for_step_figure(page, previous_src: str | None = None) -> str:
    """Wait until the panel shows a step's picture (not the short placeholder), a new one when
    ``previous_src`` is given; returns its src. The 3D frustums are sent right after it."""
    def shown():
        img = figure(page)
        if not img.count():
            return None
        src, height = img.first.evaluate("e => [e.currentSrc || e.src, e.complete ? e.naturalHeight : 0]")
        return src if height > 120 and src != previous_src else None

    return wait_for(shown, SERVER_WORK_S, "the step's picture")


@pytest.mark.slow
def test_page_loads_with_its_controls_and_panels(dashboard, browser):
    page = open_page(browser, dashboard.url)
    try:
        dismiss_webgl_notice(page)
        for label in ("Step", "Play", "Speed", "τ1 (Lowe ratio)", "τ2 (cosine)", "R: meas. σ (m)",
                      "Q: accel. σ (m/s²)", "P0: initial σ (m, m/s)", "Query rate (Hz)", "Start time (s)", "Exclusion (s)"):
            assert page.get_by_text(label, exact=True).count() >= 1, label
        assert page.get_by_text("Step 1 of 11", exact=True).is_visible()  # 1 Hz over the 11 s drive
        assert "image_00 frame 0" in row(page, "query")
        assert re.match(r"image_01 frame \d+ \([+-]\d\.\d\d s\), \d+ correspondences", row(page, "best match"))
        assert row(page, "measurement error").endswith(" m")
        assert status_text(page).startswith("Ready (run 1, paper, τ1 0.8, τ2 0.97): 11 queries of image_00")
        wait_for_step_figure(page)  # the scene's images are sent with it
        settled(page.locator("canvas").first, "the 3D view to show the step's images")
        assert screenshot(page, "dashboard_loaded.png").stat().st_size > 50_000
        assert dashboard.alive()
    finally:
        page.close()


@pytest.mark.slow
def test_scrubbing_moves_the_highlighted_step(dashboard, browser):
    page = open_page(browser, dashboard.url)
    try:
        dismiss_webgl_notice(page)
        go_to_step(page, 0)
        src = wait_for_step_figure(page)
        canvas = page.locator("canvas").first
        before = settled(canvas, "the 3D view at step 1")
        thumb = control(page, "Step").locator("[role=slider]")
        thumb.focus()
        for _ in range(3):
            thumb.press("ArrowRight")
        page.get_by_text("Step 4 of 11", exact=True).wait_for()
        assert "frame 30" in row(page, "query")
        page.get_by_role("button", name="Next ▶").click()
        page.get_by_text("Step 5 of 11", exact=True).wait_for()
        assert "frame 40" in row(page, "query")
        wait_for_step_figure(page, previous_src=src)
        after = settled(canvas, "the 3D view at step 5")
        screenshot(page, "dashboard_step5.png")
        # the highlight, the frustums and their images moved: the 3D view changed
        import cv2

        a = cv2.imdecode(np.frombuffer(before, np.uint8), cv2.IMREAD_GRAYSCALE).astype(int)
        b = cv2.imdecode(np.frombuffer(after, np.uint8), cv2.IMREAD_GRAYSCALE).astype(int)
        assert a.shape == b.shape
        assert np.mean(np.abs(a - b) > 30) > 0.002, "the 3D view did not change when the step moved"
    finally:
        page.close()


@pytest.mark.slow
def test_changing_R_refilters_without_rematching(dashboard, browser):
    page = open_page(browser, dashboard.url)
    try:
        reset(page)
        go_to_step(page, 5)
        status, measurement, estimate = status_text(page), row(page, "measurement error"), row(page, "estimate error")
        box = control(page, "R: meas. σ (m)").locator("input:not([type=hidden])")
        box.fill("2")
        box.press("Enter")
        wait_for(lambda: row(page, "estimate error") != estimate, SERVER_WORK_S, "the estimate to change with R")
        # the measurement (the best match) is the same and no matching run started
        assert row(page, "measurement error") == measurement
        assert status_text(page) == status
        screenshot(page, "dashboard_R_2m.png")
    finally:
        reset(page)
        page.close()


@pytest.mark.slow
def test_moving_tau1_rematches_in_the_background(dashboard, browser):
    """τ1 moved key by key: each run supersedes the one before, the page stays responsive while the last
    one is matched, and the re-match fills in from the first step: a step not matched yet keeps the
    previous run's numbers, marked as such in the step panel, its plot and the map, until the new run gets
    there; the first step shows the new run's numbers as soon as it is matched. (One re-match serves
    every check: matching the drive's queries again is the costliest thing the page does, so the run starts at
    ``LAST_FOUR_START_S``: four queries.)"""
    page = open_page(browser, dashboard.url)
    try:
        start_at(page, LAST_FOUR_START_S, n_steps=4)
        page.get_by_role("tab", name="Current step").click()
        dismiss_webgl_notice(page)
        go_to_step(page, 0)  # frame 70: its best match gains correspondences at τ1 0.83
        runs = run_number(page)
        best_before = row(page, "best match")
        count_before = int(re.search(r"(\d+) correspondences", best_before).group(1))
        go_to_step(page, 3)  # the last step (the slider's 4): matched last
        thumb = control(page, "τ1 (Lowe ratio)").locator("[role=slider]")
        thumb.focus()
        box = control(page, "τ1 (Lowe ratio)").locator("input:not([type=hidden])")
        for i in range(1, 4):  # 0.80 -> 0.83, one run per key press, each superseding the one before
            thumb.press("ArrowRight")
            value = f"{0.8 + 0.01 * i:.2f}".rstrip("0")
            wait_for(lambda: box.input_value() == value, SERVER_WORK_S, f"τ1 to read {value}")
        assert control(page, "τ1 (Lowe ratio)").locator("input:not([type=hidden])").input_value() == "0.83"
        wait_for(lambda: "Matching" in status_text(page), SERVER_WORK_S, "matching to start")
        # the last step keeps the previous run's numbers, marked, until the new run reaches it
        badge = page.get_by_text("previous run (τ1 0.8) — re-matching for τ1 0.83…", exact=True)
        badge.first.wait_for()
        page.get_by_text("numbers of the previous run, shown until the new run reaches this step").first.wait_for()
        title = page.locator(".uplot .u-title").first
        wait_for(lambda: "previous run" in title.inner_text(), SERVER_WORK_S, "the plot to say it is the previous run")
        page.get_by_role("tab", name="Map").click()
        wait_for(lambda: any(badge.nth(i).is_visible() for i in range(badge.count())), SERVER_WORK_S,
                 "the map's own badge")
        screenshot(page, "newcomer_stale_map.png")
        page.get_by_role("tab", name="Current step").click()
        badge.first.wait_for()
        screenshot(page, "newcomer_stale.png")
        go_to_step(page, 0)  # step 1 is matched first: the new run's numbers, whether or not the rest is
        wait_for(lambda: not any(badge.nth(i).is_visible() for i in range(badge.count())), RUN_S,
                 "step 1 of the new run")
        screenshot(page, "newcomer_refilling.png")
        # the page stays responsive while the worker matches
        page.get_by_role("button", name="Next ▶").click()
        page.get_by_text("Step 2 of 4", exact=True).wait_for()
        screenshot(page, "dashboard_matching.png")
        wait_for(lambda: run_number(page) > runs, RUN_S, "the run with τ1 = 0.83")
        assert run_number(page) == runs + 1, "superseded runs must not complete"
        assert "τ1 0.83, τ2 0.97)" in status_text(page)
        go_to_step(page, 3)
        badge.first.wait_for(state="detached")
        wait_for(lambda: "previous run" not in title.inner_text(), SERVER_WORK_S, "the plot to be current")
        go_to_step(page, 0)
        count_after = int(re.search(r"(\d+) correspondences", row(page, "best match")).group(1))
        assert count_after != count_before
        assert count_after >= count_before  # a looser ratio test admits a superset of pairs for the same image
        screenshot(page, "dashboard_tau1_083.png")
    finally:
        reset(page)
        page.close()


@pytest.mark.slow
def test_a_zero_exclusion_on_the_queries_own_drive_is_warned_of(dashboard, browser):
    page = open_page(browser, dashboard.url)
    warning = "Warning: exclusion 0 s with a database of the queries' own drive"
    try:
        assert page.get_by_text("1 s exclusion (the database holds this drive's own images)").count() >= 1
        assert page.get_by_text(warning).count() == 0
        start_at(page, LAST_FOUR_START_S, n_steps=4)  # each query is matched again to the images the exclusion left out
        runs = run_number(page)
        box = control(page, "Exclusion (s)").locator("input:not([type=hidden])")
        box.fill("0")
        box.press("Enter")
        wait_for(lambda: run_number(page) > runs, RUN_S, "the run with no exclusion")
        page.get_by_text(warning).first.wait_for()
        # queries may now be matched to images less than 1 s from them (their stereo twins, for most): the steps
        # are looked at in turn until one is
        offsets_s = []
        for step in range(4):
            go_to_step(page, step)
            offsets_s.append(abs(float(re.search(r"\(([+-]\d+\.\d\d) s\)", row(page, "best match")).group(1))))
            if offsets_s[-1] < 1.0:
                break
        assert min(offsets_s) < 1.0, offsets_s
        screenshot(page, "dashboard_exclusion_0.png")
    finally:
        reset(page)
        page.close()


@pytest.mark.slow
def test_two_tabs_see_the_same_session(dashboard, browser):
    a, b = open_page(browser, dashboard.url), open_page(browser, dashboard.url)
    try:
        go_to_step(a, 6)
        b.get_by_text("Step 7 of 11", exact=True).wait_for()  # the other tab follows
        assert row(b, "query") == row(a, "query")
    finally:
        a.close()
        b.close()


@pytest.mark.slow
def test_a_bad_store_is_reported_in_the_page_and_the_server_lives_on(dashboard, browser, kitti_evaluation):
    folder = kitti_evaluation[0] / "bad_stores"  # inside the store's folder: the page may open it
    folder.mkdir(exist_ok=True)
    page = open_page(browser, dashboard.url)
    try:
        go_to_step(page, 1)
        query = row(page, "query")
        page.get_by_text("Data", exact=True).click()
        missing = folder / "missing.sqlite"
        assert "does not exist" in open_other_store(page, missing).inner_text()
        not_a_store = folder / "notes.sqlite"
        not_a_store.write_text("not a database")
        assert "not a SQLite database" in open_other_store(page, not_a_store).inner_text()
        assert not_a_store.read_text() == "not a database"  # nothing written to the bad file
        screenshot(page, "dashboard_bad_store.png")
        # the data already shown stays, and the server still answers
        assert row(page, "query") == query
        assert dashboard.alive()
    finally:
        reset(page)  # a new run replaces the message
        page.close()


@pytest.mark.slow
def test_a_missing_store_at_start_shows_a_message(browser, tmp_path):
    proc = DashboardProcess("--db", str(tmp_path / "nothing_here.sqlite"), "--port", "8360")
    try:
        page = new_page(browser)
        visit(page, proc.url)
        page.get_by_text(re.compile("nothing_here.sqlite: database file does not exist")).wait_for()
        screenshot(page, "dashboard_missing_store.png")
        page.close()
        assert proc.alive()
    finally:
        proc.stop()


@pytest.mark.slow
def test_a_taken_port_moves_and_the_printed_url_says_where(dashboard):
    second = DashboardProcess("--db", "unused.sqlite", "--port", str(dashboard.port))
    try:
        assert second.port != dashboard.port
        import urllib.request

        with urllib.request.urlopen(second.url, timeout=SERVER_WORK_S) as response:
            assert response.status == 200
    finally:
        second.stop()


def test_bad_port_is_a_one_line_error():
    result = run_cli("dashboard", "--port", "70000")
    assert result.returncode == 2
    assert result.stderr.strip() == "visloc: error: --port: port=70000: must be an integer in [1, 65535]"


def test_query_images_that_are_not_there_or_not_needed_are_a_one_line_error(tmp_path):
    missing = tmp_path / "no_such_root"
    one_line_error(run_cli("dashboard", "--query-images", missing), f"--query-images {missing}: not found")
    one_line_error(run_cli("dashboard", "--query-images", tmp_path, "--run", tmp_path / "run.json"),
                   "--query-images: for a store's live page")


@pytest.mark.slow
def test_switching_to_the_refined_mode_measures_metric_poses(dashboard, browser):
    """From ``LAST_FOUR_START_S`` on (four queries: the refined run is the slowest of the page's runs)."""
    page = open_page(browser, dashboard.url)
    try:
        start_at(page, LAST_FOUR_START_S, n_steps=4)
        go_to_step(page, 2)
        paper_error = float(row(page, "measurement error").split()[0])
        assert row(page, "measured by") == "geotag of the best match"
        # the gate belongs to the refined modes: disabled in the paper's
        gate = control(page, "Gate χ² (refined)").locator("[role=slider]")
        assert gate.get_attribute("aria-disabled") == "true"
        runs = run_number(page)
        choose(page, "Mode", "refined")
        wait_for(lambda: gate.get_attribute("aria-disabled") != "true", SERVER_WORK_S,
                 "the gate to be enabled in the refined mode")
        wait_for(lambda: run_number(page) > runs and "refined" in status_text(page), RUN_S, "the refined run")
        go_to_step(page, 2)
        # the row says what the pose stands on, in words
        assert re.match(r"geometry: PnP against frames [\d, ]+ \(database views whose 3D points were "
                        r"triangulated with frames [\d, ]+\); \d+ inliers \(correspondences that agree",
                        row(page, "measured by"))
        refined_error = float(row(page, "measurement error").split()[0])
        assert refined_error < 1.0 < paper_error  # metric, not a neighbour's geotag 1 s away
        assert float(row(page, "measurement σ").split()[0]) < 1.0  # its own, honest R
        dismiss_webgl_notice(page)
        screenshot(page, "dashboard_refined.png")
    finally:
        reset(page)
        page.close()


def current_step(page) -> int:
    return int(re.search(r"Step (\d+) of \d+", page.get_by_text(re.compile(r"^Step \d+ of \d+$")).first.inner_text())
               .group(1))


def start_at(page, start_s: float, n_steps: int | None = None) -> None:
    """Move the start time, as a user types it, and wait for the run from there; with ``n_steps``, go to its
    first step and wait for the panel to say it has ``n_steps`` (the page's session is shared by its tabs, so
    the step the tests before left may still be selected, a later one than the shorter run has)."""
    runs = run_number(page)
    box = control(page, "Start time (s)").locator("input:not([type=hidden])")
    box.fill(f"{start_s:g}")
    box.press("Enter")
    wait_for(lambda: run_number(page) > runs, RUN_S, f"the run from {start_s:g} s")
    if n_steps is not None:
        go_to_step(page, 0)
        page.get_by_text(f"Step 1 of {n_steps}", exact=True).wait_for()


@pytest.mark.slow
def test_the_camera_rate_path_plays_every_frame_at_the_camera_rate(dashboard, browser, kitti_root):
    drive = visloc.open_source(kitti_root, drive=KITTI_DRIVE, camera="image_00")
    from_start = np.flatnonzero(drive.timestamps_s - drive.timestamps_s[0] >= CAMERA_RATE_START_S)
    n_frames, first_frame = len(from_start), drive.frames[from_start[0]].frame
    assert 20 < n_frames < 40
    page = open_page(browser, dashboard.url)
    try:
        start_at(page, CAMERA_RATE_START_S)  # the paper's mode at one query a second: a few queries
        runs = run_number(page)
        choose(page, "Mode", "refined-fast")  # its own rate: the camera's 10 Hz, without being asked
        wait_for(lambda: run_number(page) > runs and "refined-fast" in status_text(page)
                 and f"{n_frames} queries" in status_text(page), RUN_S, "the camera-rate run over every frame")
        assert control(page, "Query rate (Hz)").locator("input").first.input_value() == "10"
        # as visloc track runs it: the frames read from the drive's images, following points between full
        # localizations, and said so
        assert "following points" in status_text(page)
        summary = page.get_by_text(re.compile(rf"refined-fast mode, {n_frames} queries")).first
        assert "Camera-rate path as visloc track runs it" in summary.locator("xpath=..").first.inner_text()
        page.get_by_text(f"Step 1 of {n_frames}", exact=True).wait_for()
        assert row(page, "query").startswith(f"image_00 frame {first_frame},")  # the first frame from the start on
        assert row(page, "measured by").startswith("a relocalization that fetched new map points")
        kinds = set()
        for step in (2, 3, 15):
            go_to_step(page, step)
            kinds.add(row(page, "measured by").split(" (")[0])
            assert "geometry: PnP against frames" in row(page, "measured by")
        assert "followed points" in kinds  # a frame posed on the points followed from a relocalization
        assert float(row(page, "measurement error").split()[0]) < 1.0
        control(page, "Play").locator("input").first.check()
        wait_for(lambda: current_step(page) >= 21, SERVER_WORK_S, "playback to move on")  # the page advances by itself
        control(page, "Play").locator("input").first.uncheck()
        dismiss_webgl_notice(page)
        screenshot(page, "dashboard_camera_rate.png")
    finally:
        reset(page)
        page.close()
