"""Sharded stores: the grid, ingest on a real local Dask cluster, faults, and the same answers as one file."""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from visloc.db.shards import STAGING_NAME, Manifest, file_sha256, rows_digest, staging_images
from visloc.store.sharded import GlobalSearch, TileIndex, merged_store
from visloc.store.workspace import Workspace
from visloc.store.tiles import cells_within, owner_cells, tiles_of_images

from helpers import KITTI_DRIVE, built_once, copy_store, run_cli
from helpers import one_line_error

pytest.importorskip("distributed")

SOURCE = f"{KITTI_DRIVE}_sync"


# -- the grid, pure ----------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-500, 500), st.floats(-500, 500)), min_size=1, max_size=40),
       st.sampled_from([10.0, 25.0, 100.0]), st.sampled_from([0.0, 5.0, 30.0]))
def test_a_tile_holds_every_image_within_its_halo(points, tile_m, halo_m):
    """Each tile holds every image within ``halo_m`` of its square, and its owner holds every image."""
    pts = np.array(points)
    tiles = tiles_of_images(pts, tile_m, halo_m)
    owners = owner_cells(pts, tile_m)
    for k, owner in enumerate(map(tuple, owners)):
        assert k in tiles[owner]
    for (ix, iy), members in tiles.items():
        lo, hi = np.array([ix, iy]) * tile_m, (np.array([ix, iy]) + 1) * tile_m
        outside = np.maximum(np.maximum(lo - pts, pts - hi), 0).max(axis=1)  # Chebyshev distance to the square
        assert set(members.tolist()) == set(np.flatnonzero(outside <= halo_m + 1e-9).tolist()) or \
            set(np.flatnonzero(outside < halo_m - 1e-9).tolist()) <= set(members.tolist())


@settings(max_examples=60, deadline=None)
@given(st.floats(-1000, 1000), st.floats(-1000, 1000), st.floats(0, 120), st.sampled_from([10.0, 25.0, 250.0]))
def test_a_gate_opens_exactly_the_tiles_its_disc_meets(east, north, radius, tile_m):
    centre = np.array([east, north])
    picked = {tuple(c) for c in cells_within(centre, radius, tile_m).tolist()}
    lo = np.floor((centre - radius - tile_m) / tile_m).astype(int)
    hi = np.floor((centre + radius + tile_m) / tile_m).astype(int)
    for ix in range(lo[0], hi[0] + 1):
        for iy in range(lo[1], hi[1] + 1):
            nearest = np.clip(centre, np.array([ix, iy]) * tile_m, (np.array([ix, iy]) + 1) * tile_m)
            gap = np.linalg.norm(nearest - centre) - radius
            if abs(gap) > 1e-9:  # on the circle itself either answer is right
                assert ((ix, iy) in picked) == (gap < 0)
    # a point within the radius lies in a picked tile
    assert tuple(owner_cells(centre, tile_m)[0]) in picked


