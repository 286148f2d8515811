"""Exact nearest-two matching of one image pair as ``visloc`` does it (its query rows a block at a time, one BLAS
thread) against how it was done before (one product of all rows, with the process's BLAS threads), on real SIFT
descriptors (drive 0001's right gray camera, each frame against the frame two ahead).

    python benchmarks/matching_blocks.py [--root ../shared/data/kitti] [--drive 2011_09_26_drive_0001] [--rounds 5]

Every pair's four arrays (nearest index, both squared distances, cosine) must come out identical both ways.
Each round times every pair both ways, in an order that alternates from round to round, in one process with
the BLAS threads it starts with (one per core): the wall time and the CPU time (every thread's) per pair.
Reported: the medians over the rounds, and the medians of the rounds' paired ratios. Writes
docs/results/matching_blocks.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_info


from measuring import REPO  # noqa: E402
import visloc.retrieval.matching as matching  # noqa: E402
from visloc.features.sift import extract_sift, make_sift  # noqa: E402
from visloc.params import PAPER_SIFT  # noqa: E402
from visloc.sources.drives import load_gray  # noqa: E402
from visloc.sources.opening import open_source  # noqa: E402

FIELDS = ("index1", "dist1_sq", "dist2_sq", "cosine1")


def descriptors(root: Path, drive: str, n_frames: int) -> list[np.ndarray]:
    sequence = open_source(root, drive=drive, camera="image_01")
    sift = make_sift(PAPER_SIFT)
    return [extract_sift(load_gray(f.image_path), PAPER_SIFT, sift=sift).descriptors_u8
            for f in sequence.frames[:n_frames]]


def one_product(query_u8: np.ndarray, database_u8: np.ndarray) -> matching.NearestTwo:
    """``nearest_two`` as it was: one product of all the query rows, with the process's BLAS threads."""
    q, d = np.asarray(query_u8, np.float32), np.asarray(database_u8, np.float32)
    q_sq, d_sq = np.einsum("ij,ij->i", q, q), np.einsum("ij,ij->i", d, d)
    score = q @ d.T
    score -= 0.5 * d_sq
    index1, best, dist1_sq, dist2_sq = matching.best_two(score, q_sq)
    dot1 = best + 0.5 * d_sq[index1]
    norms = np.sqrt(q_sq) * np.sqrt(d_sq[index1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine1 = np.where(norms > 0, dot1 / norms, np.nan).astype(np.float32)
    return matching.NearestTwo(index1.astype(np.int64), dist1_sq, dist2_sq, cosine1)


def time_pairs(pairs, match) -> tuple[float, float, list]:
    """(wall ms, CPU ms of every thread) per pair, and the results."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = [match(a, b) for a, b in pairs]
    return ((time.perf_counter() - wall) / len(pairs) * 1000.0, (time.process_time() - cpu) / len(pairs) * 1000.0,
            out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "kitti")
    ap.add_argument("--drive", default="2011_09_26_drive_0001")
    ap.add_argument("--frames", type=int, default=22)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--json", type=Path, default=REPO / "docs" / "results" / "matching_blocks.json")
    args = ap.parse_args()
    d = descriptors(args.root, args.drive, args.frames)
    pairs = [(d[k], d[k + 2]) for k in range(len(d) - 2)]
    ways = {"one_product": one_product, "blocks": matching.nearest_two}
    wall = {name: [] for name in ways}
    cpu = {name: [] for name in ways}
    for r in range(args.rounds):
        results = {}
        for name in (list(ways) if r % 2 == 0 else list(ways)[::-1]):
            w, c, results[name] = time_pairs(pairs, ways[name])
            wall[name].append(w)
            cpu[name].append(c)
        if r == 0:
            for a, b in zip(results["one_product"], results["blocks"], strict=True):
                for f in FIELDS:
                    x, y = getattr(a, f), getattr(b, f)
                    if not (x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)):
                        sys.exit(f"the blocks changed {f}: they must give the same arrays")

    def ratio(times: dict) -> float:
        return round(statistics.median(o / b for o, b in zip(times["one_product"], times["blocks"], strict=True)), 3)

    report = {"drive": args.drive, "camera": "image_01", "pairs": len(pairs), "rounds": args.rounds,
              "descriptors_per_image_median": int(statistics.median(len(x) for x in d)),
              "block_bytes": matching._SCORE_BLOCK_BYTES, "blas_threads": blas_threads(), "identical": True,
              "wall_ms_per_pair_median": {k: round(statistics.median(v), 2) for k, v in wall.items()},
              "cpu_ms_per_pair_median": {k: round(statistics.median(v), 2) for k, v in cpu.items()},
              "wall_speedup_median": ratio(wall), "cpu_saving_median": ratio(cpu),
              "wall_ms_rounds": wall, "cpu_ms_rounds": cpu}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1) + "\n")
    w, c = report["wall_ms_per_pair_median"], report["cpu_ms_per_pair_median"]
    print(f"{len(pairs)} pairs of {report['descriptors_per_image_median']} descriptors (median), identical arrays, "
          f"{report['blas_threads']} BLAS threads at start:\n  one product: {w['one_product']} ms a pair, "
          f"{c['one_product']} CPU-ms\n  blocks:      {w['blocks']} ms a pair, {c['blocks']} CPU-ms\n"
          f"  {report['wall_speedup_median']}x faster, {report['cpu_saving_median']}x less CPU (medians of "
          f"{args.rounds} paired rounds)\nwrote {args.json}")


def blas_threads() -> int:
    return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1)


if __name__ == "__main__":
    main()
