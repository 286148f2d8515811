"""docs/reliability.md is exactly what the fault tables render, and every case in them is a test."""

from __future__ import annotations

import subprocess
import sys

import pytest

from fault_table import FAULT_MODULES, all_faults
from helpers import REPO

sys.path.insert(0, str(REPO / "scripts"))
sys.path.insert(0, str(REPO / "benchmarks"))
import reliability  # noqa: E402


def test_the_reliability_page_is_the_fault_tables_rendered():
    assert (REPO / "docs" / "reliability.md").read_text() == reliability.render(all_faults()), \
        "docs/reliability.md is out of date: run python scripts/reliability.py"


def test_every_fault_in_the_tables_is_collected_as_a_test():
    files = [f"tests/{name}.py" for name in FAULT_MODULES]
    collected = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                                *files], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert collected.returncode == 0, collected.stdout + collected.stderr
    names = collected.stdout  # test ids: name[fault-id] or, with other parameters, name[...-fault-id-...]
    missing = sorted(f.id for f in all_faults()
                     if not (f"[{f.id}]" in names or f"-{f.id}]" in names or f"[{f.id}-" in names
                             or f"-{f.id}-" in names))
    assert not missing, f"faults listed but not tested: {missing}"


def test_the_performance_notes_are_what_their_json_renders():
    """The checksums' measured cost on docs/performance.md is rendered from docs/results/checksum_cost.json (written by
    benchmarks/checksum_cost.py), so it cannot drift from what was measured."""
    import json

    import checksum_cost

    rendered = checksum_cost.render(json.loads(checksum_cost.OUT.read_text()))
    assert rendered in (REPO / "docs" / "performance.md").read_text()
    assert checksum_cost.SECTION.updated_page(rendered) == (REPO / "docs" / "performance.md").read_text()


def test_the_saved_run_timings_are_what_their_json_renders():
    """The saved-run opening times on docs/performance.md are rendered from docs/results/saved_run_open.json (written by
    benchmarks/saved_run_open.py), and every run file the results hold was timed."""
    import json

    import saved_run_open

    result = json.loads(saved_run_open.OUT.read_text())
    rendered = saved_run_open.render(result)
    assert rendered in (REPO / "docs" / "performance.md").read_text()
    assert {r["kind"] for r in result["runs"]} == {"track", "evaluation"}
    assert all(r["steps"] > 0 and r["first_screen_s"] > 0 and r["command_to_url_s"] > 0 for r in result["runs"])


def test_the_dashboard_feedback_timings_are_what_their_json_renders():
    """The live dashboard's timings on docs/performance.md are rendered from docs/results/dashboard_feedback.json
    (written by benchmarks/dashboard_feedback.py), with every drive of the results store in both modes."""
    import json

    import dashboard_feedback

    result = json.loads(dashboard_feedback.OUT.read_text())
    rendered = dashboard_feedback.render(result)
    assert rendered in (REPO / "docs" / "performance.md").read_text()
    assert {r["mode"] for r in result["pairs"]} == {"paper", "refined"}
    assert len({r["queries"] for r in result["pairs"]}) == 3
    assert all(0 < r["first_rematched_step_s"] < r["rematched_run_s"] for r in result["pairs"])


def test_the_point_following_figures_are_what_their_json_renders():
    """docs/performance.md's table of ``visloc track --follow-points`` against the full path is rendered from
    docs/results/track_following.json (written by benchmarks/track_following.py), every drive with all its runs."""
    import json

    import track_following

    result = json.loads(track_following.OUT.read_text())
    assert track_following.render(result) in (REPO / "docs" / "performance.md").read_text()
    assert len(result["drives"]) == 3
    for runs in result["drives"].values():
        assert set(runs) == set(track_following.RUNS)
        assert all(0 < r["estimate_nees"] and 0 <= r["estimate_inside_95"] <= 1 for r in runs.values())
        assert set(runs["full"]["kinds"]) == {"full"}
        assert {"tracked", "relocalized"} <= set(runs["follow"]["kinds"]) <= {"tracked", "relocalized", "predicted"}
        assert runs["follow_paced"]["sustained_hz"] <= 10.5 and runs["follow_paced_loaded"]["sustained_hz"] <= 10.5
        profile = runs["follow_paced"]["relocalizations"]
        assert profile["n"] > 0 and profile["total_ms"] >= profile["stages_ms"]["sift_ms"] > 0
        assert profile["guided"] == 0 and 0 < runs["follow_paced_guided"]["relocalizations"]["guided"]