def test_tile_index_and_global_search_pick_the_owners():
    rng = np.random.default_rng(1)
    cells = np.array([(0, 0), (1, 0), (5, 5)])
    index = TileIndex.of(25.0, cells, ("a", "b", "c"))
    assert sorted(index.for_gate(np.array([24.0, 10.0]), 3.0)) == [0, 1]
    assert index.for_gate(np.array([140.0, 140.0]), 1.0) == [2]
    assert index.for_gate(np.array([-500.0, 0.0]), 10.0) == []
    vectors = rng.normal(size=(200, 16)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    tiles = np.array([f"t{k % 7}" for k in range(200)], object)
    rows, owners = GlobalSearch(vectors, tiles).tiles_for(vectors[42], k=5)
    assert rows[0] == 42 and owners[0] == "t0"


# -- ingest on a real local cluster (a synthetic drive) -----------------------------------------------

def _ingest(drive, store, *extra):
    return run_cli("ingest", drive, "--db", store, *extra, timeout=900)


def _all_ids(path) -> list[int]:
    return [r[0] for r in staging_images(path)]


@pytest.mark.slow
def test_sharded_ingest_equals_one_file_row_for_row_and_resumes(tmp_path, csv_drive):
    single = tmp_path / "one.sqlite"
    assert _ingest(csv_drive, single, "--workers", "1").returncode == 0
    city = tmp_path / "city"
    first = _ingest(csv_drive, city, "--tile-m", "4", "--halo-m", "1", "--workers", "2")
    assert first.returncode == 0, first.stderr
    line = first.stdout.strip().splitlines()[-1]
    assert "tiles of 4 m" in line and "0 complete already" in line, line
    with Manifest(city, read_only=True) as manifest:
        tiles = manifest.tiles()
        index, vectors = manifest.global_index()
    assert len(tiles) >= 3  # the drive is 11 m long
    assert sum(t.n_owned for t in tiles) == 12 and len(index["image_id"]) == 12 and vectors is not None
    for t in tiles:  # each tile a complete store of its own, with the checksum the manifest states
        assert file_sha256(city / t.file) == t.sha256
        assert _all_ids(city / t.file) and rows_digest(city / t.file, _all_ids(city / t.file)) == t.rows_digest
    merged = merged_store(city)
    ids = _all_ids(single)
    assert _all_ids(merged) == ids
    assert rows_digest(merged, ids) == rows_digest(single, ids)  # every row, every BLOB's checksum

    again = _ingest(csv_drive, city, "--workers", "2")  # the grid is the store's
    assert again.returncode == 0, again.stderr
    assert f"(0 written, {len(tiles)} complete already)" in again.stdout

    info = run_cli("info", "--db", city)
    assert info.returncode == 0 and "12 images" in info.stdout, info.stdout + info.stderr
    assert f"sharded store: {len(tiles)} tiles of 4 m" in info.stdout


@pytest.mark.slow
def test_a_drive_added_elsewhere_leaves_every_tile_there_as_it_was(tmp_path, csv_drive):
    """A city grows drive by drive: a drive 1 km north writes its own tiles only; the tiles already
    there (their rows, their files) stay untouched."""
    other = tmp_path / "north"
    shutil.copytree(csv_drive.parent, other)
    lines = (other / "geotags.csv").read_text().splitlines()
    moved = [lines[0]] + [",".join([f, t, f"{float(lat) + 0.009:.9f}", lon, h])
                          for f, t, lat, lon, h in (line.split(",") for line in lines[1:])]
    (other / "geotags.csv").write_text("\n".join(moved) + "\n")
    city = tmp_path / "city"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--workers", "2").returncode == 0
    with Manifest(city, read_only=True) as manifest:
        before = {t.key: t.sha256 for t in manifest.tiles()}
    added = _ingest(other / "geotags.csv", city, "--workers", "2")
    assert added.returncode == 0, added.stderr
    with Manifest(city, read_only=True) as manifest:
        after = {t.key: t.sha256 for t in manifest.tiles()}
    assert len(after) == 2 * len(before) and all(after[k] == sha for k, sha in before.items())
    assert f"({len(before)} written, {len(before)} complete already)" in added.stdout
    info = run_cli("info", "--db", city)
    assert info.returncode == 0 and "24 images" in info.stdout, info.stdout + info.stderr


def _moved_north(csv_drive, folder) -> Path:
    """A copy of the synthetic drive 1 km north of it: its geotags.csv."""
    shutil.copytree(csv_drive.parent, folder)
    lines = (folder / "geotags.csv").read_text().splitlines()
    moved = [lines[0]] + [",".join([f, t, f"{float(lat) + 0.009:.9f}", lon, h])
                          for f, t, lat, lon, h in (line.split(",") for line in lines[1:])]
    (folder / "geotags.csv").write_text("\n".join(moved) + "\n")
    return folder / "geotags.csv"


@pytest.mark.slow
def test_a_command_reads_the_catalogue_of_the_drives_it_uses_only(tmp_path, csv_drive):
    """A city holds many drives; a command that localizes on one reads the rows of that one only, merged
    from the tiles that own its images, and answers as a store of that drive alone does."""
    north = _moved_north(csv_drive, tmp_path / "north")
    city, alone = tmp_path / "city", tmp_path / "north.sqlite"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--workers", "2").returncode == 0
    assert _ingest(north, city, "--workers", "2").returncode == 0
    assert _ingest(north, alone, "--workers", "1").returncode == 0
    ws = Workspace(city)
    assert len(ws.drive_keys()) == 2 and ws.catalogue_datasets == frozenset()  # the manifest says what it holds
    settings_only = ws._file
    assert _all_ids(settings_only) == [] and len(_all_ids(merged_store(city, features=False))) == 24
    assert settings_only.is_file()  # catalogues of other drives, or of all, are kept beside each other
    (north_key,) = Workspace(alone).drive_keys()
    db = ws.load_database(*north_key)
    assert ws.catalogue_datasets == {north_key}
    assert _all_ids(ws._file) == [im.image_id for im in db.images]  # its 12 images, none of the other drive
    with Manifest(city, read_only=True) as manifest:
        assert set(manifest.owner_tiles(*north_key).values()) < {t.key for t in manifest.tiles()}
    expected = Workspace(alone).load_database(*north_key)
    assert np.array_equal(db.east_north_m, expected.east_north_m) and len(db) == 12
    assert ws.image_count() == 24 and {d.name for d in ws.drives()} == {f"{s}/{c}" for s, c in ws.drive_keys()}
    assert len(ws.catalogue_datasets) == 2  # a summary of every drive reads them all

    here = run_cli("localize", north, "--db", city, "--steps", "4")
    there = run_cli("localize", north, "--db", alone, "--steps", "4")
    assert here.returncode == 0 and there.returncode == 0, here.stderr + there.stderr
    varying = re.compile(r"^(tiles read|Latency \(ms\)).*\n", re.M)  # the same answers; times vary
    assert varying.sub("", here.stdout) == varying.sub("", there.stdout)
    assert "tiles read: " in here.stdout


@pytest.mark.slow
def test_a_changed_store_replaces_the_catalogue_made_of_it_before(tmp_path, csv_drive):
    """The catalogue a command reads is merged from the tiles once and kept while they stay as they are:
    extending the store makes a new one and removes the old one, so the temporary folder does not fill
    up with a catalogue per version of a growing city."""
    city = tmp_path / "city"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--workers", "2").returncode == 0
    first = merged_store(city, features=False)
    assert merged_store(city, features=False) == first  # kept while the tiles stay as they are
    assert len(_all_ids(first)) == 12
    whole = merged_store(city)  # the other kind, with the features: kept beside it
    shutil.copytree(csv_drive.parent, tmp_path / "later")
    assert _ingest(tmp_path / "later" / "geotags.csv", city, "--workers", "2").returncode == 0
    second = merged_store(city, features=False)
    assert second != first and second.is_file() and not first.exists() and whole.is_file()
    assert len(_all_ids(second)) == 24

    reader = Workspace(city)  # a reader open while the store is extended again reads on
    key = reader.drive_keys()[0]
    assert reader.image_count() == 24 and len(reader.load_database(*key)) == 12
    before = reader._file
    shutil.copytree(csv_drive.parent, tmp_path / "latest")  # the same place: the same tiles change
    assert _ingest(tmp_path / "latest" / "geotags.csv", city, "--workers", "2").returncode == 0
    Workspace(city).load_database(*key)  # another command's catalogue of that drive replaces the reader's
    assert not before.exists()
    assert len(reader.load_database(*key)) == 12 and len(reader.drives()) == 3


@pytest.mark.slow
def test_a_query_reads_only_the_tiles_of_the_images_it_looks_at(tmp_path, csv_drive):
    """A sharded store's database holds every image's metadata at once; the features of an image are
    read from the tile that owns it when the engine asks for them, within the cache's budget."""
    single = tmp_path / "one.sqlite"
    assert _ingest(csv_drive, single, "--workers", "1").returncode == 0
    city = tmp_path / "city"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--halo-m", "1", "--workers", "2").returncode == 0
    with Manifest(city, read_only=True) as manifest:
        n_tiles = len(manifest.tiles())
    one = Workspace(single, read_only=True)
    (dataset,) = one.drives()
    expected = one.load_database(dataset.source, dataset.camera)
    ws = Workspace(city, tile_cache_mb=1.0)
    db = ws.load_database(dataset.source, dataset.camera)
    assert ws.tile_cache_stats.tiles_read == 0  # the metadata of every image, no features yet
    assert [im.image_id for im in db.images] == [im.image_id for im in expected.images]
    assert np.array_equal(db.east_north_m, expected.east_north_m)
    assert np.array_equal(db.descriptors_u8[1], expected.descriptors_u8[1])
    assert ws.tile_cache_stats.distinct_tiles == set(db.descriptors_u8.tiles_of([1]))  # its owner, only
    assert ws.tile_cache_stats.tiles_read == 1 and n_tiles >= 3
    geometry = db.geometry()
    for k in range(len(db)):  # every image, the same bits, whichever tile it is read from
        assert np.array_equal(db.keypoints_f32[k], expected.keypoints_f32[k])
        assert np.array_equal(db.descriptors_u8[k], expected.descriptors_u8[k])
        assert np.array_equal(geometry.keypoints_xy_px[k], expected.geometry().keypoints_xy_px[k])
    assert ws.tile_cache_stats.distinct_tiles == set(db.descriptors_u8.tiles_of(range(len(db))))
    small = Workspace(city, tile_cache_mb=1e-6)  # room for one tile at a time: read, dropped, read again
    tiny = small.load_database(dataset.source, dataset.camera)
    for k in (0, len(tiny) - 1, 0):
        assert np.array_equal(tiny.descriptors_u8[k], expected.descriptors_u8[k])
    stats = small.tile_cache_stats
    assert stats.tiles_read == 3 and stats.tiles_evicted == 2 and len(stats.distinct_tiles) == 2
    queries = small.load_queries(dataset.source, dataset.camera)
    assert np.array_equal(queries.query(5).descriptors_u8, expected.descriptors_u8[5])
    with pytest.raises(IndexError):
        tiny.descriptors_u8[len(tiny)]
    located = run_cli("localize", csv_drive, "--db", city, "--steps", "4")
    assert located.returncode == 0, located.stderr
    assert f"tiles read: {n_tiles} of {n_tiles} (" in located.stdout  # the first query is compared with every image
    squeezed = run_cli("localize", csv_drive, "--db", city, "--steps", "4", "--tile-cache-mb", "0.000001")
    assert squeezed.returncode == 0, squeezed.stderr
    tiles_line = re.compile(r"^(tiles read|Latency \(ms\)).*$", re.M)  # all but the budget's effect and times
    assert tiles_line.sub("", squeezed.stdout) == tiles_line.sub("", located.stdout)  # the same answers
    assert int(re.search(r"(\d+) dropped to stay within the cache", squeezed.stdout).group(1)) > 0
    for bad in ("0", "-1", "nan", "lots"):
        refused = run_cli("localize", csv_drive, "--db", city, "--tile-cache-mb", bad)
        assert refused.returncode == 2 and "--tile-cache-mb" in refused.stderr.splitlines()[-1], refused.stderr

    partial = tmp_path / "partial"  # a reading command never writes a sharded store: it says how to extend it
    assert _ingest(csv_drive, partial, "--tile-m", "4", "--workers", "1", "--limit", "6").returncode == 0
    refused = run_cli("evaluate", csv_drive, "--db", partial)
    one_line_error(refused, str(partial), "6 of the 12 frames", "visloc ingest")


# -- the same answers as one file (drive 0001 in 25 m tiles, two workers) -------------------------------

@pytest.fixture(scope="session")
def city_0001(kitti_evaluation, kitti_root, shared_tmp):
    """Drive 0001 in 25 m tiles, made once per run by ``visloc ingest --tile-m 25`` on a local Dask cluster: its
    right camera as the database (features, global vectors, structure, self-check), its left camera as queries
    (features only, as ``evaluate`` stores them in a file).

    The ingest resumes from a working store that already holds what its first stages make: the session's one
    file (``kitti_evaluation``, the same cameras and settings) less its counts, which is what those stages leave
    (``visloc.store.sharded``). So here the cluster cuts the tiles and the tests read them; that the cluster's
    own features, structure and self-check equal one file's row for row is checked on the synthetic drive
    (``test_sharded_ingest_equals_one_file_row_for_row_and_resumes``)."""
    one_file = kitti_evaluation[0] / "kitti.sqlite"

    def build(folder: Path) -> dict:
        staging = folder / "city" / STAGING_NAME
        copy_store(one_file, staging.parent).rename(staging)
        Workspace(staging).clear_pair_counts()  # ingest keeps no counts
        for camera, extra in (("image_01", ()), ("image_00", ("--features-only",))):
            made = run_cli("ingest", kitti_root, "--drive", KITTI_DRIVE, "--camera", camera, "--db", folder / "city",
                           "--tile-m", "25", "--workers", "2", *extra, timeout=3600)
            assert made.returncode == 0, made.stderr
            assert "0 added, 108 already stored" in made.stdout, made.stdout
        return {}

    folder, _ = built_once(shared_tmp, "city_0001", build)
    return folder / "city"


# One series (from frame 50, the later of the session's two) shows that tiles answer as one file does: a
# sharded store keeps no counts, so every series there is matched afresh, and the series are independent.
TILES_SERIES_START = 50


def _series_from(report: dict, start_frame: int) -> list[dict]:
    [series] = [s for s in report["series"] if s[0]["query_frame"] == start_frame]
    return series


@pytest.mark.slow
def test_paper_mode_on_tiles_equals_one_file(city_0001, kitti_root, kitti_evaluation, tmp_path):
    """The paper's mode on the tiles, over the first two steps of the series (the filter is causal: its first
    two steps are the six-step series' first two), exactly as one file's; the refined test below checks the
    retrieval of all six."""
    _, single, _ = kitti_evaluation
    out = tmp_path / "eval.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", city_0001, "--start-frames",
                     str(TILES_SERIES_START), "--steps", "2", "--json", out, timeout=1800)
    assert result.returncode == 0, result.stderr
    sharded = json.loads(out.read_text())
    assert len(sharded["series"]) == 1
    tiles, expected = sharded["series"][0], _series_from(single, TILES_SERIES_START)[:2]
    assert len(tiles) == len(expected) == 2
    for key in ("counts", "best_db_frame", "measurement_error_m", "estimate_error_m"):
        assert [q[key] for q in tiles] == [q[key] for q in expected], key  # exactly


