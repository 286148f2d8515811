"""The dashboard's controller: the controls write a state, one apply path brings the page up to date.

Every callback records what the user asked for in ``Controls`` and asks for an apply; a
button may move other controls as a person would (Next moves the step slider, "Paper's parameters" moves every
parameter control, a mode its rate). One thread runs ``apply``: it compares what is asked with what is shown
(``Shown``) and does the difference, in order: open a store, load a database and its queries (background), match
every query (background, cancelled by a newer request), run the filter (instant), draw the step. Background jobs
hand their results back and ask for an apply in turn. A control moved by the program calls its callback like a
user's move does; that only records the same value again: no guard needed.

Everything shown comes from the engine's public API (``import visloc``); ``page`` draws it. All browser tabs share
one state, and a line says how many tabs are open and which one made the last change (``session``). A run is shown
as it is matched; a later run over the same queries and method fills in over the one shown, its steps as they are
matched and the previous run's beyond them, marked as such (``Run.shown``).
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import viser

import visloc
from visloc.dashboard import panels, runpanels
from visloc.dashboard.gui import (Handles, build_gui, enable_for_mode, paper_values, rate_follows_mode, saved_values,
                                  tuned_from_html)
from visloc.dashboard.jobs import LatestJobRunner
from visloc.dashboard.page import Page, run_file, run_file_name
from visloc.dashboard.session import SessionView
from visloc.dashboard.state import (CONTROLLED, Allowed, Controls, Run, Shown, discover_stores, first_choices,
                                    load_features, measure_drive)
from visloc.dashboard.viewkit import flat_scene

PARTIAL_EVERY_S = 0.5  # a run being matched is redrawn at most this often


class DashboardApp:
    def __init__(self, server: viser.ViserServer, store_path: Path, *, db_camera: str | None = "image_01",
                 query_camera: str | None = "image_00", db_source: str | None = None,
                 query_source: str | None = None, allowed: Allowed | None = None,
                 tune_from: tuple[Path, visloc.LiveSettings] | None = None, tiles=None,
                 query_images: Path | None = None):
        self.server, self.query_images = server, query_images  # query_images: see visloc.dashboard.state.measure_drive
        # the stores the page may open: by default the start store's folder (``visloc dashboard --allow``)
        self.allowed = allowed or Allowed.of([Path(store_path).parent], store_path)
        self.preferred = ((db_source, db_camera), (query_source, query_camera))  # None: any
        self.controls = Controls(store_request=(1, str(store_path)))
        self.shown = Shown()
        self._lock = threading.RLock()  # guards controls and shown; callbacks re-enter it from apply
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._jobs = LatestJobRunner(on_error=lambda name, exc: self._show_error(f"{name}: {exc}"))
        # the step's images (PNG reads, Figure 3) in their own worker: scrubbing never cancels a match
        self._image_jobs = LatestJobRunner(on_error=lambda name, exc: self._show_error(f"{name}: {exc}"))
        flat_scene(server.scene)
        self.gui = build_gui(server, str(store_path))
        self.page = Page(server, self.gui, tiles)  # tiles: web-map tiles under the map (a TileSource), or None
        self.session = SessionView(self.gui.session)  # how many tabs, and which one changed what
        server.on_client_connect(self._tab_opened)
        server.on_client_disconnect(self._tab_closed)
        self._connect(self.gui)
        if tune_from is not None:  # a saved run's settings: the controls move to them before the first apply
            values, moved = saved_values(tune_from[1])
            self._set_controls(values)
            self.gui.tuned_from.content = tuned_from_html(tune_from[0], tune_from[1], moved)
        self._threads = [threading.Thread(target=loop, name=f"visloc-dashboard-{name}", daemon=True)
                         for name, loop in (("apply", self._apply_loop), ("play", self._play_loop))]
        for t in self._threads:
            t.start()
        self.request_apply()

    # -- callbacks: record what was asked ---------------------------------------------------------

    def _connect(self, g: Handles) -> None:
        def records(handle, field: str, convert=lambda v: v) -> None:
            def on_update(event) -> None:
                with self._lock:
                    setattr(self.controls, field, convert(handle.value))
                if field not in ("play",):  # playback moves the step by itself: the move that counts is Play
                    self.session.changed(event, handle.label, handle.value)
                self.request_apply()

            handle.on_update(on_update)

        for handle, field, convert in (
            (g.mode, "method", str), (g.rate, "rate_hz", float), (g.start, "start_s", float),
            (g.step, "step", int), (g.play, "play", bool),
            (g.speed, "speed", lambda v: float(v.rstrip("x"))), (g.follow, "follow", bool),
            (g.latlon, "latlon", bool), (g.db, "db_name", str), (g.queries, "query_name", str),
            (g.magnify, "magnification", lambda v: runpanels.MAGNIFICATIONS[v]),
        ):
            records(handle, field, convert)
        for layer, box in g.layers.items():
            box.on_update(lambda e, layer=layer, box=box: self._layer(e, layer, box.value))
        rate_follows_mode(g)

        def records_param(handle, name: str, control) -> None:
            def on_update(event) -> None:
                with self._lock:  # a new dict: a copy of the controls taken earlier keeps its own
                    self.controls.params = {**self.controls.params, name: control.from_shown(float(handle.value))}
                self.session.changed(event, handle.label, handle.value)
                self.request_apply()

            handle.on_update(on_update)

        for _, name, spec, _ in CONTROLLED:
            records_param(g.params[name], name, spec.control)
        g.play.on_update(lambda e: self.session.changed(e, "Play", "on" if g.play.value else "off"))
        g.store.on_update(lambda _: self._ask_for_store(g.store.value, only_if_new=True))
        g.store_path.on_update(lambda _: self._store_typed(g.store_path.value.strip()))
        g.open.on_click(lambda e: (self.session.changed(e, "Open", Path(g.store_path.value.strip()).name),
                                   self._ask_for_store(g.store_path.value.strip())))
        g.prev_next.on_click(lambda e: (self.session.changed(e, "Move", g.prev_next.value),
                                        self._move_step(-1 if "Previous" in g.prev_next.value else 1)))
        g.reset.on_click(lambda e: (self.session.changed(e, "Paper's parameters", "pressed"), self._reset_to_paper()))
        for kind in ("geojson", "csv", "mcap"):  # the Export buttons
            getattr(g, kind).on_click(lambda e, kind=kind: self._download(e.client, kind))

    # -- the shared session's tabs, the 3D view's layers and each tab's scale ----------------------------

    def _layer(self, event, layer: str, shown: bool) -> None:
        with self._lock:
            self.controls.hidden = self.controls.hidden - {layer} if shown else self.controls.hidden | {layer}
        self.session.changed(event, layer, shown)
        self.request_apply()

    def _tab_opened(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(lambda _: self._rescale(client))  # its own scale bar and north arrow
        self.session.opened(client)

    def _rescale(self, client: viser.ClientHandle) -> None:
        with self._lock:
            if self.page.scale.rescale(client):
                self.page.apply_layers()

    def _tab_closed(self, client: viser.ClientHandle) -> None:
        self.page.scale.forget(client.client_id)
        self.session.closed(client)

    def _download(self, client: viser.ClientHandle | None, kind: str) -> None:
        """Send the run shown to the tab that asked, as GeoJSON, CSV or MCAP."""
        with self._lock:
            run, db = self.shown.run, self.shown.db
            if client is None or run is None or not run.records or db is None:
                return
            name = run_file_name(run)
            content = run_file(run, db.frame, name, kind)
        client.send_file_download(f"{name}.{kind}", content, save_immediately=True)

    def _ask_for_store(self, path: str, *, only_if_new: bool = False) -> None:
        with self._lock:
            count, asked = self.controls.store_request
            if only_if_new and path == asked:
                return
            self.controls.store_request = (count + 1, path)
        self.request_apply()

    def _store_typed(self, path: str) -> None:
        """Say which path Open will read: the page's answer to typing, before anything is opened."""
        self.gui.store_message.content = panels.status_html(f"Open reads {path}" if path else "")

    def _move_step(self, delta: int) -> None:
        with self._lock:
            run = self.shown.run
            n = len(run.shown().records) if run is not None else 0  # the steps drawn
            if n:
                self.gui.step.value = int(np.clip(self.controls.step + delta, 1, n))

    def _reset_to_paper(self) -> None:
        with self._lock:  # every control moves before the next apply looks
            self._set_controls(paper_values())
            self.controls.rerun += 1
            self.gui.tuned_from.content = ""
        self.request_apply()

    def _set_controls(self, values: dict) -> None:
        """Move the controls as a user would (``paper_values``' shape); each callback records its value."""
        values = dict(values)
        for name, value in values.pop("params").items():
            self.gui.params[name].value = value
        for name, value in values.items():
            getattr(self.gui, name).value = value

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                c = self.controls
                wait_s = max(0.1, 1.0 / (c.rate_hz * c.speed))
            self._stop.wait(wait_s)
            with self._lock:
                run = self.shown.run
                n = len(run.shown().records) if run is not None else 0  # the steps drawn
                if self.controls.play and n:
                    self.gui.step.value = self.controls.step % n + 1  # 1..N, then 1 again

    # -- applying: bring the page up to what is asked ------------------------------------------------

    def request_apply(self) -> None:
        self._wake.set()

    def _apply_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            if self._stop.is_set() or not self._wake.is_set():
                continue
            self._wake.clear()
            try:
                with self._lock:
                    self._apply()
            except Exception as exc:  # shown in the page; the server keeps running
                self._show_error(str(exc))

    def _apply(self) -> None:
        c = replace(self.controls)
        s = self.shown
        if c.store_request != s.store_request:
            s.store_request = c.store_request
            self._open_store(c.store_request[1])
            return  # the dataset choices it made are applied next time
        if s.workspace is None or c.db_name is None or c.query_name is None:
            return
        data_key = (s.store_path, c.db_name, c.query_name)
        if data_key != s.data_key:
            if data_key != s.loading_key:
                self._start_loading(data_key)
            return
        match_key = c.match_key(data_key)
        enable_for_mode(self.gui, c.method)
        run = s.run
        if (run is None or run.match_key != match_key or run.partial) and \
                match_key not in (s.matching_key, s.failed_key):
            self._start_matching(c, match_key)
            run = s.run  # a run filling in over a previous one went back to it
        if run is None or not run.matches.retrievals:
            return
        for r in (run.previous, run):  # the previous run too: its steps are drawn beyond the new run's
            if r is not None and r.track_key != self._track_key(r, c):
                self._track(r, c, self._track_key(r, c))
        track_key = run.track_key
        if c.hidden != self.page.hidden:
            self.page.hidden = c.hidden
            self.page.apply_layers()
        view = run.shown()
        if (track_key, c.magnification) != s.drawn_key:
            s.drawn_key = (track_key, c.magnification)
            self.page.draw_run(view, c.magnification)
        k = int(np.clip(c.step - 1, 0, len(view.records) - 1))  # the slider says 1..N
        note = panels.step_note(view, k, s.matching_key)
        if (track_key, k, c.follow, c.latlon, note, c.magnification) != s.step_key:
            s.step_key = (track_key, k, c.follow, c.latlon, note, c.magnification)
            self.page.draw_step(view, k, s.db, s.queries, follow=c.follow, latlon=c.latlon, note=note,
                                magnification=c.magnification)
            if (track_key, k, note) != s.image_key:
                s.image_key = (track_key, k, note)
                self._show_pictures(view, k, s.image_key)

    def _open_store(self, path: str) -> None:
        """Open a store file; a bad file is reported in the page and the previous data stays."""
        if not path or path == ".":
            self._store_error("Other store: type the path of a store file first")
            return
        if not self.allowed.admits(path):  # nothing outside is opened, or looked at
            self._store_error(self.allowed.refusal(path))
            return
        try:
            workspace = visloc.Workspace(path, read_only=True)  # the page never changes a store
            datasets = workspace.drives()
            if not datasets:
                raise visloc.InputError(f"{path}: holds no images yet (build it with 'visloc ingest')")
        except visloc.VislocError as exc:
            self._store_error(str(exc))
            return
        s = self.shown
        s.workspace, s.datasets, s.store_path, s.caches = workspace, datasets, path, {}
        names = [d.name for d in datasets]
        db_choice, q_choice = first_choices(datasets, *self.preferred)
        g = self.gui
        g.store.options = discover_stores(Path(path), self.allowed)
        g.store.value = path
        g.db.options, g.queries.options = names, names
        g.db.value, g.queries.value = db_choice, q_choice
        g.store_info.content = panels.store_html(path, datasets, workspace.sift_params)
        self.gui.store_message.content = panels.status_html(f"Opened {path}: {len(datasets)} image series")  # last: box shown
        self.request_apply()

    def _start_loading(self, data_key: tuple) -> None:
        s = self.shown
        s.loading_key = data_key
        workspace = s.workspace
        by_name = {d.name: d for d in s.datasets}
        _, db_name, q_name = data_key
        if db_name not in by_name or q_name not in by_name:
            return
        self._show_status(f"Loading {db_name} and {q_name}…")

        def load(cancelled) -> None:
            db, queries, paper_features = load_features(workspace, by_name[db_name], by_name[q_name])
            fast = visloc.REFINED_FAST_METHOD
            stored, index = workspace.load_structure(db, fast.pose), workspace.global_vectors.load_database_index(db, fast.shortlist)
            with self._lock:
                if cancelled() or s.loading_key != data_key:
                    return
                s.db, s.queries, s.paper_features, s.data_key, s.loading_key = db, queries, paper_features, data_key, None
                s.caches, s.structures, s.run, s.matching_key, s.step_key = {}, visloc.StructureCache(), None, None, None
                s.image_key = None
                s.stored, s.index, s.series_images = stored, index, None
                duration_s = float(queries.timestamps_s[-1] - queries.timestamps_s[0])
                self.gui.start.max = max(0.1, round(duration_s, 1))
                if self.gui.start.value > self.gui.start.max:
                    self.gui.start.value = 0.0
                self.page.draw_static(db.frame.to_local(queries.lat_deg, queries.lon_deg), db.east_north_m, db.frame)
            self.request_apply()

        self._jobs.submit("loading", load)

    def _start_matching(self, c: Controls, match_key: tuple) -> None:
        s = self.shown
        workspace = s.workspace
        try:
            method = visloc.method_named(c.method)
            match = c.params_for(visloc.PAPER_MATCH)
            retrieval = c.params_for(visloc.PAPER_RETRIEVAL)
            indices = visloc.drive_query_indices(s.queries.timestamps_s, c.start_s, 1.0 / c.rate_hz)
        except visloc.VislocError as exc:
            s.failed_key = match_key
            self._show_error(str(exc))
            return
        s.matching_key, (db, queries) = match_key, s.features(method)
        if s.run is not None and s.run.partial and s.run.previous is not None:
            s.run = s.run.previous  # a run superseded while it filled in: back to the complete one it replaced
        counted = (match.tau1, match.tau2, db.selected_contrast or db.retrieval_contrast)  # retrieval's features
        if counted not in s.caches:  # counts the store keeps for these thresholds
            s.caches[counted] = workspace.pair_cache(db, queries, match)
        cache = s.caches[counted]
        label = f"Matching {len(indices)} queries ({method.name}, τ1 {match.tau1:g}, τ2 {match.tau2:g})"
        self._show_status(label + "…")
        self.gui.progress.value, self.gui.progress.visible = 0.0, True
        self.request_apply()  # the run shown is now the previous one: say so
        last_partial = [0.0]

        def progress(done: int, total: int) -> None:
            if s.matching_key == match_key:
                self.gui.progress.value = 100.0 * done / max(total, 1)
                self._show_status(f"{label}: {done} of {total} queries matched")

        def partial(matches: visloc.DriveMatches) -> None:
            """The queries matched so far, shown as they come: a first run fills in; a later one over the same
            queries fills in over the run it replaces (``Run.shown``); any other, like a first run."""
            now = time.monotonic()
            if (now - last_partial[0] < PARTIAL_EVERY_S and len(matches) > 1) or len(matches) >= len(indices):
                return  # the first step at once; the last with the whole run
            last_partial[0] = now
            with self._lock:
                if s.matching_key != match_key:
                    return
                shown = s.run
                complete = shown if shown is not None and not shown.partial else getattr(shown, "previous", None)
                run = Run(matches, match_key, s.runs_done + 1, c.rate_hz, len(indices), partial=True)
                if run.replaces_in_place(complete):
                    run.previous = complete
                s.run = run
                self.request_apply()

        def match_all(cancelled) -> None:
            started = time.perf_counter()
            try:
                matches, not_following = measure_drive(s, queries, db, method, match, retrieval, indices, c.rate_hz,
                                                       cache, self.query_images, progress=progress,
                                                       cancelled=cancelled, on_step=partial)
            except visloc.MatchCancelled:
                return
            except visloc.VislocError as exc:
                with self._lock:
                    if s.matching_key == match_key:
                        s.matching_key, s.failed_key = None, match_key
                        self._show_error(str(exc))
                self.request_apply()
                return
            finally:
                n_new = workspace.save_pair_counts(cache)  # work done is kept, even when superseded
            with self._lock:
                if cancelled() or s.matching_key != match_key:
                    return
                s.runs_done += 1
                s.run = Run(matches, match_key, s.runs_done, c.rate_hz, len(indices))
                s.matching_key, s.step_key = None, None
                self.gui.progress.visible = False
                self._show_status(panels.ready_text(s.runs_done, matches, queries, db, n_new,
                                                    time.perf_counter() - started, not_following))
            self.request_apply()

        self._jobs.submit("matching", match_all)

    @staticmethod
    def _track_key(run: Run, c: Controls) -> tuple:
        """What a run's filtered records depend on: its measurements and the filter's controls."""
        return run.match_key, len(run.matches), run.partial, c.filter_key()

    def _track(self, run: Run, c: Controls, track_key: tuple) -> None:
        """Rerun the Kalman filter over the run's measurements (a filter-only change is just this)."""
        s = self.shown
        try:
            filter_params = replace(c, rate_hz=run.rate_hz).filter_params()
        except visloc.VislocError as exc:
            self._show_error(str(exc))
            return
        gate = c.params_for(visloc.REFINED).gate_chi2 if run.matches.method.measures_pose else 0.0
        run.records = visloc.track_drive(run.matches, s.queries, s.db, filter_params, gate_chi2=gate)
        run.track_key = track_key

    def _show_pictures(self, run: Run, k: int, image_key: tuple) -> None:
        """Read the step's images and draw Figure 3 in the background; show them if the step is still on."""
        db, queries = self.shown.features(run.matches.method)  # the features it matched
        s = self.shown

        def job(cancelled) -> None:
            show = self.page.step_pictures(run, k, db, queries)
            with self._lock:
                if not cancelled() and s.image_key == image_key:
                    show()

        self._image_jobs.submit("drawing the step's images", job)

    # -- messages ------------------------------------------------------------------------------------

    def _show_status(self, text: str) -> None:
        self.page.status(text)

    def _store_error(self, text: str) -> None:
        """A store that cannot be opened: said in the status line and, when the page asked for it (not the store it
        started on), under Open too until the next open, where the user is looking."""
        if self.shown.store_request is not None and self.shown.store_request[0] > 1:
            self.gui.store_message.content = panels.status_html(text, error=True)
        self._show_error(text)

    def _show_error(self, text: str) -> None:
        self.page.error(text)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._jobs.shutdown()
        self._image_jobs.shutdown()
        for t in self._threads:
            t.join(timeout=5)
