"""The camera-rate part of the results page: ``visloc track`` per drive and setup, and the bench's
``refined_fast`` section (used by scripts/results.py)."""

from __future__ import annotations


def digest_track(report: dict) -> dict:
    """A ``visloc track`` JSON without its per-frame rows."""
    return {k: v for k, v in report.items() if k != "per_frame"}


def digest_refined_fast(section: dict) -> dict:
    out = {k: section[k] for k in ("queries", "database", "stride", "exclusion_s", "frames", "latency_ms",
                                   "stages_ms", "speed_ratio_exact_over_fast", "final_error_m")}
    for path in ("exact", "fast"):
        out[path] = {k: v for k, v in section[path].items() if k not in ("per_frame", "params")}
    return out


def _c(value, fmt: str = ".2f") -> str:
    return "-" if value is None else format(value, fmt)


def _cal(k: dict) -> str:
    return "-" if not k or not k["n"] else f"{_c(k['nees_mean'])}, {_c(100 * k['inside_95'], '.0f')} % ({k['n']})"


def coverage_cells(coverage: dict, levels: list) -> str:
    """A calibration curve's cells: the share (%) inside each nominal level's ellipse, "-" where not measured."""
    return " | ".join(_c(100 * coverage[p], ".0f") if p in coverage else "-" for p in levels)


