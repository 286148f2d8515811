"""Drawing what the apply path decided onto the page: the run, the current step (table, plots,
map, 3D highlight, pictures), the stale badges, the status line and the files to download.

``Page`` holds the server and the panel's handles and nothing the controls ask for; the app
calls it with the lock held (see ``visloc.dashboard.app``).
"""

from __future__ import annotations


import numpy as np
import viser

import visloc
from visloc.dashboard import mapview, panels, runpanels, scene
from visloc.dashboard.gui import Handles
from visloc.dashboard.state import Run


def run_file(run: Run, frame: visloc.LocalFrame, name: str, fmt: str) -> bytes:
    """The run's trajectories (truth, measurements, estimates with covariance) as a "geojson" or "csv" file."""
    return visloc.trajectory_text([run.records], frame, name=name, fmt=fmt).encode("utf-8")


def run_file_name(run: Run) -> str:
    """A file name (without suffix) saying which run it is."""
    tau1, tau2 = run.matches.match_params.tau1, run.matches.match_params.tau2
    which = "partial" if run.partial else f"run{run.number}"
    return f"visloc_{which}_{run.matches.method.name}_tau1-{tau1:g}_tau2-{tau2:g}_{run.rate_hz:g}Hz"


def draw_timelines(plots: dict, steps: list[visloc.SavedStep], k: int, other=None) -> None:
    """Every timeline over ``steps``, step ``k`` marked (``other``: a comparison run's steps)."""
    for kind, plot in plots.items():
        data, y_range = runpanels.timeline(kind, steps, k, other)
        plot.scales = {"x": {"time": False}, "y": {"auto": False, "range": y_range}}
        plot.data = tuple(np.asarray(d, float) for d in data)


class Page:
    def __init__(self, server: viser.ViserServer, gui: Handles):
        self.server, self.gui = server, gui
        self.truth_track_m = np.zeros((0, 2))  # every query's truth, for the map
        self.db_m = np.zeros((0, 2))
        self.pictures_shown = False  # a step's pictures are on the page (not the first placeholder)

    # -- messages ----------------------------------------------------------------------------------

    def status(self, message: str) -> None:
        self.gui.status.content = panels.status_html(message)

    def error(self, message: str) -> None:
        self.gui.progress.visible = False
        self.gui.status.content = panels.status_html(message, error=True)

    # -- the data, the run, the step -----------------------------------------------------------------

    def draw_static(self, truth_m: np.ndarray, db_m: np.ndarray) -> None:
        """The drive before any run: grid, database images, the truth track; the view on them."""
        self.truth_track_m, self.db_m = np.asarray(truth_m, float), np.asarray(db_m, float)
        scene.draw_static(self.server.scene, truth_m, db_m)
        look_at, position = scene.initial_view(truth_m, db_m)
        self.server.initial_camera.look_at, self.server.initial_camera.position = look_at, position
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            client.camera.look_at, client.camera.position = look_at, position
        self.gui.map.image = mapview.map_image(self.truth_track_m, self.db_m, [], None)

    def draw_run(self, run: Run) -> None:
        n = len(run.records)
        g = self.gui
        g.step.max = max(2, n)
        if g.step.value > n:
            g.step.value = n
        with self.server.atomic():
            scene.draw_run(self.server.scene, run.records)
        g.run_summary.content = ("" if run.partial else panels.run_summary_markdown(run.records, run.matches))
        g.geojson.disabled = g.csv.disabled = n == 0

    def draw_step(self, run: Run, k: int, db: visloc.GeoDatabase, queries: visloc.QuerySet, *, follow: bool,
                  latlon: bool, note: str | None) -> None:
        """Step ``k`` (0-based) of ``run``; ``note`` says the run shown is not the one asked for."""
        g = self.gui
        rec, retrieval = run.records[k], run.matches.retrievals[k]
        t0_s = float(queries.timestamps_s[0])
        with self.server.atomic():
            scene.draw_current(self.server.scene, rec)
        if follow:
            self.follow(rec.truth_m)
        g.step_badge.content = g.map_badge.content = panels.stale_badge_html(note)
        g.numbers.content = panels.step_html(rec, len(run.records), visloc.record_geotags(rec, db.frame),
                                             *panels.series_names(queries, db), t0_s, latlon=latlon,
                                             n_queries=run.n_queries if run.partial else None, stale=bool(note))
        suffix = " — previous run" if note else ""
        data, scales, title = panels.counts_plot(retrieval, db.timestamps_s, rec.query_timestamp_s, t0_s)
        g.counts_plot.scales, g.counts_plot.data, g.counts_plot.title = scales, data, title + suffix
        data, scales = panels.error_plot(run.records, k, t0_s)
        g.error_plot.scales, g.error_plot.data = scales, data
        g.error_plot.title = "Error per step (m), the paper's Figure 4" + suffix
        draw_timelines(g.timelines, visloc.steps_of_records(run.records, t0_s), k)
        g.map.image = mapview.map_image(self.truth_track_m, self.db_m, run.records, k,
                                        note="previous run - re-matching" if note else None)
        if not self.pictures_shown:
            g.figure.image = panels.placeholder(f"Reading the images of step {k + 1}…".replace("…", "..."))

    def step_pictures(self, run: Run, k: int, db: visloc.GeoDatabase, queries: visloc.QuerySet):
        """Slow part of a step, for a background job: the query's and best match's images read and
        Figure 3 drawn. Returns a function that shows them (call it with the lock held)."""
        q_index = int(run.matches.query_indices[k])
        best = run.matches.retrievals[k].best_index
        q_gray = panels.read_gray(queries.paths[q_index] if queries.paths else None)
        d_gray = panels.read_gray(db.images[best].path if best is not None else None)
        figure = panels.step_figure(queries, db, q_index, best, run.matches.match_params, q_gray, d_gray)

        def show() -> None:
            self.gui.figure.image, self.pictures_shown = figure, True
            rec = run.records[k]
            heading = float(queries.heading_deg[q_index]) if queries.heading_deg is not None else 0.0
            match_heading = heading if best is None or db.images[best].heading_deg is None else \
                db.images[best].heading_deg
            with self.server.atomic():
                scene.draw_cameras(self.server.scene, *self.fov_aspect(db), rec.truth_m, heading,
                                   panels.frustum_image(q_gray),
                                   None if best is None else tuple(db.east_north_m[best]), match_heading,
                                   panels.frustum_image(d_gray))

        return show

    def follow(self, target_xy: tuple[float, float]) -> None:
        """Move every tab's view so it looks at the current step, keeping its viewing angle."""
        target = np.array([target_xy[0], target_xy[1], 0.0])
        for client in self.server.get_clients().values():
            offset = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            with client.atomic():
                client.camera.look_at = target
                client.camera.position = target + offset

    @staticmethod
    def fov_aspect(db: visloc.GeoDatabase) -> tuple[float, float]:
        cal = db.calibration
        if cal is not None and cal.P_rect is not None and cal.height_px:
            return 2.0 * float(np.arctan(cal.height_px / (2.0 * cal.P_rect[1, 1]))), cal.width_px / cal.height_px
        im = db.images[0]
        return np.radians(50.0), (im.width_px / im.height_px if im.height_px else 4 / 3)
