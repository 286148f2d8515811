"""Denser SIFT as a lever for the refined measurement's support: what a lower contrast threshold gives and costs.

    python benchmarks/feature_density.py [--data ROOT] [--contrasts 0.04,0.02]
    python benchmarks/feature_density.py --page   # its section of docs/performance.md from the JSON

OpenCV's SIFT keeps a scale-space extremum when its contrast times the layers per octave reaches the contrast
threshold (0.04 in the paper's settings; a new visloc store, since this measurement, 0.02); COLMAP's SIFT, the
peer's, keeps extrema at about half that (its peak threshold 0.02 / 3 layers), so on low-texture images it finds
two or three times as many keypoints. Each contrast gets its own store, every camera of each drive's first setup ingested as a user would
(``visloc ingest --sift-contrast C``: features, global vectors, structure, self-checks) and timed, one after the
other on this machine. Each store then poses the frames the COLMAP-style peer measured at its defaults (the
drive's first setup, 1 s exclusion), one measurement each (``visloc evaluate --mode refined --steps 1``: a
full-scan retrieval, no filter), as the structure-density and thinning benchmarks do. Per drive and contrast:
keypoints per image, the pose's PnP inliers and the distinct query keypoints among them beside the peer's
inliers on the same frames, the error (median, p90, max), the NEES of the measurements posed from geometry,
the refined measurement's milliseconds per query (``measurement_ms``, structure read from the store), and the
ingest's seconds and the store's bytes per image.

It also checks, on every 10th image of each drive's query camera, how many of the keypoints and descriptors at
the default contrast are, exactly, those at a lower contrast whose response times the layers per octave reaches
the default, and how many such are not the default's: whether a store ingested at the lower contrast holds the
paper's features, selectable by response.

An interrupted measurement goes on where it stopped; a contrast whose ingest was interrupted is ingested afresh
(a resumed ingest would be timed short). Writes ``docs/results/feature_density.json`` and its section.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from measuring import REPO, Section, commit, load_1min, run_once
from thinning_stress import PEER_RUNS, peer_runs

sys.path.insert(0, str(REPO / "scripts"))
from results_peer import digest_peer  # noqa: E402
from visloc.features.sift import extract_sift  # noqa: E402
from visloc.params import PAPER_SIFT, STORE_SIFT, SiftParams  # noqa: E402
from visloc.protocols.suite import drive_protocols, drives_of  # noqa: E402
from visloc.sources.drives import default_data_root  # noqa: E402

SECTION = Section("feature-density", "feature_density", REPO / "docs" / "performance.md")
WORK = REPO / "out" / "feature_density"
SUBSET_EVERY = 10  # the subset check reads every this many images of each drive's query camera


def camera_images(drive_folder: Path, camera: str) -> list[Path]:
    return sorted((drive_folder / camera / "data").glob("*.png"))


def ingest_store(folder: Path, drives: list[tuple[Path, object]], contrast: str, out: Path) -> dict:
    """Every camera of ``drives``' setups ingested into ``out/visloc.sqlite`` at ``contrast``, each timed:
    {"cameras": [{drive, camera, images, wall_s}], "bytes": the store's size}."""
    record = out / "ingest.json"
    if record.is_file():
        return json.loads(record.read_text())
    shutil.rmtree(out, ignore_errors=True)  # an interrupted ingest: made afresh, so that its time is whole
    out.mkdir(parents=True)
    store, cameras = out / "visloc.sqlite", []
    for drive_folder, protocol in drives:
        drive = drive_folder.name.removesuffix("_sync")
        for camera in dict.fromkeys([protocol.db_camera, protocol.query_camera]):
            command = [sys.executable, "-m", "visloc", "ingest", str(folder), "--drive", drive, "--camera", camera,
                       "--db", str(store), "--sift-contrast", contrast]
            print("feature density:", " ".join(command[1:]), flush=True)
            start = time.perf_counter()
            with (out / "log.txt").open("a") as log:
                subprocess.run(command, cwd=REPO, check=True, stdout=log, stderr=subprocess.STDOUT,
                               stdin=subprocess.DEVNULL)
            cameras.append({"drive": drive, "camera": camera, "images": len(camera_images(drive_folder, camera)),
                            "wall_s": time.perf_counter() - start})
    size = sum(p.stat().st_size for p in out.glob("visloc.sqlite*"))
    result = {"cameras": cameras, "bytes": size}
    record.write_text(json.dumps(result, indent=1))
    return result


def evaluate(folder: Path, drive_folder: Path, protocol, frames: list[int], contrast: str, out: Path) -> str:
    """The refined single measurements of ``frames`` on ``out``'s store: the command, its JSON in ``out``."""
    drive = drive_folder.name.removesuffix("_sync")
    path = out / f"{drive}_{protocol.key}_refined.json"
    command = ["-m", "visloc", "evaluate", str(folder), "--drive", drive, "--query-camera", protocol.query_camera,
               "--db-camera", protocol.db_camera, "--db", str(out / "visloc.sqlite"), "--sift-contrast", contrast,
               "--mode", "refined", "--steps", "1", "--exclusion-s", "1",
               "--start-frames", ",".join(map(str, frames)), "--json", str(path)]
    run_once([sys.executable, *command], out / "log.txt", path, "feature density")
    return "python " + " ".join(command)


def subset_check(drive_folder: Path, camera: str, contrasts: list[str]) -> dict:
    """Keypoints per image at each contrast; and, for each lower contrast, how many of the default contrast's
    keypoints (position, size, angle, response, octave and descriptor alike) are among the lower contrast's whose
    response reaches the default, and how many of those are not the default's."""
    default = SiftParams()
    keypoints: dict[str, list[int]] = {c: [] for c in contrasts}
    lower = [c for c in contrasts if float(c) < default.contrast_threshold]
    found = {c: {"default": 0, "found": 0, "selected_not_default": 0} for c in lower}
    images = camera_images(drive_folder, camera)[::SUBSET_EVERY]

    def rows(f, kept=None) -> set:
        kept = np.ones(len(f.keypoints_f32), bool) if kept is None else kept
        return {k.tobytes() + d.tobytes() for k, d in zip(f.keypoints_f32[kept], f.descriptors_u8[kept])}

    for path in images:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        features = {c: extract_sift(gray, default.replace(contrast_threshold=float(c)), name=str(path))
                    for c in dict.fromkeys([*contrasts, str(default.contrast_threshold)])}
        for c in contrasts:
            keypoints[c].append(len(features[c].keypoints_f32))
        base = rows(features[str(default.contrast_threshold)])
        for c in lower:
            f = features[c]
            selected = rows(f, f.keypoints_f32[:, 4] * default.n_octave_layers >= default.contrast_threshold)
            found[c]["default"] += len(base)
            found[c]["found"] += len(base & selected)
            found[c]["selected_not_default"] += len(selected - base)
    return {"images": len(images), "keypoints_median": {c: float(statistics.median(k)) for c, k in keypoints.items()},
            "default_in_lower": found}


def measure(a) -> dict:
    folder = Path(a.data)
    contrasts = a.contrasts.split(",")
    peer = peer_runs()
    drives = [(f, drive_protocols(f)[0]) for f in drives_of(folder) if f.name.removesuffix("_sync") in peer]
    result = {"commit": commit(), "cores": os.cpu_count(), "load_before": load_1min(), "contrasts": {},
              "subset": {f.name.removesuffix("_sync"): subset_check(f, p.query_camera, contrasts) for f, p in drives}}
    for contrast in contrasts:
        out = WORK / f"contrast_{contrast}"
        ingest = ingest_store(folder, drives, contrast, out)
        commands = [evaluate(folder, f, p, [q["query_frame"] for q in
                                            json.loads(peer[f.name.removesuffix("_sync")].read_text())["queries"]],
                             contrast, out) for f, p in drives]
        digest = digest_peer(PEER_RUNS, out)
        for drive, d in digest.items():
            report = json.loads((out / d["evaluation_file"]).read_text())
            d["visloc_nees"] = report["measurement_nees"]
            d["visloc_geotag_fallbacks"] = sum(r["visloc_geotag_fallbacks"] for r in d["frames"])
            steps = [s for series in report["series"] for s in series]
            d["measurement_ms_median"] = float(statistics.median(s["measurement_ms"] for s in steps))
            d["frames"] = [{k: r[k] for k in ("frame", "visloc_error_m", "visloc_inliers", "visloc_query_keypoints",
                                              "peer_error_m", "peer_inliers")} for r in d["frames"]]
            cameras = [c for c in ingest["cameras"] if c["drive"] == drive]
            d["ingest_s_per_image"] = sum(c["wall_s"] for c in cameras) / sum(c["images"] for c in cameras)
        images = sum(c["images"] for c in ingest["cameras"])
        result["contrasts"][contrast] = {"commands": commands, "ingest": ingest, "drives": digest,
                                         "store_bytes_per_image": ingest["bytes"] / images}
    result["load_after"] = load_1min()
    return result


def render(r: dict) -> str:
    lines = [SECTION.begin, ""]
    add = lines.append
    contrasts = list(r["contrasts"])
    default, store = str(PAPER_SIFT.contrast_threshold), str(STORE_SIFT.contrast_threshold)
    add("**Denser SIFT.** OpenCV's SIFT keeps a scale-space extremum whose contrast times the layers per octave "
        f"reaches the contrast threshold (`--sift-contrast`: {default} in the paper's settings, {store} for a new "
        "store since this measurement); COLMAP's, the peer's, keeps extrema at about half the paper's. Each "
        "contrast has its own store, every camera of each drive's "
        "first setup ingested as a user would (structure and self-checks included, 2 processes) and timed; each "
        "store poses the frames the COLMAP-style peer measured, one measurement each (1 s exclusion, full-scan "
        "retrieval, no filter). Measurement: the refined measurement's time per query with the structure read "
        "from the store (median). Store: bytes per image over every camera stored. Measured by `python "
        f"benchmarks/feature_density.py` at {r['commit']} ({r['cores']} cores, load {r['load_before']:.1f} at the "
        f"start, {r['load_after']:.1f} at the end).")
    add("")
    add("| drive | SIFT contrast | keypoints per image (median) | PnP inliers min / median / max | distinct query "
        "keypoints median | peer inliers median | error median / p90 / max (m) | NEES mean, inside 95 % | geotag "
        "fallbacks | measurement (ms) | ingest (s per image) |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    drives = sorted({d for c in r["contrasts"].values() for d in c["drives"]})
    for drive in drives:
        for contrast in contrasts:
            d = r["contrasts"][contrast]["drives"].get(drive)
            if d is None:
                continue
            i, e, n = d["visloc_inliers"], d["visloc_error_m"], d["visloc_nees"]
            kp = r["subset"][drive]["keypoints_median"][contrast]
            add(f"| {drive} | {contrast} | {kp:,.0f} | {i['min']:.0f} / {i['median']:.0f} / {i['max']:.0f} | "
                f"{d['visloc_query_keypoints']['median']:.0f} | {d['peer_inliers']['median']:.0f} | "
                f"{e['median']:.3f} / {e['p90']:.3f} / {e['max']:.3f} | {n['mean']:.2f}, "
                f"{100 * n['fraction_within_95']:.0f} % | {d['visloc_geotag_fallbacks']} | "
                f"{d['measurement_ms_median']:.0f} | {d['ingest_s_per_image']:.2f} |")
    add("")
    sizes = ", ".join(f"{c}: {r['contrasts'][c]['store_bytes_per_image'] / 1e6:.2f} MB" for c in contrasts)
    add(f"Store per image: {sizes}.")
    checks = []
    for drive, s in sorted(r["subset"].items()):
        for c, n in s["default_in_lower"].items():
            checks.append(f"{drive} at {c}: {n['found']:,} of {n['default']:,} found, {n['selected_not_default']} "
                          "more")
    if checks:
        add("")
        add(f"The keypoints and descriptors at the paper's contrast are those at the lower contrast whose response "
            f"times the layers per octave reaches {default}, on every {SUBSET_EVERY}th image of each drive's query "
            f"camera ({'; '.join(checks)}, where an extremum at the lower contrast starts its interpolation from "
            "a neighbouring pixel): a store ingested at the lower contrast holds the paper's features, and visloc "
            "selects them by response for the paper's method and for the refined mode's retrieval, while the "
            "refined measurements and the camera-rate path read all of them.")
    add("")
    add(SECTION.end)
    return "\n".join(lines)


def add_arguments(p) -> None:
    p.add_argument("--data", type=Path, default=default_data_root(), help="KITTI raw root (default the shared data)")
    p.add_argument("--contrasts", default="0.04,0.02",
                   help="SIFT contrast thresholds, comma-separated, the default first (default %(default)s)")


if __name__ == "__main__":
    sys.exit(SECTION.main(__doc__, measure, render, add_arguments))