@pytest.mark.slow
def test_refined_mode_on_tiles_equals_one_file(city_0001, kitti_root, kitti_evaluation, kitti_refined, tmp_path):
    """The refined mode on the tiles, over the first three steps of the series (the filter is causal, and the
    smoother's estimates are compared below only where both runs end): its measurements and filtered estimates are
    one file's to 1e-6 m, and its retrieval (every count, every best match) is the paper mode's on one file,
    exactly."""
    _, single, _ = kitti_evaluation
    out = tmp_path / "tiles.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--mode", "refined", "--smooth", "--db", city_0001,
                     "--start-frames", str(TILES_SERIES_START), "--steps", "3", "--json", out, timeout=1800)
    assert result.returncode == 0, result.stderr
    tiles = _series_from(json.loads(out.read_text()), TILES_SERIES_START)
    one_file = _series_from(kitti_refined[0], TILES_SERIES_START)[:3]
    assert len(one_file) == len(tiles) == 3
    for key in ("measurement_error_m", "estimate_error_m"):
        runs = {"file": [q[key] for q in one_file], "tiles": [q[key] for q in tiles]}
        assert max(abs(a - b) for a, b in zip(runs["file"], runs["tiles"], strict=True)) <= 1e-6, key
    paper = _series_from(single, TILES_SERIES_START)[:3]
    for key in ("counts", "best_db_frame", "candidate_frames"):
        assert [q[key] for q in tiles] == [q[key] for q in paper], key  # exactly


