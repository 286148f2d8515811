"""Measure what the results page reports, and write the page from what was measured.

    python scripts/results.py run [--data ROOT]   # every command below, on every drive of ROOT (out/results/)
    python scripts/results.py page                 # docs/results/digest.json and docs/results.md from out/results/
    python scripts/results.py render               # docs/results.md again from docs/results/digest.json alone

``run`` calls the ``visloc`` command as a user would: ``visloc evaluate-drives`` on the data root
(default ../shared/data/kitti: every drive, each protocol it supports, both modes, the RTS
smoother); ``visloc evaluate`` in the paper's mode again with other query sampling and process
noise; ``visloc bench`` per drive; ``visloc track`` per drive and setup; benchmarks/refined_diagnostics.py per
drive; and
scripts/paper_haversine_check.py. Every run writes its JSON to out/results/ and
out/results/manifest.json records the commands. ``page`` reduces those JSON
files to docs/results/digest.json (the numbers the page shows, with their commands) and renders
docs/results.md from it; ``render`` re-renders the page from the committed digest, so the page
and its numbers cannot drift apart (the test suite checks it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from visloc.errors import InputError  # noqa: E402
from visloc.params import PAPER_SIFT, STORE_SIFT  # noqa: E402
from visloc.protocols.suite import drive_protocols, drives_of  # noqa: E402
from visloc.stats import CHI2_2DOF_95, summary_of  # noqa: E402
from results_camera_rate import coverage_cells, digest_refined_fast, digest_track, render_camera_rate  # noqa: E402
from filter_replay import render_filter_replay, replay  # noqa: E402
from results_peer import digest_peer, render_peer  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
OUT = REPO / "out" / "results"
DIGEST = REPO / "docs" / "results" / "digest.json"
PAGE = REPO / "docs" / "results.md"
PEER = REPO.parent / "shared" / "peer" / "results"  # the COLMAP-style peer's measurements, beside the project
PAPER_FINAL_ERROR_M = 1.85  # the paper's section 4, Figure 4: drive 2011_09_26_drive_0001
PAPER_DRIVE = "2011_09_26_drive_0001"
VARIANTS = {  # the paper's mode, one change each: (label, extra flags)
    "sampling_time": ("`--sampling time` (the frame nearest each whole second, not every 10th frame)",
                      ["--sampling", "time"]),
    "q_0.1": ("`--accel-var-m2-s4 0.1` (Q ten times smaller)", ["--accel-var-m2-s4", "0.1"]),
    "q_10": ("`--accel-var-m2-s4 10` (Q ten times larger)", ["--accel-var-m2-s4", "10"]),
}


# -- run: the commands --------------------------------------------------------------------------

def run(data: Path, speed_only: bool = False, suite_only: bool = False) -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    try:
        drives = drives_of(data)
    except InputError as exc:
        drives, reason = [], str(exc)
    else:
        reason = f"{data}: no KITTI drives"
    if not drives:
        print(f"results: {reason}", file=sys.stderr)
        return 2
    # paths as the commands are shown: relative to the checkout, where they run
    root = os.path.relpath(data, REPO)
    out = OUT.relative_to(REPO)
    store, fast_store = out / "visloc.sqlite", out / "visloc_s05.sqlite"
    visloc = [sys.executable, "-m", "visloc"]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                            text=True).stdout.strip()
    now = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    manifest = {"commit": commit, "started": now, "cores": os.cpu_count(), "load_before": os.getloadavg()[0],
                "runs": []}
    if speed_only:  # keep the evaluations of the last full run, measure the speed sections again
        if (OUT / "manifest.json").is_file():
            manifest = json.loads((OUT / "manifest.json").read_text())
            manifest["runs"] = [r for r in manifest["runs"] if r["kind"] not in ("bench", "track")]
        else:  # no run here to keep: the page keeps every other section of the committed digest
            manifest = {"speed_over_digest": True, "runs": []}
        manifest["speed"] = {"commit": commit, "started": now, "load_before": os.getloadavg()[0]}

    def command(name: str, args: list[str], **meta) -> None:
        print(f"results: {name}: {' '.join(args)}", flush=True)
        subprocess.run([*visloc, *args], cwd=REPO, check=True)
        manifest["runs"].append({"file": f"{name}.json", "command": "visloc " + " ".join(args), **meta})

    if suite_only:  # evaluate-drives alone; the page keeps the other sections of the committed digest
        manifest["suite_only"] = True
        evaluations(drives, root, out, store, command, manifest, variants=False)
        return finish(manifest)
    if not speed_only:
        evaluations(drives, root, out, store, command, manifest)
    for n, folder in enumerate(drives):
        drive = folder.name.removesuffix("_sync")
        command(f"bench_{drive}", ["bench", root, "--drive", drive, "--db", str(store), "--fast-db",
                                   str(fast_store), *([] if n == 0 else ["--skip-synthetic"]), "--json",
                                   str(out / f"bench_{drive}.json")], kind="bench", drive=drive)
    for folder in drives:  # every frame at camera rate, each setup the drive has, the 1 s exclusion on
        drive = folder.name.removesuffix("_sync")
        for p in drive_protocols(folder):
            name = f"track_{drive}_{p.key}"
            command(name, ["track", root, "--drive", drive, "--camera", p.query_camera, "--db-camera", p.db_camera,
                           "--db", str(store), "--exclusion-s", "1", "--no-follow-points", "--json", str(out / f"{name}.json")],
                    kind="track", drive=drive, setup=p.key, setup_label=p.label)
    if speed_only:
        manifest["speed"].update(finished=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                                 load_after=os.getloadavg()[0])
        (OUT / "manifest.json").write_text(json.dumps(manifest, indent=1))
        print(f"results: wrote {OUT / 'manifest.json'}; now: python scripts/results.py page")
        return 0
    diagnostics(drives, root, out, store, manifest)
    return finish(manifest)


def finish(manifest: dict) -> int:
    manifest["finished"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    manifest["load_after"] = os.getloadavg()[0]
    (OUT / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"results: wrote {OUT / 'manifest.json'}; now: python scripts/results.py page")
    return 0


def evaluations(drives: list, root: str, out: Path, store: Path, command, manifest: dict,
                variants: bool = True) -> None:
    """evaluate-drives on the root, then (``variants``) the paper's mode with one change per variant."""
    suite = ["evaluate-drives", root, "--db", str(store), "--smooth", "--out-dir", str(out)]
    command("drives", suite, kind="drives")
    for drive, rows in json.loads((OUT / "drives.json").read_text())["drives"].items():
        for row in rows:
            manifest["runs"].append({"file": row["file"], "command": "visloc " + " ".join(suite), "kind": "evaluate",
                                     "drive": drive, "setup": row["protocol"], "setup_label": row["protocol_label"],
                                     "mode": row["mode"]})
    for folder in drives if variants else []:
        drive = folder.name.removesuffix("_sync")
        first = drive_protocols(folder)[0]  # the paper's setup where the drive has it
        key, label, query, database = first.key, first.label, first.query_camera, first.db_camera
        for variant, (_, flags) in VARIANTS.items():
            name = f"{drive}_{key}_paper_{variant}"
            command(name, ["evaluate", root, "--drive", drive, "--query-camera", query, "--db-camera", database,
                           "--db", str(store), *flags, "--json", str(out / f"{name}.json")],
                    kind="variant", drive=drive, setup=key, setup_label=label, variant=variant)


