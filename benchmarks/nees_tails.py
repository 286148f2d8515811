"""What the refined measurements that claim too small an ellipse have in common, drive by drive.

    python benchmarks/nees_tails.py [--results out/results]   # after python scripts/results.py run
    python benchmarks/nees_tails.py --page                     # its section of docs/performance.md from the JSON

Reads the refined evaluations the results page was made from (``out/results/drives.json`` and the evaluation
JSON of each drive and protocol it lists) and takes each query frame's geometry measurement once (the series
of an evaluation measure a frame up to once per step). A measurement is in the tail when its NEES against its
own covariance exceeds the 95 % ellipse's 5.99: an honest covariance puts 5 % there. Per drive and protocol:
how many are, and how the tail differs from the rest in what a covariance could know: the views' side, how
many views were posed apart, the lever, the share of the covariance the views' spread makes, the error along
the vehicle's heading and across it, and the turn (the largest heading change between the query and its
views, along the drive's own track); and the calibration by the number of views. Nothing is measured again and nothing of the engine runs: this reads
what the evaluation wrote. Writes ``docs/results/nees_tails.json`` and its section of docs/performance.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from measuring import REPO, Section, commit
from visloc.geo import LocalFrame  # noqa: E402
from visloc.pose.uncertainty import along_across  # noqa: E402
from visloc.stats import CHI2_2DOF_95  # noqa: E402

SECTION = Section("nees-tails", "nees_tails", REPO / "docs" / "performance.md")
TURN_DEG = 10.0  # a query this far or more from its views' headings is in a turn
TRACK_HALF_WINDOW = 3  # the track's heading at a frame: from the truth 3 frames before to 3 after
VIEW_GROUPS = {"2-3 views": (2, 3), "4-5 views": (4, 5), "6 or more": (6, 10_000)}  # views posed apart


def track_heading_deg(frames: list[int], east_north_m: np.ndarray) -> dict[int, float]:
    """Compass heading of the drive's own track at each frame, from its truth positions either side."""
    out = {}
    for i, f in enumerate(frames):
        a, b = east_north_m[max(0, i - TRACK_HALF_WINDOW)], east_north_m[min(len(frames) - 1, i + TRACK_HALF_WINDOW)]
        d = b - a
        out[f] = float(np.degrees(np.arctan2(d[0], d[1])) % 360.0) if np.hypot(*d) > 0 else float("nan")
    return out


def frame_rows(evaluation: dict) -> list[dict]:
    """Each query frame's geometry measurement once, with what the tail analysis needs."""
    first: dict[int, dict] = {}
    for step in (st for s in evaluation["series"] for st in s):
        first.setdefault(step["query_frame"], step)
    frames = sorted(first)
    local = LocalFrame(first[frames[0]]["truth_lat_deg"], first[frames[0]]["truth_lon_deg"])
    truth = np.array([local.to_local(first[f]["truth_lat_deg"], first[f]["truth_lon_deg"]) for f in frames])
    heading = track_heading_deg(frames, truth.reshape(-1, 2))
    rows = []
    for f in frames:
        st = first[f]
        if st["measurement_source"] != "geometry" or st.get("measurement_nees") is None:
            continue
        e = (np.asarray(local.to_local(st["measurement_lat_deg"], st["measurement_lon_deg"]), float).reshape(2)
             - np.asarray(local.to_local(st["truth_lat_deg"], st["truth_lon_deg"]), float).reshape(2))
        u, v = along_across(st["measurement_heading_deg"])
        views = [heading[j] for j in st["view_db_frames"] if j in heading and np.isfinite(heading[j])]
        turn = max((abs((h - heading[f] + 180.0) % 360.0 - 180.0) for h in views), default=float("nan"))
        terms = st["measurement_term_sigma_m"]
        rows.append({"frame": f, "nees": st["measurement_nees"], "side": st["measurement_side"],
                     "views": len(st["view_db_frames"]), "lever_m": st["measurement_lever_m"],
                     "views_share": terms["views"] ** 2 / max(st["measurement_sigma_m"] ** 2, 1e-30),
                     "along_m": float(e @ u), "across_m": float(e @ v), "turn_deg": turn})
    return rows


def describe(rows: list[dict]) -> dict:
    """What a group of measurements is like (None for an empty group)."""
    if not rows:
        return None
    nees = np.array([r["nees"] for r in rows])
    turned = [r for r in rows if r["turn_deg"] >= TURN_DEG]
    return {"n": len(rows), "nees_mean": float(nees.mean()), "nees_median": float(np.median(nees)),
            "one_side": float(np.mean([r["side"] == "one" for r in rows])),
            "views_median": float(np.median([r["views"] for r in rows])),
            "lever_m_median": float(np.median([r["lever_m"] for r in rows])),
            "views_share_median": float(np.median([r["views_share"] for r in rows])),
            "along_rms_m": float(np.sqrt(np.mean([r["along_m"] ** 2 for r in rows]))),
            "across_rms_m": float(np.sqrt(np.mean([r["across_m"] ** 2 for r in rows]))),
            "in_turn": len(turned) / len(rows)}


