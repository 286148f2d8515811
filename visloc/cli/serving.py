"""``visloc dashboard``: the browser app on a store (live), or on saved runs (``--run``)."""

from __future__ import annotations

import argparse

from visloc.cli.choices import only_camera
from visloc.errors import InputError


def cmd_dashboard(a: argparse.Namespace) -> int:
    if not 1 <= a.port <= 65535:
        raise InputError(f"--port {a.port}: must be in 1..65535")
    from visloc.dashboard import serve, serve_runs  # on demand: the browser app (viser) is only needed here

    if a.run:  # saved runs: no store is opened
        serve_runs(a.run, host=a.host, port=a.port, announce=lambda text: print(text, flush=True))
        return 0
    only = only_camera(a.db)  # a store of one camera shows it first; a missing or bad store is reported in the page
    serve(a.db, host=a.host, port=a.port, db_camera=a.db_camera or only or "image_01",
          query_camera=a.query_camera or only or "image_00", db_source=a.db_source, query_source=a.query_source,
          allow=a.allow, announce=lambda text: print(text, flush=True))
    return 0