def diagnostics(drives: list, root: str, out: Path, store: Path, manifest: dict) -> None:
    """benchmarks/refined_diagnostics.py per drive and the paper's Haversine check."""
    for folder in drives:
        drive = folder.name.removesuffix("_sync")
        name = f"diagnostics_{drive}"
        args = ["benchmarks/refined_diagnostics.py", root, "--drive", drive, "--db", str(store), "--every", "3",
                "--json", str(out / f"{name}.json")]
        print(f"results: {name}: python {' '.join(args)}", flush=True)
        subprocess.run([sys.executable, *args], cwd=REPO, check=True)
        manifest["runs"].append({"file": f"{name}.json", "command": "python " + " ".join(args), "kind": "diagnostics",
                                 "drive": drive})
    subprocess.run([sys.executable, "scripts/paper_haversine_check.py", "--json", str(out / "haversine.json")],
                   cwd=REPO, check=True)
    manifest["runs"].append({"file": "haversine.json", "command": "python scripts/paper_haversine_check.py",
                             "kind": "haversine"})


# -- page: JSON -> digest -------------------------------------------------------------------------

def digest_evaluation(report: dict) -> dict:
    steps = [s for series in report["series"] for s in series]
    finals = [series[-1]["estimate_error_m"] for series in report["series"]]
    gaps = [b["query_timestamp_s"] - a["query_timestamp_s"] for series in report["series"]
            for a, b in zip(series, series[1:])]
    keep = ("n_series", "steps", "measurement_error_m", "estimate_error_m", "nearest_candidate_error_m",
            "smoothed_error_m", "final_error_m", "final_error_m_by_steps_ahead", "latency_ms", "measurement_latency_ms",
            "best_match_offset_s", "steps_without_measurement", "mode", "measurement_source_fraction",
            "geometry_fallback_fraction", "fallback_reasons", "gated_fraction", "measurement_sigma_m",
            "measurement_nees", "structure_build_ms")
    return {**{k: report.get(k) for k in keep},
            "exclusion_s": report["params"]["retrieval"]["exclusion_s"],
            "measurement_error_all_steps_m": summary_of(s["measurement_error_m"] for s in steps),
            "series_final_below_2m": sum(1 for f in finals if f is not None and f < 2.0),
            "query_interval_s": float(np.median(gaps)) if gaps else None}


def digest_bench(report: dict) -> dict:
    lat = report["latency"]
    out = {k: report.get(k) for k in ("drive", "query_camera", "db_camera", "load_before", "load_after", "targets",
                                      "fast_params", "global_index_build_s", "accuracy")}
    out["latency"] = {"start_frames": lat["start_frames"],
                      "speed_ratio_paper_over_fast": lat["speed_ratio_paper_over_fast"],
                      "levers": {k: {"stages_ms": v["stages_ms"], "mean_counted": v["mean_counted"],
                                     "median_keypoints": v["median_keypoints"],
                                     "best_match_agrees_with_paper": v["best_match_agrees_with_paper"]}
                                 for k, v in lat["levers"].items()}}
    ing = report["ingest"]
    out["ingest"] = {k: ing[k] for k in ("n_images", "workers", "bare_sift_images_per_s", "ingest_images_per_s",
                                        "ingest_over_bare", "ingest_over_bare_per_run")}
    out["ingest"]["structure_ms_per_image"] = ing.get("structure_ms_per_image")
    if "scale" in report:
        sc = report["scale"]
        out["scale"] = {k: sc.get(k) for k in ("n_images", "descriptors_per_image", "vector_dim", "shortlist_size",
                                               "n_queries", "store_mb", "global_vectors_mb", "index_load_s",
                                               "candidates_ms", "recall_shortlist", "best_within_1m", "peak_rss_mb",
                                               "structure_points_read_p50")}
    if "refined_fast" in report:
        out["refined_fast"] = digest_refined_fast(report["refined_fast"])
    return out


