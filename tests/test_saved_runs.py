"""Saved runs read back: the JSON that ``evaluate`` wrote on the real drive, opened as the dashboard
opens it (``visloc.load_run``), compared with a second run, and what the viewer draws from it."""

from __future__ import annotations

import html
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import visloc
from visloc.dashboard import runpanels as rp

from helpers import run_cli
from helpers import one_line_error

def test_an_evaluation_reads_back_step_for_step_in_local_metres(kitti_evaluation):
    tmp, report, _ = kitti_evaluation
    run = visloc.load_run(tmp / "eval.json")
    assert run.kind == "evaluation" and len(run.series) == len(report["series"]) == 2
    assert [len(s) for s in run.series] == [len(s) for s in report["series"]]
    assert run.series[0][0].truth_m == pytest.approx((0.0, 0.0), abs=1e-9)  # the frame: the first truth
    for series, written in zip(run.series, report["series"]):
        for step, record in zip(series, written):
            assert step.frame == record["query_frame"] and step.estimate_error_m == record["estimate_error_m"]
            # the positions in metres give back the errors the file states (geodesic on WGS84)
            e = np.subtract(step.estimate_m, step.truth_m)
            assert float(np.hypot(*e)) == pytest.approx(record["estimate_error_m"], abs=0.01)
            assert step.estimate_cov_m2 == record["estimate_cov_m2"]
    assert run.params == report["params"]
    figures = visloc.run_figures(run)
    assert figures["steps"] == sum(len(s) for s in report["series"])
    assert figures["final estimate error mean (m)"] == pytest.approx(report["final_error_m"]["mean"])


def test_kitti_two_runs_compare_in_one_frame_and_say_which_parameters_differ(kitti_two_runs):
    a = visloc.load_run(kitti_two_runs[0])
    b = visloc.load_run(kitti_two_runs[1], a.frame)
    assert b.frame == a.frame
    assert b.series[0][0].truth_m == pytest.approx(a.series[0][0].truth_m, abs=1e-9)  # the same query, same place
    differ = {name: (x, y) for name, x, y in visloc.params_that_differ(a, b)}
    assert differ["filter.meas_var_m2"][1] == 25.0 and differ["filter.meas_var_m2"][0] != 25.0
    assert "match.tau1" not in differ and "match.tau2" not in differ
    page = html.unescape(rp.runs_html(a, b))  # the page's text, every character escaped
    assert "Parameters that differ" in page and "meas_var_m2" in page


def at_tau1_0_7(run: Path, folder: Path) -> Path:
    """A copy of the saved run ``run`` in ``folder``, as if it had been made at τ1 0.7 (matching again is not
    what the tests that read it check)."""
    report = json.loads(run.read_text())
    report["params"]["match"]["tau1"] = 0.7
    copy = folder / f"{run.stem}_tau1_0.7.json"
    copy.write_text(json.dumps(report))
    return copy


def test_runs_that_differ_in_tau1_say_so(kitti_evaluation, tmp_path):
    """The parameter that differs is named whichever it is: the session's run against the same run as if made
    at τ1 0.7."""
    a = visloc.load_run(kitti_evaluation[0] / "eval.json")
    b = visloc.load_run(at_tau1_0_7(kitti_evaluation[0] / "eval.json", tmp_path), a.frame)
    differ = {name: (x, y) for name, x, y in visloc.params_that_differ(a, b)}
    assert list(differ) == ["match.tau1"] and differ["match.tau1"] == (0.8, 0.7)


def test_a_run_with_another_R_has_the_same_measurements_and_other_estimates(kitti_two_runs):
    """R is the filter's: the second saved run matched nothing again (the same best matches and measurements)
    and its estimates differ."""
    a, b = (json.loads(path.read_text())["series"] for path in kitti_two_runs)
    assert [len(s) for s in a] == [len(s) for s in b] == [6, 6]
    steps = [(x, y) for sa, sb in zip(a, b, strict=True) for x, y in zip(sa, sb, strict=True)]
    for key in ("query_frame", "counts", "best_db_frame", "measurement_error_m"):
        assert [x[key] for x, _ in steps] == [y[key] for _, y in steps], key
    assert [x["estimate_error_m"] for x, _ in steps] != [y["estimate_error_m"] for _, y in steps]


