"""Faults of the store file: read-only use, damaged rows, two writers at once. Each case runs the
visloc command as a user would and checks what it prints and that the file keeps what it held."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fault_table import Fault, params
from helpers import CSV_PAIR_FRAMES, REPO, copy_store, run_cli
from helpers import make_version_1_store, one_line_error

FAULTS = [
    Fault("read-only-medium", "store file",
          "A store on a read-only medium (a WAL store whose side files cannot be created), read by visloc info",
          "Read as it is: the images are listed, nothing is written"),
    Fault("info-writes-nothing", "store file",
          "visloc info on a store in rollback-journal mode",
          "The file stays byte for byte the same, its journal mode unchanged, no side file left"),
    Fault("old-schema-read", "store file",
          "visloc info on a store of an older schema version",
          "Refused without migrating: one line naming the file and 'visloc upgrade', exit 2; "
          "visloc upgrade then migrates it keeping every row"),
    Fault("keypoint-count-mismatch", "store file",
          "An image row whose keypoint count does not match its keypoint BLOB",
          "One line naming the store and the frame, exit 2"),
    Fault("null-descriptors", "store file",
          "An image row whose descriptors are NULL",
          "One line naming the store and the frame, exit 2"),
    Fault("concurrent-create", "store file",
          "Four processes creating and filling the same new store at the same moment",
          "Each waits for the others' lock: all succeed and the store holds every image once"),
]
CASES = {f.id: f for f in FAULTS}


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def built(csv_pair):
    """The shared synthetic store (a CSV drive, as ingest leaves it: WAL mode, checkpointed) and the drive's CSV;
    every case works on a copy of the store."""
    return csv_pair.db_csv, csv_pair.store


def copy_of(store: Path, folder: Path) -> Path:
    """A copy of the shared store in ``folder``, named store.sqlite."""
    return copy_store(store, folder)


def read_only_mount(folder: Path) -> list[str]:
    """A command prefix that runs what follows with ``folder`` bind-mounted read-only over itself, in a
    private mount namespace (nothing outside the command sees the mount)."""
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount --bind -o ro '{folder}' '{folder}' && true"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a read-only mount here: {probe.stderr.strip()}")
    return ["unshare", "-m", "sh", "-c", f"mount --bind -o ro '{folder}' '{folder}' && exec \"$@\"", "sh"]


@pytest.mark.parametrize("fault", params([CASES["read-only-medium"]]))
def test_a_store_on_a_read_only_medium_can_be_read(built, tmp_path, fault):
    _, store = built
    path = copy_of(store, tmp_path / "medium")
    assert path.read_bytes()[18:20] == b"\x02\x02"  # the file header says WAL
    before = digest(path)
    prefix = read_only_mount(path.parent)
    result = subprocess.run([*prefix, sys.executable, "-m", "visloc", "info", "--db", str(path)],
                            capture_output=True, text=True, cwd=REPO, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"{CSV_PAIR_FRAMES} images" in result.stdout and f"dbdrive/camera: {CSV_PAIR_FRAMES} images" in result.stdout
    assert digest(path) == before and sorted(p.name for p in path.parent.iterdir()) == ["store.sqlite"]


@pytest.mark.parametrize("fault", params([CASES["info-writes-nothing"]]))
def test_info_changes_nothing_in_the_file(built, tmp_path, fault):
    _, store = built
    path = copy_of(store, tmp_path / "plain")
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA journal_mode=DELETE")
    conn.close()
    before = digest(path)
    result = run_cli("info", "--db", path)
    assert result.returncode == 0, result.stderr
    assert digest(path) == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["store.sqlite"]
    assert sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0] == "delete"


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["old-schema-read"]]))
def test_reading_an_old_store_does_not_migrate_it(tmp_path, fault):
    path = tmp_path / "v1.sqlite"
    make_version_1_store(path)
    before = digest(path)
    result = run_cli("info", "--db", path)
    one_line_error(result, str(path), "schema version 1", "visloc upgrade")
    assert digest(path) == before
    upgraded = run_cli("upgrade", "--db", path)
    assert upgraded.returncode == 0, upgraded.stderr
    assert "schema version 1 -> 7" in upgraded.stdout
    again = run_cli("upgrade", "--db", path)
    assert again.returncode == 0 and "already at schema version 7" in again.stdout
    info = run_cli("info", "--db", path)
    assert info.returncode == 0, info.stderr
    assert "drive/image_01: 1 images" in info.stdout
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT count(*) FROM pair_counts").fetchone()[0] == 1  # the cached count is kept


@pytest.mark.parametrize("fault", params([CASES["keypoint-count-mismatch"], CASES["null-descriptors"]]))
def test_a_damaged_image_row_is_a_one_line_error(built, tmp_path, fault):
    csv, store = built
    path = copy_of(store, tmp_path / "damaged")
    conn = sqlite3.connect(path)
    if fault.id == "keypoint-count-mismatch":
        conn.execute("UPDATE images SET n_keypoints = n_keypoints + 1 WHERE frame = 3")
    else:
        conn.execute("UPDATE images SET descriptors_u8 = NULL WHERE frame = 3")
    conn.commit()
    conn.close()
    result = run_cli("localize", csv, "--db", path, "--db-camera", "camera", "--steps", "2")
    one_line_error(result, str(path), "dbdrive/camera frame 3", "damaged")
    assert "Traceback" not in result.stderr


def _create_and_fill(path: str, worker: int, barrier) -> None:
    from visloc.db import FeatureStore, ImageRecord

    barrier.wait()
    with FeatureStore(path, create=True) as store:
        rng = np.random.default_rng(worker)
        kp = rng.random((5, 6), dtype=np.float32)
        desc = rng.integers(0, 256, (5, 128), dtype=np.uint8)
        store.require_setting("sift", {"n_features": 0})
        for frame in range(3):
            record = ImageRecord(source=f"drive{worker}", camera="camera", frame=frame, path=f"/x/{frame}.png",
                                 timestamp_s=100.0 + frame, lat_deg=49.0, lon_deg=8.4)
            store.add_images([(record, kp, desc)])


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["concurrent-create"]]))
def test_writers_creating_one_store_at_once_wait_for_each_other(tmp_path, fault):
    ctx = mp.get_context("spawn")
    for attempt in range(3):  # the race is in the first milliseconds: try it a few times
        path = tmp_path / f"shared{attempt}.sqlite"
        barrier = ctx.Barrier(4)
        procs = [ctx.Process(target=_create_and_fill, args=(str(path), w, barrier)) for w in range(4)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(timeout=300)
        assert [p.exitcode for p in procs] == [0, 0, 0, 0]
        conn = sqlite3.connect(path)
        assert conn.execute("SELECT count(*) FROM images").fetchone()[0] == 12
        assert conn.execute("SELECT count(*) FROM visloc_schema").fetchone()[0] == 1
        conn.close()
