"""The dashboard explains itself to a first-time user: page title, step numbering from 1, local
metres with lat/lon on demand, hints and a help fold, controls of other modes disabled, a map,
static plot legends, wrapping messages, a visible shared session and downloads of the run. Stale
numbers marked while re-matching are checked during tests/test_dashboard.py's re-match, the gate of the
refined modes and what a refined pose stands on during its switch to the refined mode, and a first run
that fills in as it is matched on the sharded store (tests/test_shards.py), which keeps no counts.

``visloc dashboard`` in a subprocess on the KITTI store, driven in the session's headless Chromium
(see tests/test_dashboard.py). Screenshots go to ``out/screenshots/newcomer_*.png``.
"""

from __future__ import annotations

import csv
import io
import json
import re
from dataclasses import replace

import pytest
from helpers import (
    SERVER_WORK_S,
    DashboardProcess,
    settled,
    control,
    dismiss_webgl_notice,
    go_to_step,
    open_other_store,
    open_page,
    read_back_mcap,
    reset,
    row,
    screenshot,
    wait_for,
)

@pytest.fixture(scope="module")
def dashboard(kitti_evaluation):
    tmp, _, _ = kitti_evaluation
    proc = DashboardProcess("--db", str(tmp / "kitti.sqlite"), "--port", "8420")
    yield proc
    proc.stop()


def open_on_current_step(browser, url: str):
    """``open_page``, then the panel's "Current step" tab (the page remembers the tab last chosen)."""
    page = open_page(browser, url)
    page.get_by_role("tab", name="Current step").click()
    page.get_by_text(re.compile(r"^Step \d+ of \d+$")).first.wait_for()
    return page


def number_box(page, label: str):
    return control(page, label).locator("input:not([type=hidden])")


def set_number(page, label: str, value: str) -> None:
    box = number_box(page, label)
    box.fill(value)
    box.press("Enter")


def map_src(page) -> str:
    img = page.get_by_text("top-down map (north up, east right)", exact=True).locator("xpath=..").locator("img")
    return img.first.evaluate("e => e.currentSrc || e.src")


def two_csv_drives(tmp_path):
    """A store of two synthetic drives: (database, queries, the queries at 1 Hz)."""
    import visloc
    from helpers import write_csv_drive

    ws = visloc.Workspace(tmp_path / "s.sqlite", create=True)
    for name, offset in (("dbdrive", 0), ("querydrive", 30)):
        visloc.ingest_sequence(ws, visloc.open_csv(write_csv_drive(tmp_path / name, n_frames=10, offset_px=offset)),
                               visloc.SiftParams(), workers=1)
    db, queries = ws.load_database("dbdrive", "camera"), ws.load_queries("querydrive", "camera")
    return db, queries, visloc.drive_query_indices(queries.timestamps_s, 0.0, 1.0)


@pytest.mark.slow
def test_match_drive_hands_over_the_run_so_far_after_each_query(tmp_path):
    """The engine's ``on_step``: the partial runs the dashboard shows while the first run is matched."""
    import numpy as np

    import visloc

    db, queries, indices = two_csv_drives(tmp_path)
    partials = []
    full = visloc.match_drive(queries, db, visloc.MatchParams(), visloc.RetrievalParams(exclusion_s=0.5), indices,
                              on_step=partials.append)
    assert [len(p) for p in partials] == list(range(1, len(indices) + 1))
    for p in partials:  # each is the start of the whole run, and can be filtered as it stands
        np.testing.assert_array_equal(p.query_indices, full.query_indices[:len(p)])
        assert [m.east_north_m for m in p.measurements] == [m.east_north_m for m in full.measurements[:len(p)]]
        assert len(visloc.track_drive(p, queries, db, visloc.PAPER_FILTER)) == len(p)