@pytest.mark.slow
def test_structure_is_read_from_the_tile_that_owns_each_view(city_0001, kitti_root, kitti_evaluation, tmp_path):
    """A sharded store's catalogue holds no structure points: a view's points are read from the tile that
    owns it when the engine asks for that view, the same arrays as one file's, and track (the camera-rate
    path, which reads structure view by view) follows the same frames."""
    folder, _, _ = kitti_evaluation
    with sqlite3.connect(merged_store(city_0001, features=False)) as conn:
        n_rows, n_with_points = conn.execute("SELECT count(*), count(points_f64) FROM structures").fetchone()
    assert n_rows > 0 and n_with_points == 0
    single, tiles = Workspace(folder / "kitti.sqlite", read_only=True), Workspace(city_0001)
    dataset = next(d for d in tiles.drives() if d.camera == "image_01")  # the one file's database camera
    one = single.load_structure(single.load_database(dataset.source, dataset.camera))
    lazy = tiles.load_structure(tiles.load_database(dataset.source, dataset.camera))
    assert tiles.tile_cache_stats.tiles_read == 0  # no tile read before a view is asked for
    assert list(lazy) == list(one) and len(lazy) == len(one) > 50
    for k, variants in one.items():
        assert list(lazy[k]) == list(variants)
        for variant, s in variants.items():
            t = lazy[k][variant]
            assert (t.view, t.neighbours, t.reason) == (s.view, s.neighbours, s.reason)
            for a, b in ((t.rows, s.rows), (t.points_world, s.points_world), (t.cov_world, s.cov_world)):
                assert a.dtype == b.dtype and np.array_equal(a, b)
    assert tiles.tile_cache_stats.tiles_read > 0
    runs = []
    for store in (folder / "kitti.sqlite", city_0001):
        out = tmp_path / f"{store.name}.json"
        result = run_cli("track", kitti_root, "--drive", KITTI_DRIVE, "--camera", "image_00", "--db", store,
                         "--db-camera", "image_01", "--frames", "25", "--no-background-relocalization", "--json", out,
                         timeout=1800)
        assert result.returncode == 0, result.stderr
        run = json.loads(out.read_text())
        assert run["params"]["track"]["follow_points"] and "tracked" in run["kinds"]  # following, on either store
        runs.append([f["estimate_m"] for f in run["per_frame"]])
    assert len(runs[0]) == 25
    assert np.allclose(runs[0], runs[1], rtol=0, atol=1e-6)


