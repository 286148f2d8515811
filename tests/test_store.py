"""The SQLite store: round trip, schema, and refusing what is not ours."""

import hashlib
import sqlite3

import numpy as np
import pytest

from visloc.db import (CameraRecord, EmptyStoreError, FeatureStore, ImageRecord, NotAStoreError, SettingsMismatchError,
                StoreError)

from helpers import features, make_version_1_store


def record(frame: int, **kw) -> ImageRecord:
    base = dict(source="drive", camera="image_01", frame=frame, path=f"/x/{frame}.png", timestamp_s=100.0 + frame,
                lat_deg=49.0 + frame * 1e-5, lon_deg=8.4, alt_m=116.0, heading_deg=250.0, width_px=64,
                height_px=32, sift_ms=12.5)
    base.update(kw)
    return ImageRecord(**base)


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_round_trip_keeps_every_bit(tmp_path):
    path = tmp_path / "s.sqlite"
    stored = {}
    with FeatureStore(path, create=True) as store:
        batch = []
        for frame in range(5):
            kp, desc = features(50 + frame, frame)
            stored[frame] = (kp, desc)
            batch.append((record(frame), kp, desc))
        assert store.add_images(batch) == 5
        store.set_camera(CameraRecord("drive", "image_01", np.arange(12.0).reshape(3, 4), 64, 32))
    with FeatureStore(path) as store:  # reopened from disk
        images = store.images("drive", "image_01")
        assert [im.frame for im in images] == list(range(5))
        assert images[2].lat_deg == 49.0 + 2e-5 and images[2].heading_deg == 250.0 and images[2].sift_ms == 12.5
        got = store.features(im.image_id for im in images)
        for im in images:
            kp, desc = got[im.image_id]
            np.testing.assert_array_equal(kp, stored[im.frame][0])
            np.testing.assert_array_equal(desc, stored[im.frame][1])
            assert desc.dtype == np.uint8 and desc.flags.writeable
        cam = store.get_camera("drive", "image_01")
        np.testing.assert_array_equal(cam.P_rect, np.arange(12.0).reshape(3, 4))
        assert store.db.journal_mode == "wal"


def test_adding_an_image_twice_keeps_the_first(memory_store):
    kp, desc = features(10, 0)
    assert memory_store.add_images([(record(0), kp, desc)]) == 1
    kp2, desc2 = features(10, 1)
    assert memory_store.add_images([(record(0), kp2, desc2)]) == 0
    (image,) = memory_store.images()
    np.testing.assert_array_equal(memory_store.features([image.image_id])[image.image_id][1], desc)


def test_a_bad_row_rolls_back_the_whole_batch(memory_store):
    kp, desc = features(10, 0)
    with pytest.raises(StoreError, match="/x/1.png: descriptors must be uint8"):
        memory_store.add_images([(record(0), kp, desc), (record(1), kp, desc.astype(np.float32))])
    assert memory_store.image_count() == 0


def test_settings_are_recorded_and_a_different_set_is_refused(memory_store):
    memory_store.require_setting("sift", {"n_features": 0, "sigma": 1.6})
    memory_store.require_setting("sift", {"n_features": 0, "sigma": 1.6})
    with pytest.raises(SettingsMismatchError, match="n_features: store 0, asked 500"):
        memory_store.require_setting("sift", {"n_features": 500, "sigma": 1.6})


def test_missing_file_is_not_created_when_reading(tmp_path):
    path = tmp_path / "nope.sqlite"
    with pytest.raises(StoreError, match="nope.sqlite: database file does not exist"):
        FeatureStore(path)
    assert not path.exists()


def test_empty_file_is_refused_for_reading_and_initialised_for_writing(tmp_path):
    path = tmp_path / "empty.sqlite"
    path.write_bytes(b"")
    with pytest.raises(EmptyStoreError, match="empty.sqlite: empty database file"):
        FeatureStore(path)
    with FeatureStore(path, create=True) as store:
        assert store.image_count() == 0


def test_non_sqlite_file_is_refused_and_left_untouched(tmp_path):
    path = tmp_path / "notes.sqlite"
    path.write_text("these are my notes, not a database\n" * 20)
    before = sha(path)
    for create in (False, True):
        with pytest.raises(NotAStoreError, match="notes.sqlite: not a SQLite database"):
            FeatureStore(path, create=create)
    assert sha(path) == before


def test_foreign_sqlite_database_is_refused_and_left_untouched(tmp_path):
    path = tmp_path / "other.db"
    conn = sqlite3.connect(path)
    conn.execute("CREATE TABLE customers (id INTEGER, name TEXT)")
    conn.execute("INSERT INTO customers VALUES (1, 'Ada')")
    conn.commit()
    conn.close()
    before = sha(path)
    with pytest.raises(NotAStoreError, match=r"other.db: SQLite database but not a visloc store \(its tables: customers\)"):
        FeatureStore(path, create=True)
    assert sha(path) == before
    assert not (tmp_path / "other.db-wal").exists()


def test_newer_schema_is_refused(tmp_path):
    path = tmp_path / "s.sqlite"
    FeatureStore(path, create=True).close()
    conn = sqlite3.connect(path)
    conn.execute("UPDATE visloc_schema SET version = 99")
    conn.commit()
    conn.close()
    with pytest.raises(NotAStoreError, match="schema version 99"):
        FeatureStore(path)