def test_a_store_forgets_its_cached_counts_as_ingest_left_it(tmp_path):
    """``Workspace.clear_pair_counts``: what the first-run test and the feedback benchmark start from."""
    import visloc

    db, queries, indices = two_csv_drives(tmp_path)
    ws = visloc.Workspace(tmp_path / "s.sqlite")
    cache = ws.pair_cache(db, queries, visloc.MatchParams())
    visloc.match_drive(queries, db, visloc.MatchParams(), visloc.RetrievalParams(exclusion_s=0.5), indices, cache=cache)
    saved = ws.save_pair_counts(cache)
    assert saved > 0 and ws.clear_pair_counts() == saved and ws.clear_pair_counts() == 0
    with pytest.raises(visloc.InputError, match="read only"):
        visloc.Workspace(tmp_path / "s.sqlite", read_only=True).clear_pair_counts()


def test_a_later_run_fills_in_over_the_previous_one_step_by_step(tmp_path):
    """While a run is matched again (τ1 moved), the page draws its steps so far and the previous run's after
    them, each marked by whose it is; a run over other queries or another method does not mix with it."""
    import numpy as np

    import visloc
    from visloc.dashboard import panels
    from visloc.dashboard.state import Controls, Run

    db, queries, indices = two_csv_drives(tmp_path)
    retrieval = visloc.RetrievalParams(exclusion_s=0.5)
    asked = Controls(store_request=(1, "s"))
    old_key, new_key = asked.match_key(("s", "a", "b")), replace(asked, params={**asked.params, "tau1": 0.7}) \
        .match_key(("s", "a", "b"))
    old = visloc.match_drive(queries, db, visloc.MatchParams(), retrieval, indices)
    previous = Run(old, old_key, 1, 1.0, len(indices), records=visloc.track_drive(old, queries, db, visloc.PAPER_FILTER))
    partials = []
    visloc.match_drive(queries, db, visloc.MatchParams(tau1=0.7), retrieval, indices, on_step=partials.append)
    assert len(partials) == len(indices) >= 3
    for p in partials[:-1]:
        run = Run(p, new_key, 2, 1.0, len(indices), partial=True,
                  records=visloc.track_drive(p, queries, db, visloc.PAPER_FILTER))
        assert run.replaces_in_place(previous)
        run.previous = previous
        view, m = run.shown(), len(p)
        assert len(view.records) == len(view.matches) == len(indices) and view.fresh_steps == m
        assert view.records[:m] == run.records and view.records[m:] == previous.records[m:]
        np.testing.assert_array_equal(view.matches.query_indices, old.query_indices)
        assert [view.from_previous(k) for k in range(len(indices))] == [k >= m for k in range(len(indices))]
        assert view.match_params_of(0).tau1 == 0.7 and view.match_params_of(len(indices) - 1).tau1 == 0.8
        assert panels.step_note(view, m - 1, new_key) is None
        assert panels.step_note(view, m, new_key) == "previous run (τ1 0.8) — re-matching for τ1 0.7…"
    done = Run(partials[-1], new_key, 2, 1.0, len(indices), records=[], previous=None)
    assert done.shown() is done and not done.from_previous(len(indices) - 1)
    other_rate = Run(partials[0], new_key, 2, 1.0, len(indices) - 1, partial=True)
    assert not other_rate.replaces_in_place(previous)  # another number of queries: fills in like a first run
    refined = Run(replace(partials[0], method=visloc.REFINED_METHOD), new_key, 2, 1.0, len(indices), partial=True)
    assert not refined.replaces_in_place(previous)