@pytest.mark.slow
def test_ingest_joins_a_running_cluster_by_its_address(tmp_path, csv_drive):
    """A scheduler and a worker started as a user starts them on a real cluster (``dask scheduler``,
    ``dask worker``), and ingest pointed at the scheduler with --address."""
    import subprocess
    import sys

    dask = Path(sys.executable).parent / "dask"
    scheduler_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--port", "0", "--dashboard-address", ":0",
                               "--scheduler-file", scheduler_file], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        deadline = time.monotonic() + 120
        while not scheduler_file.exists() and time.monotonic() < deadline:  # the scheduler is up
            time.sleep(0.1)
        address = json.loads(scheduler_file.read_text())["address"]
        procs.append(subprocess.Popen([dask, "worker", address, "--nworkers", "1", "--nthreads", "1",
                                       "--dashboard-address", ":0"], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
        city = tmp_path / "city"
        made = _ingest(csv_drive, city, "--tile-m", "4", "--address", address)
        assert made.returncode == 0, made.stderr
        assert "tiles of 4 m" in made.stdout
        with Manifest(city, read_only=True) as manifest:
            assert sum(t.n_owned for t in manifest.tiles()) == 12
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=60)


@pytest.mark.slow
def test_the_dashboard_opens_a_sharded_store(city_0001, browser):
    """``visloc dashboard --db FOLDER``: the page offers the folder as its store and fills in the drive's first
    run. A sharded store keeps no counts, so that run takes a while: the page shows the steps matched so far, with
    the progress in words, before it is ready; it is looked at until two queries are matched. (That the answers
    are one file's is checked with the command line above; a first run matched from no counts is seen to the end
    on a one-file store in test_faults_dashboard.py.)"""
    from helpers import (RUN_S, SERVER_WORK_S, DashboardProcess, new_page, run_number, screenshot, status_text, visit,
                         wait_for)

    proc = DashboardProcess("--db", str(city_0001), "--port", "8431")
    try:
        page = new_page(browser)
        visit(page, proc.url)
        page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()
        seen = wait_for(lambda: (run_number(page) == 0 and re.search(r"\d+ of 11 queries matched so far",
                                                                     page.locator("body").inner_text())),
                        RUN_S, "steps shown while the first run is matched")
        assert seen
        wait_for(lambda: re.search(r"^Matching 11 queries .*: ([2-9]|1[01]) of 11 queries matched", status_text(page)),
                 SERVER_WORK_S, "the progress in words, two queries matched")
        screenshot(page, "newcomer_first_run_filling_in.png")
        page.close()
    finally:
        proc.stop()


def _allocator_in_worker() -> tuple[str | None, bool]:
    import os

    from visloc.store import cluster
    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), cluster._allocator_restored