def page() -> int:
    manifest_path = OUT / "manifest.json"
    if not manifest_path.is_file():
        print(f"results: {manifest_path}: not found (run: python scripts/results.py run)", file=sys.stderr)
        return 2
    manifest = json.loads(manifest_path.read_text())
    over_digest = bool(manifest.get("speed_over_digest"))
    if over_digest:  # a --speed-only run with no full run kept: the committed digest, its speed sections measured again
        if not DIGEST.is_file():
            print(f"results: {DIGEST}: not found; a --speed-only run needs a full run before it "
                  "(python scripts/results.py run)", file=sys.stderr)
            return 2
        digest = {**json.loads(DIGEST.read_text()), "bench": {}, "tracks": {}, "speed": manifest["speed"]}
    else:
        digest = {"commit": manifest["commit"], "started": manifest["started"], "finished": manifest["finished"],
                  "cores": manifest["cores"], "load_before": manifest["load_before"],
                  "load_after": manifest["load_after"], "drives": {}, "bench": {}, "haversine": None,
                  "speed": manifest.get("speed"), "filter_replay": {}}
    for entry in manifest["runs"]:
        report = json.loads((OUT / entry["file"]).read_text())
        if entry["kind"] == "haversine":
            digest["haversine"] = report
            continue
        if entry["kind"] == "bench":
            digest["bench"][entry["drive"]] = {"command": entry["command"], **digest_bench(report)}
            continue
        if entry["kind"] == "track":
            digest.setdefault("tracks", {})[f"{entry['drive']}, {entry['setup_label']}"] = {
                "command": entry["command"], **digest_track(report)}
            continue
        if entry["kind"] == "diagnostics":
            digest.setdefault("diagnostics", {})[entry["drive"]] = {
                "command": entry["command"], "gps_vs_velocity_over_1s_m": report["gps_vs_velocity_over_1s_m"],
                "conditions": {k: {kk: v[kk] for kk in ("error_m", "along_m_mean", "abs_along_m_mean",
                                                        "abs_across_m_mean", "fallbacks")}
                               for k, v in report["conditions"].items()}}
            continue
        if entry["kind"] == "drives":
            digest["suite"] = {"command": entry["command"], "drives": report["drives"], "pooled": report["pooled"]}
            for rows in report["drives"].values():
                for row in rows:
                    if row["mode"] != "paper" and (OUT / row.get("file", "")).is_file():
                        evaluation = json.loads((OUT / row["file"]).read_text())  # read once, large
                        row["final_minus_measurement_m"] = final_minus_measurement(evaluation["series"])
                        row["calibration_frames"] = distinct_frames(evaluation["series"])
                        digest["filter_replay"][Path(row["file"]).stem] = replay(evaluation)
                        digest["store_sift_contrast"] = evaluation["params"]["sift"]["contrast_threshold"]
            continue
        drive = digest["drives"].setdefault(entry["drive"], {"setups": {}, "variants": {}, "primary": entry["setup"]})
        setup = drive["setups"].setdefault(entry["setup"], {"label": entry["setup_label"], "modes": {}})
        result = {"command": entry["command"], **digest_evaluation(report)}
        if entry["kind"] == "evaluate":
            setup["modes"][entry["mode"]] = result
        else:
            drive["variants"][entry["variant"]] = {"setup": entry["setup"], **result}
    if not over_digest:
        digest["peer"] = digest_peer({"peer/results": PEER, "docs/results/peer": REPO / "docs" / "results" / "peer"},
                                     OUT)
    if manifest.get("suite_only"):
        carry_over(digest, json.loads(DIGEST.read_text()) if DIGEST.is_file() else {})
    DIGEST.parent.mkdir(parents=True, exist_ok=True)
    DIGEST.write_text(json.dumps(digest, indent=1, sort_keys=True) + "\n")
    PAGE.write_text(render_page(digest))
    if digest.get("suite") and not over_digest:
        calibration_figure(digest["suite"], DIGEST.parent / "calibration.png")
    print(f"results: wrote {DIGEST} and {PAGE}")
    return 0


