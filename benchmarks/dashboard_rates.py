"""How honest the dashboard's camera-rate mode is at each query rate: the rate the page gives the mode.

    python benchmarks/dashboard_rates.py [--db out/results/visloc.sqlite]
    python benchmarks/dashboard_rates.py --page   # its section of docs/dashboard.md from the JSON

For every drive of the store whose image_00 serves as queries, against each of its cameras as the database, the
refined-fast mode run as the live page runs it, from the drive's start, with the evaluation protocol's 1 s exclusion
window, at 1 Hz and at 10 Hz, then ``visloc.track_drive`` (the paper's filter with the query interval as its time
step): at 10 Hz, the camera's rate, following points on the drive's images (``visloc.follow_drive``, what the page
runs where it can read them) and on the stored query features, every query localized in full
(``visloc.match_drive``, what it runs where it cannot, and at 1 Hz). Per run: the estimate's mean error against the frames' geotags and how honest its ellipses are
(NEES, 2 when honest, and the share of errors inside the 95 % ellipse). Writes docs/results/dashboard_rates.json.
"""

from __future__ import annotations

import numpy as np

from measuring import REPO, Section, drives_and_store_arguments, load_1min, load_line

SECTION = Section("dashboard-rates", "dashboard_rates", REPO / "docs" / "dashboard.md")
RATES_HZ = (1.0, 10.0)
FOLLOWED_HZ = (10.0,)  # the page follows points at the camera's own rate only (visloc.follows_points)
EXCLUSION_S = 1.0


PATHS = {"following": "following points", "stored": "on the stored features"}


def measure_rate(db, queries, drive, sift, stored: dict, index, rate_hz: float, path: str) -> dict:
    """The mode at ``rate_hz`` over ``queries`` against ``db`` (its stored structure and global-vector index), on
    ``path``: "following" (``drive``, the queries' images, read with the store's ``sift``) or "stored"."""
    import visloc
    from visloc.pose.uncertainty import calibration

    method = visloc.REFINED_FAST_METHOD
    retrieval = visloc.PAPER_RETRIEVAL.replace(exclusion_s=EXCLUSION_S)
    filter_params = visloc.PAPER_FILTER.replace(dt_s=1.0 / rate_hz)
    indices = visloc.drive_query_indices(queries.timestamps_s, 0.0, 1.0 / rate_hz)
    if path == "following":
        matches = visloc.follow_drive(drive, queries, db, sift, retrieval, indices, method=method,
                                      filter_params=filter_params, stored=stored, shortlist_index=index)
    else:
        matches = visloc.match_drive(queries, db, visloc.PAPER_MATCH, retrieval, indices, method=method,
                                     stored=stored, shortlist_index=index, filter_params=filter_params,
                                     structures=visloc.StructureCache())
    records = visloc.track_drive(matches, queries, db, filter_params)
    errors = [r.estimate_error_m for r in records if r.estimate_error_m is not None]
    cal = calibration([r.estimate_nees for r in records])
    return {"queries": len(records), "estimate_error_mean_m": float(np.mean(errors)),
            "estimate_nees": cal.nees_mean, "estimate_inside_95": cal.inside_95,
            "tracked": sum(1 for k in matches.kinds if k == "tracked")}


def measure(a) -> dict:
    import visloc

    ws = visloc.Workspace(a.db, read_only=True)
    drives = sorted({d.source for d in ws.drives() if d.camera == "image_00"})
    out = {"store": str(a.db), "exclusion_s": EXCLUSION_S, "load_1min_before": load_1min(), "setups": []}
    for source in drives:
        queries = ws.load_queries(source, "image_00")
        drive = visloc.open_series(a.root, source, "image_00")
        for camera in sorted(d.camera for d in ws.drives() if d.source == source):
            db = ws.load_database(source, camera)
            fast = visloc.REFINED_FAST_METHOD
            stored = ws.load_structure(db, fast.pose)  # read once: every rate runs on the same store
            index = ws.global_vectors.load_database_index(db, fast.shortlist)
            runs = {path: {f"{r:g}": measure_rate(db, queries, drive, ws.sift_params, stored, index, r, path)
                           for r in (FOLLOWED_HZ if path == "following" else RATES_HZ)} for path in PATHS}
            print(f"{source} image_00 against {camera}: " + "; ".join(
                f"{p} {k} Hz {v['estimate_error_mean_m']:.3f} m NEES {v['estimate_nees']:.2f}, "
                f"{v['estimate_inside_95']:.0%}" for p, rates in runs.items() for k, v in rates.items()), flush=True)
            out["setups"].append({"drive": source, "queries": "image_00", "database": camera, "runs": runs})
    out["load_1min_after"] = load_1min()
    return out


def render(result: dict) -> str:
    runs = result["setups"][0]["runs"]
    columns = [("stored", r) for r in runs["stored"] if r not in runs["following"]] + \
        [(p, r) for r in runs["following"] for p in PATHS]
    head = " | ".join(f"{r} Hz {PATHS[p]}" for p, r in columns)
    lines = [SECTION.begin, "The refined-fast mode as the page runs it, from each drive's start, measured by "
             "`python benchmarks/dashboard_rates.py` (image_00's frames as queries, "
             f"{result['exclusion_s']:g} s exclusion window): at the camera's rate, following points on the drive's "
             "images, as the page does where it can read them, and every query localized in full on the stored "
             "features, as it does where it cannot; below the camera's rate, every query in full. Each cell: "
             "queries, estimate error mean (m), NEES (2 when honest), share inside the 95 % ellipse.", "",
             f"| drive | queries against | {head} |", "|---|---|" + "---|" * len(columns)]
    for s in result["setups"]:
        cells = " | ".join(f"{v['queries']}, {v['estimate_error_mean_m']:.3f}, {v['estimate_nees']:.2f}, "
                           f"{v['estimate_inside_95']:.0%}" for v in (s["runs"][p][r] for p, r in columns))
        lines.append(f"| {s['drive']} | {s['queries']} against {s['database']} | {cells} |")
    lines += ["", load_line(result), SECTION.end]
    return "\n".join(lines)


def main() -> int:
    return SECTION.main(__doc__, measure, render, drives_and_store_arguments)


if __name__ == "__main__":
    raise SystemExit(main())
