"""Bad input in a drive, as a user brings it to ``visloc ingest``: each fault is refused with one line
naming the file and the row, line, field or key (exit 2, no traceback), and a store that already
holds another drive keeps every image.

Each case starts from a small good drive (a CSV drive of 4 frames, or a fake KITTI drive of 3) and
breaks one thing; ``BREAKS`` maps a fault's id to the function doing so.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import pytest
from helpers import make_fake_kitti, run_cli, write_csv_drive
from fault_table import Fault, params

REFUSED = [
    Fault(id="csv-repeated-row", area="CSV drive",
          tried="A CSV in which a row appears twice, so two frames share a timestamp.",
          gets="Refused at ingest: one line naming both rows and the timestamp, exit 2; the store is untouched."),
    Fault(id="csv-same-time-written-twice", area="CSV drive",
          tried="Two rows whose timestamps are written differently but are the same time (1000.5 and 1000.50).",
          gets="Refused at ingest: one line naming both rows and both timestamps, exit 2."),
    Fault(id="csv-not-utf8", area="CSV drive",
          tried="A CSV saved in Latin-1 (an accented letter in a file name).",
          gets="Refused at ingest: one line naming the CSV and the line of the first byte that is not UTF-8, exit 2."),
    Fault(id="csv-absolute-file", area="CSV drive",
          tried="A row whose file is an absolute path (/etc/passwd).",
          gets="Refused at ingest: one line naming the row and saying the file must be inside the CSV's folder, exit 2."),
    Fault(id="csv-file-outside-folder", area="CSV drive",
          tried="A row whose file climbs out of the CSV's folder with ../",
          gets="Refused at ingest: one line naming the row and saying the file must be inside the CSV's folder, exit 2."),
    Fault(id="csv-nan-timestamp", area="CSV drive",
          tried="A row whose timestamp is nan.",
          gets="Refused at ingest: one line naming the row and the timestamp column, exit 2."),
    Fault(id="kitti-repeated-timestamp", area="KITTI drive",
          tried="A timestamps.txt in which a line is repeated (the counts still match the images).",
          gets="Refused at ingest: one line naming timestamps.txt and both line numbers, exit 2."),
    Fault(id="kitti-timestamps-go-back", area="KITTI drive",
          tried="A timestamps.txt whose lines are not in time order.",
          gets="Refused at ingest: one line naming timestamps.txt and both line numbers, exit 2."),
    Fault(id="kitti-timestamps-not-utf8", area="KITTI drive",
          tried="A timestamps.txt with a byte that is not UTF-8.",
          gets="Refused at ingest: one line naming timestamps.txt and the line, exit 2."),
    Fault(id="kitti-oxts-nan", area="KITTI drive",
          tried="An OXTS record whose latitude is nan.",
          gets="Refused at ingest: one line naming the record and the field (1, lat), exit 2."),
    Fault(id="kitti-oxts-not-utf8", area="KITTI drive",
          tried="An OXTS record with a byte that is not UTF-8.",
          gets="Refused at ingest: one line naming the record, exit 2."),
    Fault(id="kitti-singular-p-rect", area="calibration",
          tried="A calib_cam_to_cam.txt whose P_rect_01 is all zeros.",
          gets="Refused at ingest: one line naming the file and P_rect_01 (its 3x3 part is singular), exit 2."),
    Fault(id="kitti-calibration-nan", area="calibration",
          tried="A calib_cam_to_cam.txt with nan in R_rect_00.",
          gets="Refused at ingest: one line naming the file and R_rect_00, exit 2."),
    Fault(id="kitti-calibration-not-utf8", area="calibration",
          tried="A calib_cam_to_cam.txt with a byte that is not UTF-8.",
          gets="Refused at ingest: one line naming the file and the line, exit 2."),
    Fault(id="csv-calibration-json-not-utf8", area="calibration",
          tried="A calibration.json beside the CSV with a byte that is not UTF-8.",
          gets="Refused at ingest: one line naming calibration.json and the line, exit 2."),
    Fault(id="csv-calibration-json-huge-number", area="calibration",
          tried="A calibration.json whose fx is an integer of 400 digits.",
          gets="Refused at ingest: one line naming calibration.json and fx, exit 2."),
]
ACCEPTED = [
    Fault(id="csv-excel-bom", area="CSV drive",
          tried="A CSV saved by Excel as UTF-8, starting with a byte-order mark.",
          gets="Accepted: the mark is skipped and every frame is ingested."),
]
FAULTS = REFUSED + ACCEPTED

CALIBRATION_JSON = ('{"fx": 500, "fy": 500, "cx": 160, "cy": 120, "width_px": 320, "height_px": 240,\n'
                    ' "T_vehicle_camera": [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 1], [0, 0, 0, 1]]}\n')


# -- breaking a good drive: each returns (the source to ingest, fragments the error line must hold) ----------

def _csv(tmp_path: Path) -> tuple[Path, list[str]]:
    """A good CSV drive of 4 frames (rows on lines 2 to 5, timestamps 1000.000, 1000.500, ...) and its lines."""
    path = write_csv_drive(tmp_path / "drive", n_frames=4)
    return path, path.read_text().splitlines()


def _write_lines(path: Path, lines: list[str]) -> None:
    path.write_text("\n".join(lines) + "\n")


def csv_repeated_row(tmp_path):
    path, lines = _csv(tmp_path)
    _write_lines(path, lines + [lines[2]])
    return path, ["geotags.csv:3 and :6", "timestamp 1000.500 repeats", "timestamps must increase"]


def csv_same_time_written_twice(tmp_path):
    path, lines = _csv(tmp_path)
    lines[4] = lines[4].replace(",1001.500,", ",1000.50,")
    _write_lines(path, lines)
    return path, ["geotags.csv:3 and :5", "1000.500 and 1000.50", "timestamps must increase"]


def csv_not_utf8(tmp_path):
    path, lines = _csv(tmp_path)
    path.write_bytes("\n".join(lines[:3]).encode() + "\nnot_utf8_\xe9.png,1002,49,8,90\n".encode("latin-1"))
    return path, ["geotags.csv:4: not UTF-8"]


def csv_absolute_file(tmp_path):
    path, lines = _csv(tmp_path)
    lines[3] = lines[3].replace("frame_0002.png", "/etc/passwd")
    _write_lines(path, lines)
    return path, ["geotags.csv:4", "'/etc/passwd' must be a path inside", str(path.parent)]


def csv_file_outside_folder(tmp_path):
    path, lines = _csv(tmp_path)
    (tmp_path / "elsewhere.png").write_bytes((path.parent / "frame_0002.png").read_bytes())
    lines[3] = lines[3].replace("frame_0002.png", "../elsewhere.png")
    _write_lines(path, lines)
    return path, ["geotags.csv:4", "'../elsewhere.png' must be a path inside", str(path.parent)]


def csv_nan_timestamp(tmp_path):
    path, lines = _csv(tmp_path)
    lines[2] = lines[2].replace(",1000.500,", ",nan,")
    _write_lines(path, lines)
    return path, ["geotags.csv:3", "column timestamp", "'nan'"]


def _kitti(tmp_path: Path) -> Path:
    """A good fake KITTI drive of 3 frames; the root (the source to ingest) is tmp_path / "kitti"."""
    return make_fake_kitti(tmp_path / "kitti", n_frames=3)


def kitti_repeated_timestamp(tmp_path):
    drive = _kitti(tmp_path)
    stamps = drive / "image_01" / "timestamps.txt"
    lines = stamps.read_text().splitlines()
    _write_lines(stamps, [lines[0], lines[1], lines[1]])
    return tmp_path / "kitti", ["image_01/timestamps.txt:2 and :3", "repeats", "timestamps must increase"]


def kitti_timestamps_go_back(tmp_path):
    drive = _kitti(tmp_path)
    stamps = drive / "image_01" / "timestamps.txt"
    lines = stamps.read_text().splitlines()
    _write_lines(stamps, [lines[0], lines[2], lines[1]])
    return tmp_path / "kitti", ["image_01/timestamps.txt:2 and :3", "is earlier than", "timestamps must increase"]


def kitti_timestamps_not_utf8(tmp_path):
    drive = _kitti(tmp_path)
    stamps = drive / "image_01" / "timestamps.txt"
    stamps.write_bytes(stamps.read_bytes().replace(b"13:02:25.2", b"13:02:25\xb72"))
    return tmp_path / "kitti", ["image_01/timestamps.txt:3: not UTF-8"]


def kitti_oxts_nan(tmp_path):
    record = _kitti(tmp_path) / "oxts" / "data" / "0000000001.txt"
    record.write_text("nan " + record.read_text().split(" ", 1)[1])
    return tmp_path / "kitti", ["oxts/data/0000000001.txt", "field 1 (lat) is not a finite number: 'nan'"]


def kitti_oxts_not_utf8(tmp_path):
    record = _kitti(tmp_path) / "oxts" / "data" / "0000000002.txt"
    record.write_bytes(record.read_bytes() + b"\xff\n")
    return tmp_path / "kitti", ["oxts/data/0000000002.txt", "not UTF-8"]


def _calib(tmp_path: Path) -> Path:
    _kitti(tmp_path)
    return tmp_path / "kitti" / "2011_09_26" / "calib_cam_to_cam.txt"


def kitti_singular_p_rect(tmp_path):
    calib = _calib(tmp_path)
    lines = [("P_rect_01: " + " ".join(["0"] * 12)) if line.startswith("P_rect_01:") else line
             for line in calib.read_text().splitlines()]
    _write_lines(calib, lines)
    return tmp_path / "kitti", ["calib_cam_to_cam.txt", "P_rect_01: its 3x3 part is singular"]


def kitti_calibration_nan(tmp_path):
    calib = _calib(tmp_path)
    calib.write_text(calib.read_text().replace("R_rect_00: 1 0 0", "R_rect_00: nan 0 0"))
    return tmp_path / "kitti", ["calib_cam_to_cam.txt", "R_rect_00", "not finite"]


def kitti_calibration_not_utf8(tmp_path):
    calib = _calib(tmp_path)
    calib.write_bytes(b"calib_time: 09-Jan-2012 13:57:47 \xb5s\n" + calib.read_bytes())
    return tmp_path / "kitti", ["calib_cam_to_cam.txt:1: not UTF-8"]


def csv_calibration_json_not_utf8(tmp_path):
    path, _ = _csv(tmp_path)
    (path.parent / "calibration.json").write_bytes(CALIBRATION_JSON.encode() + b'\xe9\n')
    return path, ["calibration.json:3: not UTF-8"]


def csv_calibration_json_huge_number(tmp_path):
    path, _ = _csv(tmp_path)
    (path.parent / "calibration.json").write_text(CALIBRATION_JSON.replace('"fx": 500', '"fx": 1' + "0" * 400))
    return path, ["calibration.json: fx: expected a finite number"]


BREAKS: dict[str, Callable[[Path], tuple[Path, list[str]]]] = {
    "csv-repeated-row": csv_repeated_row,
    "csv-same-time-written-twice": csv_same_time_written_twice,
    "csv-not-utf8": csv_not_utf8,
    "csv-absolute-file": csv_absolute_file,
    "csv-file-outside-folder": csv_file_outside_folder,
    "csv-nan-timestamp": csv_nan_timestamp,
    "kitti-repeated-timestamp": kitti_repeated_timestamp,
    "kitti-timestamps-go-back": kitti_timestamps_go_back,
    "kitti-timestamps-not-utf8": kitti_timestamps_not_utf8,
    "kitti-oxts-nan": kitti_oxts_nan,
    "kitti-oxts-not-utf8": kitti_oxts_not_utf8,
    "kitti-singular-p-rect": kitti_singular_p_rect,
    "kitti-calibration-nan": kitti_calibration_nan,
    "kitti-calibration-not-utf8": kitti_calibration_not_utf8,
    "csv-calibration-json-not-utf8": csv_calibration_json_not_utf8,
    "csv-calibration-json-huge-number": csv_calibration_json_huge_number,
}


def test_every_refused_fault_has_a_breakage():
    assert set(BREAKS) == {f.id for f in REFUSED}


def image_count(store: Path) -> int:
    conn = sqlite3.connect(store)
    try:
        return conn.execute("SELECT count(*) FROM images").fetchone()[0]
    finally:
        conn.close()


@pytest.fixture(scope="module")
def good_store(tmp_path_factory) -> Path:
    """A store holding a good CSV drive, "good", of 4 frames."""
    tmp = tmp_path_factory.mktemp("faults_input")
    path = tmp / "store.sqlite"
    result = run_cli("ingest", write_csv_drive(tmp / "good", n_frames=4, seed=11), "--db", path, "--workers", "1")
    assert result.returncode == 0, result.stderr
    assert image_count(path) == 4
    return path


@pytest.fixture
def store(good_store, tmp_path) -> Path:
    """This test's own copy of the good store (SQLite's backup), so no case sees what another did."""
    path = tmp_path / "store.sqlite"
    source, target = sqlite3.connect(good_store), sqlite3.connect(path)
    try:
        source.backup(target)
    finally:
        source.close()
        target.close()
    return path


@pytest.mark.parametrize("fault", params(REFUSED))
def test_bad_input_is_refused_in_one_line_keeping_the_store(fault, tmp_path, store):
    source, fragments = BREAKS[fault.id](tmp_path)
    before = image_count(store)
    result = run_cli("ingest", source, "--db", store, "--workers", "1")
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("visloc: error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert image_count(store) == before == 4  # the drive already stored is all there


@pytest.mark.parametrize("fault", params(ACCEPTED))
def test_a_csv_with_a_byte_order_mark_is_ingested(fault, tmp_path):
    assert fault.id == "csv-excel-bom"
    path = write_csv_drive(tmp_path / "drive", n_frames=4)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    result = run_cli("ingest", path, "--db", tmp_path / "store.sqlite", "--workers", "1")
    assert result.returncode == 0, result.stderr
    assert "drive/camera: 4 added" in result.stdout
    assert image_count(tmp_path / "store.sqlite") == 4