def test_drives_json_lists_the_runs_beside_it(kitti_two_runs, tmp_path):
    runs = [Path(shutil.copy(run, tmp_path / run.name)) for run in kitti_two_runs]  # the shared runs stay as made
    index = tmp_path / "drives.json"
    index.write_text(json.dumps({"root": "x", "drives": {"d": [
        {"mode": "paper", "protocol_label": "left queries, right database", "file": runs[0].name},
        {"mode": "paper", "protocol_label": "R σ 5 m", "file": runs[1].name},
        {"mode": "refined", "file": "not_there.json"}]}}))
    files = visloc.run_files(index)
    assert [p for _, p in files] == runs  # a file that is not beside it is left out
    assert files[0][0] == "d, left queries, right database, paper"


@pytest.mark.parametrize("content, says", [
    (None, "no such file"), ("{ not json", "not JSON (line 1"), ("[1, 2]", "a JSON object was expected"),
    ('{"mode": "paper"}', "neither 'series' nor 'per_frame'"), ('{"series": [[]]}', "holds no steps"),
    ('{"per_frame": [{"frame": 0}]}', "frame 0 has no truth_m"),
])
def test_a_file_that_is_no_run_is_one_line_naming_it(tmp_path, content, says):
    path = tmp_path / "run <img src=x>.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(visloc.InputError) as info:
        visloc.load_run(path)
    assert str(path) in str(info.value) and says in str(info.value) and "\n" not in str(info.value)
    result = run_cli("dashboard", "--run", path, "--port", "8391", timeout=120)  # refused before serving
    one_line_error(result, str(path), says)
    result = run_cli("dashboard", "--tune-from", path, "--port", "8391", timeout=120)
    one_line_error(result, str(path), says)


def test_a_saved_run_gives_the_live_page_its_settings(kitti_two_runs, tmp_path):
    """``--tune-from``: the mode, rate, parameters, database and queries a run was made with, as the live
    controls take them; what a run does not record is left to the paper's, and said."""
    from visloc.dashboard.gui import paper_values, saved_values, tuned_from_html

    settings = visloc.live_settings(visloc.load_run(kitti_two_runs[1]))
    report = json.loads(kitti_two_runs[1].read_text())["params"]
    assert settings.method == report["mode"] == "paper" and settings.rate_hz == pytest.approx(1.0)
    assert settings.params["meas_var_m2"] == report["filter"]["meas_var_m2"] == 25.0
    assert settings.params["tau1"] == report["match"]["tau1"] and settings.params["tau2"] == report["match"]["tau2"]
    assert (settings.database, settings.queries) == (report["database"], report["queries"])
    values, moved = saved_values(settings)
    assert values["params"]["meas_var_m2"] == pytest.approx(5.0) and not moved  # R shown as its σ, as the paper's is
    assert paper_values()["params"]["meas_var_m2"] == pytest.approx(11.12)
    assert values["mode"] == "paper" and values["rate"] == "1"
    values, moved = saved_values(visloc.live_settings(visloc.load_run(at_tau1_0_7(kitti_two_runs[1], tmp_path))))
    assert values["params"]["tau1"] == 0.7 and values["params"]["meas_var_m2"] == pytest.approx(5.0) and not moved
    track = tmp_path / "track.json"  # a camera-rate run records its interval, its exclusion and its filter
    track.write_text(json.dumps({"queries": "d/image_00", "database": "d/image_01", "per_frame": [
        {"frame": 0, "truth_m": [0, 0]}], "params": {"track": {"fast": True, "exclusion_s": 99.0},
                                                   "filter": {"dt_s": 0.1034, "accel_var_m2_s4": 4.0}}}))
    settings = visloc.live_settings(visloc.load_run(track))
    assert (settings.method, settings.database, settings.queries) == ("refined-fast", "d/image_01", "d/image_00")
    values, moved = saved_values(settings)
    assert values["rate"] == "10" and values["params"]["accel_var_m2_s4"] == 2.0  # Q shown as its σ
    assert moved == ["query rate 9.67 Hz → 10 Hz", "Exclusion 99 → 3"]  # what could not be kept is said
    said = tuned_from_html(track, settings, moved)
    assert "Started from the saved run" in said and "τ1" in said  # not recorded by a track run: the paper's