def measure(a) -> dict:
    results = Path(a.results)
    suite = json.loads((results / "drives.json").read_text())
    out = {"commit": commit(), "evaluations": {}}
    for drive, drive_rows in suite["drives"].items():
        for row in drive_rows:
            if row["mode"] == "paper" or not (results / row.get("file", "")).is_file():
                continue
            rows = frame_rows(json.loads((results / row["file"]).read_text()))
            tail = [r for r in rows if r["nees"] > CHI2_2DOF_95]
            turned = [r for r in rows if r["turn_deg"] >= TURN_DEG]
            straight = [r for r in rows if not r["turn_deg"] >= TURN_DEG]
            by_views = {label: [r for r in rows if low <= r["views"] <= high] for label, (low, high) in VIEW_GROUPS.items()}
            out["evaluations"][f"{drive}, {row['protocol_label']}"] = {
                "file": row["file"], "tail": describe(tail), "rest": describe([r for r in rows if r not in tail]),
                "all": describe(rows), "turn": describe(turned), "straight": describe(straight),
                "by_views": {label: {"n": len(g), "nees_mean": float(np.mean([r["nees"] for r in g])) if g else None,
                                     "inside_95": float(np.mean([r["nees"] <= CHI2_2DOF_95 for r in g])) if g else None}
                             for label, g in by_views.items()}}
    return out


def _f(d: dict | None, key: str, fmt: str = ".2f") -> str:
    return "-" if not d else format(d[key], fmt)


def render(r: dict) -> str:
    lines = [SECTION.begin, "",
             "**Where the ellipses are too small.** Each query frame's refined measurement once, from the "
             "evaluations of the results page (`python benchmarks/nees_tails.py`, reading "
             f"`out/results/`; commit `{r['commit']}`). The tail: NEES above 5.99, outside the 95 % ellipse, where "
             "an honest covariance puts 5 %. Turn: the largest heading change between the query and its views along "
             f"the drive's own track, {TURN_DEG:g} degrees or more. Along / across: the error along the vehicle's "
             "heading and across it (RMS). Views' share: the part of the covariance the views' spread makes "
             "(median).", "",
             "| drive / protocol | measurements | tail | tail: NEES median, one side, views, lever (m), views' share "
             "| rest: the same | error along / across (m): tail | rest | NEES mean, median: in a turn | "
             "straight | tail in a turn |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, e in r["evaluations"].items():
        t, rest, a = e["tail"], e["rest"], e["all"]

        def who(d):
            return ("-" if not d else f"{d['nees_median']:.1f}, {100 * d['one_side']:.0f} %, {d['views_median']:g}, "
                    f"{d['lever_m_median']:.1f}, {100 * d['views_share_median']:.0f} %")

        def err(d):
            return "-" if not d else f"{d['along_rms_m']:.3f} / {d['across_rms_m']:.3f}"

        def nees(d):
            return "-" if not d else f"{d['nees_mean']:.2f}, {d['nees_median']:.2f} ({d['n']})"

        lines.append(f"| {name} | {a['n']} | {0 if not t else t['n']} ({100 * (0 if not t else t['n']) / a['n']:.0f} %) "
                     f"| {who(t)} | {who(rest)} | {err(t)} | {err(rest)} | {nees(e['turn'])} | {nees(e['straight'])} "
                     f"| {_f(t, 'in_turn', '.0%')} |")
    lines += ["", "By the number of views a measurement was posed on (each alone, their positions averaged, their "
              "spread in its covariance): NEES mean, share inside the 95 % ellipse (measurements).", "",
              "| drive / protocol | " + " | ".join(VIEW_GROUPS) + " |", "|---|" + "---|" * len(VIEW_GROUPS)]
    for name, e in r["evaluations"].items():
        cells = [("-" if not g["n"] else f"{g['nees_mean']:.2f}, {100 * g['inside_95']:.0f} % ({g['n']})")
                 for g in e["by_views"].values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", SECTION.end]
    return "\n".join(lines)


def add_arguments(p) -> None:
    p.add_argument("--results", default=str(REPO / "out" / "results"),
                   help="the folder python scripts/results.py run wrote (default out/results)")


if __name__ == "__main__":
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
