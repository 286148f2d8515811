"""Exported trajectories as a GIS tool reads them: GeoJSON checked by an independent parser
(python-geojson), CSV by the standard library's reader, positions and covariances against the
records they came from."""

from __future__ import annotations

import csv
import io
import json

import geojson
import numpy as np
import pytest

import visloc
from visloc.results.export import CSV_COLUMNS, points_from_track

ORIGIN = (49.011, 8.423)  # near KITTI's drives


def record(step: int, *, measured: bool = True, estimated: bool = True, source: str = "geotag") -> visloc.StepRecord:
    truth_m = (10.0 * step, 2.0 * step)
    frame = visloc.LocalFrame(*ORIGIN)
    lat, lon = frame.to_geo(np.array(truth_m))
    return visloc.StepRecord(
        step=step, query_frame=10 * step, query_timestamp_s=100.0 + step, truth_geotag_deg=(float(lat), float(lon)),
        truth_m=truth_m, n_candidates=5, best_db_index=step, best_db_frame=10 * step + 1, best_count=40,
        best_offset_s=0.1, measurement_m=(truth_m[0] + 3.0, truth_m[1] - 4.0) if measured else None,
        measurement_geotag_deg=None, estimate_m=(truth_m[0] + 1.0, truth_m[1]) if estimated else None,
        estimate_sigma_m=2.0 if estimated else None, measurement_error_m=5.0 if measured else None,
        estimate_error_m=1.0 if estimated else None, measurement_error_haversine_m=None,
        estimate_error_haversine_m=None, latency_ms=12.0,
        estimate_cov_m2=[[4.0, 1.0], [1.0, 2.0]] if estimated else None,
        measurement_source=source if measured else None,
        measurement_cov_m2=[[9.0, 0.0], [0.0, 9.0]] if measured else None)


def test_geojson_is_valid_and_holds_every_step_of_every_series():
    frame = visloc.LocalFrame(*ORIGIN)
    series = [[record(0), record(1), record(2)], [record(3, measured=False), record(4, source="geometry")]]
    text = json.dumps(visloc.trajectory_geojson(series, frame, name="drive <1>"), allow_nan=False)
    parsed = geojson.loads(text)  # the independent parser; it rounds coordinates to 1e-6 degree (about 0.1 m)
    assert parsed.is_valid, parsed.errors()
    for feature in parsed["features"]:
        assert geojson.GeoJSON.to_instance(feature["geometry"]).is_valid, feature
    collection = json.loads(text)  # the numbers as written
    kinds = [(f["properties"]["kind"], f["properties"]["series"]) for f in collection["features"]]
    assert kinds.count(("estimate", 0)) == 3 and kinds.count(("estimate", 1)) == 2
    assert kinds.count(("measurement", 1)) == 1  # step 3 measured nothing
    assert ("truth track", 0) in kinds and ("estimate track", 1) in kinds
    assert kinds.count(("estimate 2σ ellipse", 0)) == 3
    # positions: [lon, lat] of the record's local metres, covariance as recorded
    estimate = next(f for f in collection["features"] if f["properties"]["kind"] == "estimate")
    lon, lat = estimate["geometry"]["coordinates"]
    np.testing.assert_allclose(frame.to_local(lat, lon), (1.0, 0.0), atol=1e-3)
    assert estimate["properties"]["cov_m2"] == [[4.0, 1.0], [1.0, 2.0]]
    major = np.sqrt(np.linalg.eigvalsh([[4.0, 1.0], [1.0, 2.0]]).max())
    assert estimate["properties"]["sigma_major_m"] == pytest.approx(major)
    # the ellipse is 2σ: its farthest point from the estimate is 2 * the major σ away
    ellipse = next(f for f in collection["features"] if f["properties"]["kind"] == "estimate 2σ ellipse")
    ring = np.asarray(ellipse["geometry"]["coordinates"][0])
    assert (ring[0] == ring[-1]).all()
    ring_m = frame.to_local(ring[:, 1], ring[:, 0])
    assert np.linalg.norm(ring_m - (1.0, 0.0), axis=1).max() == pytest.approx(2 * major, rel=0.02)


