"""Faults of sharded stores and their ingest on a real Dask cluster: a worker killed mid-ingest, a damaged
tile, an unreadable image, bad arguments, a scheduler that is not there. Each runs as a user would (the
visloc command in a fresh process) except the killed worker, which the test kills from inside the run."""

from __future__ import annotations

import os
import signal
import sqlite3
import threading
import time
from pathlib import Path

import pytest

from visloc.db.shards import Manifest, rows_digest, staging_images
from visloc.store.sharded import merged_store, prepare_store, publish_tiles, staging_path

from helpers import KITTI_DRIVE, PAPER_CONTRAST, run_cli
from fault_table import Fault, params
from helpers import one_line_error

pytest.importorskip("distributed")

FAULTS = [
    Fault("shards-worker-killed", "sharded stores",
          "One of two Dask workers killed with SIGKILL while the drive's frames are being described",
          "Its frames are described again by the other worker and a new worker takes its place; the finished "
          "store equals, row for row, the single file one process writes"),
    Fault("shards-damaged-tile", "sharded stores",
          "A tile's file changed after it was published (a geotag edited in place)",
          "Every reading command stops with one line naming the tile's file and its checksum, exit 2; the next "
          "visloc ingest writes that tile again (and only it), and reading works"),
    Fault("shards-unreadable-image", "sharded stores",
          "An image of the drive that is not an image, ingested into a sharded store on two workers",
          "One line naming the file, exit 2, the images before it kept; with --skip-bad-frames the ingest "
          "completes and the tiles hold every other image"),
    Fault("shards-bad-arguments", "sharded stores",
          "--tile-m 0 or nan, --halo-m -1, --halo-m without --tile-m, --tile-m on a store file, and another "
          "tile size for an existing sharded store",
          "One line naming the flag (and the store's own tile size), exit 2, before any image is described"),
    Fault("shards-no-scheduler", "sharded stores",
          "--address of a port where no Dask scheduler answers",
          "One line naming the address, exit 2; no tile written"),
]
CASES = {f.id: f for f in FAULTS}


def _ingest(drive, store, *extra):
    return run_cli("ingest", drive, "--db", store, *extra, timeout=900)


def _all_ids(path) -> list[int]:
    return [r[0] for r in staging_images(path)]


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["shards-damaged-tile"]]))
def test_a_damaged_tile_is_named_and_written_again(fault, tmp_path, csv_drive):
    city = tmp_path / "city"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--workers", "2").returncode == 0
    with Manifest(city, read_only=True) as manifest:
        tile = manifest.tiles()[1]
    conn = sqlite3.connect(city / tile.file)
    conn.execute("UPDATE images SET lat_deg = lat_deg + 0.001")
    conn.commit()
    conn.close()
    refused = run_cli("info", "--db", city)
    one_line_error(refused, str(city / tile.file), "checksum")
    checked = run_cli("check", "--db", city)
    assert checked.returncode == 2 and str(city / tile.file) in checked.stdout, checked.stdout + checked.stderr
    redone = _ingest(csv_drive, city, "--workers", "2")
    assert redone.returncode == 0 and "(1 written," in redone.stdout, redone.stdout + redone.stderr
    assert run_cli("info", "--db", city).returncode == 0
    checked = run_cli("check", "--db", city)
    assert checked.returncode == 0 and "no damage found" in checked.stdout, checked.stdout + checked.stderr


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["shards-bad-arguments"]]))
def test_bad_sharded_arguments_are_refused_in_one_line(fault, tmp_path, csv_drive):
    one_line_error(_ingest(csv_drive, tmp_path / "c", "--tile-m", "0"), "--tile-m")
    one_line_error(_ingest(csv_drive, tmp_path / "c", "--tile-m", "nan"), "--tile-m")
    one_line_error(_ingest(csv_drive, tmp_path / "c", "--tile-m", "5", "--halo-m", "-1"), "--halo-m")
    assert not (tmp_path / "c").exists()  # refused before anything is made
    one_line_error(_ingest(csv_drive, tmp_path / "one.sqlite", "--halo-m", "3"), "--halo-m", "--tile-m")
    (tmp_path / "file.sqlite").write_bytes(b"")
    one_line_error(_ingest(csv_drive, tmp_path / "file.sqlite", "--tile-m", "5"), "file.sqlite", "folder")
    city = tmp_path / "city"
    assert _ingest(csv_drive, city, "--tile-m", "4", "--workers", "1").returncode == 0
    one_line_error(_ingest(csv_drive, city, "--tile-m", "8", "--workers", "1"), str(city), "4 m", "8 m")


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["shards-unreadable-image"]]))
def test_an_unreadable_image_is_named_and_the_tiles_stay_complete(fault, tmp_path):
    from helpers import write_csv_drive

    drive = write_csv_drive(tmp_path / "drive")
    (drive.parent / "frame_0007.png").write_bytes(b"not a png")
    city = tmp_path / "city"
    failed = _ingest(drive, city, "--tile-m", "4", "--workers", "2")
    one_line_error(failed, "frame_0007.png")
    skipped = _ingest(drive, city, "--workers", "2", "--skip-bad-frames")
    assert skipped.returncode == 0, skipped.stderr
    with Manifest(city, read_only=True) as manifest:
        assert sum(t.n_owned for t in manifest.tiles()) == 11
    assert run_cli("info", "--db", city).returncode == 0