def test_pure_parts_say_what_they_show():
    from visloc.dashboard import mapview, panels
    from visloc.dashboard.session import SessionLog

    from visloc.dashboard.state import Controls

    data = ("store", "x", "y")
    asked = Controls(store_request=(1, "store"))
    tau1 = replace(asked, params={**asked.params, "tau1": 0.85})
    assert panels.stale_note(asked.match_key(data), tau1.match_key(data)) == \
        "previous run (τ1 0.8) — re-matching for τ1 0.85…"
    assert panels.stale_note(asked.match_key(data), replace(asked, rerun=1).match_key(data)) == \
        "previous run — re-matching…"
    assert panels.stale_note(asked.match_key(data), replace(asked, method="refined").match_key(data)) == \
        "previous run (mode paper) — re-matching for mode refined…"
    log = SessionLog()
    one, two = log.connected(101), log.connected(102)
    assert (one, two) == (1, 2) and log.line() == "Shared by 2 open tabs · no change made yet"
    assert not log.changed(None, "τ1", "0.85")  # the page's own moves are not a tab's change
    assert log.changed(102, "τ1", "0.85")
    assert re.fullmatch(r"Shared by 2 open tabs · last change: τ1 → 0\.85 from tab 2 at \d\d:\d\d:\d\d", log.line())
    log.disconnected(101)
    assert log.line().startswith("Open in 1 tab · last change")
    assert [mapview.nice_length_m(v) for v in (0.7, 3.0, 24.0, 180.0)] == [0.5, 2.0, 20.0, 100.0]
    import numpy as np

    track = np.c_[np.linspace(-97.0, 0.0, 50), np.linspace(-45.0, 0.0, 50)]
    img = mapview.map_image(track, track, [], None)
    assert img.shape == (mapview.VIEW_HEIGHT_PX + mapview.HEADER_PX + mapview.FOOTER_PX, mapview.MAP_WIDTH_PX, 3)


def test_a_mode_plays_at_its_own_rate_unless_another_was_chosen():
    import visloc
    from visloc.dashboard.gui import RATES_HZ, mode_rate, rate_after_mode_change

    camera_rate = [m for m in visloc.METHODS if visloc.method_named(m).camera_rate]
    assert camera_rate == ["refined-fast"] and mode_rate("paper") == mode_rate("refined") == "1"
    assert mode_rate("refined-fast") == "10" and {mode_rate(m) for m in visloc.METHODS} <= set(RATES_HZ)
    assert rate_after_mode_change("paper", "refined-fast", "1") == "10"  # the camera's rate, where it is honest
    assert rate_after_mode_change("refined-fast", "refined", "10") == "1"  # back to the paper's
    assert rate_after_mode_change("paper", "refined", "1") == "1"
    assert rate_after_mode_change("paper", "refined-fast", "2") == "2"  # a rate the user chose stays
    assert rate_after_mode_change("refined-fast", "paper", "5") == "5"


@pytest.mark.slow
def test_title_numbering_units_and_help(dashboard, browser):
    page = open_on_current_step(browser, dashboard.url)
    try:
        dismiss_webgl_notice(page)
        assert page.title() == "visloc"
        # the slider counts as the panel does: 1..N
        assert number_box(page, "Step").input_value() == "1"
        page.get_by_text("Step 1 of 11", exact=True).wait_for()
        thumb = control(page, "Step").locator("[role=slider]")
        assert thumb.get_attribute("aria-valuemin") == "1" and thumb.get_attribute("aria-valuemax") == "11"
        go_to_step(page, 10)  # the last step: the slider reads 11
        assert number_box(page, "Step").input_value() == "11"
        assert page.get_by_text("P0: initial σ (m, m/s)", exact=True).count() == 1
        # positions in local metres; lat/lon on demand
        assert re.fullmatch(r"E -?\d+\.\d\d m, N -?\d+\.\d\d m", row(page, "truth"))
        assert "°" not in row(page, "estimate")
        control(page, "Show lat/lon").locator("input").first.check()
        wait_for(lambda: re.fullmatch(r"E -?\d+\.\d\d m, N -?\d+\.\d\d m \(49\.\d{7}°, 8\.\d{7}°\)",
                                      row(page, "truth")), SERVER_WORK_S, "lat/lon beside the metres")
        control(page, "Show lat/lon").locator("input").first.uncheck()
        wait_for(lambda: "°" not in row(page, "truth"), SERVER_WORK_S, "lat/lon hidden again")
        # every row explains itself on hover; the help fold explains the terms
        label = page.locator("td span[title]").filter(has_text=re.compile("^nearest allowed image$"))
        assert "floor" in label.get_attribute("title")
        page.get_by_text("What am I looking at?", exact=True).click()
        help_text = page.get_by_text(re.compile("^A car drove with a camera")).first
        help_text.wait_for()
        assert "inliers" in help_text.locator("xpath=..").inner_text()
        screenshot(page, "newcomer_help.png")
        page.get_by_text("What am I looking at?", exact=True).click()
        # the refined mode's controls and rows: tests/test_dashboard.py, on a run the page makes anyway
    finally:
        reset(page)
        page.close()


