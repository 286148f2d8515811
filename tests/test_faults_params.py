"""Out-of-range parameters and output paths that cannot be written, through the command line as a
user meets them: each is refused before any work, in one line naming the flag (and the path)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from helpers import copy_store, make_fake_kitti, run_cli
from fault_table import Fault, params

P, O = "parameters", "output files"
REFUSED = "refused before any work: one line naming {}, exit 2"

FAULTS = [
    Fault("r-zero-with-p0-zero", P, "localize --meas-var-m2 0 --init-var 0 (exact measurements, exact start)",
          REFUSED.format("--meas-var-m2 and --init-var: the innovation covariance S = P + R would be singular")),
    Fault("r-zero-with-q-zero", P, "localize --meas-var-m2 0 --accel-var-m2-s4 0",
          REFUSED.format("--meas-var-m2 and --accel-var-m2-s4: P collapses to 0 and S = P + R would be singular")),
    Fault("dt-huge", P, "localize --dt-s 1e308", REFUSED.format("--dt-s and its range [0.001, 3600] s")),
    Fault("dt-inf", P, "localize --dt-s inf", REFUSED.format("--dt-s")),
    Fault("variance-huge", P, "localize --accel-var-m2-s4 1e308",
          REFUSED.format("--accel-var-m2-s4 and its range, 0 or [1e-12, 1e12]")),
    Fault("variance-tiny", P, "localize --meas-var-m2 1e-300", REFUSED.format("--meas-var-m2")),
    Fault("geotag-sigma-huge", P, "localize --geotag-sigma-m 1e200 (its square overflows)",
          REFUSED.format("--geotag-sigma-m")),
    Fault("seed-beyond-c-int", P, "localize --seed 99999999999999999999", REFUSED.format("--seed")),
    Fault("tau1-nan", P, "localize --tau1 nan", REFUSED.format("--tau1")),
    Fault("window-nan", P, "localize --window-s nan", REFUSED.format("--window-s")),
    Fault("exclusion-inf", P, "localize --exclusion-s inf", REFUSED.format("--exclusion-s")),
    Fault("gate-nan", P, "localize --gate-chi2 nan", REFUSED.format("--gate-chi2")),
    Fault("sift-scale-nan", P, "ingest --sift-scale nan", REFUSED.format("--sift-scale; no store file is created")),
    Fault("sift-sigma-huge", P, "ingest --sift-sigma 1e308 (OpenCV's blur kernel would overflow)",
          REFUSED.format("--sift-sigma; no store file is created")),
    Fault("localize-json-folder", O, "localize --json naming an existing folder",
          REFUSED.format("--json and the folder; nothing is matched or printed")),
    Fault("localize-json-missing-folder", O, "localize --json in a folder that does not exist",
          REFUSED.format("--json and the path")),
    Fault("localize-json-unwritable", O, "localize --json /proc/visloc.json (a place no file can be created)",
          REFUSED.format("--json and the path")),
    Fault("evaluate-json-folder", O, "evaluate --json naming an existing folder",
          REFUSED.format("--json and the folder; nothing is ingested or matched")),
    Fault("evaluate-plot-folder", O, "evaluate --plot naming an existing folder",
          REFUSED.format("--plot and the folder; nothing is ingested or matched")),
    Fault("track-json-folder", O, "track --json naming an existing folder", REFUSED.format("--json and the folder")),
    Fault("drives-out-dir-missing-parent", O, "evaluate-drives --out-dir two levels below an existing folder",
          REFUSED.format("--out-dir and the missing folder")),
    Fault("dashboard-allow-missing", P, "dashboard --allow naming a folder that does not exist",
          REFUSED.format("--allow and the folder; nothing is served")),
]


@pytest.fixture(scope="module")
def drives(csv_pair, tmp_path_factory):
    """The shared synthetic pair (a CSV database drive stored in a store, a CSV query drive), the store copied
    here (each case checks that it is left untouched), and a small KITTI layout."""
    tmp = tmp_path_factory.mktemp("faults_params")
    store = copy_store(csv_pair.store, tmp)
    make_fake_kitti(tmp / "kitti", n_frames=24)
    return tmp, csv_pair.db_csv, csv_pair.query_csv, store


def _case(fault_id: str, tmp: Path, db_csv: Path, query_csv: Path, store: Path):
    """(the command's arguments, fragments the error line must hold, a file the command must not create)."""
    localize = ("localize", query_csv, "--db", store, "--db-camera", "camera", "--steps", "3")
    fresh = tmp / f"{fault_id}.sqlite"  # a store the command would create if it started any work
    evaluate = ("evaluate", tmp / "kitti", "--db", fresh, "--steps", "2", "--workers", "1", "--exclusion-s", "0")
    flags = {
        "r-zero-with-p0-zero": (["--meas-var-m2", "0", "--init-var", "0"], ["--meas-var-m2", "--init-var", "singular"]),
        "r-zero-with-q-zero": (["--meas-var-m2", "0", "--accel-var-m2-s4", "0"],
                               ["--meas-var-m2", "--accel-var-m2-s4", "singular"]),
        "dt-huge": (["--dt-s", "1e308"], ["--dt-s", "3600"]),
        "dt-inf": (["--dt-s", "inf"], ["--dt-s", "inf"]),
        "variance-huge": (["--accel-var-m2-s4", "1e308"], ["--accel-var-m2-s4", "1e+12"]),
        "variance-tiny": (["--meas-var-m2", "1e-300"], ["--meas-var-m2", "1e-12"]),
        "geotag-sigma-huge": (["--geotag-sigma-m", "1e200"], ["--geotag-sigma-m"]),
        "seed-beyond-c-int": (["--seed", "99999999999999999999"], ["--seed"]),
        "tau1-nan": (["--tau1", "nan"], ["--tau1", "nan"]),
        "window-nan": (["--window-s", "nan"], ["--window-s", "nan"]),
        "exclusion-inf": (["--exclusion-s", "inf"], ["--exclusion-s", "inf"]),
        "gate-nan": (["--gate-chi2", "nan"], ["--gate-chi2", "nan"]),
    }
    if fault_id in flags:
        extra, fragments = flags[fault_id]
        return [*localize, *extra], fragments, None
    if fault_id.startswith("sift-"):
        flag, value = ("--sift-scale", "nan") if fault_id == "sift-scale-nan" else ("--sift-sigma", "1e308")
        return ["ingest", db_csv, "--db", fresh, "--workers", "1", flag, value], [flag], fresh
    folder = tmp / "a_folder"
    folder.mkdir(exist_ok=True)
    return {
        "localize-json-folder": ([*localize, "--json", folder], ["--json", str(folder), "folder"], None),
        "localize-json-missing-folder": ([*localize, "--json", tmp / "no" / "s.json"],
                                         ["--json", str(tmp / "no" / "s.json"), "does not exist"], None),
        "localize-json-unwritable": ([*localize, "--json", "/proc/visloc.json"], ["--json", "/proc/visloc.json"], None),
        "evaluate-json-folder": ([*evaluate, "--json", folder], ["--json", str(folder), "folder"], fresh),
        "evaluate-plot-folder": ([*evaluate, "--json", tmp / "e.json", "--plot", folder],
                                 ["--plot", str(folder), "folder"], fresh),
        "track-json-folder": (["track", query_csv, "--db", store, "--db-source", "dbdrive", "--frames", "3",
                               "--json", folder], ["--json", str(folder), "folder"], None),
        "drives-out-dir-missing-parent": (["evaluate-drives", tmp / "kitti", "--db", fresh, "--modes", "paper",
                                           "--steps", "2", "--out-dir", tmp / "no" / "out"],
                                          ["--out-dir", str(tmp / "no" / "out")], fresh),
        "dashboard-allow-missing": (["dashboard", "--db", store, "--allow", tmp / "no" / "stores"],
                                    ["--allow", str(tmp / "no" / "stores"), "no such folder"], None),
    }[fault_id]


@pytest.mark.parametrize("fault", params(FAULTS))
def test_refused_before_any_work_in_one_line(drives, fault):
    tmp, db_csv, query_csv, store = drives
    args, fragments, not_created = _case(fault.id, tmp, db_csv, query_csv, store)
    before = hashlib.sha256(store.read_bytes()).hexdigest()
    result = run_cli(*args)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("visloc: error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    # fails fast: no tables or series printed, no store started, the existing store untouched
    assert result.stdout == "", result.stdout
    if not_created is not None:
        assert not not_created.exists(), f"{not_created} was created: work started before the check"
    assert hashlib.sha256(store.read_bytes()).hexdigest() == before
    assert not (tmp / "no").exists()


def test_a_singular_innovation_covariance_the_parameters_cannot_foresee_is_a_parameter_error():
    """A per-step R of 0 (a geotag stated exact) where P is 0 on the position: one error, no LinAlgError."""
    import numpy as np

    from visloc.errors import ParameterError
    from visloc.tracking.kalman import update

    with pytest.raises(ParameterError, match="singular"):
        update(np.zeros(4), np.zeros((4, 4)), np.array([1.0, 2.0]), np.zeros((2, 2)))
