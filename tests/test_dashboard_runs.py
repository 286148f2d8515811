"""Saved runs in the browser, as a person inspects them: ``visloc dashboard --run A --run B`` in a subprocess,
driven in headless Chromium. Two evaluations of the real drive (the paper's R, and R at σ 5 m) opened and
compared, the timeline's worst step jumped to, the 3D view zoomed from the whole drive to one ellipse, a layer
hidden.

Screenshots stay in each test's temporary folder (pytest keeps the last runs' folders), to be looked at.
"""

from __future__ import annotations

import re

import pytest

import visloc
from visloc.dashboard import runpanels as rp

from helpers import (OTHER_RUN_NAME, RUN_S, SERVER_WORK_S, DashboardProcess, choose, control, dismiss_webgl_notice,
                     new_page, settled, status_text, visit, wait_for)

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="module")
def viewer(kitti_two_runs):
    proc = DashboardProcess("--run", str(kitti_two_runs[0]), "--run", str(kitti_two_runs[1]), "--port", "8350")
    yield proc
    proc.stop()


def opened(browser, viewer):
    page = new_page(browser)
    visit(page, viewer.url)
    compared = re.escape(OTHER_RUN_NAME.removesuffix(".json"))
    page.get_by_text(re.compile(rf"^eval: \d+ steps in 2 series; compared with {compared}$")).wait_for()
    page.get_by_text(re.compile(r"^Step \d+ of \d+$")).first.wait_for()  # tabs share one state: any step
    dismiss_webgl_notice(page)
    return page


def step_heading(page, k: int, n: int):
    return page.get_by_text(re.compile(rf"^Step {k} of {n}$"))


def test_two_saved_runs_open_side_by_side_with_what_differs(viewer, browser, kitti_two_runs, tmp_path):
    page = opened(browser, viewer)
    page.screenshot(path=str(tmp_path / "opened.png"))
    page.get_by_role("tab", name="Runs").click()
    page.get_by_text("Parameters that differ", exact=True).wait_for()
    row = page.locator("tr", has=page.get_by_text("filter.meas_var_m2", exact=True)).first
    assert row.locator("td").nth(2).inner_text() == "25"
    page.get_by_text("final estimate error mean (m)", exact=True).first.wait_for()
    page.screenshot(path=str(tmp_path / "runs_tab.png"))
    # the step table shows both runs' fields, side by side
    page.get_by_role("tab", name="Step").click()
    header = page.locator("th", has_text="comparison").first
    header.wait_for()
    assert page.locator("tr", has=page.get_by_text("best_count", exact=True)).first.locator("td").count() == 3


def test_the_timeline_finds_the_worst_step_and_the_page_jumps_there(viewer, browser, kitti_two_runs, tmp_path):
    page = opened(browser, viewer)
    page.get_by_role("tab", name="Timelines").click()
    page.get_by_text("Error per step (m) and the estimate's 2σ", exact=True).wait_for()
    page.get_by_text("NEES per step (2 if the covariance is honest)", exact=True).wait_for()
    page.screenshot(path=str(tmp_path / "timelines.png"))
    series = visloc.load_run(kitti_two_runs[0]).series[0]
    worst = next(c for c in rp.jump_choices(series) if rp.step_of_choice(c) != 1)  # the page shows step 1
    choose(page, "Jump to", worst)
    k = rp.step_of_choice(worst)
    page.get_by_role("tab", name="Step").click()
    step_heading(page, k, len(series)).wait_for()
    assert control(page, "Step").locator("input:not([type=hidden])").first.input_value() == str(k)
    page.screenshot(path=str(tmp_path / "worst_step.png"))


def test_the_3d_view_zooms_from_the_drive_to_one_ellipse_and_layers_hide(viewer, browser, tmp_path):
    page = opened(browser, viewer)
    canvas = page.locator("canvas").first
    whole = settled(canvas, "the whole drive drawn")
    (tmp_path / "whole_drive.png").write_bytes(whole)
    choose(page, "Ellipses drawn", "×100")
    page.get_by_text(re.compile(r"ellipses drawn up to ×100$")).wait_for()
    control(page, "Camera follows").locator("input").first.check()
    zoomed = settled(canvas, "the view framing the current ellipse")
    (tmp_path / "one_ellipse.png").write_bytes(zoomed)
    assert zoomed != whole
    control(page, "Grid and scale").locator("input").first.uncheck()
    control(page, "Comparison").locator("input").first.uncheck()
    bare = settled(canvas, "the view without the grid and the comparison")
    (tmp_path / "layers_hidden.png").write_bytes(bare)
    assert bare != zoomed


def test_a_saved_run_is_tuned_live_from_its_parameters(browser, kitti_two_runs, tmp_path):
    """``--tune-from``: the live page on the run's store (the copy it was evaluated on, which keeps its counts)
    starts from the run's R (σ 5 m, not the paper's 11.12 m), filters with it, and says which run it started
    from."""
    store = kitti_two_runs[1].parent / "kitti.sqlite"
    assert store.is_file()
    proc = DashboardProcess("--db", str(store), "--tune-from", str(kitti_two_runs[1]), "--port", "8352")
    try:
        page = new_page(browser)
        visit(page, proc.url)
        page.get_by_text(re.compile(rf"^Started from the saved run .*{re.escape(OTHER_RUN_NAME)}")).wait_for()
        box = control(page, "R: meas. σ (m)").locator("input:not([type=hidden])")
        wait_for(lambda: box.input_value() == "5", SERVER_WORK_S, "R's σ to read 5")
        wait_for(lambda: re.search(r"^Ready \(run 1, paper, τ1 0\.8, τ2 0\.97\)", status_text(page)), RUN_S,
                 "the run at R σ 5 m")
        page.screenshot(path=str(tmp_path / "tuned_from_saved_run.png"))
        page.close()
    finally:
        proc.stop()
