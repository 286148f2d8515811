"""Denser database structure as a lever for the refined measurement's support: what it gives and what it costs.

    python benchmarks/structure_density.py [--data ROOT] [--db out/results/visloc.sqlite]
    python benchmarks/structure_density.py --page   # its section of docs/performance.md from the JSON

A view's 3D points come from triangulating it with database images before and after it at about the distances
``neighbour_baselines_m`` (the defaults: 2, 5 and 10 m), the poses of the view and its neighbours first adjusted
on ``max_adjusted_points`` of its points (the default 0: every one). Triangulating each view with more neighbours,
and with nearer ones, gives more of its keypoints a point (the peer triangulates each database image with every
image within 10 frames); adjusting the poses on a few hundred points rather than every one keeps the cost of more
neighbours down. This measures, on every drive of the data root (its first protocol, 1 s exclusion), the frames
the COLMAP-style peer measured, each posed once per configuration from a full-scan retrieval, no filter:

* support: the pose's PnP inliers and the distinct query keypoints among them, beside the peer's inliers on the
  same frames (its JSON: 12 px RANSAC threshold, each query keypoint once);
* accuracy: the error against the frame's geotag (median, p90, max) and the geotag fallbacks;
* cost: the structure each configuration builds for the views these queries use, per view: milliseconds, and
  database pairs matched. Ingest builds three such structures per image (before, after, both sides).

Every configuration keeps every other refined default. Nothing is stored. Writes
``docs/results/structure_density.json`` and its section of docs/performance.md.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
from pathlib import Path

from measuring import REPO, Section, drives_and_store_arguments, load_1min
from refined_support import measured_row
from thinning_stress import peer_runs

sys.path.insert(0, str(REPO / "scripts"))
from results_peer import peer_pose  # noqa: E402
from visloc import Workspace  # noqa: E402
from visloc.params import REFINED, MatchParams, RetrievalParams  # noqa: E402
from visloc.pose.refined import PoseMeasurer, StructureCache  # noqa: E402
from visloc.pose.structure import structure_settings_json  # noqa: E402
from visloc.protocols.suite import drive_protocols, drives_of  # noqa: E402
from visloc.retrieval.retrievers import WindowRetriever  # noqa: E402
from visloc.stats import CHI2_2DOF_95, summary_of  # noqa: E402

SECTION = Section("structure-density", "structure_density", REPO / "docs" / "performance.md")
DENSE = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0)
CONFIGS = {
    "defaults: 2, 5, 10 m, poses adjusted on every point": REFINED,
    "0.5, 1, 1.5, 2, 3, 4, 5, 7, 10 m, poses adjusted on 400 points": REFINED.replace(
        neighbour_baselines_m=DENSE, min_baseline_m=0.5, max_adjusted_points=400),
    "the same, poses adjusted on every point": REFINED.replace(neighbour_baselines_m=DENSE, min_baseline_m=0.5),
}


def peer_frames(path: Path) -> dict[int, dict]:
    """query frame -> the peer's inliers and error there (a failed pose: 0 inliers, its fallback's error)."""
    poses = {int(q["query_frame"]): peer_pose(q) for q in json.loads(path.read_text())["queries"]}
    return {f: {"inliers": int(p["inliers"] or 0) if p["ok"] else 0, "error_m": float(p["error_m"])}
            for f, p in poses.items()}


def measure_drive(ws: Workspace, folder: Path, peer: dict[int, dict]) -> dict:
    protocol = drive_protocols(folder)[0]
    db = ws.load_database(folder.name, protocol.db_camera)
    queries = ws.load_queries(folder.name, protocol.query_camera)
    truth = db.frame.to_local(queries.lat_deg, queries.lon_deg)
    geometry = db.geometry()
    retriever = WindowRetriever(db.timestamps_s, ws.pair_cache(db, queries, MatchParams()),
                                RetrievalParams(exclusion_s=1.0))
    index_of = {int(f): i for i, f in enumerate(queries.frames)}
    frames = [f for f in sorted(peer) if f in index_of]
    out = {"drive": folder.name, "protocol": protocol.key, "protocol_label": protocol.label, "frames": frames,
           "peer": {"inliers": summary_of([peer[f]["inliers"] for f in frames], ("min", "median", "max")),
                    "error_m": summary_of([peer[f]["error_m"] for f in frames], ("median", "p90", "max"))},
           "configs": {}}
    for name, params in CONFIGS.items():
        cache = StructureCache()  # each configuration builds its own structure, once per view
        measurer = PoseMeasurer(db.east_north_m, geometry, queries.camera_model, params, structures=cache)
        rows = []
        for f in frames:
            i = index_of[f]
            q = queries.query(i)
            retriever.reset()
            rows.append(measured_row(f, measurer.measure(q, retriever.retrieve(q, None)), truth[i]))
        views = max(len(cache), 1)
        out["configs"][name] = {
            "neighbour_baselines_m": list(params.neighbour_baselines_m), "min_baseline_m": params.min_baseline_m,
            "inliers": summary_of([r["inliers"] for r in rows], ("min", "median", "max")),
            "query_keypoints": summary_of([r["query_keypoints"] for r in rows], ("median",)),
            "error_m": summary_of([r["error_m"] for r in rows], ("median", "p90", "max"), count=True),
            "geotag_fallbacks": sum(r["source"] != "geometry" for r in rows),
            "frames_at_peer_inliers": sum(r["inliers"] >= peer[r["frame"]]["inliers"] for r in rows),
            "structures_built": len(cache), "structure_ms_per_view": cache.build_ms / views,
            "pairs_per_view": cache.pairs_matched / views, "stored": stored_cost(ws, db, params), "rows": rows}
    return out


def stored_cost(ws: Workspace, db, params) -> dict | None:
    """What the store holds of this configuration's structure, if it holds it (an ingest with these settings):
    images, kB per image (every variant's rows, points and covariances) and the ingest's build time per image."""
    records = ws.stored_structure([im.image_id for im in db.images], structure_settings_json(params))
    images = {image_id for image_id, _ in records}
    if not images:
        return None
    n_bytes = sum(r.rows_i32.nbytes + r.points_f64.nbytes + r.cov_f64.nbytes for r in records.values())
    return {"images": len(images), "kb_per_image": n_bytes / 1000 / len(images),
            "ingest_ms_per_image": sum(r.build_ms for r in records.values()) / len(images)}


def measure(a) -> dict:
    ws = Workspace(a.db, read_only=True)
    peers = peer_runs()
    result = {"load_before": load_1min(), "cores": os.cpu_count(), "drives": []}
    for folder in drives_of(a.data):
        drive = folder.name.removesuffix("_sync")
        if drive not in peers:
            print(f"structure density: {drive}: no peer measurement, skipped", flush=True)
            continue
        d = measure_drive(ws, folder, peer_frames(peers[drive]))
        result["drives"].append(d)
        for name, c in d["configs"].items():
            e = c["error_m"]
            print(f"{drive} {name}: inliers {c['inliers']['median']:.0f} (peer {d['peer']['inliers']['median']:.0f}), "
                  f"error {e['median']:.3f}/{e['p90']:.3f}/{e['max']:.3f} m, {c['structure_ms_per_view']:.0f} ms and "
                  f"{c['pairs_per_view']:.1f} pairs per view", flush=True)
    result["load_after"] = load_1min()
    return result


def render(r: dict) -> str:
    lines = [SECTION.begin,
             "**Denser structure.** A view's 3D points come from triangulating it with database images before and "
             "after it at about the configured distances (`--neighbour-baselines-m`). Measured by `python "
             "benchmarks/structure_density.py --db out/results/visloc.sqlite`: the frames the COLMAP-style peer "
             "measured, each posed once per configuration (1 s exclusion, full-scan retrieval, no filter), every "
             "other setting at its default; the peer's inliers on the same frames beside them (its 12 px RANSAC "
             "threshold, each query keypoint once; visloc's at 2 px). Structure cost: per view these queries use, "
             "as the query path builds it (ingest builds three per image: before, after, both sides); "
             f"2 cores, load {r['load_before']:.1f} at the start, {r['load_after']:.1f} at the end.", "",
             "| drive | neighbours at | PnP inliers min / median / max | distinct query keypoints median | peer "
             "inliers median | frames at or above the peer's inliers | error median / p90 / max (m) | NEES mean, inside "
             "95 % | geotag fallbacks | structure per view: ms, pairs matched |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for d in r["drives"]:
        for name, c in d["configs"].items():
            i, e = c["inliers"], c["error_m"]
            nees = [row["nees"] for row in c["rows"] if row.get("nees") is not None]
            honesty = (f"{statistics.mean(nees):.2f}, {100 * sum(x <= CHI2_2DOF_95 for x in nees) / len(nees):.0f} %"
                       if nees else "-")
            lines.append(f"| {d['drive'].removesuffix('_sync')} | {name} | {i['min']:.0f} / {i['median']:.0f} / "
                         f"{i['max']:.0f} | {c['query_keypoints']['median']:.0f} | {d['peer']['inliers']['median']:.0f} "
                         f"| {c['frames_at_peer_inliers']} of {len(d['frames'])} | {e['median']:.3f} / {e['p90']:.3f} / "
                         f"{e['max']:.3f} | {honesty} | {c['geotag_fallbacks']} | {c['structure_ms_per_view']:.0f}, "
                         f"{c['pairs_per_view']:.1f} |")
    dense_over_defaults, every_point = [], []
    for d in r["drives"]:
        defaults, dense, dense_every_point = d["configs"].values()
        dense_over_defaults.append(dense["structure_ms_per_view"] / defaults["structure_ms_per_view"])
        every_point.append(dense_every_point["structure_ms_per_view"] / dense["structure_ms_per_view"])
    stored = [(d["drive"].removesuffix("_sync"), name, c["stored"]) for d in r["drives"]
              for name, c in d["configs"].items() if c.get("stored")]
    if stored:
        lines += ["", "What ingest stored (every variant of every image of the drive, as the store holds it):", "",
                  "| drive | configuration | images | stored per image (kB) | ingest build per image (ms) |",
                  "|---|---|---|---|---|"]
        lines += [f"| {drive} | {name} | {c['images']} | {c['kb_per_image']:.0f} | {c['ingest_ms_per_image']:.0f} |"
                  for drive, name, c in stored]
    if dense_over_defaults:
        lines += ["", f"The nine baselines cost {min(dense_over_defaults):.1f}-{max(dense_over_defaults):.1f} times the "
                      f"defaults' structure time per view with the poses adjusted on 400 points, and "
                      f"{min(every_point):.1f}-{max(every_point):.1f} times that again on every point."]
    lines += ["", SECTION.end]
    return "\n".join(lines)


def add_arguments(p) -> None:
    drives_and_store_arguments(p, "--data")


if __name__ == "__main__":
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
