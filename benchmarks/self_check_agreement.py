"""Does a store's self-check still speak for its queries? The lever gain it fits beside the queries' own errors.

    python benchmarks/self_check_agreement.py [--data ROOT] [--db out/results/visloc.sqlite] [--every 2]
    python benchmarks/self_check_agreement.py --page   # its section of docs/performance.md from the JSON

A refined measurement's ellipse grows with the lever to its nearest view at a gain that each store measures on
itself: ingest poses every other database image from its neighbours (the 1 s exclusion) and fits the gain that
holds those poses' errors (``visloc.pose.selfcheck``). The gain is only as good as those poses' errors are a
stand-in for the queries'. Ingest poses them as the queries are posed; a cheaper pose (two views in one PnP, no
guided matching, as the self-check once did) is measured beside it, because a change to how the structure is
built can move such a stand-in away from the queries: make the queries' poses better while its get worse, and
the ellipses then come out too large.

This measures that, on every drive and setup of the data root, for each configuration below: the self-check is
made with the configuration on a copy of the store (the store itself is left as it is), posed both ways, each
way's gain fitted, and every ``--every``-th query of the setup posed once with that configuration (full-scan
retrieval, 1 s exclusion, no filter), against its geotag, its covariance stated at each gain. Per side (views on
both sides, on one side): the self-check's errors and the queries' (median, 80th percentile: the level the gain is
fitted at), the queries' NEES against their own covariance (the truth shares the map's receiver; 2 when honest,
95 % inside the 95 % ellipse). Writes ``docs/results/self_check_agreement.json`` and its section of
docs/performance.md.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from measuring import REPO, Section, drives_and_store_arguments, load_1min
from refined_support import measured_row

from visloc import Workspace
from visloc.params import REFINED, MatchParams, RetrievalParams
from visloc.pose.refined import PoseMeasurer
from visloc.pose.selfcheck import lever_gain_from, self_check, self_check_params, self_checked_indices
from visloc.pose.structure import seeded_structure_cache
from visloc.pose.uncertainty import SIDES, calibration, nees
from visloc.protocols.suite import drive_protocols, drives_of
from visloc.retrieval.retrievers import WindowRetriever
from visloc.stats import summary_of
from visloc.store.build import build_self_check

SECTION = Section("self-check-agreement", "self_check_agreement", REPO / "docs" / "performance.md")
CONFIGS = {"defaults (5 mm position prior)": REFINED,
           "position prior 5 cm": REFINED.replace(relative_geotag_sigma_m=0.05)}
AS_QUERIES, STAND_IN = "as the queries (ingest's)", "two views, one PnP"  # how the self-check poses an image


def _errors(values: list[float]) -> dict:
    return summary_of(values, ("median", "p80"), count=True) if values else {"n": 0}


def _nees_at(m, truth_east_north_m: np.ndarray, gain) -> float | None:
    """A geometry measurement's NEES with its lever term stated at ``gain`` (None for a geotag fallback)."""
    if m.source != "geometry":
        return None
    terms = m.cov_terms_m2
    lever = gain.covariance_m2(m.side, m.lever_m, m.heading_deg)
    return nees(np.asarray(m.east_north_m, float) - truth_east_north_m, m.cov_m2 - terms["lever"] + lever)


def measure_setup(ws: Workspace, folder: Path, protocol, every: int) -> tuple[list[dict], list]:
    """One drive's setup under each configuration: the self-check made with it both ways (ingest's, stored where
    the store has none; the stand-in, here), their gains and poses' errors by side, and every ``every``-th query
    posed once with it, its NEES at each gain; and the stored self-check's poses at the defaults. The database,
    the queries and their match counts are read once."""
    for params in CONFIGS.values():
        build_self_check(ws, folder.name, protocol.db_camera, params)
    db = ws.load_database(folder.name, protocol.db_camera)
    queries = ws.load_queries(folder.name, protocol.query_camera)
    truth = db.frame.to_local(queries.lat_deg, queries.lon_deg)
    retriever = WindowRetriever(db.timestamps_s, ws.pair_cache(db, queries, MatchParams()),
                                RetrievalParams(exclusion_s=1.0))
    vectors = ws.global_vectors.load_database_index(db).vectors_f32
    out = []
    for name, params in CONFIGS.items():
        bare = db.geometry()
        stand_in = self_check(bare, db.east_north_m, db.timestamps_s, db.keypoints_f32, db.descriptors_u8, vectors,
                              self_check_params(params).replace(fuse_views=False),
                              indices=list(self_checked_indices(len(db.images))),
                              cache=seeded_structure_cache(ws.load_structure(db, params)))
        ways = {AS_QUERIES: (ws.lever_gain(db, params), ws.self_check_poses(db, params)),
                STAND_IN: (lever_gain_from(stand_in), stand_in)}
        gain = ways[AS_QUERIES][0]
        measurer = PoseMeasurer(db.east_north_m, dataclasses.replace(db, lever_gain=gain).geometry(), queries.camera_model, params)
        measured = []
        for i in range(0, len(queries), every):
            q = queries.query(i)
            retriever.reset()
            measured.append((i, measurer.measure(q, retriever.retrieve(q, None))))
        for way, (way_gain, poses) in ways.items():
            rows = [{**measured_row(int(queries.frames[i]), m, truth[i]), "nees": _nees_at(m, truth[i], way_gain),
                     "side": m.side if m.source == "geometry" else None} for i, m in measured]
            out.append({"drive": folder.name, "protocol": protocol.key, "protocol_label": protocol.label,
                        "config": name, "self_check": way, "lever_gain": way_gain.as_dict(),
                        **_summary([p for p in poses if p.error_m is not None], rows)})
    return out, ws.self_check_poses(db, REFINED)


