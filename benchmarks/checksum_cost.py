"""What the store's checksums cost, measured on the real drives: writing (ingest) and reading (every run).

    python benchmarks/checksum_cost.py [--db out/results/visloc.sqlite] [--root ../shared/data/kitti]
    python benchmarks/checksum_cost.py --page     # the performance page from docs/results/checksum_cost.json

For each drive and camera a store holds (every drive of the data root, when the store was built by
``scripts/results.py run``):

* ingest: per image, what ingest does anyway (read the file, decode it, SIFT) against what the
  checksums add (the SHA-256 of the file's bytes, the CRC-32 of the keypoint and descriptor BLOBs),
  medians over up to 40 images spread through the drive, in the same process one after the other;
* reading: loading the drive's camera as a database for the refined and camera-rate methods
  (features, structure, global vectors: ``Workspace.load_database``, ``load_structure``,
  ``load_database_index``, which verify every BLOB) against the CRC-32 of those same bytes alone,
  medians of 5. Queries read nothing from the store once it is loaded, so the share of a whole
  ``visloc bench`` or ``visloc track`` run is smaller still;
* a re-ingest that finds nothing to do: the time to check every stored image of the drive against
  its checksums and its file.

Writes docs/results/checksum_cost.json; ``--page`` renders its section of docs/performance.md from it.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
import zlib
from pathlib import Path

import numpy as np


from measuring import REPO, Section, median_s  # noqa: E402

SECTION = Section("checksum-cost", "checksum_cost", REPO / "docs" / "performance.md")
OUT, PAGE, BEGIN, END = SECTION.out, SECTION.page, SECTION.begin, SECTION.end
from visloc.db import FeatureStore  # noqa: E402
from visloc.db.integrity import drive_blobs, scan  # noqa: E402
from visloc.features.sift import extract_sift, make_sift  # noqa: E402
from visloc.sources.drives import default_data_root, file_digest, read_image  # noqa: E402
from visloc.store.workspace import Workspace  # noqa: E402

RESULTS = REPO / "out" / "results"



def ingest_cost(ws: Workspace, source: str, camera: str, n_images: int = 40) -> dict:
    images = ws.load_database(source, camera).images
    picks = sorted({int(k) for k in np.linspace(0, len(images) - 1, min(n_images, len(images)))})
    sift = make_sift(ws.sift_params)
    described, added = [], []
    for k in picks:
        path = Path(images[k].path)
        start = time.perf_counter()
        gray, _, _ = read_image(path)
        features = extract_sift(gray, ws.sift_params, sift=sift)
        described.append(time.perf_counter() - start)
        data = path.read_bytes()
        keypoints, descriptors = features.keypoints_f32.tobytes(), features.descriptors_u8.tobytes()
        start = time.perf_counter()
        hashlib.sha256(data).hexdigest()
        zlib.crc32(keypoints)
        zlib.crc32(descriptors)
        added.append(time.perf_counter() - start)
    d, a = float(np.median(described)) * 1e3, float(np.median(added)) * 1e3
    return {"n_images": len(picks), "describe_ms": d, "checksums_ms": a, "share": a / d}


def read_cost(ws: Workspace, source: str, camera: str) -> dict:
    def load():
        db = ws.load_database(source, camera)
        ws.load_structure(db)
        ws.global_vectors.load_database_index(db)

    load()  # warm the page cache: both sides read the same bytes from memory
    with FeatureStore(ws.path, read_only=True) as store:
        blobs = drive_blobs(store, source, camera)
    load_s = median_s(load, 5)
    crc_s = median_s(lambda: [zlib.crc32(b) for b in blobs], 5)
    return {"megabytes": sum(len(b) for b in blobs) / 1e6, "load_ms": load_s * 1e3, "checksums_ms": crc_s * 1e3,
            "share": crc_s / load_s}


def reingest_check_cost(ws: Workspace, source: str, camera: str) -> dict:
    paths = [Path(im.path) for im in ws.load_database(source, camera).images]

    def check():
        with FeatureStore(ws.path, read_only=True) as store:
            list(scan(store, source=source, camera=camera))
        for p in paths:
            file_digest(p)

    check()
    seconds = median_s(check, 3)
    return {"n_images": len(paths), "seconds": seconds, "ms_per_image": seconds * 1e3 / len(paths)}


def measure(db: Path) -> dict:
    ws = Workspace(db, read_only=True)
    drives = []
    for d in ws.drives():
        source, camera = d.name.split("/")
        if not Path(ws.load_database(source, camera).images[0].path).is_file():
            print(f"{d.name}: its images are not where they were ingested from; skipped", file=sys.stderr)
            continue
        print(f"{d.name} ...", file=sys.stderr, flush=True)
        entry = {"drive": source, "camera": camera, "n_images": d.n_images,
                 "ingest": ingest_cost(ws, source, camera), "read": read_cost(ws, source, camera),
                 "reingest_check": reingest_check_cost(ws, source, camera)}
        track = RESULTS / f"track_{source.removesuffix('_sync')}_same_{camera}.json"
        if track.is_file():  # a whole camera-rate run over the drive, as scripts/results.py ran it
            wall_s = json.loads(track.read_text())["wall_s"]
            entry["track_run"] = {"file": str(track.relative_to(REPO)), "wall_s": wall_s,
                                  "share": entry["read"]["checksums_ms"] / (wall_s * 1e3)}
        drives.append(entry)
    shown = os.path.relpath(db, REPO) if Path(db).resolve().is_relative_to(REPO) else str(db)
    return {"store": shown, "command": f"python benchmarks/checksum_cost.py --db {shown}", "drives": drives}


def render(result: dict) -> str:
    rows = ["| drive / camera | ingest: describe one image (ms) | checksums add (ms) | share | "
            "load for a run (ms, MB) | checksums of it (ms) | share of the load | share of a track run | "
            "re-ingest check (ms per image) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for d in result["drives"]:
        i, r, c = d["ingest"], d["read"], d["reingest_check"]
        track = f"{100 * d['track_run']['share']:.2f} % of {d['track_run']['wall_s']:.0f} s" if "track_run" in d else "-"
        rows.append(f"| {d['drive']} / {d['camera']} | {i['describe_ms']:.0f} | {i['checksums_ms']:.2f} | "
                    f"{100 * i['share']:.2f} % | {r['load_ms']:.0f} ({r['megabytes']:.0f} MB) | {r['checksums_ms']:.1f} | "
                    f"{100 * r['share']:.0f} % | {track} | {c['ms_per_image']:.1f} |")
    worst_ingest = max(d["ingest"]["share"] for d in result["drives"])
    load_shares = [d["read"]["share"] for d in result["drives"]]
    speeds = [d["read"]["megabytes"] / d["read"]["checksums_ms"] for d in result["drives"]]  # MB/ms = GB/s
    worst_track = max((d["track_run"]["share"] for d in result["drives"] if "track_run" in d), default=float("nan"))
    return "\n".join([
        BEGIN,
        f"Every array in a store carries a CRC-32, written with it and checked whenever it is read; each image "
        f"records the SHA-256 of its file. Measured by `{result['command']}` (medians, this machine):",
        "",
        *rows,
        "",
        f"The checksums add at most {100 * worst_ingest:.2f} % to ingesting an image. Reading, they cost "
        f"{100 * min(load_shares):.0f}-{100 * max(load_shares):.0f} % of loading a drive (CRC-32 checks about "
        f"{min(speeds):.1f}-{max(speeds):.1f} GB/s here; SQLite hands the bytes over faster), "
        "but a run loads once and its queries read nothing more from the store: at most "
        f"{100 * worst_track:.2f} % of a whole `visloc track` run over the drive (its wall time from "
        "`out/results/track_*.json`), and nothing per query in `visloc bench`'s timings. A re-ingest "
        "that finds nothing to do checks every stored image against its checksums and its file (the last column).",
        END,
    ])



def main() -> int:
    def arguments(parser):
        parser.add_argument("--db", type=Path, default=REPO / "out" / "results" / "visloc.sqlite")
        parser.add_argument("--root", type=Path, default=default_data_root())

    return SECTION.main(__doc__, lambda a: measure(a.db), render, arguments)


if __name__ == "__main__":
    sys.exit(main())
