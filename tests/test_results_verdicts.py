"""The results page's verdicts: the filter's gap to its measurements with its interval, and the chance that an
honest covariance gives a small split's coverage."""

from __future__ import annotations

import json
import sys

import pytest

from helpers import REPO

sys.path.insert(0, str(REPO / "scripts"))
import results  # noqa: E402


def series(t0_s: float, estimate_m: float, measurement_m: float) -> list[dict]:
    first = {"query_timestamp_s": t0_s, "estimate_error_m": 1.0, "measurement_error_m": 1.0}
    last = {"query_timestamp_s": t0_s + 5.0, "estimate_error_m": estimate_m, "measurement_error_m": measurement_m}
    return [first, last]


def test_a_constant_gap_has_no_spread_and_blocks_follow_the_start_times():
    runs = [series(100.0 + 0.1 * i, 0.051, 0.050) for i in range(30)]
    gap = results.final_minus_measurement(runs)
    assert gap["mean"] == pytest.approx(0.001)
    assert gap["ci95"] == pytest.approx([0.001, 0.001])
    assert gap["n_series"] == 30 and gap["n_blocks"] == 3


def test_a_gap_of_either_sign_has_an_interval_around_zero():
    runs = [series(100.0 + 1.0 * i, 0.05 + (0.01 if i % 2 else -0.01), 0.05) for i in range(40)]
    gap = results.final_minus_measurement(runs)
    assert gap["ci95"][0] < 0 < gap["ci95"][1]


def test_series_without_a_final_error_are_left_out():
    runs = [series(0.0, None, 0.05), series(1.0, 0.04, 0.05)]
    gap = results.final_minus_measurement(runs)
    assert gap["n_series"] == 1 and gap["mean"] == pytest.approx(-0.01)
    assert results.final_minus_measurement([series(0.0, None, None)])["mean"] is None


def test_the_honest_chance_of_a_split_s_coverage():
    assert results._honest_chance(0.95, 20) == ""  # inside 85-99 %: nothing to explain
    # all of 24 inside: 0.95^24 = 29 %
    assert "29 %" in results._honest_chance(1.0, 24)
    # 70 of 100 inside is next to impossible for an honest 95 % ellipse
    assert "0 %" in results._honest_chance(0.70, 100)


def test_the_honest_chance_counts_each_query_frame_once():
    """Six series that measure the same four frames are four draws, not 24: all inside is then likely enough."""
    def step(frame: int, nees: float, side: str = "both") -> dict:
        return {"query_frame": frame, "measurement_nees": nees, "measurement_side": side}

    runs = [[step(f, 1.0) for f in range(4)] for _ in range(6)] + [[step(9, 7.0, "one"), step(9, 1.0, "one")]]
    frames = results.distinct_frames(runs)
    assert frames["both"] == {"n": 4, "inside_95": 1.0}
    assert frames["one"] == {"n": 1, "inside_95": 0.5} and frames["all"]["n"] == 5
    text = results._honest_chance(1.0, 24, frames["both"])
    assert "of 24, measuring 4 query frames" in text and "81 %" in text  # 0.95^4
    assert "29 %" in results._honest_chance(1.0, 24, None)


def rtk_row(final_m: float, final_measurement_m: float, one_side_inside: float) -> dict:
    k = {"n": 100, "nees_mean": 2.0, "inside_95": 0.95}
    return {"drive": "some_drive", "calibration": {"both": k, "one": {**k, "inside_95": one_side_inside}},
            "database": {"stated_accuracy_median_m": 0.02},
            "geometry_error_m": {"median": 0.05, "p90": 0.2}, "final_error_m": {"mean": final_m},
            "final_measurement_error_m": {"mean": final_measurement_m}, "gross_geometry_errors": 0,
            "fallback_fraction": 0.0,
            "final_minus_measurement_m": {"mean": final_m - final_measurement_m, "ci95": [-0.001, 0.004],
                                          "n_blocks": 12}}


def test_verdicts_name_what_is_missed_with_enough_digits():
    met = results.uncertainty_verdicts(rtk_row(0.0900, 0.0925, 0.95))
    assert all(ok for _, ok in met)
    missed = [w for w, ok in results.uncertainty_verdicts(rtk_row(0.0949, 0.0925, 0.80)) if not ok]
    assert len(missed) == 2
    assert "views on one side" in missed[0] and "80 % inside" in missed[0]
    assert "0.0949" in missed[1] and "0.0925" in missed[1] and "+2.4 mm" in missed[1] and "12 one-second" in missed[1]


def test_a_speed_only_run_with_no_full_run_kept_keeps_every_other_section_of_the_committed_digest(tmp_path,
                                                                                                   monkeypatch):
    """``run --speed-only`` where out/results holds no full run: the page is the committed digest with only its
    speed sections replaced by what that run measured, and says which commit measured them."""
    committed = json.loads((REPO / "docs" / "results" / "digest.json").read_text())
    digest, page, out = tmp_path / "digest.json", tmp_path / "results.md", tmp_path / "out"
    out.mkdir()
    digest.write_text(json.dumps(committed))
    monkeypatch.setattr(results, "DIGEST", digest)
    monkeypatch.setattr(results, "PAGE", page)
    monkeypatch.setattr(results, "OUT", out)
    speed = {"commit": "abc1234", "started": "2026-01-01T00:00:00+00:00", "finished": "2026-01-01T00:30:00+00:00",
             "load_before": 0.5, "load_after": 1.5}
    (out / "manifest.json").write_text(json.dumps({"speed_over_digest": True, "runs": [], "speed": speed}))
    assert results.page() == 0
    made = json.loads(digest.read_text())
    assert made["speed"] == speed and made["bench"] == {} and made["tracks"] == {}
    for key in ("suite", "drives", "diagnostics", "haversine", "peer", "commit", "started"):
        assert made[key] == committed[key], key
    text = page.read_text()
    assert "measured again with commit `abc1234`" in text and f"Measured with commit `{committed['commit']}`" in text


def test_a_speed_only_page_needs_a_committed_digest(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(results, "DIGEST", tmp_path / "missing.json")
    monkeypatch.setattr(results, "OUT", tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"speed_over_digest": True, "runs": [], "speed": {}}))
    assert results.page() == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.json: not found" in err[0]


def test_the_page_says_which_contrast_its_store_was_described_at():
    older = results.store_contrast_note(None)  # a digest from before a new store's default was lowered
    assert "the paper's contrast threshold, 0.04" in older and "keeps them at 0.02" in older
    assert "Denser SIFT" in older
    today = results.store_contrast_note(0.02)
    assert "contrast threshold 0.02" in today and "the ones kept at 0.04" in today
    assert "keeps them at" not in today