def test_csv_has_one_row_per_step_with_empty_cells_where_nothing_was_measured():
    frame = visloc.LocalFrame(*ORIGIN)
    series = [[record(0), record(1, measured=False, estimated=False)]]
    rows = list(csv.DictReader(io.StringIO(visloc.trajectory_csv(series, frame))))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 2
    assert rows[0]["measurement_source"] == "geotag"
    assert float(rows[0]["estimate_east_m"]) == pytest.approx(1.0)
    assert float(rows[0]["estimate_cov_en_m2"]) == pytest.approx(1.0)
    lat, lon = float(rows[0]["truth_lat_deg"]), float(rows[0]["truth_lon_deg"])
    np.testing.assert_allclose(frame.to_local(lat, lon), (0.0, 0.0), atol=1e-3)
    assert rows[1]["measurement_lat_deg"] == "" and rows[1]["estimate_cov_ee_m2"] == ""


def test_track_frames_export_the_same_way(tmp_path):
    frame = visloc.LocalFrame(*ORIGIN)
    frames = [visloc.TrackFrame(frame=i, timestamp_s=0.1 * i, truth_m=(float(i), 0.0), estimate_m=(float(i), 0.5),
                                estimate_sigma_m=1.0, error_m=0.5, measurement_m=None, measurement_sigma_m=None,
                                measurement_error_m=None, measurement_source=None, fallback_reason=None, gated=False,
                                restarted=False, view_frames=(), n_pnp_inliers=0, sift_ms=1.0, retrieval_ms=1.0,
                                geometry_ms=1.0, filter_ms=1.0, latency_ms=4.0,
                                estimate_cov_m2=[[1.0, 0.0], [0.0, 1.0]])
              for i in range(4)]
    assert [p.frame for p in points_from_track(frames)] == [0, 1, 2, 3]
    visloc.write_trajectory(tmp_path / "t.geojson", frames, frame, name="track")
    visloc.write_trajectory(tmp_path / "t.csv", frames, frame, name="track")
    assert geojson.loads((tmp_path / "t.geojson").read_text()).is_valid
    assert len(list(csv.DictReader((tmp_path / "t.csv").open()))) == 4


def test_an_unknown_suffix_is_refused_naming_the_file(tmp_path):
    with pytest.raises(visloc.ParameterError, match=r"t\.kml: .*\.geojson, \.json or \.csv"):
        visloc.write_trajectory(tmp_path / "t.kml", [[record(0)]], visloc.LocalFrame(*ORIGIN), name="x")
    assert not (tmp_path / "t.kml").exists()


def test_the_step_panel_names_the_geotags_term_only_where_it_counts():
    from dataclasses import replace

    from visloc.dashboard.panels import measurement_sigma_note

    posed = replace(record(0, source="geometry"), measurement_side="one", measurement_lever_m=4.0,
                    measurement_term_sigma_m={"pnp": 0.03, "views": 0.01, "lever": 0.02, "geotags": 0.0})
    assert measurement_sigma_note(posed) == (" (relative to the map; pnp 0.03, views 0.01, lever 0.02; views on one "
                                             "side, 4.0 m from the nearest)")
    unfixed = replace(posed, measurement_term_sigma_m={**posed.measurement_term_sigma_m, "geotags": 0.5})
    assert "lever 0.02, geotags 0.50;" in measurement_sigma_note(unfixed)


def test_the_step_panel_says_when_a_pose_stands_on_thin_support():
    from dataclasses import replace

    from visloc.dashboard.panels import source_text

    posed = replace(record(0, source="geometry"), view_db_frames=[3, 9], neighbour_db_frames=[1, 5], n_pnp_inliers=12)
    assert "12 inliers" in source_text(posed) and "thin support" not in source_text(posed)
    assert source_text(replace(posed, thin_support=True)).endswith("posed again at the looser one")


def test_the_step_panel_says_how_a_step_of_a_followed_run_was_measured():
    from dataclasses import replace

    from visloc.dashboard.panels import source_text

    posed = replace(record(0, source="geometry"), view_db_frames=[3, 9], neighbour_db_frames=[1, 5], n_pnp_inliers=40)
    assert source_text(posed, "tracked").startswith("followed points (no retrieval, no SIFT")
    assert source_text(posed, "relocalized").startswith("a relocalization that fetched new map points")
    assert source_text(posed, "tracked").endswith(source_text(posed)) and source_text(posed, None) == source_text(posed)
