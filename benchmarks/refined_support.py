"""What the refined measurement's support costs: six views, each posed alone with guided matching and averaged
(the defaults), against four views, against the defaults without the search for views on the other side of the
query, against one PnP over the six views' points and against two views in one PnP without guided matching.

    python benchmarks/refined_support.py [--data ROOT] [--db out/results/visloc.sqlite] [--every 5]

On every drive of the data root, with its first protocol (left queries against the right camera where a drive
has both, else one camera) and the 1 s exclusion, every ``--every``-th query is measured once with the refined
defaults (each view posed alone, the positions averaged), once with four views, once without the search for
views on the other side (``--other-side-candidates 0``), once with one PnP over every view's points
(``--no-fuse-views``) and once with the earliest support (``n_views=2``, ``guided_radius_px=0``, one PnP), in
rotating order, from a full-scan retrieval. Per query: the pose's PnP inliers (summed over the views posed
alone), the distinct query keypoints among them, the error against the query's geotag, its NEES against the
measurement's covariance (the truth shares the map's receiver), and the query side's time (matching, RANSAC,
guided matching, PnP; the database structure each view needs is built once and left out, as a store holds it).
Nothing new is stored; ingest's self-check poses as the defaults do. Writes
``docs/results/refined_support.json`` and its section of docs/performance.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from measuring import REPO, Section, drives_and_store_arguments, load_1min
from visloc import Workspace  # noqa: E402
from visloc.params import REFINED, MatchParams, RetrievalParams  # noqa: E402
from visloc.pose.refined import PoseMeasurer, StructureCache  # noqa: E402
from visloc.pose.uncertainty import calibration  # noqa: E402
from visloc.protocols.suite import drive_protocols, drives_of  # noqa: E402
from visloc.retrieval.retrievers import WindowRetriever  # noqa: E402
from visloc.stats import summary_of  # noqa: E402

SECTION = Section("refined-support", "refined_support", REPO / "docs" / "performance.md")
CONFIGS = {"defaults": REFINED, "four views": REFINED.replace(n_views=4),
           "no search on the other side": REFINED.replace(other_side_candidates=0),
           "one PnP over every view": REFINED.replace(fuse_views=False),
           "two views, no guided matching": REFINED.replace(n_views=2, guided_radius_px=0.0, fuse_views=False)}


def measured_row(frame: int, m, truth_east_north_m: np.ndarray) -> dict:
    """One refined measurement of ``frame``: where it came from, its error against the frame's geotag, its PnP
    inliers and the distinct query keypoints among them (0 for a geotag fallback), its NEES against its own
    covariance (None for a geotag fallback; the truth shares the map's receiver), its query side's time."""
    posed = m.source == "geometry"
    e = np.asarray(m.east_north_m, float) - truth_east_north_m
    return {"frame": frame, "source": m.source, "error_m": float(np.linalg.norm(e)),
            "nees": float(e @ np.linalg.solve(np.asarray(m.cov_m2, float), e)) if posed else None,
            "inliers": int(m.n_pnp_inliers) if posed else 0,
            "query_keypoints": len(np.unique(m.inliers.query_rows)) if posed else 0,
            "query_side_ms": float(m.query_side_ms)}


def measure_drive(ws: Workspace, folder: Path, every: int) -> dict:
    protocol = drive_protocols(folder)[0]
    db = ws.load_database(folder.name, protocol.db_camera)
    queries = ws.load_queries(folder.name, protocol.query_camera)
    truth = db.frame.to_local(queries.lat_deg, queries.lon_deg)
    geometry = db.geometry()
    cache = ws.pair_cache(db, queries, MatchParams())
    retriever = WindowRetriever(db.timestamps_s, cache, RetrievalParams(exclusion_s=1.0))
    structures = StructureCache()  # shared: each view's structure is built once, whichever configuration asks
    measurers = {name: PoseMeasurer(db.east_north_m, geometry, queries.camera_model, params, structures=structures)
                 for name, params in CONFIGS.items()}
    rows: dict[str, list[dict]] = {name: [] for name in CONFIGS}
    for n, i in enumerate(range(0, len(queries), every)):
        q = queries.query(i)
        retriever.reset()
        retrieval = retriever.retrieve(q, None)
        names = list(CONFIGS)[n % len(CONFIGS):] + list(CONFIGS)[:n % len(CONFIGS)]
        for name in names:
            rows[name].append(measured_row(int(queries.frames[i]), measurers[name].measure(q, retrieval), truth[i]))
    out = {"drive": folder.name, "protocol": protocol.key, "protocol_label": protocol.label, "configs": {}}
    for name, r in rows.items():
        out["configs"][name] = {
            "inliers": summary_of([x["inliers"] for x in r], ("min", "median", "max")),
            "query_keypoints": summary_of([x["query_keypoints"] for x in r], ("min", "median", "max")),
            "error_m": summary_of([x["error_m"] for x in r], ("median", "p90", "max"), count=True),
            "nees": calibration([x["nees"] for x in r if x["nees"] is not None]).as_dict(),
            "query_side_ms": summary_of([x["query_side_ms"] for x in r], ("median", "p90")),
            "geotag_fallbacks": sum(x["source"] != "geometry" for x in r), "frames": r}
    return out


def measure(a) -> dict:
    ws = Workspace(a.db)
    result = {"load_before": load_1min(), "cores": os.cpu_count(), "every": a.every, "drives": []}
    for folder in drives_of(a.data):
        d = measure_drive(ws, folder, a.every)
        result["drives"].append(d)
        for name, c in d["configs"].items():
            print(f"{d['drive']} {name}: inliers {c['inliers']['median']:.0f}, distinct {c['query_keypoints']['median']:.0f}, "
                  f"error {c['error_m']['median']:.3f}/{c['error_m']['p90']:.3f}/{c['error_m']['max']:.3f} m, "
                  f"{c['query_side_ms']['median']:.0f} ms", flush=True)
    result["load_after"] = load_1min()
    return result


def render(r: dict) -> str:
    lines = [SECTION.begin,
             "The refined measurement's support and what it costs per query, measured by `python "
             f"benchmarks/refined_support.py --db out/results/visloc.sqlite --every {r['every']}`: every "
             f"{r['every']}th query of each drive (1 s exclusion, full-scan retrieval), measured with the defaults "
             f"({REFINED.n_views} views, each posed alone with guided matching, their positions averaged, and where "
             "every view lies on one side of the query the images nearest it on the other side verified too), with "
             "four views, without that search (`--other-side-candidates 0`), with one PnP over the views' points "
             "(`--no-fuse-views`), and with two views in one PnP and no guided matching, in rotating order (medians; "
             f"load {r['load_before']:.1f} at the start, {r['load_after']:.1f} at the end). Query side: matching, "
             "RANSAC, guided matching and PnP; each view's structure is built once and left out, as a store holds it. "
             "Nothing new is stored: the lever gain in every configuration's covariance is the one ingest's "
             "self-check measured posing as the defaults do (not timed here), so only the defaults' NEES speaks for "
             "a self-check made their way. "
             "PnP inliers of views posed alone are summed over the views; the distinct query keypoints count each "
             "once. "
             "NEES: the error against the measurement's own covariance (the truth shares the map's receiver), over "
             "its geometry measurements; the ideal mean is 2, with 95 % inside the 95 % ellipse.", "",
             "| drive | setup | configuration | PnP inliers min / median / max | distinct query keypoints median | "
             "error median / p90 / max (m) | NEES mean / median, inside 95 % | geotag fallbacks | "
             "query side median (ms) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for d in r["drives"]:
        for name, c in d["configs"].items():
            i, e = c["inliers"], c["error_m"]
            lines.append(f"| {d['drive']} | {d['protocol_label']} | {name} | {i['min']:.0f} / {i['median']:.0f} / "
                         f"{i['max']:.0f} | {c['query_keypoints']['median']:.0f} | {e['median']:.3f} / {e['p90']:.3f} / "
                         f"{e['max']:.3f} | {_nees(c.get('nees'))} | {c['geotag_fallbacks']} | "
                         f"{c['query_side_ms']['median']:.0f} |")
    lines += ["", SECTION.end]
    return "\n".join(lines)


def _nees(c: dict | None) -> str:
    if not c or not c.get("n"):
        return "–"
    return f"{c['nees_mean']:.2f} / {c['nees_median']:.2f}, {100 * c['inside_95']:.0f} %"


def add_arguments(p) -> None:
    drives_and_store_arguments(p, "--data")
    p.add_argument("--every", type=int, default=5, help="measure every n-th query (default %(default)s)")


if __name__ == "__main__":
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