@pytest.mark.parametrize("fault", params([CASES["shards-no-scheduler"]]))
def test_an_address_where_no_scheduler_answers_is_refused(fault, tmp_path, csv_drive):
    one_line_error(_ingest(csv_drive, tmp_path / "city", "--tile-m", "4", "--address", "tcp://127.0.0.1:9"),
                   "--address", "127.0.0.1:9")
    assert not (tmp_path / "city" / "tiles").exists()


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["shards-worker-killed"]]))
def test_a_worker_killed_mid_ingest_changes_nothing(fault, kitti_root, tmp_path):
    """SIGKILL one of two workers while they describe the drive: its frames are described again by
    the other (and the worker restarted), and the store equals one written by a single process. SIFT only
    (``--features-only``) on both sides: the kill comes while frames are described, and the structure a
    cluster builds is compared with one file's in test_shards."""
    from visloc.params import SiftParams
    from visloc.sources.opening import open_source
    from visloc.store.build import ingest_sequence
    from visloc.store.cluster import open_cluster
    from visloc.store.workspace import Workspace

    limit = 24
    single = tmp_path / "one.sqlite"
    made = run_cli("ingest", kitti_root, "--drive", KITTI_DRIVE, "--camera", "image_00", "--db", single,
                   "--workers", "1", "--limit", str(limit), "--features-only", *PAPER_CONTRAST, timeout=1800)
    assert made.returncode == 0, made.stderr

    city = tmp_path / "city"
    staging = staging_path(city)
    seq = open_source(kitti_root, drive=KITTI_DRIVE, camera="image_00")
    prepare_store(city, 25.0, 50.0, seq.frames[0].lat_deg, seq.frames[0].lon_deg)
    killed: list[int] = []
    described_at_kill: list[int] = []
    with open_cluster(2) as cluster:
        pids = list(cluster.worker_pids().values())
        ws = Workspace(staging, create=True)

        def kill_one_when_started() -> None:
            deadline = time.monotonic() + 600
            while time.monotonic() < deadline:  # a condition, not a delay: the first images are stored
                if staging.exists() and (described := _count(staging)) >= 4:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
                    described_at_kill.append(described)
                    return
                time.sleep(0.05)

        watcher = threading.Thread(target=kill_one_when_started, daemon=True)
        watcher.start()
        report = ingest_sequence(ws, seq, SiftParams(), limit=limit, cluster=cluster, structure=False)
        watcher.join(timeout=5)
        publish_tiles(city, cluster, ws.global_vectors.global_vectors_by_image())
        alive = list(cluster.worker_pids().values())
    assert killed and killed[0] not in alive, "no worker was killed mid-ingest"
    assert described_at_kill[0] < limit, "the worker was killed after every frame was described"
    assert report.n_added == limit
    ids = _all_ids(single)
    assert _all_ids(merged_store(city)) == ids
    assert rows_digest(merged_store(city), ids) == rows_digest(single, ids)


def _count(path: Path) -> int:
    try:
        conn = sqlite3.connect(f"{path.absolute().as_uri()}?mode=ro", uri=True, timeout=1)
        try:
            return conn.execute("SELECT count(*) FROM images").fetchone()[0]
        finally:
            conn.close()
    except sqlite3.Error:
        return 0
