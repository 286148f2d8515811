"""Ingest is idempotent and resumable: interrupted runs lose nothing committed and leave no half image."""

import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from visloc.db import FeatureStore, SettingsMismatchError
from visloc.errors import InputError
from visloc.store.ingest import ingest
from visloc.params import STORE_SIFT, SiftParams
from visloc.sources.drives import open_csv

from helpers import REPO, make_fake_kitti, write_csv_drive
from helpers import assert_no_half_images, assert_same_snapshots, snapshot, wait_for_rows


def test_reingest_skips_everything_stored(tmp_path, csv_drive):
    seq = open_csv(csv_drive)
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        first = ingest(store, seq, SiftParams(), workers=1)
        second = ingest(store, seq, SiftParams(), workers=1)
    assert (first.n_added, first.n_skipped) == (12, 0)
    assert (second.n_added, second.n_skipped) == (0, 12)


def test_parallel_ingest_equals_serial(tmp_path, csv_drive):
    seq = open_csv(csv_drive)
    for name, workers in (("serial", 1), ("parallel", 2)):
        with FeatureStore(tmp_path / f"{name}.sqlite", create=True) as store:
            ingest(store, seq, SiftParams(), workers=workers)
    assert_same_snapshots(snapshot(tmp_path / "serial.sqlite"), snapshot(tmp_path / "parallel.sqlite"))


def test_ctrl_c_commits_finished_images_and_resume_completes(tmp_path, csv_drive):
    seq = open_csv(csv_drive)
    done = []

    def interrupt_after_five(n_done, n_total):
        if n_done:
            done.append(n_done)
        if len(done) == 5:
            raise KeyboardInterrupt

    with FeatureStore(tmp_path / "resumed.sqlite", create=True) as store:
        with pytest.raises(KeyboardInterrupt):
            ingest(store, seq, SiftParams(), workers=1, batch_size=8, progress=interrupt_after_five)
        assert store.image_count() == 5  # the five finished images, not a partial batch lost
        report = ingest(store, seq, SiftParams(), workers=1)
        assert (report.n_skipped, report.n_added) == (5, 7)
    with FeatureStore(tmp_path / "clean.sqlite", create=True) as store:
        ingest(store, seq, SiftParams(), workers=1)
    assert_same_snapshots(snapshot(tmp_path / "resumed.sqlite"), snapshot(tmp_path / "clean.sqlite"))


