"""Shared fixtures: stores, a synthetic drive with a known answer, and the real KITTI drive."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from visloc.db import FeatureStore
from visloc.sources.drives import default_data_root

REPO = Path(__file__).resolve().parent.parent
KITTI_DRIVE = "2011_09_26_drive_0001"
ORIGIN_LAT_DEG, ORIGIN_LON_DEG = 49.015003823272, 8.4342971002335  # first OXTS record of drive 0001


@pytest.fixture
def memory_store():
    store = FeatureStore.memory()
    yield store
    store.close()


@pytest.fixture
def tmp_store(tmp_path):
    store = FeatureStore(tmp_path / "store.sqlite", create=True)
    yield store
    store.close()


def require_drive(drive: Path) -> None:
    """Fail in CI, skip elsewhere, when a shared KITTI drive folder is missing."""
    if not drive.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{drive}: the KITTI drive must be present in CI")
        pytest.skip(f"{drive} not found")


@pytest.fixture(scope="session")
def kitti_root() -> Path:
    root = default_data_root()
    require_drive(root / "2011_09_26" / (KITTI_DRIVE + "_sync"))
    return root


@pytest.fixture(scope="session")
def kitti_evaluation(kitti_root, tmp_path_factory):
    """``visloc evaluate`` on three series (start frames 0, 25, 50) of the real drive, as a user
    runs it: (folder holding kitti.sqlite and eval.json, the JSON report, stdout). The store then
    holds both cameras' features and the counts of every query frame 0, 10, ..., 100."""
    import json

    tmp = tmp_path_factory.mktemp("kitti")
    out = tmp / "eval.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite",
                     "--start-frames", "0,25,50", "--json", out, timeout=1800)
    assert result.returncode == 0, result.stderr
    return tmp, json.loads(out.read_text()), result.stdout


@pytest.fixture(scope="session")
def kitti_two_runs(kitti_evaluation, kitti_root):
    """Two saved runs of the same series, as ``evaluate`` wrote them: the session's evaluation (the paper's
    parameters) and the same at τ1 0.7, matched on the same store."""
    tmp, _, _ = kitti_evaluation
    other = tmp / "eval_tau1_0.7.json"
    result = run_cli("evaluate", kitti_root, "--drive", KITTI_DRIVE, "--db", tmp / "kitti.sqlite",
                     "--start-frames", "0,25,50", "--tau1", "0.7", "--json", other, timeout=1800)
    assert result.returncode == 0, result.stderr
    return tmp / "eval.json", other


