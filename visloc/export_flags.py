"""``--geojson FILE`` and ``--csv FILE``: a run's trajectories (truth, measurements, estimates with
their covariance) written by ``visloc.export``; the paths checked before any work."""

from __future__ import annotations

import argparse
from pathlib import Path

from visloc.choices import require_output
from visloc.errors import InputError
from visloc.export import GEOJSON_SUFFIXES, write_trajectory


def require_exports(a: argparse.Namespace, store: Path | None = None) -> None:
    """``--geojson`` and ``--csv``: the right suffix and a writable place, before any work (``store``: of a
    command that makes the store's missing folder, where the files may go)."""
    for flag, path, suffixes in (("--geojson", a.geojson, GEOJSON_SUFFIXES), ("--csv", a.csv, (".csv",))):
        if path is not None and Path(path).suffix.lower() not in suffixes:
            raise InputError(f"{flag} {path}: the file name must end in {' or '.join(suffixes)}")
        require_output(path, flag, store)


def write_exports(a: argparse.Namespace, run, frame, name: str) -> None:
    """The run's trajectories to the files ``--geojson`` and ``--csv`` name (``run``: series of records,
    or a track's frames)."""
    for path in (a.geojson, a.csv):
        if path is not None:
            write_trajectory(path, run, frame, name=name)
            print(f"wrote {path}")