def _ingest_process(csv_path, db_path):
    return subprocess.Popen([sys.executable, "-m", "visloc", "ingest", str(csv_path), "--db", str(db_path),
                             "--workers", "1"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_killed_ingest_process_resumes_to_the_same_store(tmp_path, sig):
    n_frames = 120  # long enough that a loaded machine cannot finish it between the 8th row and the signal
    csv_path = write_csv_drive(tmp_path / "long", n_frames=n_frames, step_px=60)
    db_path = tmp_path / "killed.sqlite"
    proc = _ingest_process(csv_path, db_path)
    wait_for_rows(db_path, 8, proc)
    os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=60)
    interrupted = snapshot(db_path)
    assert 8 <= len(interrupted) < n_frames
    assert_no_half_images(interrupted)
    if sig == signal.SIGINT:
        assert proc.returncode == 130
        assert f"interrupted; {db_path} keeps {len(interrupted)} images" in err
    resumed = subprocess.run([sys.executable, "-m", "visloc", "ingest", str(csv_path), "--db", str(db_path)],
                             cwd=REPO, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert f"{n_frames - len(interrupted)} added, {len(interrupted)} already stored" in resumed.stdout
    with FeatureStore(tmp_path / "clean.sqlite", create=True) as store:
        ingest(store, open_csv(csv_path), STORE_SIFT, workers=2)  # what visloc ingest describes a new store at
    assert_same_snapshots(snapshot(db_path), snapshot(tmp_path / "clean.sqlite"))


def test_bad_image_stops_ingest_keeping_what_came_before(tmp_path, csv_drive):
    (csv_drive.parent / "frame_0004.png").write_bytes(b"garbage")
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        with pytest.raises(InputError, match="frame_0004.png: cannot decode image"):
            ingest(store, open_csv(csv_drive), SiftParams(), workers=1)
        assert sorted(store.stored_frames("drive", "camera")) == [0, 1, 2, 3]


def test_featureless_image_is_refused(tmp_path, csv_drive):
    import cv2

    cv2.imwrite(str(csv_drive.parent / "frame_0002.png"), np.zeros((240, 320), np.uint8))
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        with pytest.raises(InputError, match="frame_0002.png: no SIFT keypoints"):
            ingest(store, open_csv(csv_drive), SiftParams(), workers=1)


def test_other_sift_settings_are_refused_before_any_work(tmp_path, csv_drive):
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        ingest(store, open_csv(csv_drive), SiftParams(), workers=1, limit=2)
        with pytest.raises(SettingsMismatchError, match="n_features: store 0, asked 500"):
            ingest(store, open_csv(csv_drive), SiftParams(n_features=500), workers=1)
        assert store.image_count() == 2


def test_reingest_fills_attitudes_and_extrinsics_a_version_1_store_lacks(tmp_path):
    from helpers import make_fake_kitti
    from visloc.sources.drives import open_kitti

    make_fake_kitti(tmp_path / "kitti", n_frames=3)
    seq = open_kitti(tmp_path / "kitti", None, "image_01")
    path = tmp_path / "s.sqlite"
    with FeatureStore(path, create=True) as store:
        ingest(store, seq, SiftParams(), workers=1)
        ids_before = [im.image_id for im in store.images()]
        # what a migrated version-1 store looks like: no attitudes, no extrinsics
        store.db.execute("UPDATE images SET roll_rad = NULL, pitch_rad = NULL, yaw_rad = NULL")
        store.db.execute("UPDATE cameras SET t_camera_imu_json = NULL")
        store.db.conn.commit()
        assert store.frames_without_attitude(seq.source, "image_01") == {0, 1, 2}
        report = ingest(store, seq, SiftParams(), workers=1)
        assert (report.n_added, report.n_skipped, report.n_attitudes_filled) == (0, 3, 3)
        assert [im.image_id for im in store.images()] == ids_before  # features untouched
        assert store.frames_without_attitude(seq.source, "image_01") == set()
        assert store.images()[0].yaw_rad == -2.6
        np.testing.assert_allclose(store.get_camera(seq.source, "image_01").T_camera_imu, seq.T_camera_imu)
        assert ingest(store, seq, SiftParams(), workers=1).n_attitudes_filled == 0  # nothing left to fill


def test_reingest_fills_the_geotag_accuracy_a_version_2_store_lacks(tmp_path):
    from helpers import make_fake_kitti
    from visloc.sources.drives import open_kitti

    drive = make_fake_kitti(tmp_path / "kitti", n_frames=3)
    for i, record in enumerate(sorted((drive / "oxts" / "data").glob("*.txt"))):
        values = record.read_text().split()
        values[23] = f"{0.3 + 0.1 * i}"  # field 24, pos_accuracy (m)
        record.write_text(" ".join(values) + "\n")
    seq = open_kitti(tmp_path / "kitti", None, "image_01")
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        ingest(store, seq, SiftParams(), workers=1)
        assert [im.position_accuracy_m for im in store.images()] == [0.3, 0.4, 0.5]
        ids_before = [im.image_id for im in store.images()]
        store.db.execute("UPDATE images SET position_accuracy_m = NULL")  # what a migrated version-2 store holds
        store.db.conn.commit()
        report = ingest(store, seq, SiftParams(), workers=1)
        assert (report.n_added, report.n_skipped, report.n_accuracies_filled, report.n_attitudes_filled) == (0, 3, 3, 0)
        assert [im.image_id for im in store.images()] == ids_before
        assert [im.position_accuracy_m for im in store.images()] == [0.3, 0.4, 0.5]
        assert ingest(store, seq, SiftParams(), workers=1).n_accuracies_filled == 0
        # a record read as no position solution now (once read with its copied accuracy) loses it, and only it
        record = sorted((drive / "oxts" / "data").glob("*.txt"))[1]
        values = record.read_text().split()
        values[27] = "-1"  # field 28, posmode
        record.write_text(" ".join(values) + "\n")
        assert ingest(store, open_kitti(tmp_path / "kitti", None, "image_01"), SiftParams(),
                      workers=1).n_accuracies_filled == 1
        assert [im.position_accuracy_m for im in store.images()] == [0.3, None, 0.5]
        assert [im.image_id for im in store.images()] == ids_before


def test_geotags_the_source_now_states_otherwise_are_taken_again_and_their_structure_rebuilt(tmp_path):
    """A store made before its drive's geotags were taken at the images' times: ingest takes the new geotags and
    drops the structure and self-checks made at the old ones (the build steps make them again), keeping the
    features."""
    from visloc.sources.drives import open_kitti
    from visloc.store.build import build_structure
    from visloc.store.workspace import Workspace

    make_fake_kitti(tmp_path / "kitti", n_frames=4)
    seq = open_kitti(tmp_path / "kitti", None, "image_00")
    with FeatureStore(tmp_path / "s.sqlite", create=True) as store:
        ingest(store, seq, SiftParams(), workers=1)
    ws = Workspace(tmp_path / "s.sqlite")
    assert build_structure(ws, seq.source, seq.camera) == 4
    with FeatureStore(tmp_path / "s.sqlite") as store:
        features = store.features(im.image_id for im in store.images())
        store.db.execute("UPDATE images SET lat_deg = lat_deg + 3e-7 WHERE frame < 2")  # 3 cm north, as once read
        store.db.conn.commit()
        assert ingest(store, seq, SiftParams(), workers=1).n_geotags_moved == 2
        assert [(im.lat_deg, im.lon_deg) for im in store.images()] == [(f.lat_deg, f.lon_deg) for f in seq.frames]
        assert store.db.execute("SELECT COUNT(*) FROM structures").fetchone()[0] == 0
        kept = store.features(im.image_id for im in store.images())
        assert all(np.array_equal(features[i][0], kept[i][0]) and np.array_equal(features[i][1], kept[i][1])
                   for i in features)
        assert ingest(store, seq, SiftParams(), workers=1).n_geotags_moved == 0  # nothing more to take
    assert build_structure(ws, seq.source, seq.camera) == 4  # made again, at the geotags the source states
