"""Whether a store can be trusted, tried on the real drive: bytes changed inside its arrays, a table
lost, images re-made under the same names or at another size, a closed pipe, a full disk. Each case
runs the visloc command as a user would on a copy of drive 0001's left camera (its first 26 frames,
linked from the shared data: the images are the drive's own unless the case re-makes them). The clean
store is made once per test run; a case that changes a store changes a copy of it."""

from __future__ import annotations

import json
import os
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from helpers import KITTI_DRIVE, PAPER_CONTRAST, REPO, built_once, copy_store, run_cli
from fault_table import Fault, params
from helpers import SERVER_WORK_S, DashboardProcess, new_page, one_line_error, screenshot, visit

FAULTS = [
    Fault("store-bytes-changed", "store contents",
          "Bytes changed inside the descriptor BLOBs of frames 10-20 (lengths unchanged: bit rot, a bad copy)",
          "visloc check names each of the 11 frames and exits 2; evaluate stops with one line naming the store, "
          "frame 10 and visloc check, exit 2; visloc ingest of the drive repairs the 11 images, after which the "
          "store holds what the clean store holds, row for row (features, structure, self-checks)"),
    Fault("dashboard-damaged-store", "store contents",
          "The dashboard started on that damaged store",
          "The page shows one line naming the store, frame 10 and visloc check; the server keeps running"),
    Fault("store-table-lost", "store contents",
          "A store whose structures table is missing",
          "visloc check names it and exits 2; reading commands say the store is damaged and that visloc ingest "
          "rebuilds it, one line, exit 2; visloc ingest of the drive rebuilds it and check passes"),
    Fault("store-closed-pipe", "store contents",
          "visloc info piped into head -1, and visloc check piped into head -1 (the reader goes away)",
          "The first line is printed, no traceback"),
    Fault("store-full-disk", "store contents",
          "Ingest under a file-size limit (ulimit -f, as a full disk)",
          "One line saying the disk is full or a size limit is reached and that re-running goes on, exit 2; "
          "every committed image kept; re-running completes"),
    Fault("images-remade-same-names", "inputs that changed",
          "Frames 10-20 re-made (flipped) under the same file names, then evaluated against the store that "
          "holds the old ones",
          "Those 11 are described again (said on stderr), and what was made from them is rebuilt: the store "
          "then holds exactly what a fresh store of the new images holds"),
    Fault("images-half-size", "inputs that changed",
          "The drive's images at half size, its calibration unchanged",
          "The intrinsics are scaled to the images' size (said on stderr); the refined mode poses the half-size "
          "images from their geometry, each within 0.5 m"),
    Fault("images-other-aspect", "inputs that changed",
          "The drive's images cropped to another aspect ratio, its calibration unchanged",
          "Refused at ingest: one line naming the image, both sizes and the calibration, exit 2"),
    Fault("sift-scale-default-shown", "inputs that changed",
          "--sift-scale 0.5 on a store built at full scale",
          "Refused: one line naming image_scale with the store's 1.0 and the asked 0.5, exit 2"),
]
CASES = {f.id: f for f in FAULTS}
N_FRAMES = 26  # the two series (start frames 0 and 5, three steps at 1 Hz) end at frame 25
DAMAGED = range(10, 21)  # the frames a case damages or re-makes
SOURCE = f"{KITTI_DRIVE}_sync"
EVALUATE = ("--drive", KITTI_DRIVE, "--mode", "refined", "--query-camera", "image_00", "--db-camera", "image_00",
            "--start-frames", "0,5", "--steps", "3")


