"""How much of their errors consecutive pose measurements share, and whether the filter's model of it keeps the
estimate honest at the camera's rate and at one query per second.

    python benchmarks/measurement_correlation.py [--root ../shared/data/kitti] [--db out/results/visloc.sqlite]
    python benchmarks/measurement_correlation.py --page   # its section of docs/performance.md from the JSON

For every drive of the data root, queries and database from its image_00 with the 1 s exclusion window, one
``visloc track`` run localizes every frame in full (the camera-rate path at 10 Hz). Each geometry measurement's
error against its frame's geotag, in its own units (L^-1 e, L L' = R), gives the correlation of two
measurements by their time apart (``visloc.stats.error_correlation_by_lag``), pooled over the drives and fitted
as c exp(-dt / tau) (``visloc.stats.fit_error_correlation``): the refined parameters ``error_correlation`` and
``error_correlation_time_s`` are that fit. Then every drive's measurements are filtered again, at 10 Hz and
every 10th at 1 Hz, as independent (c = 0) and with the parameters' shared error: the estimate's mean error,
NEES and share inside its 95 % ellipse. Writes docs/results/measurement_correlation.json.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from measuring import REPO, Section, drives_and_store_arguments, load_1min, load_line, track_run  # noqa: E402

SECTION = Section("measurement-correlation", "measurement_correlation", REPO / "docs" / "performance.md")
BEGIN, END = SECTION.begin, SECTION.end
STRIDES = {"10 Hz": 1, "1 Hz": 10}


def whitened_errors(frames: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(times s, (n, 2) geometry measurements' errors in their own units, NaN where a frame has none)."""
    t = np.array([f["timestamp_s"] for f in frames], float)
    w = np.full((len(frames), 2), np.nan)
    for k, f in enumerate(frames):
        if f["measurement_source"] == "geometry":
            e = np.asarray(f["measurement_m"], float) - np.asarray(f["truth_m"], float)
            w[k] = np.linalg.solve(np.linalg.cholesky(np.asarray(f["measurement_cov_m2"], float)), e)
    return t, w


def refilter(run: dict, stride: int, corr_fraction: float, corr_time_s: float) -> dict:
    """The run's measurements (every ``stride``-th frame) through the refined filter with the given shared error."""
    from visloc.params import FilterParams
    from visloc.stats import CHI2_2DOF_95
    from visloc.tracking.kalman import run_filter

    frames = run["per_frame"][::stride]
    fp = run["params"]["filter"]
    fp = FilterParams(**{**fp, "dt_s": fp["dt_s"] * stride})
    pose = run["params"]["method"]["pose"]
    steps = run_filter([None if f["measurement_m"] is None else np.asarray(f["measurement_m"]) for f in frames], fp,
                       covariances_m2=[None if f["measurement_cov_m2"] is None else np.asarray(f["measurement_cov_m2"])
                                       for f in frames],
                       gate_chi2=pose["gate_chi2"], reinit_after_gated=pose["reinit_after_gated"],
                       correlated=[f["measurement_source"] == "geometry" for f in frames],
                       corr_fraction=corr_fraction, corr_time_s=corr_time_s)
    e = np.array([s.x[:2] - np.asarray(f["truth_m"], float) for s, f in zip(steps, frames)])
    nees = np.array([v @ np.linalg.solve(s.P[:2, :2], v) for v, s in zip(e, steps)])
    return {"frames": len(frames), "error_mean_m": float(np.linalg.norm(e, axis=1).mean()),
            "nees_mean": float(nees.mean()), "inside_95": float(np.mean(nees <= CHI2_2DOF_95))}