def test_tune_from_and_run_are_one_or_the_other(kitti_two_runs):
    result = run_cli("dashboard", "--run", kitti_two_runs[0], "--tune-from", kitti_two_runs[1], "--port", "8392",
                     timeout=120)
    one_line_error(result, "--tune-from", "give one")


def test_what_a_run_file_says_reaches_the_page_as_text(kitti_evaluation, tmp_path):
    report = json.loads((kitti_evaluation[0] / "eval.json").read_text())
    report["series"][0][0]["fallback_reason"] = "<img src=x onerror=alert(1)>"
    report["params"]["mode"] = "<script>alert(2)</script>"
    path = tmp_path / "evil.json"
    path.write_text(json.dumps(report))
    run = visloc.load_run(path)
    step_page = rp.step_html(run.series[0][0], len(run.series[0]), None, 1.0)
    runs_page = rp.runs_html(run, None)
    for page in (step_page, runs_page):
        assert "<img" not in page and "<script" not in page
    assert "&#60;img" in step_page and "&#60;script" in runs_page
    assert rp.jump_choices(run.series[0])[-1].startswith("step 1: fell back (<img")  # a dropdown shows text


def test_the_timelines_mark_the_current_step_and_the_fallbacks(kitti_evaluation):
    run = visloc.load_run(kitti_evaluation[0] / "eval.json")
    series = run.series[0]
    series[2].fallback_reason, series[3].gated = "too few inliers", True
    for kind in rp.TIMELINES:
        data, (low, high) = rp.timeline(kind, series, 4)
        assert all(len(column) == len(series) for column in data)
        assert len(data) == len(rp.timeline_series(kind, {k: "red" for k in
                                                          ("estimate", "measurement", "ellipse", "compare",
                                                           "current")}))
        fell_back, gated, current = data[-3], data[-2], data[-1]
        assert np.isfinite(current).sum() <= 1 and (np.isnan(current[:4]).all())
        assert np.isnan(fell_back[[0, 1, 3]]).all() and np.isnan(gated[[0, 1, 2]]).all()
        assert low == 0.0 and high > 0.0
    data, _ = rp.timeline("error", series, 4)
    assert data[-1][4] == series[4].estimate_error_m
    worst = visloc.worst_steps(series, 3)
    assert series[worst[0]].estimate_error_m == max(s.estimate_error_m for s in series)
    series[1].fields["thin_support"] = True
    choices = rp.jump_choices(series, 3)
    assert [rp.step_of_choice(c) for c in choices[:3]] == [k + 1 for k in worst]
    assert "fell back (too few inliers)" in choices[3] and choices[4] == "step 4: gated"
    assert choices[5:] == ["step 2: posed on thin support"]