def test_the_self_check_agreement_is_what_its_json_renders():
    """docs/performance.md's comparison of each store's self-check with its queries is rendered from
    docs/results/self_check_agreement.json (written by benchmarks/self_check_agreement.py): every drive and setup,
    every configuration, each with the gain its own self-check fitted, posed as the queries are and posed the
    cheaper way beside it, the same queries measured at both gains."""
    import json

    import self_check_agreement

    result = json.loads(self_check_agreement.SECTION.out.read_text())
    assert self_check_agreement.SECTION.updated_page(self_check_agreement.render(result)) == \
        (REPO / "docs" / "performance.md").read_text()
    setups = {(s["drive"], s["protocol"]) for s in result["setups"]}
    assert len(setups) == 4  # 0001 stereo and left, 0005, 0027
    ways = self_check_agreement.AS_QUERIES, self_check_agreement.STAND_IN
    assert [(s["config"], s["self_check"]) for s in result["setups"]] == \
        [(c, w) for c in self_check_agreement.CONFIGS for w in ways] * len(setups)
    for a, b in zip(result["setups"][::2], result["setups"][1::2]):  # the same queries, posed once
        assert [f["error_m"] for f in a["frames"]] == [f["error_m"] for f in b["frames"]]
    for s in result["setups"]:
        assert s["lever_gain"]["n_both"] + s["lever_gain"]["n_one"] > 0
        assert s["query_error_m"]["n"] == len(s["frames"]) > 0


def test_the_support_figures_are_what_their_json_renders():
    """docs/performance.md's support table is rendered from docs/results/refined_support.json (written by
    benchmarks/refined_support.py): every drive, both configurations, on the same frames."""
    import json

    import refined_support

    result = json.loads(refined_support.SECTION.out.read_text())
    assert refined_support.SECTION.updated_page(refined_support.render(result)) == \
        (REPO / "docs" / "performance.md").read_text()
    assert len(result["drives"]) == 3
    for d in result["drives"]:
        configs = list(d["configs"].values())
        assert list(d["configs"]) == list(refined_support.CONFIGS)
        frames = [[r["frame"] for r in c["frames"]] for c in configs]
        assert frames[0] == frames[1] and len(frames[0]) == configs[0]["error_m"]["n"] > 0


def test_the_sharding_figures_are_what_their_json_renders():
    """docs/sharding.md's tables (ingest on a local cluster against one file, the synthetic city) are rendered
    from docs/results/shard_scale.json, written by benchmarks/shard_scale.py: every drive, a city of a million
    images in at least a thousand tiles."""
    import json

    import shard_scale

    result = json.loads(shard_scale.OUT.read_text())
    assert shard_scale.render(result) in (REPO / "docs" / "sharding.md").read_text()
    assert len(result["ingest"]) == 3
    assert result["city"]["images"] >= 1_000_000 and result["city"]["tiles"] >= 1000


def test_the_one_file_ingest_speedup_is_what_its_json_renders():
    """The one-file ingest on every core against one process (docs/performance.md) is rendered from
    docs/results/ingest_cores.json (written by benchmarks/ingest_cores.py): both cameras of a drive, every round's
    two stores identical row for row."""
    import json

    import ingest_cores

    result = json.loads(ingest_cores.OUT.read_text())
    rendered = ingest_cores.render(result)
    assert rendered in (REPO / "docs" / "performance.md").read_text()
    assert result["cameras"] == ["image_00", "image_01"] and result["rounds"] >= 3
    assert result["identical_stores"] and len(result["identical_per_round"]) == result["rounds"]
    assert len(result["speedups"]) == result["rounds"]


def test_the_command_line_start_times_are_what_their_json_renders():
    """How soon the command line answers (docs/performance.md) is rendered from docs/results/cli_startup.json
    (written by benchmarks/cli_startup.py), each command against a bare interpreter of the same rounds."""
    import json

    import cli_startup

    result = json.loads(cli_startup.OUT.read_text())
    rendered = cli_startup.render(result)
    assert rendered in (REPO / "docs" / "performance.md").read_text()
    assert cli_startup.BARE in result["commands"] and "visloc --help" in result["commands"]
    assert result["commands"][cli_startup.BARE]["median_ratio_to_bare"] == 1.0


def test_the_thinning_stress_is_what_its_json_renders():
    """The thinning stress on docs/performance.md is rendered from docs/results/thinning_stress.json (written by
    benchmarks/thinning_stress.py): every drive the peer measured, at the defaults and at every cap, both pipelines
    on the same frames."""
    import json

    import thinning_stress

    result = json.loads(thinning_stress.SECTION.out.read_text())
    assert thinning_stress.SECTION.updated_page(thinning_stress.render(result)) == \
        (REPO / "docs" / "performance.md").read_text()
    caps = list(result["caps"])
    assert caps[0] == thinning_stress.DEFAULT and len(caps) >= 2
    drives = set(result["caps"][thinning_stress.DEFAULT]["drives"])
    assert len(drives) == 3
    for cap in caps:
        assert set(result["caps"][cap]["drives"]) == drives
        for d in result["caps"][cap]["drives"].values():
            assert d["peer_error_m"]["n"] == d["visloc_error_m"]["n"] == len(d["frames"]) > 0