def final_minus_measurement(series: list[list[dict]], block_s: float = 1.0, n_draws: int = 4000) -> dict:
    """Final estimate error minus the final measurement's error (m), series by series: the mean and a 95 %
    interval from a bootstrap over blocks of series that start within ``block_s`` of each other (series that
    start a frame apart end a frame apart, and their errors are not independent draws)."""
    pairs = [(s[0]["query_timestamp_s"], s[-1]["estimate_error_m"] - s[-1]["measurement_error_m"]) for s in series
             if s[-1]["estimate_error_m"] is not None and s[-1]["measurement_error_m"] is not None]
    if not pairs:
        return {"mean": None, "ci95": None, "n_series": 0, "n_blocks": 0}
    t0 = min(t for t, _ in pairs)
    blocks: dict[int, list[float]] = {}
    for t, d in pairs:
        blocks.setdefault(int((t - t0) // block_s), []).append(d)
    groups = [np.asarray(b) for b in blocks.values()]
    rng = np.random.default_rng(0)
    draws = [np.mean(np.concatenate([groups[i] for i in rng.integers(0, len(groups), len(groups))]))
             for _ in range(n_draws)]
    return {"mean": float(np.mean([d for _, d in pairs])), "ci95": [float(v) for v in np.percentile(draws, [2.5, 97.5])],
            "n_series": len(pairs), "n_blocks": len(groups)}


CARRIED_SECTIONS = ("bench", "tracks", "diagnostics", "haversine")


def carry_over(digest: dict, previous: dict) -> None:
    """A ``run --suite-only`` digest: the sections that run did not measure (the paper's mode with one change
    per variant, the Table 3 check, camera rate, speed, the refined error's sources) as ``previous`` has them,
    with the commit and time that measured them."""
    if not previous:  # no earlier digest: nothing to carry, the page shows what this run measured
        return
    carried = previous.get("carried_over") or {k: previous.get(k) for k in ("commit", "started", "finished", "speed")}
    if previous.get("speed"):  # a --speed-only run after the carried ones measured the speed sections last
        carried = {**carried, "speed": previous["speed"]}
    digest["carried_over"] = carried
    for key in CARRIED_SECTIONS:  # a section measured by the run at hand (``--speed-only``) stays
        if previous.get(key) and not digest.get(key):
            digest[key] = previous[key]
    for drive, dd in previous.get("drives", {}).items():
        if drive in digest["drives"] and dd.get("variants"):
            digest["drives"][drive]["variants"] = dd["variants"]


# -- render: digest -> Markdown ---------------------------------------------------------------------

def c(value, fmt: str = ".2f") -> str:
    return "-" if value is None else format(value, fmt)


def _steps(values, fmt: str = ".2f") -> str:
    return " / ".join(c(v, fmt) for v in values)


def _setups(drive: dict) -> list[tuple[str, dict]]:
    """A drive's setups, the one its paper-mode sensitivity runs use first (JSON keeps no order)."""
    return sorted(drive["setups"].items(), key=lambda kv: (kv[0] != drive["primary"], kv[0] != "stereo", kv[0]))


TARGETS = ("Targets, the same parameters on every drive. Where the ground truth is RTK-fixed (stated accuracy "
           "at most 0.05 m): NEES between 1 and 4 with 85-99 % of the errors inside the 95 % ellipse, for views on "
           "both sides and on one side alike; geometry error median at most 0.10 m and p90 at most 0.30 m; final "
           "estimate mean at most 0.25 m (0.07 m on 2011_09_26_drive_0001). Where it is not (float GPS): at least "
           "85 % inside the 95 % ellipse and NEES at least 0.3 with views on both sides (no ellipse more than three "
           "times too large). On every drive: the final estimate's mean error no higher than the final "
           "measurements'; no geometry measurement more than 2 m off; geotag fallbacks at most 5 % of the steps.")
RTK_STATED_M = 0.05  # a drive whose geotags state at most this is held to the RTK-fixed targets


def _honest_chance(share: float, n: int, frames: dict | None = None) -> str:
    """For a share inside the 95 % ellipse outside 85-99 %: how often n measurements with an honest covariance
    would give a share at least that far out (binomial), so a small sample's verdict can be read for what it is.
    ``frames`` (``distinct_frames``: the query frames those measurements are of, and the share of the frames
    inside): the series of an evaluation measure the same query frame up to once per step, so the chance is
    that of the distinct frames, the independent draws there are."""
    if 0.85 <= share <= 0.99 or not n:
        return ""
    what = f"of {n}"
    if frames and frames.get("n"):
        what = f"of {n}, measuring {frames['n']} query frames"
        share, n = frames["inside_95"], frames["n"]
    k = round(share * n)
    ks = range(k, n + 1) if share > 0.99 else range(0, k + 1)
    chance = sum(math.comb(n, i) * 0.95 ** i * 0.05 ** (n - i) for i in ks)
    return f" ({what}: an honest ellipse gives this {c(100 * chance, '.0f')} % of the time)"


def distinct_frames(series: list[list[dict]]) -> dict:
    """Per side of the views ("all", "both", "one"): how many distinct query frames the geometry measurements
    of an evaluation's series measure, and the share of those frames inside the 95 % ellipse (a frame measured
    in several series counts by the share of its measurements inside)."""
    inside: dict[str, dict[int, list[bool]]] = {"all": {}, "both": {}, "one": {}}
    for step in (st for s in series for st in s):
        if step.get("measurement_nees") is None:
            continue
        for side in ("all", step.get("measurement_side")):
            if side in inside:
                inside[side].setdefault(step["query_frame"], []).append(step["measurement_nees"] <= CHI2_2DOF_95)
    return {side: {"n": len(frames), "inside_95": float(np.mean([np.mean(v) for v in frames.values()]))
                   if frames else None} for side, frames in inside.items()}


def uncertainty_verdicts(r: dict) -> list[tuple[str, bool]]:
    """(what, met) for one refined row of evaluate-drives, against ``TARGETS``."""
    cal, db = r["calibration"], r.get("database") or {}
    stated = db.get("stated_accuracy_median_m")
    rtk = stated is not None and stated <= RTK_STATED_M
    out = []
    for side in ("both", "one"):
        k = cal[side]
        if not k["n"]:
            continue
        views = "views on both sides" if side == "both" else "views on one side"
        frames = (r.get("calibration_frames") or {}).get(side)
        inside = f"{c(100 * k['inside_95'], '.0f')} % inside{_honest_chance(k['inside_95'], k['n'], frames)}"
        if rtk:
            out.append((f"{views}: NEES {c(k['nees_mean'])} in 1-4, {inside} in 85-99 %",
                        1 <= k["nees_mean"] <= 4 and 0.85 <= k["inside_95"] <= 0.99))
        else:
            out.append((f"{views}: {inside} >= 85 %", k["inside_95"] >= 0.85))
            if side == "both":
                out.append((f"{views}: NEES {c(k['nees_mean'])} >= 0.3", k["nees_mean"] >= 0.3))
    g, f, fm = r["geometry_error_m"], r["final_error_m"], r["final_measurement_error_m"]
    if rtk:
        final_limit = 0.07 if r.get("drive") == PAPER_DRIVE else 0.25
        out.append((f"geometry median {c(g['median'])} <= 0.10, p90 {c(g['p90'])} <= 0.30 m",
                    g["median"] is not None and g["median"] <= 0.10 and g["p90"] <= 0.30))
        out.append((f"final estimate {c(f['mean'])} <= {final_limit:g} m", f["mean"] <= final_limit))
    gap = r.get("final_minus_measurement_m") or {}
    gap_text = ("" if not gap.get("ci95") else
                f" (difference {1000 * gap['mean']:+.1f} mm, 95 % interval {1000 * gap['ci95'][0]:+.1f} to "
                f"{1000 * gap['ci95'][1]:+.1f} mm over {gap['n_blocks']} one-second blocks of series)")
    out.append((f"final estimate {c(f['mean'], '.4f')} <= final measurements {c(fm['mean'], '.4f')} m{gap_text}",
                f["mean"] <= fm["mean"]))
    out.append((f"{r['gross_geometry_errors']} geometry measurements over 2 m", r["gross_geometry_errors"] == 0))
    out.append((f"fallbacks {c(100 * r['fallback_fraction'], '.1f')} % <= 5 %", r["fallback_fraction"] <= 0.05))
    return out


def render_uncertainty(s: dict, add) -> None:
    """How honest the refined mode's ellipses are, drive by drive, split by the side the views lie on."""
    add("## Honest uncertainty, drive by drive")
    add("")
    add("Every geometry measurement of the evaluation above (refined mode) against its covariance R: NEES is "
        "e' R^-1 e (2 on average, and 95 % of the errors inside the 95 % ellipse, if R is honest). The truth comes "
        "from the receiver that geotagged the database, on the same drive, so it shares the map's absolute error, "
        "which is stated apart (the geotags' own accuracy) and is not in R: see the [method notes](method.md). "
        "\"both\" counts measurements whose views lie before and after them, \"one\" those whose views all lie on "
        "one side. The lever gain (m of error per m from the nearest view, along the vehicle's heading / across "
        "it) is what each store's self-check measured on its own images; the camera-rate path, posed on the stored "
        "structure, has a self-check and a gain of its own. The estimate's NEES uses the filter's covariance P.")
    add("")
    rows = [(drive, r) for drive, rs in s["drives"].items() for r in rs if r["mode"] != "paper" and "calibration" in r]
    if not rows:
        add("Not measured with this commit: `python scripts/results.py run` measures it.")
        add("")
        return
    add("| drive | protocol | GPS stated (median) | heading spread | lever gain along / across: both sides; one side "
        "(self-check poses) | camera rate's | NEES, inside 95 %: all | both sides | one side | estimate (P) |")
    add("|---|---|---|---|---|---|---|---|---|---|")

    def _gain(g: dict | None) -> str:
        if not g:
            return "-"
        both, one = (f"{c(g[side], '.4f')} / {c(g.get(side + '_across', g[side]), '.4f')}"
                     for side in ("both_sides", "one_side"))
        return f"{both}; {one} ({g['n_both']} / {g['n_one']})"

    def cal(k: dict) -> str:
        return "-" if not k or not k["n"] else f"{c(k['nees_mean'])}, {c(100 * k['inside_95'], '.0f')} % ({k['n']})"

    for drive, r in rows:
        db = r.get("database") or {}
        gain, fast_gain = (_gain(db.get(k)) for k in ("lever_gain", "camera_rate_lever_gain"))
        add(f"| {drive} | {r['protocol_label']} | {c(db.get('stated_accuracy_median_m'), '.3f')} m | "
            f"{c(db.get('heading_spread_deg'), '.2f')} deg | {gain} | {fast_gain} | {cal(r['calibration']['all'])} | "
            f"{cal(r['calibration']['both'])} | {cal(r['calibration']['one'])} | {cal(r['estimate_calibration'])} |")
    add("")
    add("Calibration curve: the share of geometry measurements inside each nominal ellipse (the nominal share "
        "itself if R is honest; below it: ellipses too small; above: too large):")
    add("")
    levels = list(rows[0][1]["calibration"]["all"]["coverage"]) if rows else []
    add("| drive | protocol | " + " | ".join(f"{float(p) * 100:g} %" for p in levels) + " |")
    add("|---|---|" + "---|" * len(levels))
    for drive, r in rows:
        add(f"| {drive} | {r['protocol_label']} | {coverage_cells(r['calibration']['all']['coverage'], levels)} |")
    add("")
    estimated = [(drive, r) for drive, r in rows if (r.get("estimate_calibration") or {}).get("coverage")]
    if estimated:
        add("The same for the estimates against the filter's P, at one query a second (at the camera's rate: "
            "[Camera rate](#camera-rate)):")
        add("")
        add("| drive | protocol | " + " | ".join(f"{float(p) * 100:g} %" for p in levels) + " |")
        add("|---|---|" + "---|" * len(levels))
        for drive, r in estimated:
            add(f"| {drive} | {r['protocol_label']} | {coverage_cells(r['estimate_calibration']['coverage'], levels)} |")
        add("")
    add("![calibration curves, one panel per drive and protocol](results/calibration.png)")
    add("")
    add(TARGETS)
    add("")
    for drive, r in rows:
        verdicts = uncertainty_verdicts({**r, "drive": drive})
        missed = [w for w, ok in verdicts if not ok]
        add(f"- {drive}, {r['protocol_label']}: " + ("every target met" if not missed else
                                                      "NOT met: " + "; ".join(missed)) + ".")
    add("")


def calibration_figure(s: dict, path: Path) -> None:
    """The calibration curves of the refined mode as a PNG, one panel per drive and protocol: every geometry
    measurement, those with views on both sides and on one side (against R), and the estimate (against P)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(drive, r) for drive, rs in s["drives"].items() for r in rs
              if r["mode"] != "paper" and r.get("calibration", {}).get("all", {}).get("n")]
    n_cols = 2 if len(panels) > 1 else 1
    n_rows = max(1, -(-len(panels) // n_cols))
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(5.2 * n_cols, 4.2 * n_rows), dpi=100, squeeze=False)
    curves = (("all", "every measurement (R)", "C0", "-"), ("both", "views on both sides (R)", "C2", "--"),
              ("one", "views on one side (R)", "C3", ":"))
    for ax, (drive, r) in zip(axes.flat, panels):
        ax.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="honest")
        for key, label, colour, style in curves:
            k = r["calibration"].get(key) or {}
            if k.get("n"):
                cov = k["coverage"]
                ax.plot([float(p) for p in cov], list(cov.values()), color=colour, linestyle=style, marker="o",
                        markersize=3, label=f"{label}, n={k['n']}")
        est = r.get("estimate_calibration") or {}
        if est.get("n"):
            cov = est["coverage"]
            ax.plot([float(p) for p in cov], list(cov.values()), color="C1", marker="s", markersize=3,
                    linewidth=1, label=f"estimate (P), n={est['n']}")
        ax.set_title(f"{drive}\n{r['protocol_label']}", fontsize=9)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.set_xlabel("nominal probability of the ellipse", fontsize=8)
        ax.set_ylabel("share inside", fontsize=8)
        ax.legend(fontsize=7, loc="lower right")
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle("Refined mode: calibration of the covariances, drive by drive", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def render_suite(s: dict, add) -> None:
    add("## Every drive at once")
    add("")
    add(f"`{s['command'].split(' --out-dir ')[0]}` evaluates every drive of the data root with each protocol it "
        "supports (a stereo drive: left queries against the right camera's database; every drive: queries against "
        "its own camera's database with the 1 s exclusion), in both modes, with the same parameters. Measurement "
        "errors are over every step of every series; NEES is over the refined mode's geometry measurements (see "
        "the next section); \"final vs measured\" compares the final estimate's mean error with the mean error of "
        "the measurements at the same final steps.")
    add("")
    add("| drive | protocol | mode | measurement error median / mean / p90 / max (m) | final estimate mean (m) | "
        "final vs measured (m) | geometry error median / p90 (m) | NEES, inside 95 % | fallback | gated | "
        "geometry > 2 m off |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    rows = [(drive, r["protocol_label"], r) for drive, rs in s["drives"].items() for r in rs]
    rows += [("pooled", "every drive and protocol", r) for r in s["pooled"]]
    for drive, label, r in rows:
        m, f, fm, n = r["measurement_error_m"], r["final_error_m"], r["final_measurement_error_m"], r["nees"]
        nees = "-" if not n["n"] else f"{c(n['mean'])}, {c(100 * n['fraction_within_95'], '.0f')} %"
        fb = "-" if r["fallback_fraction"] is None else f"{c(100 * r['fallback_fraction'], '.1f')} %"
        g = r["geometry_error_m"]
        add(f"| {drive} | {label} | {r['mode']} | {c(m['median'])} / {c(m['mean'])} / {c(m['p90'])} / "
            f"{c(m['max'])} | {c(f['mean'])} | {c(f['mean'], '.3f')} vs {c(fm['mean'], '.3f')} | {c(g['median'])} / "
            f"{c(g['p90'])} | {nees} | {fb} | {c(100 * r['gated_fraction'], '.1f')} % | {r['gross_geometry_errors']} |")
    add("")


DIAGNOSTIC_LABELS = {
    "gps_both_sides": "GPS geotags and truth, views on both sides (the default)",
    "gps_best_views": "GPS geotags and truth, the best views only",
    "velocity_both_sides": "geotags and truth integrated from the OXTS velocities, views on both sides",
    "velocity_best_views": "geotags and truth integrated from the OXTS velocities, the best views only",
}


def render_diagnostics(diagnostics: dict, add) -> None:
    add("## Where the refined measurement's error comes from")
    add("")
    add("Every third query of each drive, same camera, 1 s exclusion, measured with the default refined parameters "
        "under four conditions; the error is split along the direction of travel and across it (m). See the "
        "[method notes](method.md) for what it shows.")
    add("")
    add("| drive | condition | error median / mean / p90 / max | along-track mean | mean abs along / across | "
        "fallbacks |")
    add("|---|---|---|---|---|---|")
    for drive, dg in diagnostics.items():
        for key in [k for k in DIAGNOSTIC_LABELS if k in dg["conditions"]]:  # the digest's keys are sorted
            v = dg["conditions"][key]
            e = v["error_m"]
            add(f"| {drive} | {DIAGNOSTIC_LABELS.get(key, key)} | {c(e['median'])} / {c(e['mean'])} / {c(e['p90'])} / "
                f"{c(e['max'])} | {c(v['along_m_mean'], '+.2f')} | {c(v['abs_along_m_mean'])} / "
                f"{c(v['abs_across_m_mean'])} | {v['fallbacks']} |")
    add("")
    for drive, dg in diagnostics.items():
        g = dg["gps_vs_velocity_over_1s_m"]
        add(f"- {drive}: over 1 s of driving the GPS track moves {c(g['median'])} m (median, {c(g['max'])} m at most) "
            f"differently from the track its own velocities describe. `{dg['command']}`")
    add("")


def store_contrast_note(contrast: float | None) -> str:
    """What SIFT contrast threshold the measured store describes its images at. A digest without it was
    measured before a new store's default went to half the paper's, on a store at the paper's 0.04."""
    paper, store = PAPER_SIFT.contrast_threshold, STORE_SIFT.contrast_threshold
    measured = paper if contrast is None else contrast
    note = (f"The store behind these runs keeps every keypoint SIFT finds at the paper's contrast threshold, {paper:g}."
            if measured == paper else
            f"The store behind these runs keeps every keypoint SIFT finds at contrast threshold {measured:g}; the "
            f"paper's method reads its own, the ones kept at {paper:g}.")
    if measured != store:
        note += (f" A store `visloc ingest` makes today keeps them at {store:g}: what that gives the refined mode "
                 "(more 2D-3D inliers per query) and what it costs are measured on the peer's frames as "
                 "\"Denser SIFT\" in the [performance notes](performance.md); this page is measured again by "
                 "`python scripts/results.py run`.")
    return note


def render_page(d: dict) -> str:
    L: list[str] = []
    add = L.append
    add("# Results")
    add("")
    add("<!-- generated by `python scripts/results.py page` from the JSON its `run` wrote; do not edit -->")
    add("")
    add(f"Measured with commit `{d['commit']}` from {d['started']} to {d['finished']} on a machine with "
        f"{d['cores']} cores (1-minute load average {d['load_before']:.2f} before, {d['load_after']:.2f} after). "
        "Every number below comes from the JSON of the command named beside it; `python scripts/results.py run` "
        "runs them all on every drive of the data root and `python scripts/results.py page` writes this page "
        "(its numbers are also in `docs/results/digest.json`). Distances are geodesic on WGS84; the paper's "
        "Haversine distances appear only in the check of its Table 3. What the numbers mean: "
        "[method notes](method.md).")
    add("")
    add(store_contrast_note(d.get("store_sift_contrast")))
    carried = d.get("carried_over")
    speed = d.get("speed") or (carried or {}).get("speed")  # the speed sections' own run, where there was one
    if carried:
        measured = sorted({drive for key in (("diagnostics",) if speed else ("bench", "diagnostics"))
                           for drive in d.get(key) or {}})
        sections = "the Table 3 check" + ("" if speed else ", \"Camera rate\" and \"Speed\"")
        add("")
        add(f"Only the evaluations of every drive (`python scripts/results.py run --suite-only`: the sections from "
            f"\"Every drive at once\" to \"Every drive, both modes, per step\" and the comparison with the peer) were "
            f"measured with that commit. The sensitivity rows, \"Where the refined measurement's error comes "
            f"from\" and {sections} were measured with commit "
            f"`{carried['commit']}` from {carried['started']} to {carried['finished']}, on "
            f"{', '.join(measured) or 'no drive'}: a drive of the data root missing from them has not been "
            "measured there yet.")
    if speed:
        add("")
        add(f"The sections \"Camera rate\" and \"Speed\" were measured again with commit `{speed['commit']}` "
            f"(`python scripts/results.py run --speed-only`) from {speed['started']} to {speed['finished']} (1-minute "
            f"load average {speed['load_before']:.2f} before, {speed['load_after']:.2f} after)"
            + ("." if carried else "; that commit evaluates the paper's and the refined method as the one above does."))
    add("")
    if d.get("suite"):
        render_suite(d["suite"], add)
        render_uncertainty(d["suite"], add)
    render_peer(d.get("peer") or {}, add)
    render_filter_replay(d.get("filter_replay") or {}, add)
    if d.get("diagnostics"):
        render_diagnostics(d["diagnostics"], add)
    add("## Every drive, both modes, per step")
    add("")
    add("`visloc evaluate` with the paper's protocol: series of six queries one second apart, every start frame "
        "the drive allows, database images closer than 1 s to a query excluded, the paper's Table 1 parameters, "
        "`--smooth` for the RTS smoother. No parameter differs between drives.")
    add("")
    add("| drive | setup | mode | series | mean measurement error t-5 / ... / t (m) | final error mean / median / "
        "p90 (m) | RTS-smoothed t-5 / t (m) | geotag fallback | gated | NEES (2 if honest), inside 95 % | "
        "latency p50 / p95 (ms) |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    for drive, dd in d["drives"].items():
        for key, setup in _setups(dd):
            for mode, r in setup["modes"].items():
                f = r["final_error_m"]
                sm = r["smoothed_error_m"] or [None]
                nees = r["measurement_nees"] or {}
                nees_text = "-" if not nees.get("n") else (f"{c(nees['mean'])}, "
                                                           f"{c(100 * nees['fraction_within_95'], '.0f')} %")
                fallback = r["geometry_fallback_fraction"]
                add(f"| {drive} | {setup['label']} | {mode} | {r['n_series']} | {_steps(r['measurement_error_m'])} | "
                    f"{c(f['mean'])} / {c(f['median'])} / {c(f['p90'])} | {c(sm[0])} / {c(sm[-1])} | "
                    f"{'-' if fallback is None else c(100 * fallback, '.1f') + ' %'} | "
                    f"{c(100 * r['gated_fraction'], '.1f')} % | {nees_text} | "
                    f"{c(r['latency_ms']['p50'], '.0f')} / {c(r['latency_ms']['p95'], '.0f')} |")
    add("")
    add("Measurement error over every step of every series (m), and what measured it:")
    add("")
    add("| drive | setup | mode | median | mean | p90 | max | geometry | geotag | no measurement | fallback reasons |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    for drive, dd in d["drives"].items():
        for key, setup in _setups(dd):
            for mode, r in setup["modes"].items():
                a = r["measurement_error_all_steps_m"]
                src = r["measurement_source_fraction"]
                n_steps = r["n_series"] * len(r["steps"])
                reasons = "; ".join(f"{k}: {v}" for k, v in sorted((r["fallback_reasons"] or {}).items(),
                                                                      key=lambda kv: (-kv[1], kv[0]))) or "-"
                add(f"| {drive} | {setup['label']} | {mode} | {c(a['median'])} | {c(a['mean'])} | {c(a['p90'])} | "
                    f"{c(a['max'])} | {c(100 * src['geometry'], '.0f')} % | {c(100 * src['geotag'], '.0f')} % | "
                    f"{r['steps_without_measurement']} of {n_steps} | {reasons} |")
    add("")
    add("Commands (each with `--json out/results/NAME.json`):")
    add("")
    commands = [r["command"].split(" --json ")[0] for dd in d["drives"].values() for _, setup in _setups(dd)
                for r in setup["modes"].values()]
    for command in dict.fromkeys(commands):
        add(f"- `{command}`")
    add("")
    for drive, dd in d["drives"].items():
        key, setup = _setups(dd)[0]
        r = setup["modes"]["paper"]
        add(f"## The paper's method on {drive}: {setup['label']}")
        add("")
        add("| step | " + " | ".join(r["steps"]) + " |")
        add("|---|" + "---|" * len(r["steps"]))
        add("| mean measurement error (m) | " + " | ".join(c(v) for v in r["measurement_error_m"]) + " |")
        add("| mean estimate error (m) | " + " | ".join(c(v) for v in r["estimate_error_m"]) + " |")
        add("| floor: nearest allowed database image (m) | "
            + " | ".join(c(v) for v in r["nearest_candidate_error_m"]) + " |")
        add("")
        f = r["final_error_m"]
        off = r["best_match_offset_s"]
        add(f"Final estimate error over the {r['n_series']} series: mean {c(f['mean'])} m, median {c(f['median'])} m, "
            f"p90 {c(f['p90'])} m, from {c(f['min'])} m to {c(f['max'])} m; {r['series_final_below_2m']} series end "
            f"below 2 m. Queries are {c(r['query_interval_s'], '.2f')} s apart (median). Best match against query "
            f"time: median offset {c(off['median'], '+.2f')} s, {c(100 * off['fraction_ahead'], '.0f')} % of best "
            f"matches ahead of the query, {c(100 * off['fraction_behind'], '.0f')} % behind. Final error by how many "
            "of a series' six best matches lie ahead: "
            + ", ".join(f"{k}/6 ahead {c(v['mean'])} m ({v['n_series']} series)"
                        for k, v in r["final_error_m_by_steps_ahead"].items()) + ".")
        add("")
        if drive == PAPER_DRIVE and key == "stereo":
            add(f"The paper reports, for this drive and setup, a measurement error of about 18 m (its Table 3: "
                f"16.2 to 19.0 m, see the check below) and a final error of {PAPER_FINAL_ERROR_M} m (its Figure 4).")
            add("")
        rows = [("as above", r)] + [(label, dd["variants"][k]) for k, (label, _) in VARIANTS.items()
                                    if k in dd.get("variants", {})]
        if len(rows) == 1:
            add("Sensitivity of the paper's mode to one change at a time: not measured on this drive yet "
                "(`python scripts/results.py run` measures it).")
            add("")
            continue
        add("Sensitivity, the paper's mode with one change (final error mean / median / p90, and mean measurement "
            "error at t-5 and t, m):")
        add("")
        add("| run | final error | measurement error t-5 -> t |")
        add("|---|---|---|")
        for label, v in rows:
            f = v["final_error_m"]
            add(f"| {label} | {c(f['mean'])} / {c(f['median'])} / {c(f['p90'])} | "
                f"{c(v['measurement_error_m'][0])} -> {c(v['measurement_error_m'][-1])} |")
        add("")
    h = d["haversine"]
    if h:
        add("## The paper's Table 3, recomputed")
        add("")
        add("`python scripts/paper_haversine_check.py` recomputes the distances of the paper's Table 3 from the "
            "coordinates its Tables 2 and 3 print (drive 2011_09_26_drive_0001), with the Haversine formula as "
            "the paper says, once correctly and once with latitude and longitude swapped (m):")
        add("")
        add("| | t-5 | t-4 | t-3 | t-2 | t-1 | t |")
        add("|---|---|---|---|---|---|---|")
        for name in ("measurement", "estimate"):
            add(f"| {name}: the paper | " + " | ".join(c(v) for v in h[name]["paper_m"]) + " |")
            add(f"| {name}: swapped | " + " | ".join(c(v) for v in h[name]["swapped_m"]) + " |")
            add(f"| {name}: correct | " + " | ".join(c(v) for v in h[name]["correct_m"]) + " |")
        add("")
    render_camera_rate(d, add)
    if d["bench"]:
        add("## Speed")
        add("")
        add("`visloc bench`: the paper's path and the fast path on the same queries of each drive, in one run. "
            "Accuracy covers every series of the protocol above (paper mode); latency covers the live queries of "
            "the series listed (SIFT from the PNG, the read not timed, retrieval, measurement, filter), each lever "
            "adding to the row above it. Timings are wall-clock on a shared machine; compare rows of one run.")
        add("")
        for drive, b in d["bench"].items():
            lat = b["latency"]
            acc = b.get("accuracy") or {}
            add(f"### {drive}: queries {b['query_camera']}, database {b['db_camera']}")
            add("")
            add(f"`{b['command'].split(' --json ')[0]}`; live series start at frames "
                f"{', '.join(map(str, lat['start_frames']))}; 1-minute load average {c(b['load_before']['load_1min'])} "
                f"before, {c(b['load_after']['load_1min'])} after.")
            add("")
            add("| lever | images counted per query | latency p50 / p95 (ms) | SIFT p50 (ms) | retrieval p50 (ms) | "
                "final error mean (m) | measurement error t-5 -> t (m) | best match = paper's |")
            add("|---|---|---|---|---|---|---|---|")
            names = {"paper": "paper: full-resolution SIFT, +-20 s window, a GEMM per image",
                     "faiss_nn": "+ exact faiss k-NN per image", "gate": "+ filter gate instead of +-20 s",
                     "gate_shortlist": "+ VLAD shortlist of the gate, batched GEMM",
                     "paper_scaled": "(the paper's path at SIFT scale 0.5, for reference)",
                     "fast": "+ SIFT at image scale 0.5: the fast path"}
            for lever in ("paper", "faiss_nn", "gate", "gate_shortlist", "paper_scaled", "fast"):
                lv, ac = lat["levers"].get(lever), acc.get(lever)
                st = lv["stages_ms"] if lv else None
                add(f"| {names[lever]} | {c(ac['mean_candidates_counted'] if ac else (lv or {}).get('mean_counted'), '.1f')} | "
                    f"{c(st['total_ms']['p50'], '.0f') if st else '-'} / {c(st['total_ms']['p95'], '.0f') if st else '-'} | "
                    f"{c(st['sift_ms']['p50'], '.0f') if st else '-'} | {c(st['retrieval_ms']['p50'], '.0f') if st else '-'} | "
                    f"{c(ac['final_error_m']['mean']) if ac else '-'} | "
                    f"{(c(ac['measurement_error_m'][0]) + ' -> ' + c(ac['measurement_error_m'][-1])) if ac else '-'} | "
                    f"{c(100 * ac['best_match_agrees_with_paper'], '.0f') + ' %' if ac else '-'} |")
            r = lat["speed_ratio_paper_over_fast"]
            ing = b["ingest"]
            add("")
            add(f"Speed ratio paper / fast per query, same queries: median {c(r['p50'], '.0f')}x "
                f"(from {c(r['min'], '.0f')}x to {c(r['max'], '.0f')}x). Ingest: {c(ing['ingest_images_per_s'])} "
                f"images/s against bare OpenCV SIFT's {c(ing['bare_sift_images_per_s'])} on {ing['workers']} "
                f"processes ({c(100 * ing['ingest_over_bare'], '.0f')} %, medians of 3 interleaved runs of "
                f"{ing['n_images']} images); ingest then adds global vectors and structure in "
                f"{c(ing.get('structure_ms_per_image'), '.0f')} ms per image.")
            sc = b.get("scale")
            if sc:
                add("")
                add(f"Scale (a synthetic database of {sc['n_images']} images, {sc['descriptors_per_image']} "
                    f"descriptors each, {c(sc.get('structure_points_read_p50'), '.0f')} stored 3D points read per "
                    f"query): a lost query finds its candidates and reads their structure in p50 "
                    f"{c(sc['candidates_ms']['p50'], '.0f')} "
                    f"ms, max {c(sc['candidates_ms']['max'], '.0f')} ms over {sc['n_queries']} queries (shortlist "
                    f"recall {c(sc['recall_shortlist'])}); the process peaks at {c(sc['peak_rss_mb'], '.0f')} MB "
                    f"against a {c(sc['store_mb'], '.0f')} MB store, with {c(sc['global_vectors_mb'], '.0f')} MB of "
                    "global vectors in memory.")
            add("")
    return "\n".join(L).rstrip() + "\n"


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python scripts/results.py",
                                     description="Run the commands behind docs/results.md, or write the page.")
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("run", help="run every command (out/results/)")
    p.add_argument("--speed-only", action="store_true",
                   help="run only visloc bench and visloc track again, keeping the other runs' JSON (none kept: the "
                        "page keeps the other sections of docs/results/digest.json)")
    p.add_argument("--suite-only", action="store_true",
                   help="run only visloc evaluate-drives; the page keeps the other sections of docs/results/digest.json")
    p.add_argument("--data", type=Path, default=Path(os.environ.get("VISLOC_DATA", REPO.parent / "shared" / "data"
                                                                      / "kitti")).resolve(), help="KITTI data root")
    sub.add_parser("page", help="digest and page from out/results/")
    sub.add_parser("render", help="the page from the committed digest")
    a = parser.parse_args(argv)
    if a.what == "run":
        return run(a.data, a.speed_only, a.suite_only)
    if a.what == "page":
        return page()
    PAGE.write_text(render_page(json.loads(DIGEST.read_text())))
    print(f"results: wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
