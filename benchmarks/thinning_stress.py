"""Support thinned on purpose: visloc's refined measurement and the COLMAP-style peer with fewer keypoints per image.

    python benchmarks/thinning_stress.py [--data ROOT] [--caps 1000,500] [--peer-python PEER_VENV/bin/python]
    python benchmarks/thinning_stress.py --peer-from docs/results/thinning_stress.json   # the peer's side reused
    python benchmarks/thinning_stress.py --page   # its section of docs/performance.md from the JSON

Where texture is thin, both pipelines find fewer keypoints, and a pose stands on fewer 2D-3D matches. This
makes that happen on the shared drives: every image, database and query alike, keeps at most N keypoints
(visloc: ``--sift-features N``, OpenCV's strongest N; the peer: ``--max-features N``, COLMAP's). Each cap gets
its own store, ingested as a user would (features, structure, the self-check), and its own peer run.

The queries are the frames the peer measured at its defaults (``docs/results/peer``, ``../shared/peer/results``),
under the same protocol: the drive's first setup (left queries against the right camera where a drive has
both, else one camera), the 1 s exclusion. visloc poses each one as the first step of a series (``--steps 1``:
a full-scan retrieval, no filter), as the peer does; a failed pose counts with its fallback geotag's error on
either side. Per drive and cap: both pipelines' errors (median, p90, max), their PnP inliers, and the NEES of
visloc's measurements (the peer states no covariance). The row "default" is each pipeline at its own defaults
(visloc keeps every SIFT keypoint; the peer at most 8192), on the peer's existing runs. Writes ``docs/results/thinning_stress.json`` and its section of docs/performance.md.

The peer takes 10-20 s per query. ``--peer-from`` takes its side, frame by frame, from an earlier run of this
benchmark (same frames, caps and data; the peer's code is not this project's and does not change) where its own
run is not in ``out/thinning`` yet, and the page says which commit measured it.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

from measuring import REPO, Section, commit, load_1min, run_once

sys.path.insert(0, str(REPO / "scripts"))
from results_peer import PEER_THRESHOLD, PEER_VARIANT, digest_peer  # noqa: E402
from visloc.protocols.suite import drive_protocols, drives_of  # noqa: E402
from visloc.sources.drives import default_data_root  # noqa: E402

SECTION = Section("thinning-stress", "thinning_stress", REPO / "docs" / "performance.md")
WORK = REPO / "out" / "thinning"
PEER_RUNS = {"peer/results": REPO.parent / "shared" / "peer" / "results",
             "docs/results/peer": REPO / "docs" / "results" / "peer"}
PEER_SCRIPT = REPO.parent / "shared" / "peer" / "colmap_baseline.py"
DEFAULT = "default"
RESULTS_STORE = REPO / "out" / "results" / "visloc.sqlite"  # scripts/results.py's store, made with the defaults
STRICT = ["--thin-support-pnp-px", "0"]  # visloc without its second, looser pose where support is thin


def peer_runs() -> dict[str, Path]:
    """drive -> the peer's JSON at its defaults (the first folder of ``PEER_RUNS`` that has the drive)."""
    runs: dict[str, Path] = {}
    for folder in PEER_RUNS.values():
        for path in sorted(folder.glob("peer_*.json")) if folder.is_dir() else []:
            runs.setdefault(json.loads(path.read_text())["params"]["drive"], path)
    return runs


def reuse_peer(earlier: dict, cap: str, drive: str, protocol, path: Path) -> bool:
    """Write the peer's run of ``drive`` at ``cap`` as ``earlier`` (a previous result of this benchmark) measured
    it, in the peer's JSON layout, to ``path``; False when it has none."""
    d = earlier["caps"].get(cap, {}).get("drives", {}).get(drive)
    if d is None:
        return False
    queries = [{"query_frame": r["frame"], "variants": {PEER_VARIANT: {"pnp": {PEER_THRESHOLD: {
        "ok": r["peer_ok"], "num_inliers": r["peer_inliers"] if r["peer_ok"] else None,
        "error_m": r["peer_error_m"], "fallback_error_m": r["peer_error_m"]}}}}} for r in d["frames"]]
    path.write_text(json.dumps({"params": {"drive": drive, "query_camera": protocol.query_camera,
                                           "db_camera": protocol.db_camera},
                                "versions": d.get("peer_versions", {}), "queries": queries,
                                "reused_from": f"docs/results/thinning_stress.json at {earlier['commit']}"}))
    return True