def render_camera_rate(d: dict, add) -> None:
    """The "Camera rate" section: every track run, then the bench's exact-against-fast comparison."""
    # sorted: the digest is stored with sorted keys, and the page must render the same from it
    tracks = dict(sorted((d.get("tracks") or {}).items()))
    bench = {k: v["refined_fast"] for k, v in sorted(d.get("bench", {}).items()) if v.get("refined_fast")}
    if not tracks and not bench:
        return
    add("## Camera rate")
    add("")
    add("`visloc track` localizes every frame of a drive in order, as a vehicle would, on the camera-rate path "
        "(the database's stored structure and global vectors, the filter's gate, SIFT on the frame at three quarters of its size). "
        "Latency per frame counts SIFT from the decoded image, retrieval, geometry and the filter; the sustained "
        "rate is frames per second of wall time over the whole run, reading included. Errors are against each "
        "frame's own geotag. The 1 s exclusion window is on in every run (a same-camera database would otherwise "
        "give a frame its own image).")
    add("")
    if tracks:
        add("| drive / setup | frames | latency p50 / p95 / max (ms) | SIFT / retrieval / geometry p50 (ms) | "
            "sustained (frames/s) | estimate error mean / median / p90 / max (m) | measurement error mean / median "
            "(m) | posed by geometry |")
        add("|---|---|---|---|---|---|---|---|")
        for name, t in tracks.items():
            lat, st, e, m = t["latency_ms"], t["stages_ms"], t["error_m"], t["measurement_error_m"]
            add(f"| {name} | {t['frames']} | {_c(lat['p50'], '.0f')} / {_c(lat['p95'], '.0f')} / "
                f"{_c(lat['max'], '.0f')} | {_c(st['sift_ms'], '.0f')} / {_c(st['retrieval_ms'], '.0f')} / "
                f"{_c(st['geometry_ms'], '.0f')} | {_c(t['sustained_hz'], '.1f')} | {_c(e['mean'], '.3f')} / "
                f"{_c(e['median'], '.3f')} / {_c(e['p90'], '.3f')} / {_c(e['max'], '.3f')} | {_c(m['mean'], '.3f')} / "
                f"{_c(m['median'], '.3f')} | {_c(100 * t['geometry_fraction'], '.0f')} % |")
        add("")
        for name, t in tracks.items():
            add(f"- {name}: `{t['command']}`")
        add("")
        if any(t.get("calibration") for t in tracks.values()):
            add("How honest its ellipses are at the camera's rate (NEES, 2 if honest, and the share inside the 95 % "
                "ellipse; the geometry measurements against their own covariance, the estimates against the "
                "filter's P, which models the error consecutive measurements share: see the "
                "[method notes](method.md)):")
            add("")
            add("| drive / setup | measurements: all | views on both sides | on one side | estimates |")
            add("|---|---|---|---|---|")
            for name, t in tracks.items():
                k = t.get("calibration")
                if not k:
                    continue
                add(f"| {name} | {_cal(k['all'])} | {_cal(k['both'])} | {_cal(k['one'])} | "
                    f"{_cal(t['estimate_calibration'])} |")
            add("")
            curves = {name: t for name, t in tracks.items() if (t.get("estimate_calibration") or {}).get("coverage")}
            if curves:
                levels = list(next(iter(curves.values()))["estimate_calibration"]["coverage"])
                add("Calibration curves at the camera's rate: the share of the geometry measurements (against R) and "
                    "of the estimates (against P) inside each nominal ellipse (the nominal share itself if honest):")
                add("")
                add("| drive / setup | of | " + " | ".join(f"{float(p) * 100:g} %" for p in levels) + " |")
                add("|---|---|" + "---|" * len(levels))
                for name, t in curves.items():
                    for label, k in (("measurements", t["calibration"]["all"]), ("estimates", t["estimate_calibration"])):
                        add(f"| {name} | {label} | {coverage_cells(k.get('coverage') or {}, levels)} |")
                add("")
    if bench:
        add("`visloc bench` runs the exact refined path (the paper's retrieval, every candidate verified, "
            "full-resolution SIFT) and the camera-rate path on the same frames of each drive, one after the other in "
            "one process, both as `visloc track` runs them. The speed ratio is per frame, exact over fast.")
        add("")
        add("| drive | frames (every n-th) | exact: latency p50 / p95 (ms) | camera-rate: latency p50 / p95 (ms) | "
            "speed ratio median (min-max) | estimate error mean, exact -> camera-rate (m) | measurement error mean, "
            "exact -> camera-rate (m) | posed by geometry, exact -> camera-rate |")
        add("|---|---|---|---|---|---|---|---|")
        for drive, b in bench.items():
            ex, fa, r = b["exact"], b["fast"], b["speed_ratio_exact_over_fast"]
            add(f"| {drive}: {b['queries'].split('/')[-1]} against {b['database'].split('/')[-1]} | {b['frames']} "
                f"({b['stride']}) | {_c(ex['latency_ms']['p50'], '.0f')} / {_c(ex['latency_ms']['p95'], '.0f')} | "
                f"{_c(fa['latency_ms']['p50'], '.0f')} / {_c(fa['latency_ms']['p95'], '.0f')} | "
                f"{_c(r['p50'], '.0f')}x ({_c(r['min'], '.0f')}-{_c(r['max'], '.0f')}x) | "
                f"{_c(b['final_error_m']['exact'], '.3f')} -> {_c(b['final_error_m']['fast'], '.3f')} | "
                f"{_c(ex['measurement_error_m']['mean'], '.3f')} -> {_c(fa['measurement_error_m']['mean'], '.3f')} | "
                f"{_c(100 * ex['geometry_fraction'], '.0f')} % -> {_c(100 * fa['geometry_fraction'], '.0f')} % |")
        add("")
        add("Targets (each drive): camera-rate latency p50 at most 100 ms and p95 at most 150 ms; at least 20x faster "
            "than the exact path; mean estimate error within 10 % (or 2 cm, whichever is larger) of the exact "
            "path's.")
        add("")
        for drive, b in sorted(d["bench"].items()):
            targets = {k: v for k, v in (b.get("targets") or {}).items() if k.startswith("refined_fast")}
            if targets:
                add(f"- {drive}: " + "; ".join(f"{k.removeprefix('refined_fast_')} "
                                               f"{'met' if v['met'] else 'NOT met'} ({v['value']})"
                                               for k, v in sorted(targets.items())))
        add("")