def drive_copy(kitti_root: Path, dst: Path, remake=None, n_frames: int = N_FRAMES) -> Path:
    """A KITTI root at ``dst`` holding the first ``n_frames`` frames of drive 0001's left camera: the
    calibration, OXTS records and images linked from ``kitti_root``; ``remake(frame, image) -> image``
    re-makes images (None: keep the frame linked)."""
    src = kitti_root.resolve() / "2011_09_26"
    drive = dst / "2011_09_26" / SOURCE
    for sub in ("image_00/data", "oxts/data"):
        (drive / sub).mkdir(parents=True)
    for calib in src.glob("calib_*.txt"):
        (dst / "2011_09_26" / calib.name).symlink_to(calib)
    for name in ("image_00/timestamps.txt", "oxts/timestamps.txt"):
        text = (src / SOURCE / name).read_text().splitlines()[:n_frames]
        (drive / name).write_text("\n".join(text) + "\n")
    for frame in range(n_frames):
        stem = f"{frame:010d}"
        (drive / "oxts/data" / f"{stem}.txt").symlink_to(src / SOURCE / "oxts/data" / f"{stem}.txt")
        image = src / SOURCE / "image_00/data" / f"{stem}.png"
        made = None if remake is None else remake(frame, cv2.imread(str(image), cv2.IMREAD_UNCHANGED))
        if made is None:
            (drive / "image_00/data" / f"{stem}.png").symlink_to(image)
        else:
            assert cv2.imwrite(str(drive / "image_00/data" / f"{stem}.png"), made)
    return dst


def ingest(root: Path, store: Path, *extra: str) -> subprocess.CompletedProcess:
    return run_cli("ingest", root, "--drive", KITTI_DRIVE, "--camera", "image_00", "--db", store, *extra,
                   timeout=1800)


@pytest.fixture(scope="session")
def clean(kitti_root, shared_tmp):
    """(the drive copy, a store of it built by ingest), made once per test run: a case that writes into the store
    copies it (``copy_store``)."""
    def build(folder: Path) -> dict:
        root = drive_copy(kitti_root, folder / "kitti")
        store = folder / "clean.sqlite"
        result = ingest(root, store, *PAPER_CONTRAST)  # later runs on it read the store's, as a user's do
        assert result.returncode == 0, result.stderr
        assert f"{N_FRAMES} added" in result.stdout
        checked = run_cli("check", "--db", store)
        assert checked.returncode == 0 and "no damage found" in checked.stdout, checked.stdout + checked.stderr
        return {}

    folder, _ = built_once(shared_tmp, "trust_0001", build)
    return folder / "kitti", folder / "clean.sqlite"


def damaged_copy(store: Path, folder: Path) -> Path:
    """A copy of ``store`` with a few bytes changed in the descriptor BLOBs of frames 10-20, lengths unchanged."""
    store = copy_store(store, folder)
    conn = sqlite3.connect(store)
    for frame, blob in conn.execute("SELECT frame, descriptors_u8 FROM images WHERE frame BETWEEN ? AND ?",
                                    [DAMAGED[0], DAMAGED[-1]]).fetchall():
        damaged = bytearray(blob)
        for k in range(0, len(damaged), 997):
            damaged[k] ^= 0x5A
        conn.execute("UPDATE images SET descriptors_u8 = ? WHERE frame = ?", [bytes(damaged), frame])
    conn.commit()
    conn.close()
    return store


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["store-bytes-changed"]]))
def test_changed_bytes_are_named_refused_and_repaired(clean, tmp_path, fault):
    root, clean_store = clean
    store = damaged_copy(clean_store, tmp_path)

    checked = run_cli("check", "--db", store)
    assert checked.returncode == 2, checked.stdout + checked.stderr
    named = [line for line in checked.stdout.splitlines() if "checksum mismatch" in line]
    assert [f"{SOURCE}/image_00 frame {f}:" in line for f, line in zip(DAMAGED, named)] == [True] * len(DAMAGED)
    assert f"{len(DAMAGED)} images damaged" in checked.stdout.splitlines()[-1]

    refused = run_cli("evaluate", root, *EVALUATE, "--db", store, "--json", tmp_path / "e.json")
    one_line_error(refused, str(store), f"{SOURCE}/image_00 frame {DAMAGED[0]}", "checksum mismatch", "visloc check")
    assert not (tmp_path / "e.json").exists()

    repaired = ingest(root, store)
    assert repaired.returncode == 0, repaired.stderr
    assert f"{len(DAMAGED)} repaired" in repaired.stdout
    assert run_cli("check", "--db", store).returncode == 0
    assert table_rows(store) == table_rows(clean_store)  # the same answers, to the bit


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["dashboard-damaged-store"]]))
def test_the_dashboard_shows_a_damaged_store_in_the_page(clean, tmp_path, browser, fault):
    _, clean_store = clean
    store = damaged_copy(clean_store, tmp_path)
    proc = DashboardProcess("--db", str(store), "--db-camera", "image_00", "--query-camera", "image_00",
                            "--port", "8395")
    page = new_page(browser)
    try:
        visit(page, proc.url)
        page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()  # the GUI arrives over the websocket
        shown = page.get_by_text(re.compile("checksum mismatch")).first
        shown.wait_for(timeout=SERVER_WORK_S * 1000)
        text = shown.inner_text()
        assert str(store) in text and f"{SOURCE}/image_00 frame {DAMAGED[0]}" in text and "visloc check" in text, text
        assert "Traceback" not in text
        screenshot(page, f"faults_{fault.id}.png")
        assert proc.alive()
    finally:
        page.close()
        proc.stop()


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["store-table-lost"]]))
def test_a_lost_table_is_named_and_rebuilt_by_ingest(clean, tmp_path, fault):
    root, clean_store = clean
    store = copy_store(clean_store, tmp_path)
    conn = sqlite3.connect(store)
    conn.execute("DROP TABLE structures")
    conn.commit()
    conn.close()
    checked = run_cli("check", "--db", store)
    assert checked.returncode == 2 and f"{store}: missing table structures" in checked.stdout, checked.stdout
    info = run_cli("info", "--db", store)
    one_line_error(info, str(store), "damaged visloc store: missing table structures", "visloc ingest")
    assert "Traceback" not in info.stderr
    rebuilt = ingest(root, store)
    assert rebuilt.returncode == 0, rebuilt.stderr
    assert run_cli("check", "--db", store).returncode == 0
    assert sqlite3.connect(store).execute("SELECT count(DISTINCT image_id) FROM structures").fetchone()[0] == N_FRAMES


