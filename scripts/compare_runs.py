"""Compare two `visloc evaluate --json` outputs number by number, leaving out what is timed.

    python scripts/compare_runs.py BEFORE.json AFTER.json [--ignore KEY ...]

Every value of BEFORE (summary and every step of every series) must be in AFTER and equal to
it exactly: the same numbers, bit for bit. Timings (latency_ms, measurement_ms,
measurement_latency_ms, structure_build_ms, wall_s, sustained_hz and the other timed keys below)
are wall-clock measurements and differ from run to run, so they are left out, as is every key
given with --ignore (a record whose meaning changed on purpose, e.g. a parameter listing).
Prints what differs and exits 1, or prints a count and exits 0.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

TIMED = {"latency_ms", "measurement_ms", "measurement_latency_ms", "structure_build_ms", "wall_s", "sustained_hz",
         "stages_ms", "latency_p50_ms", "latency_p95_ms", "build_ms", "sift_ms", "retrieval_ms", "geometry_ms",
         "filter_ms",
         # a track's (visloc track --json): the processor it used and what its stages and relocalizations took
         "cpu_s", "cpu_share_of_one_core", "flow_ms", "points_ms", "per_s", "total_ms"}


def differences(before, after, path: str = "") -> list[str]:
    """Where ``after`` differs from ``before`` (keys of ``before`` only), as 'path: before != after'."""
    if isinstance(before, dict):
        if not isinstance(after, dict):
            return [f"{path}: {type(before).__name__} != {type(after).__name__}"]
        out = []
        for key, value in before.items():
            if key in TIMED:
                continue
            if key not in after:
                out.append(f"{path}.{key}: missing")
            else:
                out += differences(value, after[key], f"{path}.{key}")
        return out
    if isinstance(before, list):
        if not isinstance(after, list) or len(after) != len(before):
            return [f"{path}: a list of {len(before)} != {after if not isinstance(after, list) else len(after)}"]
        return [d for k, (b, a) in enumerate(zip(before, after)) for d in differences(b, a, f"{path}[{k}]")]
    same = before == after or (isinstance(before, float) and isinstance(after, float)
                                and math.isnan(before) and math.isnan(after))
    return [] if same else [f"{path}: {before!r} != {after!r}"]


def count_values(value) -> int:
    if isinstance(value, dict):
        return sum(count_values(v) for k, v in value.items() if k not in TIMED)
    if isinstance(value, list):
        return sum(count_values(v) for v in value)
    return 1


def main(before_path: str, after_path: str, ignore: list[str] | None = None) -> int:
    TIMED.update(ignore or [])
    before, after = (json.loads(Path(p).read_text()) for p in (before_path, after_path))
    found = differences(before, after)
    for line in found[:40]:
        print(line)
    if found:
        print(f"{len(found)} values differ ({before_path} -> {after_path})")
        return 1
    n_steps = sum(len(s) for s in before.get("series", []))
    print(f"identical: {count_values(before)} values, {n_steps} steps ({before_path} -> {after_path})")
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    ignored = [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--ignore"]
    paths = [a for i, a in enumerate(args) if a != "--ignore" and (i == 0 or args[i - 1] != "--ignore")]
    if len(paths) != 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        sys.exit(2)
    sys.exit(main(paths[0], paths[1], ignored))
