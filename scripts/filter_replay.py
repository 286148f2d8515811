"""Can a motion model add to the refined measurements? Replays every refined evaluation's measurements (with
their covariances R) through other filters and compares each series' final estimate with its final measurement.

    python scripts/filter_replay.py [OUT_DIR] [--json out/results/filter_replay.json]

OUT_DIR (default out/results) holds the per-drive JSON of ``visloc evaluate-drives --out-dir``. Filters:

* ``as run``: the refined mode's filter (constant velocity, the gate, the maneuver and retraction
  predictions) with the evaluation's parameters: its final errors must equal the recorded ones;
* the same filter with the white acceleration variance Q scaled;
* constant velocity and constant acceleration (white jerk) without a gate, every measurement applied.

For each: the final estimate's mean error minus the final measurements' (mm; below zero, the filter adds to
the measurements) and the mean squared Mahalanobis distance of the innovations after the first two steps
(2 if the prediction and R together are honest; how much of the innovation is prediction error shows in
how it moves with Q).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from visloc.geo import LocalFrame  # noqa: E402
from visloc.params import FilterParams, RefinedParams  # noqa: E402
from visloc.tracking.kalman import run_filter  # noqa: E402

ACCEL_SCALES = (0.25, 4.0, 16.0)
JERK_VARS_M2_S6 = (0.1, 1.0, 10.0)


def constant_acceleration_filter(zs: list[np.ndarray], Rs: list[np.ndarray], dt_s: float,
                                 jerk_var_m2_s6: float) -> tuple[np.ndarray, list[float]]:
    """A constant-acceleration Kalman filter (white jerk of variance ``jerk_var_m2_s6``) per axis, every
    measurement applied; the first measurement initialises the position with its R, velocity and acceleration
    with 1000. The engine has constant velocity only, hence this one. Returns the final position and the
    squared Mahalanobis distances of the innovations after the second step."""
    F1 = np.array([[1, dt_s, dt_s**2 / 2], [0, 1, dt_s], [0, 0, 1]])
    g = np.array([dt_s**3 / 6, dt_s**2 / 2, dt_s])
    F, Q = np.kron(np.eye(2), F1), np.kron(np.eye(2), jerk_var_m2_s6 * np.outer(g, g))
    H = np.zeros((2, 6))
    H[0, 0] = H[1, 3] = 1
    x, P = np.zeros(6), 1000.0 * np.eye(6)
    x[[0, 3]] = zs[0]
    P[np.ix_([0, 3], [0, 3])] = Rs[0]
    d2 = []
    for i, (z, R) in enumerate(zip(zs[1:], Rs[1:]), start=1):
        x, P = F @ x, F @ P @ F.T + Q
        y, S = z - H @ x, H @ P @ H.T + R
        if i >= 2:
            d2.append(float(y @ np.linalg.solve(S, y)))
        K = P @ H.T @ np.linalg.inv(S)
        x, P = x + K @ y, (np.eye(6) - K @ H) @ P
    return H @ x, d2


def replay(report: dict) -> dict:
    """Every filter on one evaluation's series (only series measured at every step)."""
    p = report["params"]
    fp = FilterParams(**p["filter"])
    refined = RefinedParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in p["refined"].items()})
    first = report["series"][0][0]
    frame = LocalFrame(first["truth_lat_deg"], first["truth_lon_deg"])
    # name -> ("engine", FilterParams, gated) or ("ca", jerk variance)
    filters = {"as run": ("engine", fp, True)}
    filters.update({f"Q x {s:g}": ("engine", replace(fp, accel_var_m2_s4=fp.accel_var_m2_s4 * s), True)
                    for s in ACCEL_SCALES})
    filters[f"constant velocity, no gate, q {fp.accel_var_m2_s4:g}"] = ("engine", fp, False)
    filters.update({f"constant acceleration, no gate, jerk {j:g} m2/s6": ("ca", j) for j in JERK_VARS_M2_S6})
    finals = {name: [] for name in filters}
    d2 = {name: [] for name in filters}
    measured, recorded, geometry_final = [], [], []
    for series in report["series"]:
        if any(r["measurement_lat_deg"] is None for r in series):
            continue
        zs = [frame.to_local(r["measurement_lat_deg"], r["measurement_lon_deg"]) for r in series]
        Rs = [np.asarray(r["measurement_cov_m2"], float) for r in series]
        truth = frame.to_local(series[-1]["truth_lat_deg"], series[-1]["truth_lon_deg"])
        measured.append(float(np.linalg.norm(zs[-1] - truth)))
        recorded.append(series[-1]["estimate_error_m"])
        geometry_final.append(series[-1]["measurement_source"] == "geometry")
        for name, (kind, *args) in filters.items():
            if kind == "engine":
                params, gated = args
                steps = run_filter(zs, params, covariances_m2=Rs, gate_chi2=refined.gate_chi2 if gated else 0.0,
                                   reinit_after_gated=refined.reinit_after_gated if gated else 0,
                                   correlated=[r["measurement_source"] == "geometry" for r in series],
                                   corr_fraction=refined.error_correlation,
                                   corr_time_s=refined.error_correlation_time_s)
                final = steps[-1].x[:2]
                d2[name] += [s.innovation.mahalanobis**2 for s in steps[2:] if s.innovation is not None]
            else:
                final, dd = constant_acceleration_filter(zs, Rs, fp.dt_s, args[0])
                d2[name] += dd
            finals[name].append(float(np.linalg.norm(final - truth)))
    m = float(np.mean(measured))
    g = np.asarray(geometry_final, bool)
    as_run_geometry = np.asarray(finals["as run"])[g] - np.asarray(measured)[g]
    return {"n_series": len(measured), "final_measurement_mean_m": m, "recorded_final_estimate_mean_m":
            float(np.mean(recorded)), "n_series_ending_on_a_fallback": int((~g).sum()),
            "as_run_minus_measurement_mm_geometry_finals": float(1000 * as_run_geometry.mean()) if g.any() else None,
            # a list, in the order above (the results digest sorts the keys of a dict)
            "filters": [{"name": name, "final_estimate_mean_m": float(np.mean(v)),
                         "minus_measurement_mm": float(1000 * (np.mean(v) - m)),
                         "innovation_d2_mean": float(np.mean(d2[name])) if d2[name] else None}
                        for name, v in finals.items()]}