def test_sources_summarise_per_camera(memory_store):
    kp, desc = features(20, 0)
    memory_store.add_images([(record(i), kp, desc) for i in range(3)] +
                            [(record(i, camera="image_00"), kp, desc) for i in range(2)])
    rows = {(r["source"], r["camera"]): r for r in memory_store.sources()}
    assert rows[("drive", "image_01")]["n_images"] == 3 and rows[("drive", "image_00")]["n_images"] == 2
    assert rows[("drive", "image_01")]["last_timestamp_s"] - rows[("drive", "image_01")]["first_timestamp_s"] == 2.0


def test_pair_counts_cache_round_trip_per_threshold(memory_store):
    memory_store.add_pair_counts({(1, 2): (17, 25.0), (1, 3): (0, 30.5)}, 0.8, 0.97)
    memory_store.add_pair_counts({(1, 2): (30, 26.0)}, 0.9, 0.97)
    assert memory_store.pair_counts([1], 0.8, 0.97) == {(1, 2): (17, 25.0), (1, 3): (0, 30.5)}
    assert memory_store.pair_counts([1], 0.9, 0.97) == {(1, 2): (30, 26.0)}
    assert memory_store.pair_counts([2], 0.8, 0.97) == {}


def test_a_version_1_store_is_migrated_in_place_keeping_its_data(tmp_path):
    from visloc.db import SCHEMA_VERSION

    path = tmp_path / "v1.sqlite"
    kp, desc = make_version_1_store(path)
    with FeatureStore(path) as store:
        (image,) = store.images()
        assert image.frame == 0 and image.lat_deg == 49.0 and image.sift_ms == 12.5
        assert (image.roll_rad, image.pitch_rad, image.yaw_rad, image.position_accuracy_m) == (None, None, None, None)
        got_kp, got_desc = store.features([image.image_id])[image.image_id]
        np.testing.assert_array_equal(got_kp, kp)
        np.testing.assert_array_equal(got_desc, desc)
        assert store.pair_counts([1], 0.8, 0.97) == {(1, 1): (42, 3.5)}
        cam = store.get_camera("drive", "image_01")
        assert cam.P_rect.shape == (3, 4) and cam.T_camera_imu is None
        assert store.frames_without_attitude("drive", "image_01") == {0}
        # the new columns can be filled without touching anything else
        assert store.set_attitudes("drive", "image_01", {0: (0.01, 0.02, -2.6)}) == 1
        assert store.frames_without_accuracy("drive", "image_01") == {0}
        assert store.set_position_accuracies("drive", "image_01", {0: 0.3, 7: 0.5}) == 1  # frame 7 is not stored
        store.set_camera(CameraRecord("drive", "image_01", cam.P_rect, 64, 32, T_camera_imu=np.eye(4)))
    with FeatureStore(path) as store:
        assert next(store.db.query("SELECT version FROM visloc_schema"))["version"] == SCHEMA_VERSION == 7
        (image,) = store.images()
        assert (image.roll_rad, image.pitch_rad, image.yaw_rad) == (0.01, 0.02, -2.6)
        assert image.position_accuracy_m == 0.3 and store.frames_without_accuracy("drive", "image_01") == set()
        assert store.frames_without_attitude("drive", "image_01") == set()
        np.testing.assert_array_equal(store.get_camera("drive", "image_01").T_camera_imu, np.eye(4))


def test_attitudes_and_accuracies_round_trip_in_a_new_store(memory_store):
    kp, desc = features(5, 0)
    memory_store.add_images([(record(0, roll_rad=0.1, pitch_rad=-0.2, yaw_rad=3.0, position_accuracy_m=0.45), kp, desc),
                             (record(1), kp, desc)])
    a, b = memory_store.images()
    assert (a.roll_rad, a.pitch_rad, a.yaw_rad, a.position_accuracy_m) == (0.1, -0.2, 3.0, 0.45)
    assert b.position_accuracy_m is None
    assert memory_store.frames_without_attitude("drive", "image_01") == {1}
    assert memory_store.frames_without_accuracy("drive", "image_01") == {1}


def test_a_version_2_store_gains_the_accuracy_column_keeping_its_rows(tmp_path):
    path = tmp_path / "v2.sqlite"
    kp, desc = features(9, 4)
    with FeatureStore(path, create=True) as store:
        store.add_images([(record(0, roll_rad=0.1, pitch_rad=0.2, yaw_rad=0.3), kp, desc)])
    conn = sqlite3.connect(path)  # what version 2 wrote: no accuracy column
    conn.execute("ALTER TABLE images DROP COLUMN position_accuracy_m")
    conn.execute("UPDATE visloc_schema SET version = 2")
    conn.commit()
    conn.close()
    with FeatureStore(path) as store:
        (image,) = store.images()
        assert (image.yaw_rad, image.position_accuracy_m) == (0.3, None)
        np.testing.assert_array_equal(store.features([image.image_id])[image.image_id][1], desc)
        assert store.set_position_accuracies("drive", "image_01", {0: 0.03}) == 1
    with FeatureStore(path) as store:
        assert next(store.db.query("SELECT version FROM visloc_schema"))["version"] == 7
        assert store.images()[0].position_accuracy_m == 0.03