@pytest.mark.slow
def test_the_3d_view_has_a_scale_layers_and_follows_the_estimate(dashboard, browser, tmp_path):
    """The live 3D view: a grid labelled in metres, a scale bar and a north arrow (drawn in the canvas: look at
    the screenshots, kept in the test's folder); a checkbox per layer; "Camera follows" frames the current
    estimate."""
    page = open_on_current_step(browser, dashboard.url)
    try:
        dismiss_webgl_notice(page)
        canvas = page.locator("canvas").first
        whole = settled(canvas, "the whole drive")
        (tmp_path / "live_whole.png").write_bytes(whole)
        page.get_by_text("3D view layers", exact=True).click()
        control(page, "Camera follows").locator("input").first.check()
        followed = settled(canvas, "the view on the current estimate")
        (tmp_path / "live_followed.png").write_bytes(followed)
        assert followed != whole
        control(page, "Grid and scale").locator("input").first.uncheck()
        control(page, "Database geotags").locator("input").first.uncheck()
        bare = settled(canvas, "the view without grid, scale and database")
        (tmp_path / "live_layers_hidden.png").write_bytes(bare)
        assert bare != followed
    finally:
        for name in ("Grid and scale", "Database geotags"):
            control(page, name).locator("input").first.check()
        control(page, "Camera follows").locator("input").first.uncheck()
        page.close()


@pytest.mark.slow
def test_the_map_follows_the_step_and_the_plots_read_as_data(dashboard, browser):
    page = open_on_current_step(browser, dashboard.url)
    try:
        dismiss_webgl_notice(page)
        # static legends: no "--" placeholders where values would be
        legends = page.locator(".u-legend")
        assert legends.count() >= 2
        for text in legends.all_inner_texts():
            assert "--" not in text, text
        assert "estimate 2σ" in " ".join(legends.all_inner_texts())
        # the last plot ends inside the panel once scrolled to
        plots = page.locator(".uplot >> visible=true")  # the tab shown: its plots
        last = plots.nth(plots.count() - 1)
        last.scroll_into_view_if_needed()
        box, viewport = last.bounding_box(), page.viewport_size
        assert box["y"] + box["height"] <= viewport["height"], (box, viewport)
        screenshot(page, "newcomer_plots.png")
        # every per-step signal over time, in its own tab
        page.get_by_role("tab", name="Timelines").click()
        for title in ("Error per step (m) and the estimate's 2σ", "NEES per step (2 if the covariance is honest)",
                      "PnP inliers per step", "Latency per step (ms)"):
            page.get_by_text(title, exact=True).wait_for()
        screenshot(page, "newcomer_timelines.png")
        page.get_by_role("tab", name="Current step").click()
        go_to_step(page, 2)
        page.get_by_role("tab", name="Map").click()
        before = wait_for(lambda: map_src(page), SERVER_WORK_S, "the map")
        set_number(page, "Step", "8")  # the step table is in the other tab: the map alone answers
        wait_for(lambda: map_src(page) != before, SERVER_WORK_S, "the map to follow the step")
        screenshot(page, "newcomer_map.png")
    finally:
        page.get_by_role("tab", name="Current step").click()
        page.close()


