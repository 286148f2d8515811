"""Exact nearest-two matching of one image pair, its query rows a block at a time against one product of all
rows, on real SIFT descriptors (drive 0001's right gray camera, each frame against the frame two ahead).

    python scripts/matching_blocks.py [--root ../shared/data/kitti] [--drive 2011_09_26_drive_0001] [--rounds 5]

Every pair's four arrays (nearest index, both squared distances, cosine) must come out identical both ways.
Each round times every pair both ways, in an order that alternates from round to round, in one process with
one BLAS thread (as ingest and the self-check run). Reported: the medians over the rounds of the time per
pair, and the median of the rounds' paired ratios. Writes docs/results/matching_blocks.json.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import visloc.retrieval.matching as matching  # noqa: E402
from visloc.features.sift import extract_sift, make_sift  # noqa: E402
from visloc.params import PAPER_SIFT  # noqa: E402
from visloc.sources.drives import load_gray, open_source  # noqa: E402

FIELDS = ("index1", "dist1_sq", "dist2_sq", "cosine1")


def descriptors(root: Path, drive: str, n_frames: int) -> list[np.ndarray]:
    sequence = open_source(root, drive=drive, camera="image_01")
    sift = make_sift(PAPER_SIFT)
    return [extract_sift(load_gray(f.image_path), PAPER_SIFT, sift=sift).descriptors_u8
            for f in sequence.frames[:n_frames]]


def time_pairs(pairs, block_bytes: int) -> tuple[float, list]:
    matching._SCORE_BLOCK_BYTES = block_bytes
    start = time.perf_counter()
    out = [matching.nearest_two(a, b) for a, b in pairs]
    return (time.perf_counter() - start) / len(pairs) * 1000.0, out


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
    ways = {"one_product": 1 << 40, "blocks": matching._SCORE_BLOCK_BYTES}
    times = {name: [] for name in ways}
    with threadpool_limits(1, user_api="blas"):
        for r in range(args.rounds):
            results = {}
            for name in (list(ways) if r % 2 == 0 else list(ways)[::-1]):
                ms, results[name] = time_pairs(pairs, ways[name])
                times[name].append(ms)
            if r == 0:
                for a, b in zip(results["one_product"], results["blocks"], strict=True):
                    for f in FIELDS:
                        x, y = getattr(a, f), getattr(b, f)
                        if not (x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)):
                            sys.exit(f"the blocks changed {f}: they must give the same arrays")
    ratios = [o / b for o, b in zip(times["one_product"], times["blocks"], strict=True)]
    report = {"drive": args.drive, "camera": "image_01", "pairs": len(pairs), "rounds": args.rounds,
              "descriptors_per_image_median": int(statistics.median(len(x) for x in d)),
              "block_bytes": ways["blocks"], "identical": True,
              "ms_per_pair_median": {k: round(statistics.median(v), 2) for k, v in times.items()},
              "speedup_median": round(statistics.median(ratios), 3), "ms_per_pair_rounds": times}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1) + "\n")
    print(f"{len(pairs)} pairs of {report['descriptors_per_image_median']} descriptors (median), identical arrays: "
          f"one product {report['ms_per_pair_median']['one_product']} ms a pair, blocks "
          f"{report['ms_per_pair_median']['blocks']} ms; {report['speedup_median']}x (median of {args.rounds} "
          f"paired rounds)\nwrote {args.json}")


if __name__ == "__main__":
    main()
