"""Drawing what the apply path decided onto the page: the run, the current step (table, plots,
map, 3D highlight, pictures), the stale badges, the status line and the files to download.

``Page`` holds the server and the panel's handles and nothing the controls ask for; the app
calls it with the lock held (see ``visloc.dashboard.app``).
"""

from __future__ import annotations

import threading

import numpy as np
import viser

import visloc
from visloc.dashboard import mapview, panels, runpanels, scene
from visloc.dashboard.gui import LAYER_NODES, Handles
from visloc.dashboard.state import Run
from visloc.dashboard.viewkit import KeptScene, ScaleFollower, apply_layers, draw_grid


def run_file(run: Run, frame: visloc.LocalFrame, name: str, fmt: str) -> bytes:
    """The run's trajectories (truth, measurements, estimates with covariance) as a "geojson", "csv" or
    "mcap" file."""
    if fmt == "mcap":
        import tempfile
        from pathlib import Path

        with tempfile.TemporaryDirectory(prefix="visloc-mcap-") as folder:
            path = Path(folder) / f"{name}.mcap"
            visloc.write_run_mcap(path, [run.records], frame, name=name)
            return path.read_bytes()
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
    def __init__(self, server: viser.ViserServer, gui: Handles, tile_source=None):
        self.server, self.gui = server, gui
        self.scene = KeptScene(server.scene)  # every node kept by name, for the layer checkboxes
        self.scale = ScaleFollower(server, self.scene)  # each tab's scale bar and north arrow
        self.hidden: frozenset[str] = frozenset()  # the layers hidden
        self.largest_m, self.farthest_m = 10.0, 200.0  # a magnified ellipse's largest size; camera-follow's reach
        self.truth_track_m = np.zeros((0, 2))  # every query's truth, for the map
        self.db_m = np.zeros((0, 2))
        self.pictures_shown = False  # a step's pictures are on the page (not the first placeholder)
        self.tile_source = tile_source  # web-map tiles under the map (``visloc.dashboard.tiles.TileSource``), or None
        self.tiles = None  # that source on the drive shown (``TileLayer``)
        self._map_shown = None  # (records, step, note) of the map on the page, drawn again when tiles come
        self._map_lock = threading.Lock()  # the map is drawn by the apply path and by the tiles' thread
        if tile_source is not None:
            tile_source.on_fetched = self._tiles_came

    # -- messages ----------------------------------------------------------------------------------

    def status(self, message: str) -> None:
        self.gui.status.content = panels.status_html(message)

    def error(self, message: str) -> None:
        self.gui.progress.visible = False
        self.gui.status.content = panels.status_html(message, error=True)

    # -- the data, the run, the step -----------------------------------------------------------------

    def draw_static(self, truth_m: np.ndarray, db_m: np.ndarray, frame: visloc.LocalFrame | None = None) -> None:
        """The drive before any run: grid, database images, the truth track; the view on them (``frame``: the
        database's local frame, where the map's tiles go)."""
        from visloc.dashboard.tiles import TileLayer

        self.truth_track_m, self.db_m = np.asarray(truth_m, float), np.asarray(db_m, float)
        self.tiles = TileLayer(self.tile_source, frame) if self.tile_source is not None and frame else None
        every = np.concatenate([self.truth_track_m, self.db_m])
        extent_m = float(max(every.max(axis=0) - every.min(axis=0)))
        self.largest_m, self.farthest_m = max(extent_m / 4, 1.0), max(1.5 * extent_m, 50.0)
        scene.draw_static(self.scene, truth_m, db_m)
        draw_grid(self.scene, every, margin_m=40.0)
        self.apply_layers()
        look_at, position = scene.initial_view(truth_m, db_m)
        self.server.initial_camera.look_at, self.server.initial_camera.position = look_at, position
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():  # look_at last: viser moves it with a new position
            client.camera.position, client.camera.look_at = position, look_at
        self.show_map([], None, None)

    def show_map(self, records: list, k: int | None, note: str | None) -> None:
        """The top-down map of ``records`` at step ``k`` (``note``: it is not the run asked for), on its tiles."""
        with self._map_lock:
            self._map_shown = (records, k, note)
            self._draw_map()

    def _tiles_came(self) -> None:
        with self._map_lock:
            if self._map_shown is not None:
                self._draw_map()

    def _draw_map(self) -> None:
        records, k, note = self._map_shown
        self.gui.map.image = mapview.map_image(self.truth_track_m, self.db_m, records, k, note=note, tiles=self.tiles)
        if self.tiles is not None:  # under the map: its tiles' attribution, or why it has none now (no network)
            self.gui.map_tiles.content = panels.tiles_html(self.tiles.caption, problem=bool(self.tiles.source.problem))

    def factor(self, magnification: float):
        """How many times larger each ellipse is drawn (``runpanels.drawn_factor``), as a function of its covariance."""
        return lambda cov: runpanels.drawn_factor(cov, magnification, self.largest_m)

    def apply_layers(self) -> None:
        apply_layers(self.scene, LAYER_NODES, set(self.hidden))

    def draw_run(self, run: Run, magnification: float = 1.0) -> None:
        n = len(run.records)
        g = self.gui
        g.step.max = max(2, n)
        if g.step.value > n:
            g.step.value = n
        with self.server.atomic():
            scene.draw_run(self.scene, run.records, self.factor(magnification))
            self.apply_layers()
        g.run_summary.content = ("" if run.partial else panels.run_summary_markdown(run.records, run.matches))
        g.geojson.disabled = g.csv.disabled = g.mcap.disabled = n == 0

    def draw_step(self, run: Run, k: int, db: visloc.GeoDatabase, queries: visloc.QuerySet, *, follow: bool,
                  latlon: bool, note: str | None, magnification: float = 1.0) -> None:
        """Step ``k`` (0-based) of ``run``; ``note`` says the run shown is not the one asked for."""
        g = self.gui
        rec, retrieval = run.records[k], run.matches.retrievals[k]
        t0_s = float(queries.timestamps_s[0])
        shown = runpanels.drawn_factor(rec.estimate_cov_m2, magnification, self.largest_m)
        with self.server.atomic():
            scene.draw_current(self.scene, rec, self.factor(magnification),
                               marker_m=runpanels.marker_m(rec.estimate_sigma_m, shown),
                               label=f"step {k + 1}" + ("" if shown == 1.0 else f", ellipse ×{shown:.3g}"))
            self.apply_layers()
        if follow:
            self.follow(rec.estimate_m or rec.truth_m, runpanels.follow_distance_m(rec, shown, self.farthest_m))
        g.step_badge.content = g.map_badge.content = panels.stale_badge_html(note)
        g.numbers.content = panels.step_html(rec, len(run.records), visloc.record_geotags(rec, db.frame),
                                             *panels.series_names(queries, db), t0_s, latlon=latlon,
                                             matched=self.matched(run), stale=bool(note),
                                             kind=run.matches.kinds[k] if run.matches.follows_points else None)
        suffix = " — previous run" if note else ""
        data, scales, title = panels.counts_plot(retrieval, db.timestamps_s, rec.query_timestamp_s, t0_s)
        g.counts_plot.scales, g.counts_plot.data, g.counts_plot.title = scales, data, title + suffix
        data, scales = panels.error_plot(run.records, k, t0_s)
        g.error_plot.scales, g.error_plot.data = scales, data
        g.error_plot.title = "Error per step (m), the paper's Figure 4" + suffix
        draw_timelines(g.timelines, visloc.steps_of_records(run.records, t0_s), k)
        self.show_map(run.records, k, "previous run - re-matching" if note else None)
        if not self.pictures_shown:
            g.figure.image = panels.placeholder(f"Reading the images of step {k + 1}…".replace("…", "..."))

    def step_pictures(self, run: Run, k: int, db: visloc.GeoDatabase, queries: visloc.QuerySet):
        """Slow part of a step, for a background job: the query's and best match's images read and
        Figure 3 drawn. Returns a function that shows them (call it with the lock held)."""
        q_index = int(run.matches.query_indices[k])
        best = run.matches.retrievals[k].best_index
        q_gray = panels.read_gray(queries.paths[q_index] if queries.paths else None)
        d_gray = panels.read_gray(db.images[best].path if best is not None else None)
        figure = panels.step_figure(queries, db, q_index, best, run.match_params_of(k), q_gray, d_gray,
                                    run.matches.kinds[k] if run.matches.follows_points else None)

        def show() -> None:
            self.gui.figure.image, self.pictures_shown = figure, True
            rec = run.records[k]
            heading = float(queries.heading_deg[q_index]) if queries.heading_deg is not None else 0.0
            match_heading = heading if best is None or db.images[best].heading_deg is None else \
                db.images[best].heading_deg
            with self.server.atomic():
                scene.draw_cameras(self.scene, *self.fov_aspect(db), rec.truth_m, heading,
                                   panels.frustum_image(q_gray),
                                   None if best is None else tuple(db.east_north_m[best]), match_heading,
                                   panels.frustum_image(d_gray))
                self.apply_layers()

        return show

    @staticmethod
    def matched(run: Run) -> tuple[int, int] | None:
        """(queries matched so far, queries in the run) while ``run`` is being matched, else None."""
        if not run.partial:
            return None
        return (run.fresh_steps if run.fresh_steps is not None else len(run.records)), run.n_queries

    def follow(self, target_xy: tuple[float, float], distance_m: float) -> None:
        """Move every tab's view to look at the current estimate from ``distance_m`` (framing its ellipse),
        keeping its viewing angle."""
        target = np.array([target_xy[0], target_xy[1], 0.0])
        for client in self.server.get_clients().values():
            offset = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            offset = offset / max(float(np.linalg.norm(offset)), 1e-9) * distance_m
            with client.atomic():
                client.camera.position = target + offset  # a position set moves look_at with it: look_at last
                client.camera.look_at = target

    @staticmethod
    def fov_aspect(db: visloc.GeoDatabase) -> tuple[float, float]:
        cal = db.calibration
        if cal is not None and cal.P_rect is not None and cal.height_px:
            return 2.0 * float(np.arctan(cal.height_px / (2.0 * cal.P_rect[1, 1]))), cal.width_px / cal.height_px
        im = db.images[0]
        return np.radians(50.0), (im.width_px / im.height_px if im.height_px else 4 / 3)
