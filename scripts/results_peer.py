"""The results page's comparison with the COLMAP-style peer (../shared/peer), frame by frame.

The peer measures single measurements (no filter) on some frames of a drive, under the same protocol as
``visloc evaluate --mode refined``: the same cameras and the 1 s exclusion. Its JSON holds each query's error
under ``queries[i].variants.counts.pnp["12.0"]``, and its position, measured here against visloc's truth. visloc's error on a frame is its refined measurement at that
frame, the median over the series that pose it (a frame is posed once per series it lies in; the series differ
only in the retrieval window). A peer query whose pose failed counts with the error of its fallback geotag.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from visloc.geo import geodesic_distance_m, moved_deg
from visloc.stats import summary_of

PEER_VARIANT, PEER_THRESHOLD = "counts", "12.0"  # the peer's default variant and its PnP threshold, px


def protocol_key(query_camera: str, db_camera: str) -> str | None:
    """The evaluate-drives protocol key of a (query, database) camera pair, as visloc.protocols.suite names it."""
    if (query_camera, db_camera) == ("image_00", "image_01"):
        return "stereo"
    return f"same_{query_camera}" if query_camera == db_camera else None


INLIER_FIGURES = ("min", "median", "max")


def peer_pose(query: dict, truth_lat_lon_deg: tuple[float, float] | None = None) -> dict:
    """One query of the peer's JSON at its default variant and threshold: ok, its inliers (None when it
    failed) and its error (a failed pose: its fallback geotag's). With ``truth_lat_lon_deg``, the error of a pose
    against that truth (visloc's for the frame: its geotag at the image's time), where the peer's JSON has the
    pose's position; else against the peer's own truth (its frame's OXTS record), as its JSON states it."""
    pnp = query["variants"][PEER_VARIANT]["pnp"][PEER_THRESHOLD]
    error_m = pnp["error_m"] if pnp["ok"] else pnp["fallback_error_m"]
    if pnp["ok"] and truth_lat_lon_deg is not None and "east_north_m" in pnp and "truth_east_north_m" in query:
        east_m, north_m = (np.asarray(pnp["east_north_m"], float) - np.asarray(query["truth_east_north_m"], float))
        lat, lon = moved_deg(query["truth_lat_deg"], query["truth_lon_deg"], float(east_m), float(north_m))
        error_m = float(geodesic_distance_m(lat, lon, *truth_lat_lon_deg))
    return {"ok": bool(pnp["ok"]), "inliers": pnp.get("num_inliers"), "error_m": error_m}


def digest_peer(peer_dirs: dict[str, Path], out: Path) -> dict:
    """drive -> the peer's and visloc's per-frame errors and support on the peer's frames, for every peer JSON
    that has a matching refined evaluation in ``out`` (evaluate-drives' per-drive JSON). ``peer_dirs``: how the
    page names each directory of peer JSONs -> the directory; a drive found in two is taken from the first."""
    digest = {}
    paths = [(shown, path) for shown, folder in peer_dirs.items() if Path(folder).is_dir()
             for path in sorted(Path(folder).glob("peer_*.json"))]
    for shown, path in paths:
        peer = json.loads(path.read_text())
        params = peer["params"]
        key = protocol_key(params["query_camera"], params["db_camera"])
        ours_path = out / f"{params['drive']}_{key}_refined.json"
        if key is None or not ours_path.is_file() or params["drive"] in digest:
            continue
        ours: dict[int, list[float]] = {}
        sources: dict[int, list[str]] = {}
        support: dict[int, list[tuple[int, int]]] = {}
        truth: dict[int, tuple[float, float]] = {}
        for series in json.loads(ours_path.read_text())["series"]:
            for step in series:
                if step.get("truth_lat_deg") is not None:
                    truth[step["query_frame"]] = (step["truth_lat_deg"], step["truth_lon_deg"])
                if step["measurement_error_m"] is not None:
                    ours.setdefault(step["query_frame"], []).append(step["measurement_error_m"])
                    sources.setdefault(step["query_frame"], []).append(step["measurement_source"])
                    if step["measurement_source"] == "geometry":
                        support.setdefault(step["query_frame"], []).append(
                            (step.get("n_pnp_inliers", 0), step.get("n_pnp_query_keypoints", 0)))
        frames = []
        for q in peer["queries"]:
            f = q["query_frame"]
            pose = peer_pose(q, truth.get(f))
            if f not in ours:
                continue
            frames.append({"frame": f, "peer_error_m": pose["error_m"], "peer_ok": pose["ok"],
                           "peer_inliers": pose["inliers"],
                           "visloc_error_m": float(np.median(ours[f])),
                           "visloc_geotag_fallbacks": sum(s == "geotag" for s in sources[f]),
                           # a frame posed by no series has no support: 0, as a failed peer pose counts its own
                           "visloc_inliers": float(np.median([n for n, _ in support[f]])) if f in support else 0.0,
                           "visloc_query_keypoints": (float(np.median([k for _, k in support[f]])) if f in support
                                                      else 0.0)})
        if not frames:
            continue
        peer_e = [r["peer_error_m"] for r in frames]
        ours_e = [r["visloc_error_m"] for r in frames]
        digest[params["drive"]] = {
            "peer_file": f"{shown}/{path.name}", "evaluation_file": ours_path.name,
            "protocol": key, "peer_versions": peer.get("versions", {}), "frames": frames,
            "peer_error_m": summary_of(peer_e, count=True), "visloc_error_m": summary_of(ours_e, count=True),
            "peer_failures": sum(not r["peer_ok"] for r in frames),
            "peer_inliers": summary_of([r["peer_inliers"] or 0 for r in frames], INLIER_FIGURES),
            "visloc_inliers": summary_of([r["visloc_inliers"] for r in frames], INLIER_FIGURES),
            "visloc_query_keypoints": summary_of([r["visloc_query_keypoints"] for r in frames], INLIER_FIGURES),
            "visloc_better": sum(o < p for o, p in zip(ours_e, peer_e))}
    return dict(sorted(digest.items()))  # by drive, as the digest's JSON keeps them


def render_peer(peer: dict, add) -> None:
    """The page's section: visloc's refined measurement against the peer's, on the peer's frames."""
    if not peer:
        return
    add("## Against a COLMAP-style peer")
    add("")
    add("The peer in `../shared/peer` (pycolmap: RootSIFT, a multi-view map of every allowed database image within "
        "10 frames at its known pose, the 5 images with most matches, LO-RANSAC PnP and refinement) measured the "
        "same queries under the same protocol (1 s exclusion), one measurement per query, no filter. visloc's "
        "error on a frame is its refined measurement there (the median over the series that pose it, from the "
        "evaluation above); a failed peer pose counts with its fallback geotag's error. Both are measured against "
        "the same truth, the frame's geotag at its image's time (the peer's own JSON states its errors against the "
        "frame's OXTS record, up to 5 ms away: on 2011_09_26_drive_0001 a few centimetres along the road).")
    add("")
    add("| drive | protocol | frames | peer mean / median / p90 / max (m) | visloc mean / median / p90 / max (m) | "
        "visloc better on | peer failures | visloc geotag fallbacks |")
    add("|---|---|---|---|---|---|---|---|")
    for drive, d in peer.items():
        p, v = d["peer_error_m"], d["visloc_error_m"]
        fallbacks = sum(r["visloc_geotag_fallbacks"] for r in d["frames"])
        add(f"| {drive} | {d['protocol']} | {p['n']} | {p['mean']:.3f} / {p['median']:.3f} / {p['p90']:.3f} / "
            f"{p['max']:.3f} | {v['mean']:.3f} / {v['median']:.3f} / {v['p90']:.3f} / {v['max']:.3f} | "
            f"{d['visloc_better']} of {p['n']} | {d['peer_failures']} | {fallbacks} |")
    add("")
    supported = {drive: d for drive, d in peer.items() if "peer_inliers" in d}  # digests from before lack it
    if supported:
        add("Support, on the same frames: the pose's PnP inliers. The peer counts each query keypoint once per 3D point of "
            "its merged multi-view tracks, with a 12 px RANSAC threshold; visloc counts its 2D-3D inliers at 2 px, where a "
            "query keypoint that meets the same point in two views' structure counts twice, and, stricter, the distinct "
            "query keypoints among them. A failed pose counts 0; visloc's figure on a frame is the median over the series "
            "that pose it. Both describe the images at about the same SIFT contrast: a visloc store keeps every "
            "keypoint at 0.02, half the paper's threshold, as COLMAP's SIFT does at its defaults (what that gave "
            "and cost on these frames: \"Denser SIFT\" in the [performance notes](performance.md)).")
        add("")
        add("| drive | peer inliers min / median / max | visloc inliers min / median / max | visloc distinct query "
            "keypoints min / median / max | frames where visloc's distinct keypoints reach the peer's inliers |")
        add("|---|---|---|---|---|")
        for drive, d in supported.items():
            f = lambda s: f"{s['min']:.0f} / {s['median']:.0f} / {s['max']:.0f}"  # noqa: E731
            reach = sum(r["visloc_query_keypoints"] >= (r["peer_inliers"] or 0) for r in d["frames"])
            add(f"| {drive} | {f(d['peer_inliers'])} | {f(d['visloc_inliers'])} | {f(d['visloc_query_keypoints'])} | "
                f"{reach} of {len(d['frames'])} |")
        add("")
        for drive, d in supported.items():
            add(f"<details><summary>{drive}, frame by frame</summary>")
            add("")
            add("| frame | peer error (m) | peer inliers | visloc error (m) | visloc inliers | visloc distinct keypoints |")
            add("|---|---|---|---|---|---|")
            for r in d["frames"]:
                add(f"| {r['frame']} | {r['peer_error_m']:.3f}{'' if r['peer_ok'] else ' (failed)'} | "
                    f"{r['peer_inliers'] or 0} | {r['visloc_error_m']:.3f} | {r['visloc_inliers']:.0f} | "
                    f"{r['visloc_query_keypoints']:.0f} |")
            add("")
            add("</details>")
            add("")
    for drive, d in peer.items():
        worst = sorted(d["frames"], key=lambda r: -r["visloc_error_m"])[:3]
        add(f"- {drive}: visloc's largest errors at frames "
            + ", ".join(f"{r['frame']} ({r['visloc_error_m']:.2f} m; peer {r['peer_error_m']:.2f} m)" for r in worst)
            + f". Peer numbers from `{d['peer_file']}`, visloc's from `out/results/{d['evaluation_file']}`.")
    if any(d["peer_file"].startswith("docs/results/peer/") for d in peer.values()):
        add("")
        add("The peer's JSON under `docs/results/peer/` were measured with its README's command on this machine, "
            "`--query-frames stride10` on 2011_09_26_drive_0001 (left queries, right database) and `stride5` on the "
            "others, same camera.")
    add("")