def render_filter_replay(replays: dict, add) -> None:
    """The results page's section: per refined evaluation, how far each filter's final estimate lies from the
    final measurements (``replay``'s figures)."""
    if not replays:
        return
    names = [f["name"] for f in next(iter(replays.values()))["filters"]]
    add("## Can a motion model add to the refined measurements?")
    add("")
    add("`python scripts/filter_replay.py out/results` replays every refined evaluation's measurements, with their "
        "covariances, through other filters: the final estimate's mean error minus the final measurements' (mm; "
        "below zero the filter adds to its measurements), and in brackets the innovations' mean squared "
        "Mahalanobis distance after the second step (2 if the prediction and R are honest together). \"as run\" "
        "is the refined mode's filter and reproduces the evaluation.")
    add("")
    add("| evaluation | series (ending on a fallback) | " + " | ".join(names) + " | as run, series ending on geometry |")
    add("|---|---|" + "---|" * (len(names) + 1))
    for stem, r in sorted(replays.items()):
        cells = [f"{f['minus_measurement_mm']:+.1f} ({f['innovation_d2_mean']:.2f})" for f in r["filters"]]
        geometry = r["as_run_minus_measurement_mm_geometry_finals"]
        add(f"| {stem.removesuffix('_refined')} | {r['n_series']} ({r['n_series_ending_on_a_fallback']}) | "
            + " | ".join(cells) + f" | {'-' if geometry is None else format(geometry, '+.1f')} |")
    add("")
    add("At one query a second the measurements are good to centimetres or decimetres while a constant-velocity or "
        "constant-acceleration prediction of a car is not: the prediction carries little weight, "
        "a looser Q moves the estimate onto the measurement and a tighter one pulls it off. What the filter adds "
        "is to weigh each measurement by its own covariance: a series that ends on a geotag fallback metres off, "
        "with its σ of metres, ends where its geometry measurements put it, and only such series make the "
        "filter's final estimate better than its final measurements by more than a few millimetres. Motion measured between "
        "the queries (the camera-rate frames, the vehicle's odometry) is what a prediction good to centimetres "
        "would take.")
    add("")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out_dir", nargs="?", type=Path, default=Path("out/results"),
                    help="the per-drive JSON of visloc evaluate-drives --out-dir (default out/results)")
    ap.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    a = ap.parse_args(argv)
    paths = sorted(a.out_dir.glob("*_refined.json"))
    if not paths:
        print(f"filter_replay: {a.out_dir}: no *_refined.json (run: visloc evaluate-drives ... --out-dir {a.out_dir})",
              file=sys.stderr)
        return 2
    results = {}
    for path in paths:
        try:
            r = results[path.stem] = replay(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            print(f"filter_replay: {path}: not an evaluation's JSON with series and params ({exc!r})", file=sys.stderr)
            return 2
        print(f"{path.stem}: {r['n_series']} series, final measurements {r['final_measurement_mean_m']:.4f} m, "
              f"recorded final estimate {r['recorded_final_estimate_mean_m']:.4f} m")
        for f in r["filters"]:
            print(f"  {f['name']:46s} final estimate {f['final_estimate_mean_m']:.4f} m  "
                  f"({f['minus_measurement_mm']:+6.1f} mm)  innovation d2 {f['innovation_d2_mean']:.2f}")
    if a.json:
        a.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
