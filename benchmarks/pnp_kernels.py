"""PnP RANSAC's kernel: AP3P on four points, the inliers refined until they settle, against the five-point kernel
OpenCV uses with the SQPnP flag, refined once (what ``solve_pnp`` did before), on the PnP problems of real queries.

    python benchmarks/pnp_kernels.py [--root ../shared/data/kitti] [--db out/results/visloc.sqlite]
    python benchmarks/pnp_kernels.py --page   # its section of docs/performance.md from the JSON

For every drive of the data root, ``visloc track --follow-points --no-background-relocalization`` on its image_00
against its own image_00 with the 1 s exclusion window (the camera-rate path: full localizations, their
widening and the frames posed on followed points) is run once with every 2D-3D problem it hands ``solve_pnp``
recorded. Each problem is then solved by both kernels, one after the other, in this process: the time of each
call, the inliers each keeps and how far apart the two camera centres are. How the choice moves the
localization itself is measured end to end by the results page and ``benchmarks/track_following.py``.
Writes docs/results/pnp_kernels.json.
"""

from __future__ import annotations

import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from measuring import REPO, Section, drives_and_store_arguments, load_1min, load_line  # noqa: E402

SECTION = Section("pnp-kernels", "pnp_kernels", REPO / "docs" / "performance.md")
KERNELS = {"five_point_once": ("SOLVEPNP_SQPNP", 1), "ap3p_settled": ("SOLVEPNP_AP3P", None)}


def record(out: Path, track_args: list[str]) -> None:
    """Run ``visloc track track_args`` in this process, every ``solve_pnp`` problem written to ``out``."""
    import numpy as np

    from visloc.cli.parser import main
    from visloc.geometry import projective
    from visloc.pose import viewpose

    problems = []
    solve = projective.solve_pnp

    def recorded(points_world, xy_px, K, **kwargs):
        kept = {k: v for k, v in kwargs.items() if k in ("reprojection_px", "iterations", "min_inliers", "seed")}
        problems.append((np.array(points_world, float), np.array(xy_px, float), np.array(K, float), kept))
        return solve(points_world, xy_px, K, **kwargs)

    viewpose.solve_pnp = recorded
    code = main(track_args)
    out.write_bytes(pickle.dumps(problems))
    raise SystemExit(code)


def compare(problems: list) -> dict:
    import cv2
    import numpy as np

    from visloc.geometry.projective import REFINE_ROUNDS, solve_pnp

    ms = {k: [] for k in KERNELS}
    hard = []  # the problems where fewer than half the correspondences are the five-point kernel's inliers
    inliers = {k: [] for k in KERNELS}
    apart_m, posed = [], {k: 0 for k in KERNELS}
    for X, x, K, kwargs in problems:
        centres, share = {}, 0.0
        for name, (flag, rounds) in KERNELS.items():
            start = time.perf_counter()
            r = solve_pnp(X, x, K, **kwargs, kernel=getattr(cv2, flag), refine_rounds=rounds or REFINE_ROUNDS)
            ms[name].append((time.perf_counter() - start) * 1000.0)
            if not isinstance(r, str):
                posed[name] += 1
                inliers[name].append(len(r.inliers))
                centres[name] = r.T_world_camera[:3, 3]
                if name == "five_point_once":
                    share = len(r.inliers) / len(X)
        hard.append(share < 0.5)
        if len(centres) == 2:
            apart_m.append(float(np.linalg.norm(centres["five_point_once"] - centres["ap3p_settled"])))
    apart = np.array(apart_m) if apart_m else np.zeros(1)
    hard_ms = {k: statistics.fmean([t for t, h in zip(v, hard) if h] or [0.0]) for k, v in ms.items()}
    return {"problems": len(problems), "posed": posed, "hard_problems": int(sum(hard)), "hard_ms_mean": hard_ms,
            "ms": {k: {"median": statistics.median(v), "mean": statistics.fmean(v), "total_s": sum(v) / 1000.0}
                   for k, v in ms.items() if v},
            "inliers_median": {k: statistics.median(v) for k, v in inliers.items() if v},
            "centres_apart_m": {"median": float(np.median(apart)), "p90": float(np.percentile(apart, 90)),
                                "max": float(apart.max()), "over_0_3": int((apart > 0.3).sum())}}


def measure(a) -> dict:
    from visloc.protocols.suite import drives_of

    result = {"load_1min_before": load_1min(), "kernels": {k: v[0] for k, v in KERNELS.items()}, "drives": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for folder in drives_of(a.root):
            drive = folder.name.removesuffix("_sync")
            out = Path(tmp) / f"{drive}.pkl"
            args = ["track", str(a.root), "--drive", drive, "--camera", "image_00", "--db-camera", "image_00",
                    "--db", str(a.db), "--exclusion-s", "1", "--follow-points", "--no-background-relocalization", "--pace-hz", "0",
                    "--json", str(Path(tmp) / f"{drive}.json")]
            done = subprocess.run([sys.executable, __file__, "--record", str(out), *args], cwd=REPO,
                                  stdin=subprocess.DEVNULL, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"{drive}: recording failed: {done.stderr.strip().splitlines()[-1:]}")
            result["drives"][drive] = compare(pickle.loads(out.read_bytes()))
            print(drive, result["drives"][drive], flush=True)
    result["load_1min_after"] = load_1min()
    return result


def render(r: dict) -> str:
    lines = [SECTION.begin, "",
             "PnP RANSAC's kernel on the PnP problems of a camera-rate track (`python benchmarks/pnp_kernels.py`): "
             "every problem the track posed, solved by the five-point kernel OpenCV uses with the SQPnP flag "
             "(refined once) and by AP3P on four points (the inliers refined until they settle, the default), "
             "one after the other in one process.", "",
             "| drive | problems | ms per problem, median (mean): five-point -> AP3P | problems under half inliers: "
             "how many, ms mean five-point -> AP3P | posed: five-point / AP3P "
             "| inliers median: five-point / AP3P | camera centres apart, median / p90 / max (m) | apart > 0.3 m |",
             "|---|---|---|---|---|---|---|---|"]
    for drive, d in r["drives"].items():
        a, b = d["ms"]["five_point_once"], d["ms"]["ap3p_settled"]
        c = d["centres_apart_m"]
        lines.append(f"| {drive} | {d['problems']} | {a['median']:.1f} ({a['mean']:.1f}) -> {b['median']:.1f} "
                     f"({b['mean']:.1f}) | {d['hard_problems']}: {d['hard_ms_mean']['five_point_once']:.1f} -> "
                     f"{d['hard_ms_mean']['ap3p_settled']:.1f} | {d['posed']['five_point_once']} / {d['posed']['ap3p_settled']} | "
                     f"{d['inliers_median']['five_point_once']:.0f} / {d['inliers_median']['ap3p_settled']:.0f} | "
                     f"{c['median']:.3f} / {c['p90']:.3f} / {c['max']:.2f} | {c['over_0_3']} |")
    lines += ["", "Which of two poses a few decimetres apart is right, the problems alone cannot say: the drives' "
              "evaluations (the results page) and `benchmarks/track_following.py` measure the localization "
              "against the geotags with the default kernel.", "", load_line(r), "", SECTION.end]
    return "\n".join(lines)


def add_arguments(parser) -> None:
    drives_and_store_arguments(parser)


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--record":
        record(Path(sys.argv[2]), sys.argv[3:])
    raise SystemExit(SECTION.main(__doc__, measure, render, add_arguments))
