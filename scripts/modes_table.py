"""Print the README's table of both modes and both camera setups from `visloc evaluate --json` outputs.

Usage: python scripts/modes_table.py out/modes   (the folder scripts/compare_modes.sh writes)
"""

import json
import sys
from pathlib import Path

SETUPS = [("image_00", "image_01", "left queries, right database (paper)"),
          ("image_01", "image_01", "right queries, right database")]


def cell(value, fmt=".2f"):
    return "-" if value is None else format(value, fmt)


def main(folder: Path) -> int:
    rows = []
    for query, database, label in SETUPS:
        for mode in ("paper", "refined"):
            path = folder / f"{mode}_{query}_{database}.json"
            if not path.is_file():
                print(f"modes_table: {path}: not found (run scripts/compare_modes.sh)", file=sys.stderr)
                return 2
            r = json.loads(path.read_text())
            final = r["final_error_m"]
            nees = (r.get("measurement_nees") or {}).get("mean")
            rows.append(
                f"| {label} | {mode} | {r['n_series']} | "
                + " / ".join(cell(v) for v in r["measurement_error_m"])
                + f" | {cell(final['mean'])} / {cell(final['median'])} / {cell(final['p90'])} | "
                + " / ".join(cell(v) for v in r["smoothed_error_m"][:1] + r["smoothed_error_m"][-1:])
                + f" | {cell(r['geometry_fallback_fraction'], '.1%')} | {cell(r['gated_fraction'], '.1%')} | "
                f"{cell(nees)} | {cell(r['latency_ms']['p50'], '.0f')} / {cell(r['latency_ms']['p95'], '.0f')} | "
                f"{cell(r['measurement_latency_ms']['p50'], '.0f')} / {cell(r['measurement_latency_ms']['p95'], '.0f')} |")
    print("| setup | mode | series | mean measurement error t-5 / … / t (m) | final error mean / median / p90 (m) "
          "| RTS-smoothed error t-5 / t (m) | geotag fallback | gated | NEES | latency p50 / p95 (ms) "
          "| of which measurement p50 / p95 (ms) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "out/modes")))