def panorama(seed: int = 7, width_px: int = 2400, height_px: int = 240) -> np.ndarray:
    """A textured strip: blurred noise plus random shapes, rich in SIFT keypoints."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (height_px, width_px), dtype=np.uint8), (0, 0), 2.0)
    for _ in range(width_px // 6):
        x, y = int(rng.integers(0, width_px)), int(rng.integers(0, height_px))
        color = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(3, 18)), color, -1)
        else:
            w, h = (int(v) for v in rng.integers(4, 30, 2))
            cv2.rectangle(img, (x, y), (x + w, y + h), color, -1)
    return img


def write_csv_drive(folder: Path, n_frames: int = 12, *, step_px: int = 120, offset_px: int = 0,
                    seed: int = 7, rate_hz: float = 2.0, crop_px: int = 320) -> Path:
    """A synthetic drive: frame i is a crop of a panorama at x = i*step_px + offset_px, geotagged
    on a straight line east of the origin at 1 m per frame. Returns the CSV path."""
    folder.mkdir(parents=True, exist_ok=True)
    assert 0 <= offset_px <= 200
    pano = panorama(seed, width_px=n_frames * step_px + crop_px + 200)  # same strip whatever the offset
    lines = ["file,timestamp,lat,lon,heading"]
    for i in range(n_frames):
        x = i * step_px + offset_px
        name = f"frame_{i:04d}.png"
        cv2.imwrite(str(folder / name), pano[:, x : x + crop_px])
        lon = ORIGIN_LON_DEG + i * 1.0 / (111_320.0 * np.cos(np.radians(ORIGIN_LAT_DEG)))
        lines.append(f"{name},{1000.0 + i / rate_hz:.3f},{ORIGIN_LAT_DEG:.9f},{lon:.9f},90")
    csv_path = folder / "geotags.csv"
    csv_path.write_text("\n".join(lines) + "\n")
    return csv_path


@pytest.fixture
def csv_drive(tmp_path) -> Path:
    return write_csv_drive(tmp_path / "drive")


def make_fake_kitti(root: Path, n_frames: int = 3, *, cameras=("image_00", "image_01"), with_oxts: bool = True,
                    with_calib: bool = True) -> Path:
    """A KITTI raw layout with synthetic images and real-looking OXTS records. Returns the drive folder."""
    drive = root / "2011_09_26" / "2011_09_26_drive_0001_sync"
    pano = panorama(3, width_px=n_frames * 60 + 400)
    for cam in cameras:
        data = drive / cam / "data"
        data.mkdir(parents=True)
        for i in range(n_frames):
            cv2.imwrite(str(data / f"{i:010d}.png"), pano[:, i * 60 : i * 60 + 400])
        (drive / cam / "timestamps.txt").write_text(
            "".join(f"2011-09-26 13:02:{25 + i * 0.1:012.9f}\n" for i in range(n_frames)))
    if with_oxts:
        oxts = drive / "oxts" / "data"
        oxts.mkdir(parents=True)
        for i in range(n_frames):
            values = [ORIGIN_LAT_DEG - i * 1e-5, ORIGIN_LON_DEG - i * 1e-5, 116.4, 0.03, 0.01, -2.6] + [0.0] * 24
            (oxts / f"{i:010d}.txt").write_text(" ".join(f"{v:.12g}" for v in values) + "\n")
        (drive / "oxts" / "timestamps.txt").write_text(
            "".join(f"2011-09-26 13:02:{25 + i * 0.1:012.9f}\n" for i in range(n_frames)))
    if with_calib:
        (root / "2011_09_26" / "calib_cam_to_cam.txt").write_text(
            "R_rect_00: 1 0 0 0 1 0 0 0 1\n"
            "P_rect_00: 7.215377e+02 0 6.095593e+02 0 0 7.215377e+02 1.728540e+02 0 0 0 1 0\n"
            "P_rect_01: 7.215377e+02 0 6.095593e+02 -3.875744e+02 0 7.215377e+02 1.728540e+02 0 0 0 1 0\n")
        # velodyne: x forward, y left, z up, 0.8 m behind and 0.8 m above the IMU; camera 0: x right, y down,
        # z forward, 0.27 m ahead of the velodyne (KITTI's layout, rounded)
        (root / "2011_09_26" / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: -0.8 0.3 -0.8\n")
        (root / "2011_09_26" / "calib_velo_to_cam.txt").write_text(
            "calib_time: 15-Mar-2012 11:37:16\nR: 0 -1 0 0 0 -1 1 0 0\nT: 0 -0.08 -0.27\n")
    return drive


CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="session")
def browser():
    """One headless Debian chromium for the whole session, driven through playwright (its sync API
    allows one instance per thread, so every browser test shares this one)."""
    if not CHROMIUM.exists():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} missing: scripts/test.sh installs it (scripts/install_chromium.sh)")
        pytest.skip(f"{CHROMIUM} not installed (bash scripts/install_chromium.sh)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True,
                              args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                    "--disable-background-networking", "--disable-component-update",
                                    "--no-first-run"])
        yield b
        b.close()


def run_cli(*args: str, timeout: float = 600, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the visloc command as a user would, in a fresh process."""
    return subprocess.run([sys.executable, "-m", "visloc", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd or REPO, env={**os.environ, "PYTHONUNBUFFERED": "1"})
