"""Every drive of a data root, with every protocol it supports, in every method: one table per drive
and a pooled line per method.

Protocols (``drive_protocols``):

* ``stereo``: a drive with both gray cameras: left queries (image_00) against the right camera's
  database (image_01), the paper's setup;
* ``same_<camera>``: queries and database from one camera, the left one where there are two. The
  evaluation's exclusion window keeps a query from matching itself and its neighbours in time.

``protocol_row`` reduces one evaluation to the numbers a reader compares across drives;
``pooled_rows`` pools the steps of every drive's evaluations of one method.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from visloc.protocols.evaluation import Evaluation, measurement_calibration
from visloc.pose.measurement import GEOMETRY
from visloc.protocols.records import StepRecord
from visloc.sources.drives import kitti_drives
from visloc.stats import CHI2_2DOF_95, summary_of
from visloc.pose.uncertainty import calibration

GROSS_ERROR_M = 2.0


@dataclass(frozen=True)
class Protocol:
    key: str  # "stereo" or "same_<camera>"
    label: str
    query_camera: str
    db_camera: str


def drive_protocols(drive_folder: Path) -> list[Protocol]:
    """The protocols a KITTI drive folder supports, by the gray cameras it holds."""
    gray = [c for c in ("image_00", "image_01") if (Path(drive_folder) / c / "data").is_dir()]
    out = []
    if gray == ["image_00", "image_01"]:
        out.append(Protocol("stereo", "left queries, right database", "image_00", "image_01"))
    if gray:
        camera = gray[0]
        side = "left" if camera == "image_00" else "right"
        out.append(Protocol(f"same_{camera}", f"{side} queries, {side} database", camera, camera))
    return out


def drives_of(root: Path) -> list[Path]:
    """Drive folders of a KITTI raw root (``InputError`` naming the root if it has none)."""
    root = Path(root)
    return [next(root.glob(f"*/{name}")) for name in kitti_drives(root)]


def _row(records: list[StepRecord], finals: list[float], final_measurements: list[float], mode: str) -> dict:
    measured = [r for r in records if r.measurement_error_m is not None]
    geometry = [r for r in measured if r.measurement_source == GEOMETRY]
    nees = np.array([r.measurement_nees for r in geometry if r.measurement_nees is not None], float)
    return {
        "mode": mode,
        "n_steps": len(records),
        "measurement_error_m": summary_of([r.measurement_error_m for r in measured], count=True),
        "geometry_error_m": summary_of([r.measurement_error_m for r in geometry], count=True),
        "final_error_m": summary_of(finals, count=True),
        # the measurements at the same (final) steps, to compare the filter with
        "final_measurement_error_m": summary_of(final_measurements, count=True),
        "nees": {"mean": float(nees.mean()) if nees.size else None,
                 "fraction_within_95": float(np.mean(nees <= CHI2_2DOF_95)) if nees.size else None,
                 "n": int(nees.size)},
        "fallback_fraction": (sum(1 for r in measured if r.fallback_reason is not None) / len(measured)
                              if measured and mode != "paper" else None),
        "gated_fraction": sum(r.gated for r in records) / len(records) if records else None,
        "gross_geometry_errors": sum(1 for r in geometry if r.measurement_error_m > GROSS_ERROR_M),
        "calibration": measurement_calibration(records) if mode != "paper" else None,
        "estimate_calibration": (calibration([r.estimate_nees for r in records]).as_dict() if mode != "paper"
                                 else None),
    }


def protocol_row(evaluation: Evaluation) -> dict:
    """One evaluation's row: measurement and final-estimate errors (m), NEES of the geometry
    measurements (counting the truth's stated accuracy), fallback and gated fractions, and how many
    geometry measurements were more than ``GROSS_ERROR_M`` off."""
    records = [r for s in evaluation.series for r in s]
    finals = [s[-1].estimate_error_m for s in evaluation.series if s[-1].estimate_error_m is not None]
    final_meas = [s[-1].measurement_error_m for s in evaluation.series if s[-1].measurement_error_m is not None]
    return _row(records, finals, final_meas, evaluation.method.name)


def pooled_rows(evaluations: list[Evaluation]) -> list[dict]:
    """Per method, one row over the steps of all the given evaluations."""
    out = []
    for mode in dict.fromkeys(e.method.name for e in evaluations):
        chosen = [e for e in evaluations if e.method.name == mode]
        records = [r for e in chosen for s in e.series for r in s]
        finals = [s[-1].estimate_error_m for e in chosen for s in e.series if s[-1].estimate_error_m is not None]
        final_meas = [s[-1].measurement_error_m for e in chosen for s in e.series
                      if s[-1].measurement_error_m is not None]
        out.append(_row(records, finals, final_meas, mode))
    return out


def _cell(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def table_text(title: str, rows: list[tuple[str, dict]]) -> str:
    """A plain-text table of rows (label, row) under a title."""
    header = (f"{'':34s} {'measurement error (m)':>29s} {'final (m)':>9s} {'vs meas.':>8s} {'NEES':>5s} "
              f"{'in 95%':>6s} {'fallback':>8s} {'gated':>6s} {'>2 m':>4s}")
    sub = f"{'':34s} {'median':>7s} {'mean':>7s} {'p90':>7s} {'max':>6s}"
    lines = [title, header, sub]
    for label, r in rows:
        m, f, fm = r["measurement_error_m"], r["final_error_m"], r["final_measurement_error_m"]
        lines.append(
            f"{label[:34]:34s} {_cell(m['median'], '7.3f')} {_cell(m['mean'], '7.3f')} {_cell(m['p90'], '7.3f')} "
            f"{_cell(m['max'], '6.2f')} {_cell(f['mean'], '9.3f')} {_cell(fm['mean'], '8.3f')} "
            f"{_cell(r['nees']['mean'], '5.2f')} {_cell(r['nees']['fraction_within_95'], '6.0%')} "
            f"{_cell(r['fallback_fraction'], '8.0%')} {_cell(r['gated_fraction'], '6.0%')} "
            f"{r['gross_geometry_errors']:4d}")
    return "\n".join(lines)


def database_row(db) -> dict:
    """What a database's own data says of its geotags: their stated accuracy, its heading spread, and the
    lever gains its self-checks measured (``visloc.pose.uncertainty``): the refined path's and the camera-rate
    path's."""
    geometry = db.geometry()
    sigma = db.geotag_sigma_m[np.isfinite(db.geotag_sigma_m)] if db.geotag_sigma_m is not None else np.zeros(0)
    spread = geometry.heading_spread_rad
    return {"name": f"{db.source}/{db.camera}", "images": len(db),
            "stated_accuracy_median_m": float(np.median(sigma)) if sigma.size else None,
            "heading_spread_deg": None if spread is None else float(np.degrees(spread)),
            "lever_gain": None if db.lever_gain is None else db.lever_gain.as_dict(),
            "camera_rate_lever_gain": (None if db.camera_rate_lever_gain is None
                                       else db.camera_rate_lever_gain.as_dict())}
