"""``visloc bench``, section ``refined_fast``: the exact and the camera-rate refined paths on the same frames.

Both run as ``visloc track`` runs: every ``stride``-th frame of the drive in order, the filter's
time step the interval between them, the evaluation protocol's 1 s exclusion window (so a
same-camera database never gives a frame its own image or its immediate neighbours), the query
camera against the database camera the drive's other sections use. The exact path first, then
the fast one, in one process: per frame, end-to-end latency (SIFT from the decoded image,
retrieval, geometry, filter) and the errors of the measurement and of the filter's estimate
against the frame's geotag.
"""

from __future__ import annotations

import numpy as np

from visloc.params import PAPER_FILTER, TrackParams
from visloc.progress import progress_reporter
from visloc.sources.drives import Drive
from visloc.protocols.track import TrackRun, run_track, track_filter, track_localizer
from visloc.store.workspace import Workspace

EXCLUSION_S = 1.0


def _path_summary(run: TrackRun) -> dict:
    s = run.summary()
    return {"latency_ms": s["latency_ms"], "stages_ms": s["stages_ms"], "final_error_m": s["error_m"],
            "measurement_error_m": s["measurement_error_m"],
            "geometry_measurement_error_m": s["geometry_measurement_error_m"],
            "geometry_fraction": s["geometry_fraction"], "sustained_hz": s["sustained_hz"], "wall_s": s["wall_s"],
            "per_frame": [{"frame": f.frame, "latency_ms": f.latency_ms, "error_m": f.error_m,
                           "measurement_error_m": f.measurement_error_m, "source": f.measurement_source}
                          for f in run.frames]}


def refined_fast(ws: Workspace, queries: Drive, db_camera: str, stride: int, say) -> dict:
    """Both refined paths on every ``stride``-th frame of ``queries`` against ``db_camera`` of the same drive."""
    db = ws.load_database(queries.source, db_camera)
    out: dict = {"queries": queries.name, "database": f"{db.source}/{db.camera}", "stride": stride,
                 "exclusion_s": EXCLUSION_S}
    runs = {}
    for name, fast in (("exact", False), ("fast", True)):
        params = TrackParams(fast=fast, exclusion_s=EXCLUSION_S, stride=stride)
        filt = track_filter(queries, params, PAPER_FILTER)
        localizer, sift = track_localizer(ws, db, queries.camera_model, filt, params, query_what=queries.name)
        runs[name] = run_track(localizer, queries, sift, db, params,
                               progress=progress_reporter(f"bench refined {name} path {queries.name}", "frames"))
        out[name] = _path_summary(runs[name])
        out[name]["params"] = runs[name].params
        lat, err = out[name]["latency_ms"], out[name]["final_error_m"]
        say(f"  refined {name:5s} path: latency p50 {lat['p50']:.0f} ms, p95 {lat['p95']:.0f} ms; estimate error "
            f"mean {err['mean']:.3f} m, median {err['median']:.3f} m over {len(runs[name].frames)} frames")
    ratio = [e.latency_ms / f.latency_ms for e, f in zip(runs["exact"].frames, runs["fast"].frames)]
    out["frames"] = len(ratio)
    out["latency_ms"] = {"p50": out["fast"]["latency_ms"]["p50"], "p95": out["fast"]["latency_ms"]["p95"]}
    out["stages_ms"] = out["fast"]["stages_ms"]
    out["speed_ratio_exact_over_fast"] = {"p50": float(np.median(ratio)), "min": float(np.min(ratio)),
                                          "max": float(np.max(ratio))}
    out["final_error_m"] = {"exact": out["exact"]["final_error_m"]["mean"], "fast": out["fast"]["final_error_m"]["mean"]}
    r = out["speed_ratio_exact_over_fast"]
    say(f"  speed ratio exact / fast per frame: median {r['p50']:.0f}x (min {r['min']:.0f}x, max {r['max']:.0f}x)")
    return out


def refined_fast_targets(section: dict) -> dict:
    """The camera-rate targets: p50 <= 100 ms and p95 <= 150 ms end to end, at least 20x faster than the exact
    path, and a mean estimate error within 10 % (or 2 cm, whichever is larger) of the exact path's."""
    lat, r, e = section["latency_ms"], section["speed_ratio_exact_over_fast"], section["final_error_m"]
    allowed_m = max(0.1 * e["exact"], 0.02)
    return {
        "refined_fast_latency": {"met": lat["p50"] <= 100 and lat["p95"] <= 150,
                                 "value": f"refined fast path p50 {lat['p50']:.0f} ms, p95 {lat['p95']:.0f} ms"},
        "refined_fast_speed": {"met": r["p50"] >= 20, "value": f"exact / fast median {r['p50']:.0f}x"},
        "refined_fast_accuracy": {"met": e["fast"] <= e["exact"] + allowed_m,
                                  "value": f"mean estimate error fast {e['fast']:.3f} m vs exact {e['exact']:.3f} m "
                                           f"(allowed +{allowed_m:.3f} m)"},
    }
