"""Property-based fuzzing of the drive parsers: whatever a file holds, reading it gives a result or a
``VislocError`` (the CLI's one-line error, exit 2), never another exception.

Fuzzed: the CSV drive (``open_csv``: raw bytes, and well-formed CSV with mutated cells beside two
small valid images), KITTI's OXTS record (``read_oxts``) and ``timestamps.txt`` (``_read_timestamps``),
its calibration files (``read_kitti_calibration``, ``read_kitti_extrinsics``) and a CSV drive's
``calibration.json`` (``read_calibration``: any JSON value, near-valid objects, raw bytes).
Derandomized, so every run tries the same inputs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from visloc.errors import VislocError
from visloc.sources.calibration import read_calibration, read_kitti_calibration, read_kitti_extrinsics
from visloc.sources.drives import _read_timestamps, open_csv
from visloc.sources.oxts import read_oxts

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def survives(read, *args) -> None:
    """``read(*args)`` returns or raises a VislocError whose message is one line."""
    try:
        read(*args)
    except VislocError as exc:
        assert "\n" not in str(exc), str(exc)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """A folder with two small valid images, a.png and b.png, and a subfolder sub/."""
    out = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(out / name), rng.integers(0, 256, (16, 24), dtype=np.uint8))
    (out / "sub").mkdir()
    return out


def written(path: Path, content: bytes | str) -> Path:
    if isinstance(content, str):
        path.write_text(content, encoding="utf-8")
    else:
        path.write_bytes(content)
    return path


# -- pieces of plausible input, often slightly wrong ---------------------------------------------

NUMBER_TEXT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**6, 10**6).map(str),
    st.sampled_from(["nan", "NaN", "-inf", "inf", "1e309", "-1e-320", "0", "-0", "1_000", " 49 ", "", "  ",
                     "0x10", "1,5", "١٢", "٣.٥", "\u00a0", "e", "."]),
)
TIME_TEXT = st.one_of(
    NUMBER_TEXT,
    st.datetimes().map(lambda d: d.isoformat()),
    st.datetimes(timezones=st.timezones()).map(lambda d: d.isoformat()),
    st.sampled_from(["2011-09-26T13:02:25.5", "2011-09-26 13:02:25+14:00", "0001-01-01T00:00:00+01:00",
                     "9999-12-31T23:59:59-23:59", "2011-02-30", "soon"]),
)
FILE_TEXT = st.one_of(
    st.sampled_from(["a.png", "b.png", "sub", "sub/../a.png", "../a.png", "/etc/passwd", "a.png\x00", "",
                     "missing.png", "./b.png", "sub/../../x.png", "~/a.png", "C:\\a.png", "a" * 300]),
    st.text(max_size=20),
)
CELL = st.one_of(NUMBER_TEXT, TIME_TEXT, FILE_TEXT, st.text(max_size=12))
# cells a user would write, per column: small timestamps, so that rows often share one
GOOD_CELL = {
    "file": st.sampled_from(["a.png", "b.png", "./b.png", "sub/../a.png"]),
    "timestamp": st.one_of(st.integers(0, 6).map(str), st.floats(0, 10).map(repr),
                           st.sampled_from(["2011-09-26T13:02:25.5", "2011-09-26T13:02:26+02:00"])),
    "lat": st.floats(-90, 90).map(repr),
    "lon": st.floats(-180, 180).map(repr),
}
OPTIONAL_COLUMNS = ["alt", "heading", "roll_deg", "pitch_deg", "accuracy_m", "extra"]
OPTIONAL_GROUPS = [("alt",), ("heading",), ("roll_deg", "pitch_deg", "heading"), ("accuracy_m",), ("extra",)]
OTHER_CELL = st.one_of(st.just(""), st.floats(-400, 400).map(repr))


def mostly(draw, good: st.SearchStrategy, bad: st.SearchStrategy):
    """Four times in five a good value, else a bad one."""
    return draw(bad) if draw(st.integers(0, 4)) == 4 else draw(good)  # 0, hypothesis's simplest, is good


def csv_cell(text: str) -> str:
    return '"' + text.replace('"', '""') + '"' if any(c in text for c in ',"\r\n') else text


@st.composite
def csv_text(draw) -> str:
    """A CSV as a user writes it (the needed columns, some optional ones, cells of the right kind), with
    a few cells, rows or header names replaced by plausible mistakes."""
    groups = draw(st.lists(st.sampled_from(OPTIONAL_GROUPS), unique=True))
    good_header = st.permutations(["file", "timestamp", "lat", "lon"] + sorted({c for g in groups for c in g}))
    header = mostly(draw, good_header, st.lists(st.sampled_from(list(GOOD_CELL) + OPTIONAL_COLUMNS + [
        " file", "lat ", "", "FILE"]), max_size=10))
    rows = []
    for _ in range(draw(st.integers(0, 5))):
        row = [mostly(draw, GOOD_CELL.get(column, OTHER_CELL), CELL) for column in header]
        rows.append(mostly(draw, st.just(row), st.lists(CELL, max_size=len(header) + 2)))
    ending = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    body = ending.join(",".join(csv_cell(c) for c in row) for row in [header, *rows])
    return draw(st.sampled_from(["", "\ufeff"])) + body + draw(st.sampled_from(["", ending, ending * 2]))


@FUZZ
@given(content=st.binary(max_size=300))
def test_open_csv_survives_any_bytes(folder, content):
    survives(open_csv, written(folder / "bytes.csv", b"file,timestamp,lat,lon\n" + content))
    survives(open_csv, written(folder / "bytes.csv", content))


@pytest.mark.slow
@FUZZ
@given(text=csv_text())
def test_open_csv_survives_mutated_csv(folder, text):
    survives(open_csv, written(folder / "geotags.csv", text))


@FUZZ
@given(content=st.one_of(st.binary(max_size=200), st.text(max_size=200),
                         st.lists(NUMBER_TEXT, max_size=32).map(" ".join)))
def test_oxts_record_survives_anything(folder, content):
    survives(read_oxts, written(folder / "0000000000.txt", content))


KITTI_TIME = st.datetimes().map(lambda d: d.strftime("%Y-%m-%d %H:%M:%S.%f") + "000")


@FUZZ
@given(content=st.one_of(
    st.binary(max_size=200), st.text(max_size=200),
    st.lists(st.one_of(KITTI_TIME, TIME_TEXT, st.sampled_from(["2011-09-26 13:02:25.", "2011-09-26 13:02:25.1e5",
                                                               "2011-09-26 13:02:25.-1", "2011-09-26 13:02:25.٣"])),
             max_size=6).map("\n".join)))
def test_timestamps_survive_anything(folder, content):
    survives(_read_timestamps, written(folder / "timestamps.txt", content))


CALIB_KEYS = ["P_rect_00", "P_rect_01", "R_rect_00", "R", "T", "calib_time", "S_00"]
KITTI_LIKE = {3: "-0.8 0.3 -0.8".split(), 9: "0 -1 0 0 0 -1 1 0 0".split(),
              12: "721.5377 0 609.5593 -387.5744 0 721.5377 172.854 0 0 0 1 0".split()}
CALIB_NUMBER = st.one_of(NUMBER_TEXT, st.just("0"), st.floats(-1e308, 1e308).map(repr))


@st.composite
def calib_text(draw, keys: dict[str, int]) -> str:
    """A KITTI calibration file: mostly each of ``keys`` (name: count) with that many numbers (KITTI's,
    any, or all zeros), in any order among a few lines of other keys, else a line gone or wrong."""
    lines = []
    for key, count in keys.items():
        good = st.one_of(st.just(KITTI_LIKE[count]), st.lists(st.floats(-1000, 1000).map(repr), min_size=count,
                                                               max_size=count), st.just(["0"] * count))
        values = mostly(draw, good, st.lists(CALIB_NUMBER, max_size=count + 1))
        if draw(st.integers(0, 9)) != 9:
            lines.append(f"{key}: {' '.join(values)}")
    for _ in range(draw(st.integers(0, 2))):
        key = draw(st.sampled_from([k for k in CALIB_KEYS if k not in keys]))
        lines.append(f"{key}: {' '.join(draw(st.lists(CALIB_NUMBER, max_size=13)))}")
    return "\n".join(draw(st.permutations(lines)))


@FUZZ
@given(cam=st.one_of(*[calib_text({"R_rect_00": 9, "P_rect_00": 12, "P_rect_01": 12})] * 3, st.text(max_size=100),
                     st.binary(max_size=100)),
       velo=calib_text({"R": 9, "T": 3}), imu=calib_text({"R": 9, "T": 3}),
       camera=st.sampled_from(["image_00", "image_01"]))
@pytest.mark.slow
def test_kitti_calibration_survives_anything(folder, cam, velo, imu, camera):
    date = folder / "calib"
    date.mkdir(exist_ok=True)
    written(date / "calib_cam_to_cam.txt", cam)
    written(date / "calib_velo_to_cam.txt", velo)
    written(date / "calib_imu_to_velo.txt", imu)
    survives(read_kitti_calibration, date / "calib_cam_to_cam.txt", camera)
    survives(read_kitti_extrinsics, date, camera)


def test_good_kitti_calibration_files_are_read(folder):
    """What the fuzzer mutates is read when left alone."""
    date = folder / "good_calib"
    date.mkdir()
    written(date / "calib_cam_to_cam.txt", "R_rect_00: 1 0 0 0 1 0 0 0 1\nP_rect_00: 700 0 600 0 0 700 170 0 0 0 1 0\n")
    written(date / "calib_velo_to_cam.txt", "R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    written(date / "calib_imu_to_velo.txt", "R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    assert read_kitti_extrinsics(date, "image_00").shape == (4, 4)


JSON_VALUE = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.integers(-10**400, 10**400), st.floats(),
              st.text(max_size=8)),
    lambda children: st.one_of(st.lists(children, max_size=5), st.dictionaries(st.text(max_size=6), children,
                                                                               max_size=5)),
    max_leaves=20)
GOOD_CALIBRATION = {"fx": 721.5, "fy": 721.5, "cx": 609.6, "cy": 172.9, "width_px": 1242, "height_px": 375,
                    "distortion": [-0.37, 0.2, 0.0022, 0.0014, -0.072],
                    "T_vehicle_camera": [[0, 0, 1, 1.08], [-1, 0, 0, -0.31], [0, -1, 0, 0.73], [0, 0, 0, 1]]}


@st.composite
def near_calibration(draw) -> dict:
    """The good calibration with a few values replaced by anything, or keys dropped."""
    out = dict(GOOD_CALIBRATION)
    for key in draw(st.lists(st.sampled_from(sorted(GOOD_CALIBRATION)), min_size=1, max_size=3)):
        if draw(st.booleans()):
            out.pop(key, None)
        else:
            out[key] = draw(st.one_of(JSON_VALUE, st.sampled_from([math.nan, math.inf, 0, -1, 10**400, 2**63]),
                                      st.lists(st.floats(), min_size=16, max_size=16),
                                      st.lists(st.lists(st.floats(), min_size=4, max_size=4), min_size=4,
                                               max_size=4)))
    return out


@FUZZ
@given(value=st.one_of(JSON_VALUE, near_calibration()))
@example(value={**GOOD_CALIBRATION, "fx": 10**400})  # an integer beyond float range
@example(value={**GOOD_CALIBRATION, "T_vehicle_camera": [10**400] * 16})
@example(value={**GOOD_CALIBRATION, "distortion": [10**400] * 5})
@example(value={**GOOD_CALIBRATION, "T_vehicle_camera": [[1e200, 0, 0, 0], [0, 1e200, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]})
def test_calibration_json_survives_any_json(folder, value):
    survives(read_calibration, written(folder / "calibration.json", json.dumps(value)))


@FUZZ
@given(content=st.one_of(st.binary(max_size=200),
                         st.sampled_from(["[" * 100_000, "1" * 5000, '{"fx": ' + "9" * 5000 + "}", "\ufeff{}"])))
def test_calibration_json_survives_any_bytes(folder, content):
    survives(read_calibration, written(folder / "calibration.json", content))
