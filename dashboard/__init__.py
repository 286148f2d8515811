"""visloc's browser dashboard (viser): scrub through a drive, see the trajectory and its
uncertainty in 3D, tune tau1, tau2, R, Q and P0 live. Start it with ``visloc dashboard``.

Layout, in viser's own style: ``state`` (what the controls ask for, what the page shows),
``gui`` (the control panel, built once), ``explain`` (hints, the terms, the help fold),
``scene``, ``panels`` and ``mapview`` (pure drawing: the 3D scene, the step table, the plots
and pictures, the top-down map), ``page`` (puts a run and a step on the page), ``session``
(the tabs sharing the page and the last change), ``app`` (callbacks record, one apply path
redraws), ``jobs`` (the background worker), ``server`` (``serve``), and the saved-run viewer:
``runview`` (a run file opened without its store, compared with another) drawing through ``runpanels``. It calls only the
engine's public API (``import visloc``).
"""

from visloc.dashboard.app import DashboardApp
from visloc.dashboard.server import serve, serve_runs

__all__ = ["DashboardApp", "serve", "serve_runs"]