@pytest.mark.skipif(not Path("/lib/x86_64-linux-gnu/libc.so.6").exists() and not Path("/lib64/libc.so.6").exists(),
                    reason="glibc's allocator only")
def test_a_task_runs_with_the_allocator_a_plain_process_has():
    """A Dask nanny starts its workers with MALLOC_TRIM_THRESHOLD_ set, which fixes glibc's mmap threshold:
    structure and self-check tasks ran a fifth to a third slower in a worker than in a plain process. Every
    task runs after the worker's allocator is given glibc's usual thresholds back."""
    from visloc.store.cluster import open_cluster

    with open_cluster(1) as engine:
        [(_, (trim_setting, restored))] = list(engine.run_all(_allocator_in_worker, [()]))
    assert trim_setting is not None  # what the nanny sets, and the reason for the restoring
    assert restored


def _opencv_threads_in_worker() -> int:
    import cv2
    return cv2.getNumThreads()


@pytest.mark.parametrize("workers", [1, 2])
def test_a_local_cluster_shares_the_cores_among_its_workers_opencv(workers):
    """One worker on a machine of several cores gives its SIFT and matching the cores, as a one-file ingest
    does; a worker per core runs OpenCV on one thread, with no contention between workers."""
    import os

    from visloc.store.cluster import open_cluster

    with open_cluster(workers) as engine:
        threads = [n for _, n in engine.run_all(_opencv_threads_in_worker, [()] * (2 * workers))]
    assert threads == [max(1, (os.cpu_count() or 1) // workers)] * (2 * workers)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 5000), st.integers(1, 64), st.integers(1, 32))
def test_tasks_take_every_item_once_and_shrink_to_one_at_the_end(n_items, n_workers, most):
    from visloc.store.build import task_sizes

    sizes = task_sizes(n_items, n_workers, most)
    assert sum(sizes) == n_items
    assert all(1 <= s <= most for s in sizes)
    assert sizes == sorted(sizes, reverse=True)  # the long tasks first, the short ones last
    if n_items >= n_workers:  # every worker's last task is a single item
        assert sizes[-n_workers:] == [1] * n_workers
