"""Helpers shared by several test modules: the checkout and the shared data, synthetic drives, the
command line run as a user runs it and checks of its output, snapshots of a store being ingested, an
old store written by hand, and driving the dashboard in a browser.

This is the one place for them: fixtures live in conftest.py (which uses these), and a test module
imports these as ``from helpers import ...``."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import struct
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from filelock import FileLock

from visloc.params import PAPER_SIFT

# -- the checkout, the data and synthetic drives -----------------------------------------------------------

REPO = Path(__file__).resolve().parent.parent
KITTI_DRIVE = "2011_09_26_drive_0001"
SERIES_STARTS = "0,50"  # the shared evaluations' series of drive 0001 (conftest.kitti_evaluation): frames 0-100
DRIVE_0005 = "2011_09_26_drive_0005"
DRIVE_0005_FRAMES = 40  # frames of drive 0005's left camera in the shared store (conftest.store_0005)
ORIGIN_LAT_DEG, ORIGIN_LON_DEG = 49.015003823272, 8.4342971002335  # first OXTS record of drive 0001
OTHER_MEAS_VAR_M2 = "25"  # R of the second saved run (conftest.kitti_two_runs), m^2: σ 5 m
OTHER_RUN_NAME = "eval_meas_var_25.json"
CSV_PAIR_FRAMES = 14  # frames of each drive of the shared synthetic pair (conftest.csv_pair)
# The shared real-data stores are described at the paper's SIFT contrast threshold, not a new store's lower one:
# they test the paper's features and every path on them at half the cost; a store at the new store's threshold
# is tested on a few frames (test_contrast_selection) and measured on whole drives by the benchmarks.
PAPER_CONTRAST = ("--sift-contrast", str(PAPER_SIFT.contrast_threshold))


def require_drive(drive: Path) -> None:
    """Fail in CI, skip elsewhere, when a shared KITTI drive folder is missing."""
    if not drive.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"{drive}: the KITTI drive must be present in CI")
        pytest.skip(f"{drive} not found")


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


# -- artifacts made once per test run ---------------------------------------------------------------------

def built_once(shared_tmp: Path, name: str, build: Callable[[Path], dict]) -> tuple[Path, dict]:
    """``build(folder)`` once per test run, in ``shared_tmp/name``, by whichever worker asks first; the others
    wait for it and get the same (folder, what ``build`` returned, JSON-serializable). A build that fails is
    not tried again by the next worker: it fails with the first one's message."""
    folder = shared_tmp / name
    done, failed = shared_tmp / f"{name}.done.json", shared_tmp / f"{name}.failed.txt"
    with FileLock(str(shared_tmp / f"{name}.lock")):
        if failed.exists():
            pytest.fail(f"{name} could not be built (by another worker):\n{failed.read_text()}", pytrace=False)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            try:
                made = build(folder)
            except BaseException:
                failed.write_text(traceback.format_exc())
                raise
            done.write_text(json.dumps(made))
    return folder, json.loads(done.read_text())


def copy_store(store: Path, folder: Path) -> Path:
    """A copy of a shared store in ``folder`` (same file name), for a test that writes into it: a consistent
    snapshot even while another test's command writes into the store (SQLite's backup), in the same journal
    mode, one file with no side files, as ingest leaves a store."""
    folder.mkdir(parents=True, exist_ok=True)
    copy = folder / store.name
    source = sqlite3.connect(f"file:{store}?mode=ro", uri=True, timeout=60)
    target = sqlite3.connect(copy)
    try:
        mode = source.execute("PRAGMA journal_mode").fetchone()[0]
        source.backup(target)
        target.execute(f"PRAGMA journal_mode={mode}")
    finally:
        source.close()
        target.close()
    return copy


# -- the command line --------------------------------------------------------------------------------------