@pytest.mark.parametrize("fault", params([CASES["store-closed-pipe"]]))
@pytest.mark.parametrize("command", ["info", "check"])
def test_a_closed_pipe_ends_the_command_quietly(clean, fault, command):
    _, store = clean
    result = subprocess.run(f"'{sys.executable}' -m visloc {command} --db '{store}' | head -1", shell=True,
                            capture_output=True, text=True, cwd=REPO, timeout=600)
    assert result.stdout.startswith(str(store)) and len(result.stdout.splitlines()) == 1, result.stdout
    assert "Traceback" not in result.stderr and "Error" not in result.stderr, result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["store-full-disk"]]))
def test_a_full_disk_is_said_and_rerunning_goes_on(clean, tmp_path, fault):
    root, _ = clean
    store = tmp_path / "full.sqlite"
    limit_kib = 6 * 1024  # the 26 images' features take about 17 MB: the limit is met part way through them
    # features only, both times: the disk fills while frames are described, and what is kept is what was described
    result = subprocess.run(["bash", "-c", f"ulimit -f {limit_kib} && exec \"$@\"", "bash", sys.executable, "-m",
                             "visloc", "ingest", str(root), "--drive", KITTI_DRIVE, "--camera", "image_00", "--db",
                             str(store), "--features-only", *PAPER_CONTRAST], capture_output=True, text=True, cwd=REPO,
                            timeout=1800)
    one_line_error(result, str(store), "the disk is full or a file-size limit is reached", "run the same command")
    kept = sqlite3.connect(store).execute("SELECT count(*) FROM images").fetchone()[0]
    assert 0 < kept < N_FRAMES
    again = ingest(root, store, "--features-only")
    assert again.returncode == 0, again.stderr
    assert f"{N_FRAMES - kept} added, {kept} already stored" in again.stdout
    assert run_cli("check", "--db", store).returncode == 0


def table_rows(store: Path) -> dict[str, list[tuple]]:
    """What a store holds that answers depend on, row by row (not when or how fast it was made)."""
    conn = sqlite3.connect(store)
    timing = {"sift_ms", "created_at", "build_ms", "checked_at", "path"}
    out = {}
    for table in ("images", "structures", "global_vectors", "arrays", "self_checks", "cameras"):
        columns = [r[1] for r in conn.execute(f"PRAGMA table_info({table})") if r[1] not in timing]
        out[table] = sorted(conn.execute(f"SELECT {', '.join(columns)} FROM {table}").fetchall(), key=repr)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["images-remade-same-names"]]))