def test_the_structure_density_is_what_its_json_renders():
    """The structure-density section of docs/performance.md is rendered from docs/results/structure_density.json
    (written by benchmarks/structure_density.py): every drive the peer measured, each configuration posing the
    peer's frames, the defaults first."""
    import json

    import structure_density

    from visloc.params import REFINED

    result = json.loads(structure_density.SECTION.out.read_text())
    assert structure_density.SECTION.updated_page(structure_density.render(result)) == \
        (REPO / "docs" / "performance.md").read_text()
    assert len(result["drives"]) == 3
    for d in result["drives"]:
        assert list(d["configs"]) == list(structure_density.CONFIGS)
        defaults = list(d["configs"].values())[0]
        assert defaults["neighbour_baselines_m"] == list(REFINED.neighbour_baselines_m)
        assert all(c["stored"] is None or c["stored"]["images"] > 0 for c in d["configs"].values())
        for c in d["configs"].values():
            assert c["error_m"]["n"] == len(d["frames"]) > 0 and c["structures_built"] > 0


def test_the_feature_density_is_what_its_json_renders():
    """The denser-SIFT section of docs/performance.md is rendered from docs/results/feature_density.json (written
    by benchmarks/feature_density.py): every drive the peer measured at every contrast, the default first, on the
    peer's frames, with what each store cost; the default's features were all found among the denser ones."""
    import json

    import feature_density

    from visloc.params import SiftParams

    result = json.loads(feature_density.SECTION.out.read_text())
    assert feature_density.SECTION.updated_page(feature_density.render(result)) == \
        (REPO / "docs" / "performance.md").read_text()
    contrasts = list(result["contrasts"])
    assert float(contrasts[0]) == SiftParams().contrast_threshold and len(contrasts) >= 2
    assert len(result["subset"]) == 3
    for contrast, c in result["contrasts"].items():
        assert set(c["drives"]) == set(result["subset"]) and c["store_bytes_per_image"] > 0
        for d in c["drives"].values():
            assert d["peer_error_m"]["n"] == d["visloc_error_m"]["n"] == len(d["frames"]) > 0
            assert d["ingest_s_per_image"] > 0 and d["measurement_ms_median"] > 0
    for s in result["subset"].values():
        assert all(n["found"] == n["default"] > 0 for n in s["default_in_lower"].values())


def test_the_shared_error_figures_are_what_their_json_renders_and_the_parameters_are_their_fit():
    """docs/performance.md's table of the error consecutive measurements share is rendered from
    docs/results/measurement_correlation.json (written by benchmarks/measurement_correlation.py), every drive at
    10 Hz and 1 Hz, and the refined parameters are the fit over all drives it records."""
    import json

    import measurement_correlation

    from visloc.params import REFINED

    result = json.loads(measurement_correlation.SECTION.out.read_text())
    assert measurement_correlation.render(result) in (REPO / "docs" / "performance.md").read_text()
    assert len(result["drives"]) == 3
    assert all(set(r["filters"]) == {"10 Hz", "1 Hz"} for r in result["drives"].values())
    fit = result["pooled"]["fit"]
    assert REFINED.error_correlation == pytest.approx(fit["fraction"], abs=0.01)
    assert REFINED.error_correlation_time_s == pytest.approx(fit["time_s"], abs=0.01)


def test_the_dashboard_rate_figures_are_what_their_json_renders():
    """docs/dashboard.md's table of the camera-rate mode at 1 Hz and 10 Hz is rendered from
    docs/results/dashboard_rates.json (written by benchmarks/dashboard_rates.py): every shared drive, and at 10 Hz,
    the rate the page gives the mode, every frame; following points, as the page runs the mode, and on the stored
    features, as it runs it where it cannot read the images."""
    import json

    import dashboard_rates

    result = json.loads(dashboard_rates.SECTION.out.read_text())
    assert dashboard_rates.render(result) in (REPO / "docs" / "dashboard.md").read_text()
    shared = {p.name.removesuffix("_sync") for p in (REPO.parent / "shared" / "data" / "kitti").glob("*/*_sync")}
    assert {s["drive"].removesuffix("_sync") for s in result["setups"]} == shared
    for s in result["setups"]:
        assert set(s["runs"]) == {"following", "stored"}
        assert set(s["runs"]["stored"]) == {"1", "10"} and set(s["runs"]["following"]) == {"10"}
        assert s["runs"]["following"]["10"]["queries"] == s["runs"]["stored"]["10"]["queries"] > \
            9 * s["runs"]["stored"]["1"]["queries"]
        assert s["runs"]["following"]["10"]["tracked"] > 0 == s["runs"]["stored"]["10"]["tracked"]
