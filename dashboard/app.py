"""The visloc dashboard: scrub through a drive, see trajectory and uncertainty in 3D, tune live.

Layers: this module only draws and reacts. Everything it shows comes from the
engine's public API (``visloc``): ``Workspace`` loads a store, ``match_drive``
retrieves the best match of every query (slow: runs on the background worker,
cancelled by newer changes), ``track_drive`` runs the Kalman filter (fast: runs
in the callback), ``correspondence_figure`` draws the paper's Figure 3.

All browser tabs share one state: what one tab changes, every tab sees.
"""

from __future__ import annotations

import html
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

import visloc
from dashboard import scene
from dashboard.jobs import LatestJobRunner

RATES_HZ = ("0.5", "1", "2", "5", "10")
SPEEDS = ("0.5x", "1x", "2x", "5x")
FIGURE_WIDTH_PX = 620
FRUSTUM_IMAGE_WIDTH_PX = 320
STORE_SUFFIXES = (".sqlite", ".sqlite3", ".db")


@dataclass(frozen=True)
class Tuning:
    """What the controls say, as engine parameters."""

    match: visloc.MatchParams
    retrieval: visloc.RetrievalParams
    filter: visloc.FilterParams
    start_s: float


def _fmt(value: float | None, fmt: str = ".2f", unit: str = " m") -> str:
    return "–" if value is None else f"{value:{fmt}}{unit}"