def test_the_scale_marks_read_well_at_every_zoom():
    assert [rp.nice_length_m(x) for x in (0.013, 0.4, 3.7, 18.0, 260.0)] == [0.01, 0.2, 2.0, 10.0, 200.0]
    assert rp.length_text(0.05) == "5 cm" and rp.length_text(20.0) == "20 m"
    for distance_m in (0.5, 5.0, 50.0, 500.0):
        marks = rp.scale_marks(np.array([10.0, -4.0, 0.0]), distance_m)
        length = np.linalg.norm(marks["bar"][1] - marks["bar"][0])
        assert distance_m / 10 <= length <= distance_m / 4 + 1e-9  # a tenth to a quarter of the view
        north = marks["arrow"][1] - marks["arrow"][0]
        assert north[0] == 0.0 and north[1] > 0.0  # it points north
    # a refined 2σ ellipse of a few centimetres: invisible at drive scale, readable when followed
    cov = [[0.004, 0.0], [0.0, 0.003]]
    assert rp.ellipse_px(cov, 300.0) < 3.0
    step = visloc.SavedStep(0, 0, 0.0, (0.0, 0.0), (0.01, 0.0), cov, 0.063, 0.01, None, None, None, None, None,
                            None, False, None, None, None, None)
    assert rp.ellipse_px(cov, rp.follow_distance_m(step, 1.0, 500.0)) > 100.0
    assert rp.ellipse_px(rp.magnified(cov, 100.0), 300.0) > 50.0  # ×100: tens of pixels at 300 m
    # magnified, but never beyond a quarter of the drive: a paper run's 10 m ellipse stays true, and the camera
    # that follows it stays near the drive
    assert rp.drawn_factor(cov, 100.0, 30.0) == 100.0 and rp.drawn_factor(cov, 100.0, 12.65) < 100.0
    assert rp.drawn_factor([[100.0, 0.0], [0.0, 100.0]], 100.0, 25.0) == 1.0
    assert rp.drawn_factor([[1.0, 0.0], [0.0, 1.0]], 100.0, 25.0) == pytest.approx(6.25)
    paper_step = visloc.SavedStep(0, 0, 0.0, (0.0, 0.0), (5.0, 0.0), [[100.0, 0.0], [0.0, 100.0]], 10.0, 5.0, None,
                                  None, None, None, None, None, False, None, None, None, None)
    assert rp.follow_distance_m(paper_step, 1.0, 220.0) == 120.0
    assert rp.follow_distance_m(paper_step, 100.0, 220.0) == 220.0
    assert rp.ground_point((0.0, 0.0, 10.0), (0.6, 0.0, -0.8)) == pytest.approx([7.5, 0.0, 0.0])
    assert rp.ground_point((0.0, 0.0, 10.0), (0.0, 0.0, 1.0)) is None


def test_the_map_close_up_is_closer_than_the_overview_and_says_its_size(kitti_evaluation):
    from visloc.dashboard import mapview

    run = visloc.load_run(kitti_evaluation[0] / "eval.json")
    series = run.series[0]  # a 50-frame stretch, about 60 m: shorter than the usual 50 m close-up is useful for
    truth = np.array([s.truth_m for s in series])
    overview = mapview.View.fitting(truth, mapview.MAP_WIDTH_PX, mapview.VIEW_HEIGHT_PX)
    half_m = mapview.closeup_half_m(overview)
    overview_half_m = (overview.height_px - 2 * mapview.MARGIN_PX) / (2 * overview.px_per_m)
    assert half_m <= overview_half_m / 4 + 1e-9 and half_m >= 2.0
    long_drive = mapview.View.fitting(np.array([[0.0, 0.0], [2000.0, 900.0]]), mapview.MAP_WIDTH_PX,
                                      mapview.VIEW_HEIGHT_PX)
    assert mapview.closeup_half_m(long_drive) == mapview.ZOOM_HALF_M
    # the map draws with a close-up on any step (saved steps carry the records' names)
    image = mapview.map_image(truth, truth, series, 3)
    assert image.ndim == 3 and image.shape[0] > mapview.VIEW_HEIGHT_PX


def test_a_step_shows_its_geotags_to_a_centimetre_and_other_numbers_to_four_digits():
    from visloc.results.saved import SavedStep

    fields = {"truth_geotag_deg": [49.01103951, 8.42320412], "measurement_heading_deg": 126.6912,
              "measurement_error_m": 0.123456}
    step = SavedStep(0, 45, 0.0, (0.0, 0.0), None, None, None, None, None, None, None, None, "geometry", None, False,
                     51, None, None, None, fields=fields)
    page = html.unescape(rp.step_html(step, 1, None, 1.0))
    assert "49.0110395, 8.4232041" in page and "126.7" in page and "0.1235" in page