@pytest.mark.slow
def test_every_tab_sees_the_shared_session_and_who_changed_what(dashboard, browser):
    a = open_on_current_step(browser, dashboard.url)
    b = open_on_current_step(browser, dashboard.url)
    try:
        for page in (a, b):
            page.get_by_text(re.compile(r"^Shared by [2-9] open tabs")).first.wait_for()
        tab_a = int(re.search(r"This is tab (\d+)", a.get_by_text(re.compile(r"^This is tab \d+$")).first
                              .inner_text()).group(1))
        tab_b = int(re.search(r"This is tab (\d+)", b.get_by_text(re.compile(r"^This is tab \d+$")).first
                              .inner_text()).group(1))
        assert tab_a != tab_b
        set_number(a, "R: meas. σ (m)", "5")
        said = re.compile(rf"last change: R: meas\. σ \(m\) → 5 from tab {tab_a} at \d\d:\d\d:\d\d$")
        for page in (a, b):
            page.get_by_text(said).first.wait_for()
        wait_for(lambda: number_box(b, "R: meas. σ (m)").input_value() == "5", SERVER_WORK_S, "b to follow")
        set_number(b, "R: meas. σ (m)", "11.12")
        said = re.compile(rf"last change: R: meas\. σ \(m\) → 11\.12 from tab {tab_b} at")
        for page in (a, b):
            page.get_by_text(said).first.wait_for()
        screenshot(a, "newcomer_two_tabs.png")
    finally:
        a.close()
        b.close()


@pytest.mark.slow
def test_the_run_downloads_as_geojson_csv_and_mcap(dashboard, browser, tmp_path):
    page = open_on_current_step(browser, dashboard.url)
    try:
        with page.expect_download() as got:
            page.get_by_role("button", name="Download GeoJSON").click()
        download = got.value
        assert re.fullmatch(r"visloc_run\d+_paper_tau1-0\.8_tau2-0\.97_1Hz\.geojson", download.suggested_filename)
        download.save_as(tmp_path / "run.geojson")
        geojson = json.loads((tmp_path / "run.geojson").read_text())
        assert geojson["type"] == "FeatureCollection"
        kinds = {f["properties"]["kind"] for f in geojson["features"]}
        assert {"truth track", "estimate track", "truth"} <= kinds
        with page.expect_download() as got:
            page.get_by_role("button", name="Download CSV").click()
        download = got.value
        assert download.suggested_filename.endswith(".csv")
        download.save_as(tmp_path / "run.csv")
        rows = list(csv.DictReader(io.StringIO((tmp_path / "run.csv").read_text())))
        assert len(rows) == 11
        assert rows[0]["truth_east_m"] and rows[0]["estimate_cov_ee_m2"]
        with page.expect_download() as got:  # for Foxglove: the same steps, each message decoded with its schema
            page.get_by_role("button", name="Download MCAP").click()
        download = got.value
        assert download.suggested_filename.endswith(".mcap")
        download.save_as(tmp_path / "run.mcap")
        steps = [{"series": int(r["series"]), "step": int(r["step"]),
                  **{f"{kind}_{axis}_deg": float(r[f"{kind}_{axis}_deg"]) if r[f"{kind}_{axis}_deg"] else None
                     for kind in ("truth", "measurement", "estimate") for axis in ("lat", "lon")},
                  "estimate_cov_m2": [[float(r["estimate_cov_ee_m2"]), float(r["estimate_cov_en_m2"])]]} for r in rows]
        read_back_mcap(tmp_path / "run.mcap", steps, images=False, places=1e-9, rel=1e-5)
    finally:
        page.close()


@pytest.mark.slow
def test_a_long_error_wraps_inside_the_panel(dashboard, browser, kitti_evaluation):
    page = open_on_current_step(browser, dashboard.url)
    try:
        page.get_by_text("Data", exact=True).click()
        # inside the store's folder, which the page may open
        deep = kitti_evaluation[0].joinpath(*[f"a_rather_long_folder_name_{i}" for i in range(6)]) / "not_a_store.sqlite"
        deep.parent.mkdir(parents=True, exist_ok=True)
        deep.write_text("not a database")
        message = open_other_store(page, deep)
        assert "not a SQLite database" in message.inner_text()
        message.scroll_into_view_if_needed()
        fits = message.evaluate("e => [e.scrollWidth <= e.clientWidth + 1, e.getBoundingClientRect().right,"
                                " e.parentElement.getBoundingClientRect().right]")
        assert fits[0] and fits[1] <= fits[2] + 1, fits
        status = page.get_by_text(re.compile("^⚠ " + re.escape(str(deep)))).nth(0)
        assert str(deep) in status.inner_text()
        screenshot(page, "newcomer_long_error.png")
    finally:
        reset(page)
        page.close()