def _summary(poses: list, rows: list[dict]) -> dict:
    """The self-check's ``poses`` and the queries' ``rows`` by side, and the queries' figures over all."""
    posed = [r for r in rows if r["source"] == "geometry"]
    sides = {}
    for side in SIDES:
        mine = [r for r in posed if r["side"] == side]
        sides[side] = {"self_check_error_m": _errors([float(np.linalg.norm(p.error_m)) for p in poses
                                                      if p.side == side]),
                       "query_error_m": _errors([r["error_m"] for r in mine]),
                       "query_nees": calibration([r["nees"] for r in mine]).as_dict()}
    return {"sides": sides,
            "query_error_m": summary_of([r["error_m"] for r in rows], ("median", "p90", "max"), count=True),
            "query_nees": calibration([r["nees"] for r in posed]).as_dict(),
            "geotag_fallbacks": len(rows) - len(posed), "frames": rows}


def measure(a) -> dict:
    result = {"load_before": load_1min(), "cores": os.cpu_count(), "every": a.every, "configs": list(CONFIGS),
              "self_checks": [AS_QUERIES, STAND_IN], "setups": []}
    with tempfile.TemporaryDirectory(prefix="visloc-self-check-") as tmp:
        copy = Path(tmp) / "store.sqlite"
        shutil.copyfile(a.db, copy)  # the self-checks made here stay out of the store measured
        ws = Workspace(copy)
        pooled = []  # each setup's database is its own (0001: right, left; 0005; 0027)
        for folder in drives_of(a.data):
            for protocol in drive_protocols(folder):
                setups, poses = measure_setup(ws, folder, protocol, a.every)
                pooled += poses
                for s in setups:
                    result["setups"].append(s)
                    g, n = s["lever_gain"], s["query_nees"]
                    print(f"{s['drive']} {s['protocol']} {s['config']}, self-check {s['self_check']}: gain "
                          f"{g['both_sides']:.4f} / {g['one_side']:.4f}, error median "
                          f"{s['query_error_m']['median']:.3f} m, NEES {n['nees_mean']:.2f} "
                          f"({100 * n['inside_95']:.0f} % inside)", flush=True)
    # what a store without a self-check of its own takes (visloc.pose.uncertainty.DEFAULT_LEVER_GAIN)
    result["pooled_lever_gain"] = lever_gain_from(pooled, source="the shared drives' self-checks pooled").as_dict()
    result["load_after"] = load_1min()
    return result


def _pair(c: dict) -> str:
    return "–" if not c.get("n") else f"{c['median']:.3f} / {c['p80']:.3f} ({c['n']})"


def _nees(c: dict) -> str:
    return "–" if not c.get("n") else f"{c['nees_mean']:.2f}, {100 * c['inside_95']:.0f} % ({c['n']})"


def render(r: dict) -> str:
    lines = [SECTION.begin,
             "Whether each store's self-check still speaks for its queries, measured by `python "
             f"benchmarks/self_check_agreement.py --db out/results/visloc.sqlite --every {r['every']}` (load "
             f"{r['load_before']:.1f} at the start, {r['load_after']:.1f} at the end). The self-check poses every "
             "other database image from its neighbours, 1 s excluded: as the queries are posed (what ingest "
             "stores), or with two views in one PnP and no guided matching (a cheaper stand-in); each way's lever "
             "gain is fitted so that 80 % of its errors lie inside their 80 % ellipse. One query in "
             f"{r['every']} of the setup is posed once with the configuration (full-scan retrieval, 1 s exclusion, "
             "no filter), its covariance stated at each gain. Errors: median / 80th percentile (count), metres, "
             "against the image's geotag; NEES: the queries' mean against their own covariance, and the share "
             "inside the 95 % ellipse (2 and 95 % when honest). Where the self-check's errors grow while the "
             "queries' shrink, the gain over-states the queries' error and their ellipses come out too large.", "",
             "| drive | setup | configuration | self-check | lever gain both / one | self-check error, both sides | "
             "queries' error, both sides | self-check error, one side | queries' error, one side | "
             "queries' NEES, inside 95 % |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for s in r["setups"]:
        g, b, o = s["lever_gain"] or {}, s["sides"]["both"], s["sides"]["one"]
        gains = f"{g['both_sides']:.4f} / {g['one_side']:.4f}" if g else "–"
        lines.append(f"| {s['drive'].removesuffix('_sync')} | {s['protocol_label']} | {s['config']} | "
                     f"{s.get('self_check', AS_QUERIES)} | {gains} | "
                     f"{_pair(b['self_check_error_m'])} | {_pair(b['query_error_m'])} | "
                     f"{_pair(o['self_check_error_m'])} | {_pair(o['query_error_m'])} | {_nees(s['query_nees'])} |")
    if "pooled_lever_gain" in r:
        g = r["pooled_lever_gain"]
        lines += ["", f"Pooled over every setup's database at the defaults ({g['n_both']} poses with views on both "
                      f"sides, {g['n_one']} on one side), the self-check fits {g['both_sides']:.4f} / "
                      f"{g['one_side']:.4f}: the gain a store without a self-check of its own takes "
                      "(`DEFAULT_LEVER_GAIN`)."]
    lines += ["", SECTION.end]
    return "\n".join(lines)


def add_arguments(p) -> None:
    drives_and_store_arguments(p, "--data")
    p.add_argument("--every", type=int, default=2, help="pose every n-th query (default %(default)s: the frames the "
                                                        "self-check poses)")


if __name__ == "__main__":
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