def measure(root: Path, db: Path) -> dict:
    from visloc.params import REFINED
    from visloc.sources.drives import kitti_drives, resolve_drive
    from visloc.stats import error_correlation_by_lag, fit_error_correlation

    drives = [name.removesuffix("_sync") for name in kitti_drives(root)
              if (resolve_drive(root, name) / "image_00").is_dir()]
    c, tau = REFINED.error_correlation, REFINED.error_correlation_time_s
    out = {"root": str(root), "store": str(db), "load_1min_before": load_1min(), "drives": {},
           "params": {"error_correlation": c, "error_correlation_time_s": tau}}
    times, errors = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n, drive in enumerate(drives):
            run = track_run(root, drive, db, [], Path(tmp) / f"{drive}.json")
            t, w = whitened_errors(run["per_frame"])
            times.append(t + 1e6 * n)  # drives apart: no pair across two drives
            errors.append(w)
            lags, rho, pairs = error_correlation_by_lag(t, w)
            fit = fit_error_correlation(lags, rho, pairs)
            out["drives"][drive] = {
                "correlation": {"lag_s": lags.round(3).tolist(), "rho": rho.round(4).tolist(), "pairs": pairs.tolist()},
                "fit": {"fraction": fit[0], "time_s": fit[1]},
                "filters": {rate: {"independent": refilter(run, stride, 0.0, 1.0), "shared": refilter(run, stride, c, tau)}
                            for rate, stride in STRIDES.items()}}
            print(f"{drive}: fit c {fit[0]:.2f}, tau {fit[1]:.2f} s; " + "; ".join(
                f"{rate} NEES {f['independent']['nees_mean']:.2f} -> {f['shared']['nees_mean']:.2f}"
                for rate, f in out["drives"][drive]["filters"].items()), flush=True)
    lags, rho, pairs = error_correlation_by_lag(np.concatenate(times), np.concatenate(errors))
    fraction, time_s = fit_error_correlation(lags, rho, pairs)
    out["pooled"] = {"lag_s": lags.round(3).tolist(), "rho": rho.round(4).tolist(), "pairs": pairs.tolist(),
                     "fit": {"fraction": fraction, "time_s": time_s}}
    out["load_1min_after"] = load_1min()
    return out


def render(result: dict) -> str:
    p, pooled = result["params"], result["pooled"]
    lags = np.asarray(pooled["lag_s"])
    shown = [0.1, 0.2, 0.5, 1.0, 2.0]
    at = [int(np.argmin(np.abs(lags - s))) for s in shown]
    lines = [BEGIN, "How much of their errors consecutive pose measurements share, measured by "
             "`python benchmarks/measurement_correlation.py`: every frame of each drive localized in full by "
             "`visloc track` (queries and database from image_00, 1 s exclusion window), each geometry "
             "measurement's error in its own units, and the correlation of two measurements by their time apart:", "",
             "| drive | " + " | ".join(f"{s:g} s" for s in shown) + " | fit: shared fraction c, time τ (s) |",
             "|---|" + "---|" * (len(shown) + 1)]
    for drive, r in result["drives"].items():
        dl = np.asarray(r["correlation"]["lag_s"])
        cells = [f"{r['correlation']['rho'][int(np.argmin(np.abs(dl - s)))]:.2f}" for s in shown]
        lines.append(f"| {drive} | " + " | ".join(cells) + f" | {r['fit']['fraction']:.2f}, {r['fit']['time_s']:.2f} |")
    lines.append("| all drives | " + " | ".join(f"{pooled['rho'][k]:.2f}" for k in at) +
                 f" | **{pooled['fit']['fraction']:.2f}, {pooled['fit']['time_s']:.2f}** |")
    fit = pooled["fit"]
    agree = (abs(fit["fraction"] - p["error_correlation"]) <= 0.01
             and abs(fit["time_s"] - p["error_correlation_time_s"]) <= 0.01 * p["error_correlation_time_s"] + 0.005)
    held = "hold the fit over all drives" if agree else "differ from the fit over all drives"
    lines += ["", f"The refined parameters {held}: `error_correlation` {p['error_correlation']:g}, "
              f"`error_correlation_time_s` {p['error_correlation_time_s']:g}. The filter carries that shared part "
              "as a measurement-bias state, so measurements made faster than it fades are not taken as independent. "
              "Each drive's measurements filtered again, taken as independent and with the shared part "
              "(estimate: mean error, NEES, share inside its 95 % ellipse; honest is NEES near 2 and 95 %):", "",
              "| drive | rate | independent | shared part modelled |", "|---|---|---|---|"]
    for drive, r in result["drives"].items():
        for rate, f in r["filters"].items():
            a, b = f["independent"], f["shared"]
            lines.append(f"| {drive} | {rate} | {a['error_mean_m']:.3f} m, {a['nees_mean']:.2f}, {a['inside_95']:.0%} | "
                         f"{b['error_mean_m']:.3f} m, {b['nees_mean']:.2f}, {b['inside_95']:.0%} |")
    lines += ["", load_line(result), END]
    return "\n".join(lines)


def main() -> int:
    return SECTION.main(__doc__, lambda a: measure(a.root, a.db), render, drives_and_store_arguments)


if __name__ == "__main__":
    raise SystemExit(main())