def measure_cap(a, cap: str, folder: Path, peer: dict[str, Path]) -> dict:
    """Every drive at one cap: visloc's single measurements and the peer's, in ``WORK/cap_<cap>``."""
    out = WORK / f"cap_{cap}"
    out.mkdir(parents=True, exist_ok=True)
    log = out / "log.txt"
    store = out / "visloc.sqlite"
    if cap == DEFAULT and RESULTS_STORE.is_file():  # the defaults, ingested already: only counts are added to it
        store = RESULTS_STORE
    sift = [] if cap == DEFAULT else ["--sift-features", cap]
    commands = []
    for drive_folder in drives_of(folder):
        drive = drive_folder.name.removesuffix("_sync")
        if drive not in peer:
            continue
        protocol = drive_protocols(drive_folder)[0]
        frames = [q["query_frame"] for q in json.loads(peer[drive].read_text())["queries"]]
        cameras = ["--query-camera", protocol.query_camera, "--db-camera", protocol.db_camera]
        ours = ["-m", "visloc", "evaluate", folder, "--drive", drive, *cameras, "--db", store, *sift,
                "--mode", "refined", "--steps", "1", "--exclusion-s", "1",
                "--start-frames", ",".join(map(str, frames)),
                "--json", out / f"{drive}_{protocol.key}_refined.json"]
        run_once([sys.executable, *ours], log, out / f"{drive}_{protocol.key}_refined.json", "thinning")
        commands.append("python " + " ".join(map(str, ours)))
        if cap == DEFAULT:  # the peer's own run at its defaults; with every keypoint no query needs the thin pose
            shutil.copy(peer[drive], out / peer[drive].name)
            continue
        without = [*ours[:-2], *STRICT, "--json", out / "strict" / f"{drive}_{protocol.key}_refined.json"]
        (out / "strict").mkdir(exist_ok=True)  # the same without the thin-support pose
        run_once([sys.executable, *without], log, without[-1], "thinning")
        commands.append("python " + " ".join(map(str, without)))
        if a.earlier is not None and not (out / f"peer_{drive}.json").is_file():
            if reuse_peer(a.earlier, cap, drive, protocol, out / f"peer_{drive}.json"):
                print(f"thinning: the peer's {drive} at {cap} taken from {a.earlier['commit']}", flush=True)
        theirs = [PEER_SCRIPT, "--data", folder, "--drive", drive, "--db-camera", protocol.db_camera,
                  "--query-camera", protocol.query_camera, "--query-frames", ",".join(map(str, frames)),
                  "--variants", "counts", "--vlad-words", "0", "--max-features", cap,
                  "--work", out / f"peer_work_{drive}", "--json", out / f"peer_{drive}.json", "--resume"]
        run_once([a.peer_python, *theirs], log, out / f"peer_{drive}.json", "thinning")
        for partial in out.glob("peer_*.partial.json"):  # the peer's progress file, not a run
            partial.unlink()
        commands.append(f"{a.peer_python} " + " ".join(map(str, theirs)))
    digest = digest_peer({f"out/thinning/cap_{cap}": out}, out)
    for drive, d in digest.items():
        d["peer_reused_from"] = json.loads((out / f"peer_{drive}.json").read_text()).get("reused_from") \
            if cap != DEFAULT else None
        report = json.loads((out / d["evaluation_file"]).read_text())
        d["visloc_nees"] = report["measurement_nees"]
        d["visloc_geotag_fallbacks"] = sum(r["visloc_geotag_fallbacks"] for r in d["frames"])
    without = digest_peer({f"out/thinning/cap_{cap}": out}, out / "strict") if cap != DEFAULT else {}
    for drive, d in without.items():
        digest[drive]["visloc_strict"] = {"error_m": d["visloc_error_m"], "inliers": d["visloc_inliers"],
                                          "geotag_fallbacks": sum(r["visloc_geotag_fallbacks"] for r in d["frames"])}
    return {"commands": commands, "drives": digest}


def measure(a) -> dict:
    folder = Path(a.data)
    peer = peer_runs()
    a.earlier = json.loads(Path(a.peer_from).read_text()) if a.peer_from else None
    result = {"commit": commit(), "cores": os.cpu_count(), "load_before": load_1min(), "caps": {}}
    for cap in [DEFAULT, *a.caps.split(",")]:
        result["caps"][cap] = measure_cap(a, cap, folder, peer)
    result["load_after"] = load_1min()
    return result


