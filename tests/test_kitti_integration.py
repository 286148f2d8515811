"""The paper's protocol on the real drive (KITTI raw 2011_09_26_drive_0001): are the numbers sane?

Runs ``visloc evaluate`` on two series (start frames 0 and 50) of left-camera
queries against the right-camera database with the 1 s exclusion, then
``visloc localize`` for one series, as a user would.
"""

import json

import numpy as np
import pytest

from helpers import KITTI_DRIVE, run_cli

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="session")
def evaluation(kitti_evaluation):
    return kitti_evaluation


def test_evaluation_writes_the_documented_keys(evaluation):
    tmp, report, stdout = evaluation
    for key in ("series", "steps", "measurement_error_m", "estimate_error_m", "final_error_m", "latency_ms", "params"):
        assert key in report
    assert report["steps"] == ["t-5", "t-4", "t-3", "t-2", "t-1", "t"]
    assert set(report["final_error_m"]) == {"mean", "median", "p90", "min", "max"}
    assert set(report["latency_ms"]) == {"p50", "p95"}
    assert report["params"]["match"] == {"tau1": 0.8, "tau2": 0.97}
    assert report["params"]["retrieval"]["exclusion_s"] == 1.0
    assert (tmp / "eval.png").stat().st_size > 10_000
    assert "final estimate error (m)" in stdout


def test_series_follow_the_protocol(evaluation):
    _, report, _ = evaluation
    assert [s[0]["query_frame"] for s in report["series"]] == [0, 50]
    for series in report["series"]:
        times = [step["query_timestamp_s"] for step in series]
        np.testing.assert_allclose(np.diff(times), 1.0, atol=0.06)  # one query per second
        for step in series:
            # the 1 s exclusion holds, and every query found a match
            assert step["best_offset_s"] is not None and abs(step["best_offset_s"]) >= 1.0
            assert step["best_count"] > 0


def test_errors_are_physically_sane(evaluation):
    _, report, _ = evaluation
    meas = np.array(report["measurement_error_m"])
    est = np.array(report["estimate_error_m"])
    # At ~10 m/s with database images at least 1 s away from the query, a correct best
    # match is 4-14 m away; a wrong place would be tens of metres off.
    assert np.all((meas > 3.0) & (meas < 25.0)), meas
    assert np.all(est < 40.0), est
    for series in report["series"]:
        for step in series:
            assert abs(step["best_offset_s"]) < 3.0  # the best match is a nearby image, not a random one
    # retrieval is near its floor: the candidate nearest to the truth is at most a few metres better
    floor = np.array(report["nearest_candidate_error_m"])
    assert np.all(meas >= floor - 1e-9) and np.all(meas - floor < 3.0), (meas, floor)
    # geodesic and Haversine agree to half a percent at this range
    np.testing.assert_allclose(report["measurement_error_haversine_m"], meas, rtol=5e-3)
    assert report["latency_ms"]["p50"] > 0


def test_same_camera_without_exclusion_finds_the_query_image_itself(evaluation, kitti_root, tmp_path):
    tmp, _, _ = evaluation
    result = run_cli("localize", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite",
                     "--camera", "image_01", "--db-camera", "image_01", "--start-frame", "30", "--steps", "1",
                     "--exclusion-s", "0", "--json", tmp_path / "self.json")
    assert result.returncode == 0, result.stderr
    assert "warning: --exclusion-s 0 with a database (2011_09_26_drive_0001_sync/image_01)" in result.stdout
    steps = json.loads((tmp_path / "self.json").read_text())["steps"]
    assert [s["best_db_frame"] for s in steps] == [s["query_frame"] for s in steps]
    assert all(s["measurement_error_m"] == 0.0 for s in steps)


def readme_python_block(k: int) -> str:
    """The k-th Python block of the README's "Python API" section."""
    from helpers import REPO

    section = (REPO / "README.md").read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    return section.split("```python\n")[k + 1].split("```", 1)[0]


def test_readme_python_example_runs(evaluation, kitti_root, capsys):
    code = readme_python_block(0)
    tmp, report, _ = evaluation
    code = code.replace('"out/visloc.sqlite"', repr(str(tmp / "kitti.sqlite")))
    code = code.replace('"../shared/data/kitti"', repr(str(kitti_root)))
    exec(compile(code, "README.md", "exec"), {})
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == ["frame 0", "frame 10", "frame 20"]
    # the same best matches as the evaluation's series starting at frame 0
    first = next(s for s in report["series"] if s[0]["query_frame"] == 0)
    assert [f"best match {s['best_db_frame']}," in line for s, line in zip(first, lines)] == [True] * 3


