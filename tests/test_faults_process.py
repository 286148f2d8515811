"""Faults while ingesting: a worker process that dies, images too large to describe, frames that
cannot be described, and signals to a command started in the background. Each case runs the
visloc command as a user would and waits for conditions, never for time."""

from __future__ import annotations

import os
import signal
import sqlite3
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from fault_table import Fault, params
from helpers import REPO, run_cli, write_csv_drive
from helpers import assert_no_half_images, error_lines, one_line_error, snapshot, wait_for_rows

FAULTS = [
    Fault("killed-sift-worker", "ingest",
          "One SIFT worker process killed (kill -9, or the kernel's out-of-memory killer) during visloc ingest",
          "The ingest ends at once with one line saying a worker died, exit 2; what was committed stays, "
          "and running it again completes the store"),
    Fault("huge-image-header", "ingest",
          "A 1 MB PNG of 30000x30000 pixels among the frames",
          "Refused from its header before any pixel is decoded: one line naming the file, its size and "
          "--max-image-mp, exit 2; the frames before it are stored"),
    Fault("image-limit-lowered", "ingest",
          "--max-image-mp lower than the drive's frames",
          "The first frame is refused naming the limit; --max-image-mp 0 is refused as a parameter"),
    Fault("featureless-frame", "ingest",
          "An all-black frame (no SIFT keypoints) in the middle of a drive",
          "Stops with one line naming the frame and --skip-bad-frames, exit 2, the frames before it stored; "
          "with --skip-bad-frames the frame is skipped, recorded in the store, listed by visloc info, and "
          "evaluate runs on the drive"),
    Fault("corrupt-frame", "ingest",
          "A corrupt PNG in the middle of a drive",
          "The same as a frame without keypoints: named, then skippable and recorded"),
    Fault("sigint-in-background", "signals",
          "kill -INT to an ingest started in the background (SIGINT ignored, as a shell does for & jobs), "
          "with one and with two worker processes",
          "Stops cleanly: 'interrupted', exit 130, every finished image kept"),
    Fault("sigterm-ingest", "signals",
          "kill (SIGTERM) to an ingest in progress",
          "It stops as on Ctrl-C: the finished images committed, one line saying SIGTERM stopped it and how "
          "many images the store keeps, exit 143; running it again goes on"),
    Fault("dashboard-sigint-in-background", "signals",
          "kill -INT to a dashboard started in the background (SIGINT ignored)",
          "The server stops: 'interrupted', exit 130"),
]
CASES = {f.id: f for f in FAULTS}


def ingest_process(csv_path: Path, db_path: Path, workers: int, *, background: bool = False) -> subprocess.Popen:
    def ignore_sigint() -> None:  # what a shell does to a job started with &
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    return subprocess.Popen([sys.executable, "-m", "visloc", "ingest", str(csv_path), "--db", str(db_path),
                             "--workers", str(workers)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=ignore_sigint if background else None, start_new_session=True)


def stop_group(proc: subprocess.Popen) -> None:
    """Kill what is left of ``proc``'s process group (its worker processes hold its output pipes open)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.communicate(timeout=120)


def sift_workers(pid: int) -> list[int]:
    """Process ids of the worker processes ``pid`` spawned (not its resource tracker)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and b"spawn_main" in cmdline and b"resource_tracker" not in cmdline:
            out.append(int(entry.name))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["killed-sift-worker"]]))
def test_a_killed_worker_ends_the_ingest_keeping_what_was_committed(tmp_path, fault):
    n_frames = 200
    csv_path = write_csv_drive(tmp_path / "long", n_frames=n_frames, step_px=60)
    db_path = tmp_path / "store.sqlite"
    proc = ingest_process(csv_path, db_path, workers=2)
    try:
        wait_for_rows(db_path, 8, proc, timeout_s=600)
        workers = sift_workers(proc.pid)
        assert workers, "no worker process found"
        os.kill(workers[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=600)  # old versions waited for the dead worker forever
    finally:
        if proc.returncode is None:  # it did not end: no worker of its group is left behind
            stop_group(proc)
    assert proc.returncode == 2, err
    lines = error_lines(err)  # progress lines aside
    assert len(lines) == 1 and lines[0].startswith("visloc: error: ") and "worker process died" in lines[0], err
    interrupted = snapshot(db_path)
    assert 8 <= len(interrupted) < n_frames
    assert_no_half_images(interrupted)
    resumed = run_cli("ingest", csv_path, "--db", db_path, "--workers", "2")
    assert resumed.returncode == 0, resumed.stderr
    assert f"{n_frames - len(interrupted)} added, {len(interrupted)} already stored" in resumed.stdout
    assert not sift_workers(proc.pid)


WORKER_DIES_WHILE_SENDING = """
import sys
from helpers import die_halfway_through_sending
from visloc.errors import InputError
from visloc.store.processes import local_processes

if __name__ == "__main__":
    try:
        with local_processes(2, "structure") as pool:
            list(pool.run_all(die_halfway_through_sending, [(k,) for k in range(8)]))
    except InputError as exc:
        print(exc)
        sys.exit(2)
"""


@pytest.mark.parametrize("fault", params([CASES["killed-sift-worker"]]))
def test_a_worker_killed_while_sending_its_result_ends_the_step_at_once(tmp_path, fault):
    """CPython's process pool waits forever for the rest of a result its worker died sending (the race a kill
    -9 can hit); the pool's wait sees the dead worker instead, and the process exits."""
    script = tmp_path / "pool.py"
    script.write_text(WORKER_DIES_WHILE_SENDING)
    result = subprocess.run([sys.executable, script], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), str(REPO)])})
    assert result.returncode == 2, result.stderr
    assert result.stdout.startswith("structure: a worker process died"), result.stdout


