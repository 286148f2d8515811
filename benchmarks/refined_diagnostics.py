"""Where the refined measurement's error comes from, on one KITTI drive: the evidence behind the method notes.

    python benchmarks/refined_diagnostics.py [ROOT] --drive 2011_09_26_drive_0005 --db out/results/visloc.sqlite \
        [--every 2] --json out/diagnostics_0005.json

Same-camera protocol (queries and database from one camera, 1 s exclusion, full-scan retrieval).
Every --every-th query is measured with the default refined parameters under four conditions:

* database geotags from GPS, as stored (the product) / from the drive's own OXTS velocities,
  integrated from the first frame's GPS position (a track consistent with the car's motion), with
  the ground truth taken from the same track;
* views on both sides of the query where the database has them (the default) / the best views
  only (``both_sides=False``).

Each measurement's error is split along the direction of travel and across it. The ground truth
of each query is the stored GPS position (or the integrated track), with its stated accuracy.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from measuring import REPO  # noqa: F401 (puts this checkout's engine first on the path)
from visloc import InputError, Workspace  # noqa: E402
from visloc.params import REFINED, MatchParams, RetrievalParams  # noqa: E402
from visloc.pose.refined import PoseMeasurer  # noqa: E402
from visloc.retrieval.retrievers import WindowRetriever  # noqa: E402
from visloc.sources.drives import default_data_root, oxts_records, resolve_drive  # noqa: E402
from visloc.stats import summary_of  # noqa: E402


def velocity_track(gps_east_north_m: np.ndarray, records: np.ndarray, stamps_s: np.ndarray) -> np.ndarray:
    """East/north from the records' own velocities (ve, vn), trapezoid-integrated from the first GPS fix."""
    v = records[:, [7, 6]]
    out = np.zeros_like(gps_east_north_m)
    out[0] = gps_east_north_m[0]
    for k in range(1, len(out)):
        out[k] = out[k - 1] + 0.5 * (v[k - 1] + v[k]) * (stamps_s[k] - stamps_s[k - 1])
    return out


def stats(values) -> dict:
    return summary_of(values, ("median", "mean", "p90", "max"), count=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", nargs="?", type=Path, default=None)
    p.add_argument("--drive", required=True)
    p.add_argument("--camera", default="image_00")
    p.add_argument("--db", type=Path, required=True, help="a store holding the drive's camera ('visloc ingest')")
    p.add_argument("--every", type=int, default=2, help="measure every n-th query (default %(default)s)")
    p.add_argument("--json", type=Path, required=True)
    a = p.parse_args()
    try:
        folder = resolve_drive(a.root or default_data_root(), a.drive)
        ws = Workspace(a.db)
        db = ws.load_database(folder.name, a.camera)
        queries = ws.load_queries(folder.name, a.camera)
    except InputError as exc:
        print(f"refined_diagnostics: {exc}", file=sys.stderr)
        return 2
    records, stamps = oxts_records(folder)
    yaw = records[db.frames, 5]
    tracks = {"gps": db.east_north_m, "velocity": velocity_track(db.east_north_m, records, stamps)[db.frames]}
    cache = ws.pair_cache(db, queries, MatchParams())
    out = {"drive": folder.name, "camera": a.camera, "every": a.every, "conditions": {}}
    for track_name, track in tracks.items():
        geometry = db.geometry()
        geometry = replace(geometry, T_world_camera=geometry.T_world_camera.copy())
        geometry.T_world_camera[:, :2, 3] += (track - db.east_north_m)[:, :2]  # move each camera with its geotag
        for sides in (True, False):
            params = REFINED.replace(both_sides=sides)
            retriever = WindowRetriever(db.timestamps_s, cache, RetrievalParams(exclusion_s=1.0))
            measurer = PoseMeasurer(track, geometry, queries.camera_model, params)
            rows = []
            for i in range(0, len(queries), a.every):
                q = queries.query(i)
                retriever.reset()
                m = measurer.measure(q, retriever.retrieve(q, None))
                if m.source != "geometry":
                    rows.append({"frame": int(queries.frames[i]), "geometry": False, "reason": m.fallback_reason})
                    continue
                e = np.asarray(m.east_north_m) - track[i]
                forward = np.array([math.cos(yaw[i]), math.sin(yaw[i])])
                left = np.array([-forward[1], forward[0]])
                views = [int(db.frames[v]) for v in m.view_indices]
                rows.append({"frame": int(queries.frames[i]), "geometry": True, "error_m": float(np.linalg.norm(e)),
                             "along_m": float(e @ forward), "across_m": float(e @ left), "views": views,
                             "sides": "both" if min(views) < queries.frames[i] < max(views) else "one",
                             "sigma_m": m.sigma_m})
            g = [r for r in rows if r["geometry"]]
            name = f"{track_name}_{'both_sides' if sides else 'best_views'}"
            out["conditions"][name] = {
                "error_m": stats([r["error_m"] for r in g]), "along_m_mean": float(np.mean([r["along_m"] for r in g])),
                "abs_along_m_mean": float(np.mean([abs(r["along_m"]) for r in g])),
                "abs_across_m_mean": float(np.mean([abs(r["across_m"]) for r in g])),
                "fallbacks": len(rows) - len(g), "steps": rows}
            c = out["conditions"][name]
            print(f"{name:28s} error median/mean/p90/max {c['error_m']['median']:.3f} {c['error_m']['mean']:.3f} "
                  f"{c['error_m']['p90']:.3f} {c['error_m']['max']:.3f}  along mean {c['along_m_mean']:+.3f}  "
                  f"|along| {c['abs_along_m_mean']:.3f}  |across| {c['abs_across_m_mean']:.3f}  "
                  f"fallbacks {c['fallbacks']}", flush=True)
    # how far the GPS track strays from the one its own velocities describe, over 1 s
    gps, vel = tracks["gps"], tracks["velocity"]
    drift = [float(np.linalg.norm((gps[k + 10] - gps[k]) - (vel[k + 10] - vel[k]))) for k in range(len(gps) - 10)]
    out["gps_vs_velocity_over_1s_m"] = stats(drift)
    print(f"GPS vs its own velocities over 1 s: median {np.median(drift):.3f} m, max {np.max(drift):.3f} m")
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps(out, indent=1))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