def test_readme_drive_example_runs(evaluation, capsys):
    code = readme_python_block(1)
    tmp, report, _ = evaluation
    code = code.replace('"out/visloc.sqlite"', repr(str(tmp / "kitti.sqlite")))
    exec(compile(code, "README.md", "exec"), {})
    errors = eval(capsys.readouterr().out.strip().splitlines()[-1])
    assert len(errors) == 11  # frames 0, 10, ..., 100 of the 108-frame drive
    # the drive run's first six steps are the evaluation's series starting at frame 0
    first = next(s for s in report["series"] if s[0]["query_frame"] == 0)
    assert errors[:6] == [round(step["estimate_error_m"], 2) for step in first]


# -- the refined mode on the same series ----------------------------------------------------

@pytest.fixture(scope="session")
def refined(kitti_refined):
    return kitti_refined


def test_refined_mode_reports_the_same_keys_as_the_paper(evaluation, refined):
    _, paper, _ = evaluation
    report, stdout = refined
    assert set(report) == set(paper)
    assert set(report["series"][0][0]) == set(paper["series"][0][0])
    assert report["mode"] == "refined" and paper["mode"] == "paper"
    assert "mode refined: geometry" in stdout


def test_refined_mode_beats_the_paper_on_the_same_series(evaluation, refined):
    _, paper, _ = evaluation
    report, _ = refined
    # the same queries, the same retrievals
    for ps, rs in zip(paper["series"], report["series"]):
        assert [s["query_frame"] for s in ps] == [s["query_frame"] for s in rs]
        assert [s["best_db_frame"] for s in ps] == [s["best_db_frame"] for s in rs]
    # geometry works on most steps of a moving car, and when it does it is metric, not a neighbour's geotag:
    # the paper's measurements are at least 3 m off (test_errors_are_physically_sane)
    assert report["measurement_source_fraction"]["geometry"] >= 0.8
    geometry_errors = [s["measurement_error_m"] for series in report["series"] for s in series
                       if s["measurement_source"] == "geometry"]
    assert np.median(geometry_errors) < 1.0
    assert report["final_error_m"]["mean"] < paper["final_error_m"]["mean"]
    assert np.mean(report["measurement_error_m"]) < np.mean(paper["measurement_error_m"])
    # the smoother never changes the last step and is finite everywhere
    np.testing.assert_allclose(report["smoothed_error_m"][-1], report["estimate_error_m"][-1])


def test_refined_mode_keeps_the_exclusion_window_and_says_why_it_falls_back(refined):
    report, _ = refined
    for series in report["series"]:
        for s in series:
            # every database image used for structure is >= 1 s (10 frames at 9.7 Hz) from the query
            for frame in s["view_db_frames"] + s["neighbour_db_frames"]:
                assert abs(frame - s["query_frame"]) >= 10, (s["query_frame"], frame)
            if s["measurement_source"] == "geometry":
                assert s["fallback_reason"] is None and s["view_db_frames"] and s["neighbour_db_frames"]
                assert 0 < s["measurement_sigma_m"] < 2.0 and s["n_pnp_inliers"] >= 15
            else:
                assert s["fallback_reason"]  # a geotag in the refined mode always says why


def test_localize_prints_the_tables_and_agrees_with_evaluate_in_both_modes(evaluation, refined, kitti_root,
                                                                          tmp_path):
    """The first two steps of one series through ``localize`` in the refined mode (fresh SIFT) against the same
    series through ``evaluate`` (stored SIFT): the same keypoints, so the paper's retrieval picks the same images
    and the refined mode the same poses; its Tables 2 and 3 are printed."""
    tmp, paper, _ = evaluation
    report, _ = refined
    result = run_cli("localize", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite", "--start-frame",
                     "50", "--steps", "2", "--exclusion-s", "1", "--mode", "refined", "--json", tmp_path / "r50.json")
    assert result.returncode == 0, result.stderr
    assert "Table 2" in result.stdout and "Table 3" in result.stdout
    steps = json.loads((tmp_path / "r50.json").read_text())["steps"]
    assert len(steps) == 2
    assert [s["best_db_frame"] for s in steps] == [s["best_db_frame"] for s in paper["series"][1][:2]]
    series = report["series"][1][:2]
    assert [s["measurement_source"] for s in steps] == [s["measurement_source"] for s in series]
    np.testing.assert_allclose([s["measurement_lat_deg"] for s in steps],
                               [s["measurement_lat_deg"] for s in series], atol=1e-7)