def write_huge_png(path: Path, width_px: int, height_px: int) -> None:
    """A valid gray PNG of the given size, all zeros, written without holding its pixels in memory."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    packer, row, parts = zlib.compressobj(9), b"\x00" * (width_px + 1), []
    for _ in range(height_px):
        parts.append(packer.compress(row))
    parts.append(packer.flush())
    header = struct.pack(">IIBBBBB", width_px, height_px, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", b"".join(parts))
                     + chunk(b"IEND", b""))


def stored_frames(db_path: Path) -> list[int]:
    conn = sqlite3.connect(db_path)
    try:
        return [r[0] for r in conn.execute("SELECT frame FROM images ORDER BY frame")]
    finally:
        conn.close()


def test_a_worker_dead_before_the_next_frame_is_handed_out_is_said_too(tmp_path, monkeypatch):
    """A worker can die between two frames: then the pool refuses the next frame itself (not its result).
    That too ends the ingest with the one line naming a frame, whatever was in flight coming back first."""
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    import visloc
    from visloc.store import ingest as ingest_module

    class DiesAfterTwo(ProcessPoolExecutor):  # a real pool; the third hand-out finds it broken
        handed = 0

        def submit(self, *args, **kwargs):
            DiesAfterTwo.handed += 1
            if DiesAfterTwo.handed > 2:
                raise BrokenProcessPool("a child process terminated abruptly")
            return super().submit(*args, **kwargs)

    monkeypatch.setattr(ingest_module, "ProcessPoolExecutor", DiesAfterTwo)
    seq = visloc.open_csv(write_csv_drive(tmp_path / "d", n_frames=6))
    frames = [f for f in seq.frames]
    done = []
    with pytest.raises(ingest_module.WorkerDiedError) as info:
        for frame, result in ingest_module._extracted(frames, visloc.SiftParams(), 2, seq, 100.0):
            done.append(frame)
    assert done == frames[:2]  # the two in flight came back first
    message = str(info.value)
    assert "a SIFT worker process died" in message and str(frames[2].image_path) in message and "\n" not in message


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["huge-image-header"]]))
def test_an_image_too_large_is_refused_from_its_header(tmp_path, fault):
    csv_path = write_csv_drive(tmp_path / "drive", n_frames=6)
    huge = csv_path.parent / "frame_0003.png"
    write_huge_png(huge, 30000, 30000)
    assert huge.stat().st_size < 2_000_000
    assert cv2.imread(str(huge), cv2.IMREAD_REDUCED_GRAYSCALE_8).shape == (3750, 3750)  # a real PNG
    db_path = tmp_path / "store.sqlite"
    result = run_cli("ingest", csv_path, "--db", db_path, "--workers", "1")
    one_line_error(result, str(huge), "30000x30000", "900.0 megapixels", "--max-image-mp")
    assert stored_frames(db_path) == [0, 1, 2]


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["image-limit-lowered"]]))
def test_the_image_limit_can_be_lowered_and_is_checked(tmp_path, fault):
    csv_path = write_csv_drive(tmp_path / "drive", n_frames=4)  # 320x240: 0.077 megapixels
    result = run_cli("ingest", csv_path, "--db", tmp_path / "a.sqlite", "--max-image-mp", "0.05", "--workers", "1")
    one_line_error(result, "frame_0000.png", "320x240", "--max-image-mp")
    result = run_cli("ingest", csv_path, "--db", tmp_path / "b.sqlite", "--max-image-mp", "0")
    one_line_error(result, "--max-image-mp")
    assert not (tmp_path / "b.sqlite").exists()
    result = run_cli("ingest", csv_path, "--db", tmp_path / "c.sqlite", "--max-image-mp", "0.08", "--workers", "1")
    assert result.returncode == 0, result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["featureless-frame"], CASES["corrupt-frame"]]))
def test_a_bad_frame_is_named_then_skipped_and_recorded(tmp_path, fault):
    csv_path = write_csv_drive(tmp_path / "drive", n_frames=8)
    bad = csv_path.parent / "frame_0004.png"
    if fault.id == "featureless-frame":
        cv2.imwrite(str(bad), np.zeros((240, 320), np.uint8))
        reason = "no SIFT keypoints"
    else:
        bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"broken" * 50)
        reason = "cannot decode image"
    db_path = tmp_path / "store.sqlite"
    for workers in ("1", "2"):
        result = run_cli("ingest", csv_path, "--db", db_path, "--workers", workers)
        one_line_error(result, str(bad), reason, "frame 4", "--skip-bad-frames")
        assert stored_frames(db_path) == [0, 1, 2, 3]
    result = run_cli("ingest", csv_path, "--db", db_path, "--skip-bad-frames")
    assert result.returncode == 0, result.stderr
    assert "3 added, 4 already stored, 8 frames, 1 bad frame skipped" in result.stdout
    assert stored_frames(db_path) == [0, 1, 2, 3, 5, 6, 7]
    info = run_cli("info", "--db", db_path)
    assert info.returncode == 0, info.stderr
    assert "1 frame skipped at ingest" in info.stdout
    assert f"drive/camera frame 4 ({bad}): " in info.stdout and reason in info.stdout
    # a command that ingests first goes on: the recorded frame is tried again and skipped again
    evaluation = run_cli("evaluate", csv_path, "--db", db_path, "--steps", "2", "--start-frames", "0")
    assert evaluation.returncode == 0, evaluation.stderr
    # once the frame is fixed, ingest stores it and the record goes
    cv2.imwrite(str(bad), cv2.imread(str(csv_path.parent / "frame_0003.png"), cv2.IMREAD_GRAYSCALE))
    fixed = run_cli("ingest", csv_path, "--db", db_path)
    assert fixed.returncode == 0, fixed.stderr
    assert "1 added, 7 already stored, 8 frames" in fixed.stdout and "skipped" not in fixed.stdout
    assert "skipped at ingest" not in run_cli("info", "--db", db_path).stdout


def stopped_ingest(tmp_path: Path, signum: int, workers: int, *, background: bool = False):
    """An ingest of a 200-frame drive sent ``signum`` once it has committed 8 images: (its exit status,
    its stderr, what the store then holds, the drive's CSV, the store)."""
    csv_path = write_csv_drive(tmp_path / "long", n_frames=200, step_px=60)
    db_path = tmp_path / "store.sqlite"
    proc = ingest_process(csv_path, db_path, workers, background=background)
    try:
        wait_for_rows(db_path, 8, proc, timeout_s=600)
        os.kill(proc.pid, signum)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.returncode is None:
            stop_group(proc)
    return proc.returncode, err, snapshot(db_path), csv_path, db_path


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["sigint-in-background"]]))
@pytest.mark.parametrize("workers", [1, 2])
def test_sigint_stops_an_ingest_started_in_the_background(tmp_path, fault, workers):
    status, err, interrupted, _, db_path = stopped_ingest(tmp_path, signal.SIGINT, workers, background=True)
    assert status == 130, err
    assert 8 <= len(interrupted) < 200
    assert_no_half_images(interrupted)
    assert f"interrupted; {db_path} keeps {len(interrupted)} images" in err


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["sigterm-ingest"]]))
def test_sigterm_stops_an_ingest_as_ctrl_c_does(tmp_path, fault):
    status, err, stopped, csv_path, db_path = stopped_ingest(tmp_path, signal.SIGTERM, 2)
    assert status == 128 + signal.SIGTERM, err
    assert 8 <= len(stopped) < 200
    assert_no_half_images(stopped)
    assert f"visloc: stopped by SIGTERM; {db_path} keeps {len(stopped)} images" in err and "Traceback" not in err
    again = run_cli("ingest", csv_path, "--db", db_path, "--workers", "2")
    assert again.returncode == 0, again.stderr
    assert f"{200 - len(stopped)} added, {len(stopped)} already stored" in again.stdout


@pytest.mark.slow
@pytest.mark.parametrize("fault", params([CASES["dashboard-sigint-in-background"]]))
def test_sigint_stops_a_dashboard_started_in_the_background(tmp_path, fault):
    csv_path = write_csv_drive(tmp_path / "drive", n_frames=4)
    db_path = tmp_path / "store.sqlite"
    assert run_cli("ingest", csv_path, "--db", db_path, "--workers", "1").returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "visloc", "dashboard", "--db", str(db_path), "--port", "8391"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        seen = []
        for line in proc.stdout:  # until the server announces itself (or the process ends)
            seen.append(line)
            if line.startswith("visloc dashboard: http://"):
                break
        assert seen and seen[-1].startswith("visloc dashboard: http://"), "".join(seen) + proc.stderr.read()
        os.kill(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "interrupted" in err