def _placeholder(text: str, width_px: int = FIGURE_WIDTH_PX, height_px: int = 120) -> np.ndarray:
    import cv2

    img = np.full((height_px, width_px, 3), 235, np.uint8)
    y = 30
    for line in text.split("\n"):
        cv2.putText(img, line[:90], (10, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (90, 90, 90), 1, cv2.LINE_AA)
        y += 24
    return img


def discover_stores(*paths: Path) -> list[str]:
    """Store files to offer: the given ones plus SQLite files beside them."""
    found: list[str] = []
    for p in paths:
        candidates = [p] + (sorted(p.parent.glob("*")) if p.parent.is_dir() else [])
        for c in candidates:
            if (c == p or c.suffix in STORE_SUFFIXES) and str(c) not in found and not c.is_dir():
                found.append(str(c))
    return found


class Dashboard:
    def __init__(self, server: viser.ViserServer, store_path: Path, *, db_camera: str = "image_01",
                 query_camera: str = "image_00"):
        self.server = server
        self.store_path = Path(store_path)
        self.preferred = (db_camera, query_camera)
        self._lock = threading.RLock()
        self._jobs = LatestJobRunner(on_error=lambda name, exc: self._show_error(f"{name}: {exc}"))
        # images of the current step (PNG reads, correspondences, Figure 3): off the callbacks too, in
        # their own worker so scrubbing never cancels a matching run; a newer step supersedes an older one
        self._image_jobs = LatestJobRunner(on_error=lambda name, exc: self._show_error(f"{name}: {exc}"))
        self._stop = threading.Event()
        self._quiet = False  # set while the reset button moves several controls at once

        self.workspace: visloc.Workspace | None = None
        self.datasets: list[visloc.Dataset] = []
        self.db: visloc.GeoDatabase | None = None
        self.queries: visloc.QuerySet | None = None
        self.caches: dict[tuple[float, float], visloc.PairCountCache] = {}
        self.structures = visloc.StructureCache()  # refined mode: database-side 3D structure, per database
        self.matches: visloc.DriveMatches | None = None
        self.records: list[visloc.StepRecord] = []
        self._figure_cache: dict[tuple, np.ndarray] = {}
        self._run_number = 0  # completed matching runs, shown in the status line

        server.scene.set_up_direction("+z")
        server.gui.configure_theme(control_layout="fixed", control_width="medium", show_share_button=False,
                                   titlebar_content=None, show_logo=False)
        self._build_gui()
        self._play_thread = threading.Thread(target=self._play_loop, name="visloc-dashboard-play", daemon=True)
        self._play_thread.start()
        self._open_store(self.store_path)

    # -- GUI ---------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.set_panel_label("visloc")
        legend = "".join(f"<div>{item}</div>" for item in [
            scene.swatch_html(scene.TRUTH_RGB, "ground truth"),
            scene.swatch_html(scene.MEASUREMENT_RGB, "measurement"),
            scene.swatch_html(scene.ESTIMATE_RGB, "Kalman estimate"),
            scene.swatch_html(scene.ELLIPSE_RGB, "2σ ellipse"),
            scene.swatch_html(scene.DATABASE_RGB, "database images"),
            scene.swatch_html(scene.CURRENT_RGB, "current step"),
        ])
        gui.add_html('<div style="font-size:12px;line-height:1.7;display:grid;grid-template-columns:1fr 1fr">'
                     f'{legend}</div>')
        self.gui_status = gui.add_html(self._status_html("Starting…"))
        self.gui_progress = gui.add_progress_bar(0.0, visible=False, animated=True)

        with gui.add_folder("Time"):
            self.gui_step = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0,
                                           hint="Query step of the drive run; everything follows it")
            self.gui_prev_next = gui.add_button_group("Move", ["◀ Previous", "Next ▶"])
            self.gui_play = gui.add_checkbox("Play", False, hint="Step through the drive")
            self.gui_speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x",
                                              hint="1x: one step per query interval, as the car drove")
            self.gui_follow = gui.add_checkbox("Camera follows", False,
                                               hint="Keep the 3D view centred on the current step")
        with gui.add_folder("Matching (re-matches in the background)"):
            self.gui_mode = gui.add_dropdown("Mode", visloc.MODES, initial_value="paper",
                                             hint="paper: the best match's geotag; refined: a metric pose from the "
                                                  "database's geometry (PnP), geotag as fallback")
            p = visloc.PAPER_MATCH
            self.gui_tau1 = gui.add_slider("τ1 (Lowe ratio)", min=0.5, max=1.0, step=0.01, initial_value=p.tau1,
                                           hint="Equation (1): d1²/d2² < τ1²")
            self.gui_tau2 = gui.add_slider("τ2 (cosine)", min=0.8, max=1.0, step=0.005, initial_value=p.tau2,
                                           hint="Equation (2): cosine similarity > τ2")
        with gui.add_folder("Filter (instant)"):
            f = visloc.PAPER_FILTER
            self.gui_r = gui.add_slider("R: meas. σ (m)", min=0.1, max=40.0, step=0.01,
                                        initial_value=round(float(np.sqrt(f.meas_var_m2)), 2),
                                        hint="R = σ² I for geotag measurements (the paper's 0.0001° is 11.12 m); "
                                             "refined poses bring their own R")
            self.gui_q = gui.add_slider("Q: accel. σ (m/s²)", min=0.0, max=5.0, step=0.05,
                                        initial_value=round(float(np.sqrt(f.accel_var_m2_s4)), 2),
                                        hint="White-acceleration process noise")
            self.gui_p0 = gui.add_slider("P0: initial σ", min=1.0, max=100.0, step=0.1,
                                         initial_value=round(float(np.sqrt(f.init_var)), 1),
                                         hint="P0 = σ² I (m, m/s); the paper's 1000·I is σ = 31.6")
            self.gui_gate = gui.add_slider("Gate χ² (refined)", min=0.0, max=50.0, step=0.01,
                                           initial_value=visloc.REFINED.gate_chi2,
                                           hint="Refined mode: skip a measurement whose squared Mahalanobis distance "
                                                "to the prediction exceeds this (13.82 = 99.9 %); 0 = off")
        with gui.add_folder("Queries"):
            self.gui_rate = gui.add_dropdown("Query rate (Hz)", RATES_HZ, initial_value="1",
                                             hint="One query every 1/rate s; also the filter's Δt")
            self.gui_start = gui.add_slider("Start time (s)", min=0.0, max=1.0, step=0.1, initial_value=0.0)
            self.gui_exclusion = gui.add_slider("Exclusion (s)", min=0.0, max=3.0, step=0.1,
                                                initial_value=visloc.PAPER_EVAL_RETRIEVAL.exclusion_s,
                                                hint="Ignore database images closer in time to the query")
            self.gui_window = gui.add_slider("Search window ± (s)", min=1.0, max=60.0, step=1.0,
                                             initial_value=visloc.PAPER_RETRIEVAL.window_s)
        self.gui_reset = gui.add_button("Paper's parameters", hint="τ1 0.8, τ2 0.97, R 0.0001°, P0 1000·I, 1 Hz")
        with gui.add_folder("Data", expand_by_default=False):
            self.gui_store = gui.add_dropdown("Store file", [str(self.store_path)], initial_value=str(self.store_path))
            self.gui_store_path = gui.add_text("Other store", "", hint="Path of another store file")
            self.gui_open = gui.add_button("Open")
            self.gui_db = gui.add_dropdown("Database", ["–"])
            self.gui_queries = gui.add_dropdown("Queries", ["–"])
            self.gui_store_info = gui.add_markdown("")

        panel = gui.add_panel()
        with panel.add_tab("Current step"):
            self.gui_figure = gui.add_image(_placeholder("No step yet"), label="query (top) and best match (bottom)",
                                            format="jpeg", jpeg_quality=85)
            self.gui_numbers = gui.add_markdown("")
            self.gui_counts_plot = gui.add_uplot(
                (np.zeros(1), np.zeros(1), np.zeros(1), np.full(1, np.nan)),
                ({"label": "database time (s)"},
                 {"label": "earlier images", "stroke": "rgb(120,120,120)", "width": 1.5,
                  "points": {"show": True, "size": 4}},
                 {"label": "later images", "stroke": "rgb(150,90,200)", "width": 1.5,
                  "points": {"show": True, "size": 4}},
                 {"label": "best match", "stroke": self._css(scene.CURRENT_RGB), "width": 0,
                  "points": {"show": True, "size": 9, "fill": self._css(scene.CURRENT_RGB)}}),
                title="Correspondences per candidate", aspect=2.0, scales={"x": {"time": False}})
            self.gui_error_plot = gui.add_uplot(
                (np.zeros(1),) + tuple(np.full(1, np.nan) for _ in range(4)),
                ({"label": "query time (s)"},
                 {"label": "measurement", "stroke": self._css(scene.MEASUREMENT_RGB), "width": 2,
                  "points": {"show": True, "size": 5}},
                 {"label": "estimate", "stroke": self._css(scene.ESTIMATE_RGB), "width": 2,
                  "points": {"show": True, "size": 5}},
                 {"label": "2σ", "stroke": self._css(scene.ELLIPSE_RGB), "width": 1.5, "dash": (5.0, 4.0)},
                 {"label": "current", "stroke": self._css(scene.CURRENT_RGB), "width": 0,
                  "points": {"show": True, "size": 10, "fill": self._css(scene.CURRENT_RGB)}}),
                title="Error per step (m), the paper's Figure 4", aspect=2.0, scales={"x": {"time": False}})
            self.gui_run_summary = gui.add_markdown("")
        panel.dock_left()
        panel.set_width(460)

        self.gui_step.on_update(lambda _: self._render_step())
        self.gui_prev_next.on_click(self._on_prev_next)
        for h in (self.gui_mode, self.gui_tau1, self.gui_tau2, self.gui_rate, self.gui_start, self.gui_exclusion,
                  self.gui_window):
            h.on_update(lambda _: self._schedule_match())
        for h in (self.gui_r, self.gui_q, self.gui_p0, self.gui_gate):
            h.on_update(lambda _: self._retrack())
        self.gui_reset.on_click(lambda _: self._reset_to_paper())
        self.gui_store.on_update(lambda _: self._open_store(Path(self.gui_store.value)))
        self.gui_open.on_click(lambda _: self._open_store(Path(self.gui_store_path.value.strip())))
        self.gui_db.on_update(lambda _: self._schedule_load())
        self.gui_queries.on_update(lambda _: self._schedule_load())

    @staticmethod
    def _css(rgb: tuple[int, int, int]) -> str:
        return f"rgb({rgb[0]},{rgb[1]},{rgb[2]})"

    @staticmethod
    def _status_html(text: str, *, error: bool = False) -> str:
        color = "#b00020" if error else "#333"
        weight = "600" if error else "400"
        return (f'<div style="font-size:13px;color:{color};font-weight:{weight};padding:2px 0;overflow-wrap:anywhere">'
                f'{html.escape(text)}</div>')

    def _show_status(self, text: str) -> None:
        self.gui_status.content = self._status_html(text)

    def _show_error(self, text: str) -> None:
        self.gui_progress.visible = False
        self.gui_status.content = self._status_html("⚠ " + text, error=True)

    # -- reading the controls -------------------------------------------------------------------

    def tuning(self) -> Tuning:
        interval_s = 1.0 / float(self.gui_rate.value)
        return Tuning(
            match=visloc.MatchParams(tau1=float(self.gui_tau1.value), tau2=float(self.gui_tau2.value)),
            retrieval=visloc.RetrievalParams(window_s=float(self.gui_window.value),
                                             exclusion_s=float(self.gui_exclusion.value)),
            filter=visloc.FilterParams(dt_s=interval_s, meas_var_m2=float(self.gui_r.value) ** 2,
                                       accel_var_m2_s4=float(self.gui_q.value) ** 2,
                                       init_var=float(self.gui_p0.value) ** 2),
            start_s=float(self.gui_start.value),
        )

    # -- data -----------------------------------------------------------------------------------

    def _open_store(self, path: Path) -> None:
        """Open a store file; a bad file is reported in the page and the previous data stays."""
        if not str(path) or str(path) == ".":
            self._show_error("Other store: type the path of a store file first")
            return
        try:
            workspace = visloc.Workspace(path)
            datasets = workspace.datasets()
            if not datasets:
                raise visloc.InputError(f"{path}: holds no images yet (build it with 'visloc ingest')")
        except visloc.VislocError as exc:
            self._show_error(str(exc))
            return
        with self._lock:
            self.workspace, self.datasets = workspace, datasets
            self.store_path = Path(path)
            self.caches = {}
            options = discover_stores(self.store_path)
            self.gui_store.options = options
            self.gui_store.value = str(self.store_path)
            names = [d.name for d in datasets]
            db_choice = next((d.name for d in datasets if d.camera == self.preferred[0]), names[0])
            q_choice = next((d.name for d in datasets if d.camera == self.preferred[1]), db_choice)
            self._quiet = True
            try:
                self.gui_db.options = names
                self.gui_queries.options = names
                self.gui_db.value, self.gui_queries.value = db_choice, q_choice
            finally:
                self._quiet = False
            sift = workspace.sift_params
            lines = [f"**{html.escape(str(path))}**", ""]
            lines += [f"- {d.name}: {d.n_images} images over {d.duration_s:.1f} s, "
                      f"{d.mean_keypoints:.0f} keypoints/image" + ("" if d.has_calibration else ", no calibration")
                      for d in datasets]
            lines += ["", "SIFT settings: " + (", ".join(f"{k}={v}" for k, v in sift.as_dict().items())
                                                if sift else "none yet")]
            self.gui_store_info.content = "\n".join(lines)
        self._schedule_load()

    def _schedule_load(self) -> None:
        if self._quiet or self.workspace is None:
            return
        workspace, db_name, q_name = self.workspace, self.gui_db.value, self.gui_queries.value
        by_name = {d.name: d for d in self.datasets}
        if db_name not in by_name or q_name not in by_name:
            return
        self._show_status(f"Loading {db_name} and {q_name}…")

        def load(cancelled) -> None:
            d, q = by_name[db_name], by_name[q_name]
            db = workspace.load_database(d.source, d.camera)
            queries = workspace.load_queries(q.source, q.camera)
            if cancelled():
                return
            with self._lock:
                self.db, self.queries, self.caches = db, queries, {}
                self.structures = visloc.StructureCache()
                self.matches, self.records = None, []
                self._figure_cache.clear()
                duration_s = float(queries.timestamps_s[-1] - queries.timestamps_s[0])
                self._quiet = True
                try:
                    self.gui_start.max = max(0.1, round(duration_s, 1))
                    if self.gui_start.value > self.gui_start.max:
                        self.gui_start.value = 0.0
                finally:
                    self._quiet = False
                self._draw_static_scene()
            self._match(cancelled)

        self._jobs.submit("loading", load)

    # -- matching (background) and tracking (inline) ----------------------------------------------

    def _schedule_match(self) -> None:
        if self._quiet or self.db is None:
            return
        self._jobs.submit("matching", self._match)

    def _match(self, cancelled) -> None:
        db, queries, workspace = self.db, self.queries, self.workspace
        if db is None or queries is None or workspace is None:
            return
        try:
            tuning = self.tuning()
            indices = visloc.drive_query_indices(queries.timestamps_s, tuning.start_s, tuning.filter.dt_s)
        except visloc.VislocError as exc:
            self._show_error(str(exc))
            return
        key = (tuning.match.tau1, tuning.match.tau2)
        if key not in self.caches:
            self.caches[key] = workspace.pair_cache(db, queries, tuning.match)
        cache = self.caches[key]
        mode = self.gui_mode.value
        label = f"Matching {len(indices)} queries ({mode}, τ1 {tuning.match.tau1:g}, τ2 {tuning.match.tau2:g})"
        self._show_status(label + "…")
        self.gui_progress.value = 0.0
        self.gui_progress.visible = True

        def progress(done: int, total: int) -> None:
            if not cancelled():
                self.gui_progress.value = 100.0 * done / max(total, 1)
                self._show_status(f"{label}: {done}/{total}")

        started = time.perf_counter()
        try:
            matches = visloc.match_drive(queries, db, tuning.match, tuning.retrieval, indices, cache=cache,
                                         progress=progress, cancelled=cancelled, mode=mode,
                                         structure_cache=self.structures)
        except visloc.MatchCancelled:
            return
        finally:
            n_new = workspace.save_pair_counts(cache)  # work done is kept, even when superseded
        if cancelled():
            return
        elapsed_s = time.perf_counter() - started
        work = f"{n_new} new image pairs matched in {elapsed_s:.1f} s" if n_new else "all image pairs cached"
        with self._lock:
            self.matches = matches
            self._figure_cache.clear()
            self._retrack()
            self.gui_progress.visible = False
            self._run_number += 1
            self._show_status(f"Ready (run {self._run_number}, {mode}, τ1 {tuning.match.tau1:g}, "
                              f"τ2 {tuning.match.tau2:g}): "
                              f"{len(matches)} queries of {queries.camera} against {len(db)} images of {db.camera}; "
                              f"{work}")

    def _retrack(self) -> None:
        """Filter-only change: rerun the Kalman filter over the cached measurements and redraw."""
        if self._quiet:
            return
        with self._lock:
            if self.matches is None or self.db is None or self.queries is None:
                return
            try:
                filter_params = self.tuning().filter
            except visloc.VislocError as exc:
                self._show_error(str(exc))
                return
            # the query interval is part of the match; the filter's dt follows it
            gate = float(self.gui_gate.value) if self.matches.mode == "refined" else 0.0
            self.records = visloc.track_drive(self.matches, self.queries, self.db, filter_params, gate_chi2=gate)
            n = len(self.records)
            self._quiet = True
            try:
                self.gui_step.max = max(1, n - 1)
                if self.gui_step.value > n - 1:
                    self.gui_step.value = n - 1
            finally:
                self._quiet = False
            self._draw_run()
            self._render_step()

    # -- drawing ----------------------------------------------------------------------------------

    def _draw_static_scene(self) -> None:
        """Database positions, the full ground-truth track, the grid and the initial view."""
        db, queries = self.db, self.queries
        s = self.server.scene
        truth_xy = db.frame.to_local(queries.lat_deg, queries.lon_deg)
        all_xy = np.concatenate([truth_xy, db.east_north_m])
        lo, hi = all_xy.min(axis=0), all_xy.max(axis=0)
        center = 0.5 * (lo + hi)
        extent_m = float(max(hi - lo)) + 40.0
        s.add_grid("/grid", width=extent_m, height=extent_m, plane="xy", cell_size=5.0, section_size=25.0,
                   position=(float(center[0]), float(center[1]), 0.0))
        s.add_point_cloud("/database/geotags", np.c_[db.east_north_m, np.full(len(db), scene.TRACK_HEIGHT_M)],
                          colors=scene.DATABASE_RGB, point_size=0.6, point_shape="circle")
        s.add_line_segments("/truth/track", scene.polyline_segments(truth_xy), colors=scene.TRUTH_RGB, thickness=0.25)
        # look from behind the start and to one side, from above: the whole track in view, and the
        # camera frustums (which face along the track) seen from behind so their images show
        cam = self.server.initial_camera
        span = max(float(max(hi - lo)), 20.0)
        along = truth_xy[-1] - truth_xy[0]
        along = along / np.linalg.norm(along) if np.linalg.norm(along) > 0 else np.array([0.0, 1.0])
        across = np.array([along[1], -along[0]])  # to the right of the direction of travel
        eye = center + span * (-0.75 * along + 0.55 * across)
        cam.look_at = (float(center[0]), float(center[1]), 0.0)
        cam.position = (float(eye[0]), float(eye[1]), 0.75 * span)
        cam.up = (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            client.camera.look_at = cam.look_at
            client.camera.position = cam.position

    def _draw_run(self) -> None:
        recs, db = self.records, self.db
        s = self.server.scene
        truth = db.frame.to_local(np.array([r.truth_lat_deg for r in recs]), np.array([r.truth_lon_deg for r in recs]))
        meas = self._local([(r.measurement_lat_deg, r.measurement_lon_deg) for r in recs])
        est = self._local([(r.estimate_lat_deg, r.estimate_lon_deg) for r in recs])
        z = scene.TRACK_HEIGHT_M
        with self.server.atomic():
            s.add_point_cloud("/truth/queries", np.c_[truth, np.full(len(recs), z)], colors=scene.TRUTH_RGB,
                              point_size=0.9, point_shape="circle")
            ok = np.all(np.isfinite(meas), axis=1)
            s.add_point_cloud("/measurement/points", np.c_[meas[ok], np.full(ok.sum(), z + 0.02)],
                              colors=scene.MEASUREMENT_RGB, point_size=1.4, point_shape="diamond")
            # dotted association: each measurement to its query's true position
            links = np.stack([np.c_[truth[ok], np.full(ok.sum(), z)], np.c_[meas[ok], np.full(ok.sum(), z)]], axis=1)
            s.add_line_segments("/measurement/offsets", links, colors=scene.MEASUREMENT_RGB, thickness=0.05)
            s.add_line_segments("/estimate/track", scene.polyline_segments(est, z + 0.04), colors=scene.ESTIMATE_RGB,
                                thickness=0.25)
            ok_est = np.all(np.isfinite(est), axis=1)
            s.add_point_cloud("/estimate/points", np.c_[est[ok_est], np.full(ok_est.sum(), z + 0.04)],
                              colors=scene.ESTIMATE_RGB, point_size=1.0, point_shape="circle")
            ellipses = [scene.closed_loop_segments(self._ellipse(r, e), z + 0.03)
                        for r, e in zip(recs, est) if np.all(np.isfinite(e))]
            if ellipses:
                s.add_line_segments("/estimate/ellipses", np.concatenate(ellipses), colors=scene.ELLIPSE_RGB,
                                    thickness=0.08)
            # refined measurements bring their own covariance: their 2-sigma ellipses (centimetres)
            own = [scene.closed_loop_segments(visloc.covariance_ellipse_m(mxy, np.array(r.measurement_cov_m2)),
                                              z + 0.05)
                   for r, mxy in zip(recs, meas) if r.measurement_source == "geometry" and r.measurement_cov_m2]
            s.add_line_segments("/measurement/ellipses", np.concatenate(own) if own else np.zeros((0, 2, 3)),
                                colors=scene.MEASUREMENT_RGB, thickness=0.03)
        t0 = float(self.queries.timestamps_s[0])
        times = np.array([r.query_timestamp_s - t0 for r in recs])
        self._error_series = (
            times,
            np.array([np.nan if r.measurement_error_m is None else r.measurement_error_m for r in recs]),
            np.array([np.nan if r.estimate_error_m is None else r.estimate_error_m for r in recs]),
            np.array([np.nan if r.estimate_sigma_m is None else 2.0 * r.estimate_sigma_m for r in recs]),
        )
        summary = visloc.drive_summary(recs)
        m = self.matches
        refined = (f"geometry on {100 * summary['geometry_fraction']:.0f}% of steps, "
                   f"{summary['gated_steps']} gated; " if m.mode == "refined" else "")
        self.gui_run_summary.content = (
            f"**This run** ({m.mode} mode, {summary['n_steps']} queries, {m.retrieval_params.exclusion_s:g} s "
            f"exclusion): {refined}"
            f"mean measurement error {_fmt(summary['mean_measurement_error_m'])}, "
            f"mean estimate error {_fmt(summary['mean_estimate_error_m'])}, "
            f"final estimate error {_fmt(summary['final_estimate_error_m'])}; "
            f"query latency median {np.median(m.latency_ms) / 1000.0:.2f} s (SIFT + matching, when first computed)."
        )

    def _local(self, lat_lon: list[tuple[float | None, float | None]]) -> np.ndarray:
        out = np.full((len(lat_lon), 2), np.nan)
        ok = [i for i, (la, lo) in enumerate(lat_lon) if la is not None and lo is not None]
        if ok:
            lat = np.array([lat_lon[i][0] for i in ok])
            lon = np.array([lat_lon[i][1] for i in ok])
            out[ok] = self.db.frame.to_local(lat, lon)
        return out

    @staticmethod
    def _ellipse(record: visloc.StepRecord, center_xy: np.ndarray) -> np.ndarray:
        return visloc.covariance_ellipse_m(center_xy, np.array(record.estimate_cov_m2), n_sigma=2.0)

    def _render_step(self) -> None:
        if self._quiet:
            return
        with self._lock:
            if not self.records:
                return
            k = int(np.clip(self.gui_step.value, 0, len(self.records) - 1))
            rec = self.records[k]
            db = self.db
            q_index = int(self.matches.query_indices[k])
            retrieval = self.matches.retrievals[k]
            truth = db.frame.to_local(rec.truth_lat_deg, rec.truth_lon_deg).reshape(2)
            est = self._local([(rec.estimate_lat_deg, rec.estimate_lon_deg)])[0]
            meas = self._local([(rec.measurement_lat_deg, rec.measurement_lon_deg)])[0]
            s = self.server.scene
            z = scene.TRACK_HEIGHT_M
            with self.server.atomic():
                s.add_icosphere("/current/truth", radius=0.9, color=scene.TRUTH_RGB,
                                position=(float(truth[0]), float(truth[1]), z))
                if np.all(np.isfinite(meas)):
                    s.add_icosphere("/current/measurement", radius=0.9, color=scene.MEASUREMENT_RGB,
                                    position=(float(meas[0]), float(meas[1]), z))
                else:
                    s.add_icosphere("/current/measurement", radius=0.9, color=scene.MEASUREMENT_RGB, visible=False)
                if np.all(np.isfinite(est)):
                    s.add_line_segments("/current/ellipse", scene.closed_loop_segments(self._ellipse(rec, est), z + 0.06),
                                        colors=scene.CURRENT_RGB, thickness=0.3)
                    s.add_icosphere("/current/estimate", radius=0.9, color=scene.ESTIMATE_RGB,
                                    position=(float(est[0]), float(est[1]), z + 0.04))
            if self.gui_follow.value:
                self._follow(truth)
            matches = self.matches
            self._image_jobs.submit("drawing the step's images",
                                    lambda cancelled: self._draw_step_images(k, matches, truth, cancelled))
            self.gui_numbers.content = self._numbers(rec, q_index)
            self._plot_counts(retrieval, rec)
            self._plot_errors(k)

    def _follow(self, target_xy: np.ndarray) -> None:
        """Move every tab's view so it looks at the current step, keeping its viewing angle."""
        target = np.array([float(target_xy[0]), float(target_xy[1]), 0.0])
        for client in self.server.get_clients().values():
            offset = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
            with client.atomic():
                client.camera.look_at = target
                client.camera.position = target + offset

    def _draw_step_images(self, k: int, matches: visloc.DriveMatches, truth_xy: np.ndarray, cancelled) -> None:
        """Background: read the query's and best match's images once, draw Figure 3 and the two
        camera frustums, and show them if step ``k`` of ``matches`` is still the one on screen."""
        db, queries = self.db, self.queries
        q_index = int(matches.query_indices[k])
        best = matches.retrievals[k].best_index
        q_path = queries.paths[q_index] if queries.paths else None
        d_path = db.images[best].path if best is not None else None
        q_gray, d_gray = self._read_image(q_path), self._read_image(d_path)
        if cancelled():
            return
        figure = self._figure(k, matches, q_index, best, q_gray, d_gray, q_path, d_path)
        if cancelled():
            return
        with self._lock:
            if self.matches is not matches or int(self.gui_step.value) != k:
                return
            self.gui_figure.image = figure
            self._draw_cameras(q_index, best, truth_xy, self._frustum_image(q_gray), self._frustum_image(d_gray))

    def _draw_cameras(self, q_index: int, best: int | None, truth_xy: np.ndarray, q_img: np.ndarray | None,
                      d_img: np.ndarray | None) -> None:
        db, queries = self.db, self.queries
        s = self.server.scene
        fov, aspect = self._fov_aspect()
        heading = float(queries.heading_deg[q_index]) if queries.heading_deg is not None else 0.0
        with self.server.atomic():
            s.add_camera_frustum("/current/query_camera", fov=fov, aspect=aspect, scale=5.0, color=scene.TRUTH_RGB,
                                 image=q_img, wxyz=scene.camera_wxyz(heading),
                                 position=(float(truth_xy[0]), float(truth_xy[1]), scene.CAMERA_HEIGHT_M),
                                 thickness=0.08)
            if best is None:
                s.add_camera_frustum("/current/match_camera", fov=fov, aspect=aspect, visible=False)
                return
            im = db.images[best]
            d_heading = im.heading_deg if im.heading_deg is not None else heading
            at = db.east_north_m[best]  # the database camera sits at its geotag (the paper's measurement)
            s.add_camera_frustum("/current/match_camera", fov=fov, aspect=aspect, scale=5.0,
                                 color=scene.MEASUREMENT_RGB, image=d_img, wxyz=scene.camera_wxyz(d_heading),
                                 position=(float(at[0]), float(at[1]), scene.CAMERA_HEIGHT_M), thickness=0.08)

    def _fov_aspect(self) -> tuple[float, float]:
        cal = self.db.calibration
        if cal is not None and cal.P_rect is not None and cal.height_px:
            return 2.0 * float(np.arctan(cal.height_px / (2.0 * cal.P_rect[1, 1]))), cal.width_px / cal.height_px
        im = self.db.images[0]
        return np.radians(50.0), (im.width_px / im.height_px if im.height_px else 4 / 3)

    @staticmethod
    def _read_image(path: str | None) -> np.ndarray | None:
        if not path or not Path(path).is_file():
            return None
        try:
            return visloc.load_gray(Path(path))
        except visloc.VislocError:
            return None

    @staticmethod
    def _frustum_image(gray: np.ndarray | None) -> np.ndarray | None:
        import cv2

        if gray is None:
            return None
        h, w = gray.shape
        small = cv2.resize(gray, (FRUSTUM_IMAGE_WIDTH_PX, max(1, round(h * FRUSTUM_IMAGE_WIDTH_PX / w))),
                           interpolation=cv2.INTER_AREA)
        return np.repeat(small[:, :, None], 3, axis=2)

    def _figure(self, k: int, matches: visloc.DriveMatches, q_index: int, best: int | None,
                q_gray: np.ndarray | None, d_gray: np.ndarray | None, q_path: str | None,
                d_path: str | None) -> np.ndarray:
        key = (k, q_index, best, matches.match_params)
        if key in self._figure_cache:
            return self._figure_cache[key]
        queries, db = self.queries, self.db
        if best is None:
            fig = _placeholder(f"Query frame {queries.frames[q_index]}: no database image has a correspondence")
        elif q_gray is None or d_gray is None:
            missing = q_path if q_gray is None else d_path
            fig = _placeholder(f"Image file not reachable:\n{missing}\n(the store keeps features, not images)")
        else:
            pairs = visloc.correspondences(queries.descriptors_u8[q_index], db.descriptors_u8[best],
                                           matches.match_params)
            q_xy = queries.keypoints_f32[q_index][pairs[:, 0], :2]
            d_xy = db.keypoints_f32[best][pairs[:, 1], :2]
            fig = visloc.correspondence_figure(
                q_gray, d_gray, q_xy, d_xy, width_px=FIGURE_WIDTH_PX,
                labels=(f"query {queries.camera} frame {queries.frames[q_index]}",
                        f"best match {db.camera} frame {db.images[best].frame}: {len(pairs)} correspondences"))
        self._figure_cache[key] = fig
        return fig

    def _numbers(self, rec: visloc.StepRecord, q_index: int) -> str:
        queries, db = self.queries, self.db
        t0 = float(queries.timestamps_s[0])
        rows = [
            ("query", f"{queries.camera} frame {rec.query_frame}, t = {rec.query_timestamp_s - t0:.2f} s"),
            ("best match", "none" if rec.best_db_frame is None else
             f"{db.camera} frame {rec.best_db_frame} ({rec.best_offset_s:+.2f} s), {rec.best_count} correspondences, "
             f"{rec.n_candidates} candidates"),
            ("measurement", "–" if rec.measurement_lat_deg is None else
             f"{rec.measurement_lat_deg:.7f}°, {rec.measurement_lon_deg:.7f}°"),
            ("measured by", self._source_text(rec)),
            ("measurement error", _fmt(rec.measurement_error_m)),
            ("measurement σ", _fmt(rec.measurement_sigma_m) + ("" if rec.measurement_source != "geotag" else
                                                              " (the filter's R)")),
            ("estimate", "–" if rec.estimate_lat_deg is None else
             f"{rec.estimate_lat_deg:.7f}°, {rec.estimate_lon_deg:.7f}°"),
            ("estimate error", _fmt(rec.estimate_error_m) + ("  (measurement gated: prediction only)"
                                                              if rec.gated else "")),
            ("estimate 2σ", _fmt(None if rec.estimate_sigma_m is None else 2.0 * rec.estimate_sigma_m)),
            ("nearest allowed image", _fmt(rec.nearest_candidate_error_m)),
            ("truth", f"{rec.truth_lat_deg:.7f}°, {rec.truth_lon_deg:.7f}°"),
        ]
        body = "\n".join(f"| {a} | {b} |" for a, b in rows)
        return f"**Step {rec.step + 1} of {len(self.records)}**\n\n| | |\n|---|---|\n{body}"

    @staticmethod
    def _source_text(rec: visloc.StepRecord) -> str:
        if rec.measurement_source == "geometry":
            return (f"geometry: PnP against frames {', '.join(map(str, rec.view_db_frames))} "
                    f"(triangulated with {', '.join(map(str, rec.neighbour_db_frames))}), "
                    f"{rec.n_pnp_inliers} inliers")
        if rec.measurement_source == "geotag":
            return "geotag of the best match" + (f" (fallback: {rec.fallback_reason})" if rec.fallback_reason else "")
        return "nothing" + (f" ({rec.fallback_reason})" if rec.fallback_reason else "")

    def _plot_counts(self, retrieval, rec: visloc.StepRecord) -> None:
        """Correspondences against database time: every database image, gaps where an image
        was no candidate (outside the search window, or inside the exclusion window)."""
        db = self.db
        t0 = float(self.queries.timestamps_s[0])
        times = db.timestamps_s - t0
        counts = np.full(len(db), np.nan)
        counts[retrieval.candidates] = retrieval.counts
        best = np.full(len(db), np.nan)
        if retrieval.best_index is not None:
            best[retrieval.best_index] = counts[retrieval.best_index]
        top = float(np.nanmax(counts)) if np.isfinite(counts).any() else 1.0
        # uPlot joins a line across NaN, so the images before and after the query are two
        # series; the exclusion window between them stays a gap
        earlier = np.where(db.timestamps_s < rec.query_timestamp_s, counts, np.nan)
        later = np.where(db.timestamps_s >= rec.query_timestamp_s, counts, np.nan)
        # an explicit y range: uPlot's automatic range breaks on NaN
        self.gui_counts_plot.scales = {"x": {"time": False}, "y": {"auto": False, "range": (0.0, 1.1 * top + 1.0)}}
        self.gui_counts_plot.data = (times, earlier, later, best)
        self.gui_counts_plot.title = f"Correspondences per database image (query at {rec.query_timestamp_s - t0:.1f} s)"

    def _plot_errors(self, k: int) -> None:
        times, m_err, e_err, two_sigma = self._error_series
        current = np.full(len(times), np.nan)
        current[k] = e_err[k] if np.isfinite(e_err[k]) else m_err[k]
        values = np.concatenate([m_err, e_err, two_sigma])
        top = float(np.nanmax(values)) if np.isfinite(values).any() else 1.0
        self.gui_error_plot.scales = {"x": {"time": False}, "y": {"auto": False, "range": (0.0, 1.1 * top + 0.1)}}
        self.gui_error_plot.data = (times, m_err, e_err, two_sigma, current)

    # -- time control ----------------------------------------------------------------------------

    def _on_prev_next(self, event) -> None:
        if not self.records:
            return
        delta = -1 if "Previous" in self.gui_prev_next.value else 1
        self.gui_step.value = int(np.clip(self.gui_step.value + delta, 0, len(self.records) - 1))

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            try:
                interval_s = 1.0 / float(self.gui_rate.value)
                speed = float(self.gui_speed.value.rstrip("x"))
            except ValueError:
                interval_s, speed = 1.0, 1.0
            self._stop.wait(max(0.1, interval_s / speed))
            if self.gui_play.value and self.records:
                self.gui_step.value = (int(self.gui_step.value) + 1) % len(self.records)

    def _reset_to_paper(self) -> None:
        m, f = visloc.PAPER_MATCH, visloc.PAPER_FILTER
        self._quiet = True
        try:
            self.gui_mode.value = "paper"
            self.gui_gate.value = visloc.REFINED.gate_chi2
            self.gui_tau1.value, self.gui_tau2.value = m.tau1, m.tau2
            self.gui_r.value = round(float(np.sqrt(f.meas_var_m2)), 2)
            self.gui_q.value = round(float(np.sqrt(f.accel_var_m2_s4)), 2)
            self.gui_p0.value = round(float(np.sqrt(f.init_var)), 1)
            self.gui_rate.value = "1"
            self.gui_start.value = 0.0
            self.gui_exclusion.value = visloc.PAPER_EVAL_RETRIEVAL.exclusion_s
            self.gui_window.value = visloc.PAPER_RETRIEVAL.window_s
        finally:
            self._quiet = False
        self._schedule_match()

    def close(self) -> None:
        self._stop.set()
        self._jobs.shutdown()
        self._image_jobs.shutdown()