def run_cli(*args: str, timeout: float = 600, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run the visloc command as a user would, in a fresh process."""
    return subprocess.run([sys.executable, "-m", "visloc", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd or REPO, env={**os.environ, "PYTHONUNBUFFERED": "1"})


# a progress line of a long command off a terminal (visloc.progress), printed before an error may stop it
PROGRESS_LINE = re.compile(r"^[^:]+: \d+/\d+ [a-z ]+( \(\d+%\))?, (started|done in .+|.+ elapsed, about .+ left)$")


def error_lines(stderr: str) -> list[str]:
    """stderr without progress lines."""
    return [line for line in stderr.strip().splitlines() if not PROGRESS_LINE.match(line)]


def one_line_error(result, *fragments):
    assert result.returncode == 2, result.stderr
    lines = error_lines(result.stderr)
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("visloc: error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


# -- a run exported as MCAP, read back ----------------------------------------------------------------

def mcap_topics(path: Path) -> dict[str, list]:
    """{topic: its messages decoded} of an MCAP file, by ``mcap``'s own reader: protobuf messages with the
    protobuf decoder, JSON ones checked against their JSON schema."""
    import jsonschema
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    topics: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                decoded = json.loads(message.data)
                jsonschema.validate(decoded, json.loads(schema.data))
            else:
                assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
                decoded = DecoderFactory().decoder_for("protobuf", schema)(message.data)
            topics.setdefault(channel.topic, []).append(decoded)
    return topics


def read_back_mcap(path: Path, steps: list[dict], *, images: bool, places: float = 1e-12, rel: float = 1e-12) -> None:
    """Every message of a run's MCAP decodes with its schema (protobuf for Foxglove's, JSON schema for the
    steps') by ``mcap``'s own reader and decoders; its steps are the run's (``steps``: as its JSON has them,
    each with its ``series``, 0 when not given), and its truth, measurement and estimate fixes are theirs
    (latitude and longitude, and the estimate's covariance), step for step."""
    topics = mcap_topics(path)
    expected = {"/visloc/truth", "/visloc/measurement", "/visloc/estimate", "/visloc/scene", "/visloc/step"}
    assert expected | ({"/visloc/image/query", "/visloc/image/match"} if images else set()) == set(topics)
    by_key = {(s.get("series", 0), s["step"]): s for s in steps}
    order = [(m["series"], m["step"]) for m in topics["/visloc/step"]]  # the file's order: by time
    assert sorted(order) == sorted(by_key)
    for kind in ("truth", "measurement", "estimate"):
        fixes = iter(topics[f"/visloc/{kind}"])
        shown = [by_key[k] for k in order if by_key[k].get(f"{kind}_lat_deg") is not None]
        assert len(topics[f"/visloc/{kind}"]) == len(shown), kind
        for fix, step in zip(fixes, shown):
            assert (fix.latitude, fix.longitude) == pytest.approx((step[f"{kind}_lat_deg"], step[f"{kind}_lon_deg"]),
                                                                  abs=places), (kind, step["step"])
            if kind == "estimate":
                assert list(fix.position_covariance)[:2] == pytest.approx(step["estimate_cov_m2"][0], rel=rel)
    assert topics["/visloc/estimate"], "no estimate"


# -- a store being ingested, read with plain sqlite3 -----------------------------------------------------

def snapshot(path):
    """(frame -> (n_keypoints, keypoint bytes, descriptor bytes)) of a store, read with plain sqlite3."""
    conn = sqlite3.connect(path)
    rows = conn.execute("SELECT frame, n_keypoints, keypoints_f32, descriptors_u8 FROM images").fetchall()
    conn.close()
    return {r[0]: r[1:] for r in rows}


def assert_same_snapshots(ours: dict, theirs: dict) -> None:
    """Two snapshots are equal; if not, say where in one line (pytest's diff of two stores' BLOBs takes hours)."""
    if ours == theirs:
        return
    only = sorted(set(ours) ^ set(theirs))
    differ = [f for f in sorted(set(ours) & set(theirs)) if ours[f] != theirs[f]]
    first = f"frame {differ[0]}: {ours[differ[0]][0]} vs {theirs[differ[0]][0]} keypoints" if differ else "-"
    raise AssertionError(f"stores differ: frames in one only {only[:10]}, {len(differ)} frames differ (first {first})")


def assert_no_half_images(snap):
    for n, kp, desc in snap.values():
        assert n > 0 and len(kp) == n * 6 * 4 and len(desc) == n * 128


def wait_for_rows(db_path, at_least, proc, timeout_s=120):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if db_path.exists():
            try:
                conn = sqlite3.connect(db_path, timeout=0.1)
                n = conn.execute("SELECT count(*) FROM images").fetchone()[0]
                conn.close()
                if n >= at_least:
                    return n
            except sqlite3.OperationalError:
                pass  # schema not created yet, or locked for a moment
        assert proc.poll() is None, "ingest ended before it could be interrupted"
        time.sleep(0.005)
    raise AssertionError("ingest made no progress")


# -- stores as older versions wrote them ------------------------------------------------------------------

def features(n: int, seed: int):
    rng = np.random.default_rng(seed)
    return rng.random((n, 6), dtype=np.float32) * 100, rng.integers(0, 256, (n, 128), dtype=np.uint8)


def make_version_1_store(path):
    """A store exactly as schema version 1 wrote it: one image, one cached count, no attitude columns."""
    conn = sqlite3.connect(path)
    conn.executescript("""
        CREATE TABLE visloc_schema (version INTEGER, created_at TEXT);
        INSERT INTO visloc_schema VALUES (1, '2025-01-01T00:00:00+00:00');
        CREATE TABLE settings (key TEXT PRIMARY KEY, value_json TEXT);
        INSERT INTO settings VALUES ('sift', '{"n_features": 0}');
        CREATE TABLE cameras (source TEXT, camera TEXT, p_rect_json TEXT, width_px INTEGER, height_px INTEGER,
                              PRIMARY KEY (source, camera));
        INSERT INTO cameras VALUES ('drive', 'image_01', '[[1,0,0,0],[0,1,0,0],[0,0,1,0]]', 64, 32);
        CREATE TABLE images (id INTEGER PRIMARY KEY, source TEXT NOT NULL, camera TEXT NOT NULL,
            frame INTEGER NOT NULL, path TEXT, timestamp_s FLOAT NOT NULL, lat_deg FLOAT NOT NULL,
            lon_deg FLOAT NOT NULL, alt_m FLOAT, heading_deg FLOAT, width_px INTEGER, height_px INTEGER,
            sift_ms FLOAT, n_keypoints INTEGER NOT NULL, keypoints_f32 BLOB, descriptors_u8 BLOB, created_at TEXT);
        CREATE UNIQUE INDEX idx_images_source_camera_frame ON images (source, camera, frame);
        CREATE TABLE pair_counts (query_image_id INTEGER, db_image_id INTEGER, tau1 FLOAT, tau2 FLOAT,
            n_correspondences INTEGER, match_ms FLOAT, PRIMARY KEY (query_image_id, db_image_id, tau1, tau2));
        INSERT INTO pair_counts VALUES (1, 1, 0.8, 0.97, 42, 3.5);
    """)
    kp, desc = features(7, 3)
    conn.execute("INSERT INTO images VALUES (1, 'drive', 'image_01', 0, '/x/0.png', 100.0, 49.0, 8.4, 116.0, 250.0,"
                 " 64, 32, 12.5, 7, ?, ?, '2025-01-01')", [kp.tobytes(), desc.tobytes()])
    conn.commit()
    conn.close()
    return kp, desc


# -- the dashboard in a browser ----------------------------------------------------------------------------
# Machines running these tests are shared and busy, so every wait is for a condition, with a generous
# timeout: SERVER_WORK_S where the server has work to do, and the pages' default timeout for
# playwright's own waits and actions.

SCREENSHOTS = REPO / "out" / "screenshots"
URL_LINE = re.compile(r"visloc dashboard: (http://\S+)")
SERVER_WORK_S = 120  # a wait for the server to do something (apply controls, draw a step, open a store)
RUN_S = 600  # a wait for a matching run over a whole drive
PAGE_TIMEOUT_MS = 120_000  # playwright's default for every wait and action on a page


class DashboardProcess:
    """``visloc dashboard`` started as a user starts it; ``url`` is the URL it printed."""

    def __init__(self, *args: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "visloc", "dashboard", *args], cwd=REPO,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.output: list[str] = []
        found = threading.Event()
        self.url = None

        def read() -> None:
            for line in self.proc.stdout:
                self.output.append(line)
                m = URL_LINE.search(line)
                if m and self.url is None:
                    self.url = m.group(1)
                    found.set()

        threading.Thread(target=read, daemon=True).start()
        if not found.wait(180):  # Python, numpy, OpenCV and viser import slowly on a busy machine
            self.stop()
            raise AssertionError("dashboard printed no URL:\n" + "".join(self.output))

    @property
    def port(self) -> int:
        return int(self.url.rsplit(":", 1)[1])

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        if self.alive():
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)  # a grace period for a clean exit, then it is killed
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def status_text(page) -> str:
    return page.locator("text=/^(⚠|Ready|Matching|Loading|Starting)/").first.inner_text()