def test_images_remade_under_the_same_names_are_described_again(clean, kitti_root, tmp_path, fault):
    _, clean_store = clean
    remade = drive_copy(kitti_root, tmp_path / "remade",
                        remake=lambda frame, image: cv2.flip(image, 1) if frame in DAMAGED else None)
    store = copy_store(clean_store, tmp_path / "old")
    # evaluate ingests first (the paper's mode: what is checked is what its ingest stores, not the poses)
    evaluated = run_cli("evaluate", remade, *EVALUATE, "--mode", "paper", "--db", store, timeout=1800)
    assert evaluated.returncode == 0, evaluated.stderr
    assert f"image_00: {len(DAMAGED)} images described again (their image file changed" in evaluated.stderr, \
        evaluated.stderr
    again = ingest(remade, store)
    assert again.returncode == 0 and f"0 added, {N_FRAMES} already stored" in again.stdout, again.stdout
    fresh = tmp_path / "fresh.sqlite"
    assert ingest(remade, fresh, *PAPER_CONTRAST).returncode == 0  # described as the clean store was
    assert table_rows(store) == table_rows(fresh)


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["images-half-size"]]))
def test_images_at_half_size_get_scaled_intrinsics(kitti_root, tmp_path, fault):
    """Intrinsics that were not scaled would pose nothing, or pose it metres off. Two queries with views on both
    sides (frames 12 and 22 of 35, 1 s excluded) posed on a store of the half-size images' features, the
    structure triangulated as a query does: on a quarter of the pixels each pose is coarser than at full size,
    but metric."""
    half = drive_copy(kitti_root, tmp_path / "half", remake=lambda frame, image: cv2.resize(
        image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA), n_frames=35)
    store = tmp_path / "half.sqlite"
    result = ingest(half, store, "--features-only")
    assert result.returncode == 0, result.stderr
    assert "images are 621x187 px, the calibration is for 1242x375 px: its intrinsics are scaled" in result.stderr
    posed = run_cli("localize", half, "--drive", KITTI_DRIVE, "--camera", "image_00", "--db-camera", "image_00",
                    "--db", store, "--mode", "refined", "--start-frame", "12", "--steps", "2", "--exclusion-s", "1",
                    "--json", tmp_path / "half.json", timeout=1800)
    assert posed.returncode == 0, posed.stderr
    steps = json.loads((tmp_path / "half.json").read_text())["steps"]
    assert [s["measurement_source"] for s in steps] == ["geometry", "geometry"], steps
    assert max(s["measurement_error_m"] for s in steps) < 0.5, steps


@pytest.mark.parametrize("fault", params([CASES["images-other-aspect"]]))
def test_images_of_another_aspect_ratio_are_refused(kitti_root, tmp_path, fault):
    cropped = drive_copy(kitti_root, tmp_path / "cropped", remake=lambda frame, image: image[:, :900])
    store = tmp_path / "cropped.sqlite"
    result = ingest(cropped, store)
    one_line_error(result, "0000000000.png", "image is 900x375 px", "calibration", "1242x375 px", "aspect ratio")
    assert not store.exists()


@pytest.mark.parametrize("fault", params([CASES["sift-scale-default-shown"]]))
def test_a_sift_setting_the_store_records_by_default_is_shown_as_it_takes_effect(clean, tmp_path, fault):
    root, clean_store = clean
    store = copy_store(clean_store, tmp_path)
    result = ingest(root, store, "--sift-scale", "0.5")
    one_line_error(result, str(store), "built with other SIFT settings", "image_scale: store 1.0, asked 0.5")


def test_the_drive_copy_is_the_shared_drive(clean, kitti_root):
    """The copy links the shared drive's own files (no data of the drive is written into the project)."""
    root, _ = clean
    image = root / "2011_09_26" / SOURCE / "image_00" / "data" / "0000000005.png"
    assert image.is_symlink() and os.path.samefile(image, kitti_root.resolve() / "2011_09_26" / SOURCE / "image_00" / "data" /
                                                    "0000000005.png")
