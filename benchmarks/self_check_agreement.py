"""Does a store's self-check still speak for its queries? The lever gain it fits beside the queries' own errors.

    python benchmarks/self_check_agreement.py [--data ROOT] [--db out/results/visloc.sqlite] [--every 2]
    python benchmarks/self_check_agreement.py --page   # its section of docs/performance.md from the JSON

A refined measurement's ellipse grows with the lever to its nearest view at a gain that each store measures on
itself: ingest poses every other database image from its neighbours (the 1 s exclusion, two views, one PnP, no
guided matching: a cheaper pose than a query's) and fits the gain that holds those poses' errors
(``visloc.pose.selfcheck``). The gain is only as good as that cheaper pose's errors are a stand-in for the
queries'. A change to how the structure is built can move the two apart: it can make the queries' poses better
while the self-check's get worse, and the ellipses then come out too large.

This measures that, on every drive and setup of the data root, for each configuration below: the self-check is
made with the configuration on a copy of the store (the store itself is left as it is), its gain fitted, and
every ``--every``-th query of the setup posed once with that configuration and that gain (full-scan retrieval,
1 s exclusion, no filter), against its geotag. Per side (views on both sides, on one side): the self-check's
errors and the queries' (median, 80th percentile: the level the gain is fitted at), the queries' NEES against
their own covariance (the truth shares the map's receiver; 2 when honest, 95 % inside the 95 % ellipse).
Writes ``docs/results/self_check_agreement.json`` and its section of docs/performance.md.
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
from visloc.pose.uncertainty import SIDES, calibration
from visloc.protocols.suite import drive_protocols, drives_of
from visloc.retrieval.retrievers import WindowRetriever
from visloc.stats import summary_of
from visloc.store.build import build_self_check

SECTION = Section("self-check-agreement", "self_check_agreement", REPO / "docs" / "performance.md")
CONFIGS = {"defaults": REFINED,
           "position prior 5 mm": REFINED.replace(relative_geotag_sigma_m=0.005)}


def _errors(values: list[float]) -> dict:
    return summary_of(values, ("median", "p80"), count=True) if values else {"n": 0}


def measure_setup(ws: Workspace, folder: Path, protocol, every: int) -> list[dict]:
    """One drive's setup under each configuration: the self-check made with it (where the store has none), its
    gain, its poses' errors by side, and every ``every``-th query posed with it and that gain. The database,
    the queries and their match counts are read once for every configuration."""
    for params in CONFIGS.values():
        build_self_check(ws, folder.name, protocol.db_camera, params)
    db = ws.load_database(folder.name, protocol.db_camera)
    queries = ws.load_queries(folder.name, protocol.query_camera)
    truth = db.frame.to_local(queries.lat_deg, queries.lon_deg)
    retriever = WindowRetriever(db.timestamps_s, ws.pair_cache(db, queries, MatchParams()),
                                RetrievalParams(exclusion_s=1.0))
    out = []
    for name, params in CONFIGS.items():
        gain = ws.lever_gain(db, params)
        poses = [p for p in ws.self_check_poses(db, params) if p.error_m is not None]
        geometry = dataclasses.replace(db, lever_gain=gain).geometry()
        measurer = PoseMeasurer(db.east_north_m, geometry, queries.camera_model, params)
        rows = []
        for i in range(0, len(queries), every):
            q = queries.query(i)
            retriever.reset()
            m = measurer.measure(q, retriever.retrieve(q, None))
            rows.append({**measured_row(int(queries.frames[i]), m, truth[i]),
                         "side": m.side if m.source == "geometry" else None})
        out.append({"drive": folder.name, "protocol": protocol.key, "protocol_label": protocol.label,
                    "config": name, "lever_gain": gain.as_dict() if gain is not None else None,
                    **_summary(poses, rows)})
    return out


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
              "setups": []}
    with tempfile.TemporaryDirectory(prefix="visloc-self-check-") as tmp:
        copy = Path(tmp) / "store.sqlite"
        shutil.copyfile(a.db, copy)  # the self-checks made here stay out of the store measured
        ws = Workspace(copy)
        for folder in drives_of(a.data):
            for protocol in drive_protocols(folder):
                for s in measure_setup(ws, folder, protocol, a.every):
                    result["setups"].append(s)
                    g, n = s["lever_gain"] or {}, s["query_nees"]
                    print(f"{s['drive']} {s['protocol']} {s['config']}: gain {g.get('both_sides', float('nan')):.4f} / "
                          f"{g.get('one_side', float('nan')):.4f}, error median {s['query_error_m']['median']:.3f} m, "
                          f"NEES {n['nees_mean']:.2f} ({100 * n['inside_95']:.0f} % inside)", flush=True)
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
             "other database image from its neighbours, 1 s excluded, with two views in one PnP; the lever gain is "
             "fitted so that 80 % of its errors lie inside their 80 % ellipse. One query in "
             f"{r['every']} of the setup is posed once with the same configuration and that gain (full-scan "
             "retrieval, 1 s exclusion, no filter). Errors: median / 80th percentile (count), metres, against the "
             "image's geotag; NEES: the queries' mean against their own covariance, and the share inside the 95 % "
             "ellipse (2 and 95 % when honest). Where the self-check's errors grow while the queries' shrink, the "
             "gain over-states the queries' error and their ellipses come out too large.", "",
             "| drive | setup | configuration | lever gain both / one | self-check error, both sides | "
             "queries' error, both sides | self-check error, one side | queries' error, one side | "
             "queries' NEES, inside 95 % |",
             "|---|---|---|---|---|---|---|---|---|"]
    for s in r["setups"]:
        g, b, o = s["lever_gain"] or {}, s["sides"]["both"], s["sides"]["one"]
        gains = f"{g['both_sides']:.4f} / {g['one_side']:.4f}" if g else "–"
        lines.append(f"| {s['drive'].removesuffix('_sync')} | {s['protocol_label']} | {s['config']} | {gains} | "
                     f"{_pair(b['self_check_error_m'])} | {_pair(b['query_error_m'])} | "
                     f"{_pair(o['self_check_error_m'])} | {_pair(o['query_error_m'])} | {_nees(s['query_nees'])} |")
    lines += ["", SECTION.end]
    return "\n".join(lines)


def add_arguments(p) -> None:
    drives_and_store_arguments(p, "--data")
    p.add_argument("--every", type=int, default=2, help="pose every n-th query (default %(default)s: the frames the "
                                                        "self-check poses)")


if __name__ == "__main__":
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