def row(page, name: str) -> str:
    """The value in the step table's row ``name``."""
    return page.locator("tr", has=page.get_by_text(name, exact=True)).first.locator("td").nth(1).inner_text()


def control(page, label: str):
    return page.get_by_text(label, exact=True).locator("xpath=../../..")


def wait_for(predicate, timeout_s: float, what: str, poll_s: float = 0.25):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")


def run_number(page) -> int:
    m = re.search(r"Ready \(run (\d+),", status_text(page))
    return int(m.group(1)) if m else 0


# The 3D view is drawn by a software rasterizer here (SwiftShader): a frame of it at full resolution costs about
# 0.19 CPU-s, and viser draws one a second even when nothing moves (its heartbeat), more while the page changes.
# Pages opened by the tests draw it at half resolution (viser's own ``fixedDpr`` setting), which costs about 40 %
# less; the page, its controls and panels are the same.
CANVAS_DPR = 0.5
# CSS keyframe animations (the striped progress bar while a run is matched) repaint the page every frame: about a
# fifth of a core for as long as a run is matched with a page open, in a test browser that paints in software.
# Pages opened by the tests hold them still (``animation: none``); transitions, and everything a test reads, stay.
STILL_ANIMATIONS = """document.addEventListener("DOMContentLoaded", () => {
  const style = document.createElement("style");
  style.textContent = "*, *::before, *::after { animation: none !important; }";
  document.head.appendChild(style);
});"""


