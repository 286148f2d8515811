"""visloc's browser dashboard (viser): scrub through a drive, see the trajectory and
uncertainty in 3D, tune tau1, tau2, R, Q and P0 live. Start it with ``visloc dashboard``.

It calls only the engine's public API (``import visloc``)."""

from dashboard.app import Dashboard
from dashboard.server import serve

__all__ = ["Dashboard", "serve"]