def render(r: dict) -> str:
    lines = [SECTION.begin, ""]
    add = lines.append
    add("**Support thinned on purpose.** Every image of the shared drives, database and queries alike, keeps at most "
        "N SIFT keypoints (visloc `--sift-features N`, the peer `--max-features N`), so that the poses stand on "
        "fewer matches, as where texture is thin. Each cap has its own store, ingested as a user would (structure "
        "and self-check included), and its own peer run. Both pose the frames the peer measured at its defaults, "
        "one measurement each (visloc: a one-step series, full-scan retrieval, no filter), same setup, 1 s "
        "exclusion; a failed pose counts with its fallback geotag's error. \"default\": each at its own defaults "
        "(visloc every SIFT keypoint; the peer at most 8192). NEES: visloc's "
        "measurements posed from geometry (2 when honest). The last column is visloc on the same store with "
        "`--thin-support-pnp-px 0`: no second, looser pose where none holds 15 inliers at 2 px (not measured with "
        f"every keypoint, where no query falls back). Measured by `python benchmarks/thinning_stress.py` at "
        f"{r['commit']} ({r['cores']} cores, load {r['load_before']:.1f} at the start, {r['load_after']:.1f} at the end)"
        + reused_note(r) + ".")
    add("")
    add("| drive | keypoints per image | frames | peer error median / p90 / max (m) | visloc error median / p90 / max "
        "(m) | peer inliers median | visloc inliers median | peer failures | visloc geotag fallbacks | visloc NEES "
        "mean, inside 95 % | visloc without the thin-support pose: error median / p90 / max (m), fallbacks |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    drives = sorted({d for cap in r["caps"].values() for d in cap["drives"]})
    for drive in drives:
        for cap, c in r["caps"].items():
            d = c["drives"].get(drive)
            if d is None:
                continue
            p, v, nees = d["peer_error_m"], d["visloc_error_m"], d["visloc_nees"]
            shown = "default" if cap == DEFAULT else f"at most {int(cap):,}"
            nees_text = (f"{nees['mean']:.2f}, {100 * nees['fraction_within_95']:.0f} %" if nees and nees.get("n")
                         else "-")
            add(f"| {drive} | {shown} | {p['n']} | {p['median']:.2f} / {p['p90']:.2f} / {p['max']:.2f} | "
                f"{v['median']:.2f} / {v['p90']:.2f} / {v['max']:.2f} | {d['peer_inliers']['median']:.0f} | "
                f"{d['visloc_inliers']['median']:.0f} | {d['peer_failures']} | {d['visloc_geotag_fallbacks']} | "
                f"{nees_text} | {strict_text(d.get('visloc_strict'))} |")
    add("")
    add(SECTION.end)
    return "\n".join(lines)


def strict_text(strict: dict | None) -> str:
    """visloc's figures without the thin-support pose, or "-" where they were not measured (every keypoint)."""
    if not strict:
        return "-"
    e = strict["error_m"]
    return f"{e['median']:.2f} / {e['p90']:.2f} / {e['max']:.2f}, {strict['geotag_fallbacks']}"


def reused_note(r: dict) -> str:
    """How the page says that the peer's capped runs were taken from an earlier measurement (empty if not)."""
    reused = [(drive.removesuffix("_sync"), d["peer_reused_from"]) for c in r["caps"].values()
              for drive, d in c["drives"].items() if d.get("peer_reused_from")]
    if not reused:
        return ""
    fresh = sorted({drive.removesuffix("_sync") for c in r["caps"].values() for drive in c["drives"]}
                   - {drive for drive, _ in reused})
    where = f" on {', '.join(sorted({drive for drive, _ in reused}))}" if fresh else ""
    return (f"; the peer's capped runs{where} are those of {', '.join(sorted({s for _, s in reused}))}, its code and "
            f"inputs unchanged" + (f" (measured now on {', '.join(fresh)})" if fresh else ""))


def add_arguments(p) -> None:
    p.add_argument("--data", type=Path, default=default_data_root(), help="KITTI raw root (default the shared data)")
    p.add_argument("--caps", default="1000,500", help="keypoints per image, comma-separated (default 1000,500)")
    p.add_argument("--peer-from", default=None,
                   help="an earlier JSON of this benchmark whose peer runs are reused where out/thinning has none")
    p.add_argument("--peer-python", default=str(REPO.parent / "peer-venv" / "bin" / "python"),
                   help="the Python of a venv with the peer's packages (its README: pycolmap, numpy, "
                        "opencv-python-headless, pyproj)")


if __name__ == "__main__":
    sys.exit(SECTION.main(__doc__, measure, render, add_arguments))