def new_page(browser):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.add_init_script(STILL_ANIMATIONS)
    page.set_default_timeout(PAGE_TIMEOUT_MS)
    return page


def visit(page, url: str) -> None:
    """Open the dashboard at ``url`` in ``page``, its 3D view drawn at ``CANVAS_DPR``."""
    page.goto(f"{url}{'&' if '?' in url else '?'}fixedDpr={CANVAS_DPR:g}")


def open_page(browser, url: str):
    page = new_page(browser)
    visit(page, url)
    page.get_by_text("τ1 (Lowe ratio)", exact=True).wait_for()  # the GUI arrives over the websocket
    wait_for(lambda: run_number(page) > 0, 2 * RUN_S, "the first run to be ready")
    page.get_by_text("Step", exact=True).first.wait_for()
    return page


def dismiss_webgl_notice(page) -> None:
    # Software rendering (swiftshader) makes viser show a notice that would cover the scene
    notice = page.get_by_text("Software WebGL rendering detected")
    if notice.count():
        notice.first.locator("xpath=../..").locator("button").first.click()
        notice.first.wait_for(state="hidden")


def screenshot(page, name: str) -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    path = SCREENSHOTS / name
    page.screenshot(path=str(path))
    return path


def reset(page) -> None:
    before = run_number(page)
    page.get_by_role("button", name="Paper's parameters").click()
    wait_for(lambda: run_number(page) > before, RUN_S, "the reset run")


def go_to_step(page, step: int) -> None:
    """Type a step into the slider's number box, as a user may; ``step`` counts from 0, the slider
    and the panel ("Step k of N") from 1."""
    box = control(page, "Step").locator("input:not([type=hidden])")
    box.fill(str(step + 1))
    box.press("Enter")
    page.get_by_text(re.compile(rf"^Step {step + 1} of \d+$")).wait_for()


def open_other_store(page, path: Path | str):
    """Type a store's path under Data, press Open, and return the error the page answers with
    under Open (it stays there; the status line above moves on with the next run).

    The page answers the typing ("Open reads PATH") before Open is pressed: viser's client sends
    at most one control change per 50 ms and drops the ones in between, so a click right after
    the typing could otherwise reach the server before the path does."""
    box = control(page, "Other store").locator("input, textarea").first
    box.fill(str(path))
    page.get_by_text(f"Open reads {path}", exact=True).wait_for()
    page.get_by_role("button", name="Open", exact=True).click()
    message = page.get_by_text(re.compile("^⚠ " + re.escape(str(path)))).first
    message.wait_for()
    return message


def choose(page, label: str, option: str) -> None:
    control(page, label).locator("input").first.click()
    page.get_by_role("option", name=option, exact=True).click()


def settled(locator, what: str) -> bytes:
    """A screenshot of ``locator`` once two consecutive ones, half a second apart, are identical:
    the 3D view has drawn what it was sent and stopped changing."""
    shots = [locator.screenshot()]

    def still() -> bytes | None:
        shots.append(locator.screenshot())
        return shots[-1] if shots[-1] == shots[-2] else None

    return wait_for(still, SERVER_WORK_S, what, poll_s=0.5)


# -- a worker process that dies as the kernel's out-of-memory killer can leave it -------------------------------

def die_halfway_through_sending(*_args) -> None:
    """A task for a ``concurrent.futures`` worker process that dies as one killed while sending its result: it
    holds the result queue's lock, writes the header of a message and none of its bytes, and is killed."""
    frame = sys._getframe(1)
    while frame is not None and "result_queue" not in frame.f_locals:
        frame = frame.f_back
    queue = frame.f_locals["result_queue"]
    queue._wlock.acquire()
    os.write(queue._writer.fileno(), struct.pack("!i", 1 << 20))
    os.kill(os.getpid(), signal.SIGKILL)
