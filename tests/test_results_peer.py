"""The results page's comparison with the COLMAP-style peer: frames matched one by one, failures counted."""

from __future__ import annotations

import json
import sys

import pytest

from helpers import REPO

sys.path.insert(0, str(REPO / "scripts"))
import results_peer  # noqa: E402


def peer_query(frame: int, error_m: float, ok: bool = True, fallback_m: float = 9.0) -> dict:
    return {"query_frame": frame, "variants": {"counts": {"pnp": {"12.0": {
        "ok": ok, "error_m": error_m if ok else None, "num_inliers": 100 if ok else 3,
        "fallback_error_m": fallback_m}}}}}


def step(frame: int, error_m: float | None, source: str | None = "geometry", inliers: int = 0) -> dict:
    return {"query_frame": frame, "measurement_error_m": error_m, "measurement_source": source,
            "n_pnp_inliers": inliers, "n_pnp_query_keypoints": inliers // 2}


def test_each_peer_frame_meets_visloc_s_median_measurement_there(tmp_path):
    peer_dir, out = tmp_path / "peer", tmp_path / "out"
    peer_dir.mkdir()
    out.mkdir()
    drive = "2011_10_03_drive_0027"
    (peer_dir / f"peer_{drive}.json").write_text(json.dumps({
        "params": {"drive": drive, "query_camera": "image_00", "db_camera": "image_00"},
        "versions": {"pycolmap": "4.2.1"},
        "queries": [peer_query(0, 0.30), peer_query(5, 0.10), peer_query(10, None, ok=False, fallback_m=8.0),
                    peer_query(15, 0.2)]}))  # frame 15: visloc never posed it, so it is left out
    (out / f"{drive}_same_image_00_refined.json").write_text(json.dumps({"series": [
        [step(0, 0.10, inliers=300), step(5, 0.40, inliers=120), step(10, 9.5, "geotag")],
        [step(5, 0.20, inliers=160), step(10, 0.50, inliers=40), step(15, None, None)],
        [step(10, 0.70, inliers=60)]]}))
    # a stereo peer run with no matching evaluation is skipped, not an error
    (peer_dir / "peer_2011_09_26_drive_0001.json").write_text(json.dumps({
        "params": {"drive": "2011_09_26_drive_0001", "query_camera": "image_00", "db_camera": "image_01"},
        "queries": [peer_query(0, 0.05)]}))

    digest = results_peer.digest_peer({"peer/results": peer_dir, "elsewhere": tmp_path / "missing"}, out)

    assert list(digest) == [drive]
    d = digest[drive]
    assert [r["frame"] for r in d["frames"]] == [0, 5, 10]
    assert [r["visloc_error_m"] for r in d["frames"]] == pytest.approx([0.10, 0.30, 0.70])  # medians over the series
    assert [r["peer_error_m"] for r in d["frames"]] == [0.30, 0.10, 8.0]  # the failure at its fallback's error
    assert d["peer_failures"] == 1 and d["visloc_better"] == 2
    assert [r["visloc_geotag_fallbacks"] for r in d["frames"]] == [0, 0, 1]
    assert d["visloc_error_m"]["mean"] == pytest.approx(1.1 / 3)
    # support: the median over the series that posed the frame (a geotag fallback is no pose)
    assert [r["visloc_inliers"] for r in d["frames"]] == [300, 140, 50]
    assert [r["visloc_query_keypoints"] for r in d["frames"]] == [150, 70, 25]
    assert [r["peer_inliers"] for r in d["frames"]] == [100, 100, 3]
    assert d["peer_inliers"]["median"] == 100 and d["visloc_query_keypoints"]["median"] == 70

    # a pose whose position the peer's JSON states is measured against visloc's truth of the frame, not the peer's
    query = peer_query(5, 0.10)
    query.update(truth_lat_deg=49.0, truth_lon_deg=8.4, truth_east_north_m=[10.0, 20.0])
    query["variants"]["counts"]["pnp"]["12.0"]["east_north_m"] = [10.0, 20.1]  # 0.1 m north of the peer's truth
    assert results_peer.peer_pose(query)["error_m"] == 0.10  # no truth of visloc's: the peer's own figure
    north_of_it = results_peer.peer_pose(query, (49.0 + 0.04 / 111_200, 8.4))  # visloc's truth 4 cm north of it
    assert north_of_it["error_m"] == pytest.approx(0.06, abs=1e-3)

    lines: list[str] = []
    results_peer.render_peer(digest, lines.append)
    row = next(line for line in lines if line.startswith(f"| {drive} "))
    assert "| 2 of 3 | 1 | 1 |" in row
    support = [line for line in lines if line.startswith(f"| {drive} ")][1]
    assert support == f"| {drive} | 3 / 100 / 100 | 50 / 140 / 300 | 25 / 70 / 150 | 2 of 3 |"
    assert "| 10 | 8.000 (failed) | 3 | 0.700 | 50 | 25 |" in lines
