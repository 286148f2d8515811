"""The saved-run viewer: a run that ``evaluate``, ``evaluate-drives`` or ``track`` wrote, opened in the
browser without its store (``visloc dashboard --run FILE``), scrubbed like a live run, and compared
with a second run.

One lock guards the viewer's state; every control's callback changes the state and redraws what
it touched (reading a run file is the only slow part, a second or two for a long evaluation).
The 3D view carries its own sense of scale: a grid labelled in metres, and a scale bar and a north
arrow that follow each tab's camera as it zooms. Clicking the trajectory jumps to the nearest step.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import viser

import visloc
from visloc.dashboard import runpanels as rp
from visloc.dashboard import scene
from visloc.dashboard.gui import timeline_plots
from visloc.dashboard.page import draw_timelines
from visloc.dashboard.panels import status_html
from visloc.dashboard.viewkit import SCALE_NODES, KeptScene, ScaleFollower, apply_layers, draw_grid, flat_scene

COMPARE_RGB = rp.COMPARE_RGB
LAYERS = ("Truth", "Measurements", "Estimate", "Estimate ellipses", "Measurement ellipses", "Comparison",
          "Grid and scale")
Z = scene.TRACK_HEIGHT_M
LAYER_NODES = {"Truth": ("/truth",), "Measurements": ("/measurement/points",), "Estimate": ("/estimate/track",),
               "Estimate ellipses": ("/estimate/ellipses",), "Measurement ellipses": ("/measurement/ellipses",),
               "Comparison": ("/comparison",), "Grid and scale": SCALE_NODES}


@dataclass
class ViewerState:
    main: visloc.SavedRun | None = None
    other: visloc.SavedRun | None = None
    series: int = 0
    k: int = 0  # 0-based step in the series
    magnification: float = 1.0
    hidden: set[str] = field(default_factory=set)
    follow: bool = False
    play: bool = False


def unique_labels(files: list[tuple[str, Path]]) -> list[str]:
    seen: dict[str, int] = {}
    out = []
    for label, _ in files:
        seen[label] = seen.get(label, 0) + 1
        out.append(label if seen[label] == 1 else f"{label} ({seen[label]})")
    return out


class RunViewer:
    def __init__(self, server: viser.ViserServer, files: list[tuple[str, Path]], compare: int | None = None):
        self.server, self.files = server, files
        self.scene = KeptScene(server.scene)
        self._scale = ScaleFollower(server, self.scene)
        self.labels = unique_labels(files)
        self.state = ViewerState()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        flat_scene(server.scene)
        self._largest_m, self._farthest_m, self._marker_m = 10.0, 200.0, 0.1  # set for each series drawn
        self._build_gui(compare)
        server.on_client_connect(self._tab_opened)
        server.scene.on_click()(self._clicked)  # a click near the trajectory jumps to the nearest step
        self._open(0, compare)
        self._player = threading.Thread(target=self._play_loop, name="visloc-run-player", daemon=True)
        self._player.start()

    # -- the controls ----------------------------------------------------------------------------------

    def _build_gui(self, compare: int | None) -> None:
        gui = self.server.gui
        gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False,
                            titlebar_content=None, show_logo=False)
        gui.set_panel_label("visloc: saved runs")
        self.status = gui.add_html(status_html("Reading the run…"))
        self.run = gui.add_dropdown("Run", self.labels, initial_value=self.labels[0],
                                    hint="The saved run shown (a file written by evaluate, evaluate-drives or track)")
        self.compare = gui.add_dropdown("Compare with", (rp.NO_COMPARISON, *self.labels),
                                        initial_value=rp.NO_COMPARISON if compare is None else self.labels[compare],
                                        hint="A second run drawn beside the first, in purple, and on the timelines")
        self.series = gui.add_dropdown("Series", ["–"], hint="An evaluation has one series per start frame; "
                                       "a track run one series of every frame")
        with gui.add_folder("Time"):
            self.step = gui.add_slider("Step", min=1, max=2, step=1, initial_value=1,
                                       hint="The step shown: 3D view, step table and the timelines' mark")
            self.move = gui.add_button_group("Move", ["◀ Previous", "Next ▶"])
            self.play = gui.add_checkbox("Play", False, hint="Step through the series at its own time step")
            self.jump = gui.add_dropdown("Jump to", ["–"], hint="The worst steps by estimate error, then every "
                                         "step that fell back to a geotag, was gated or was posed on thin support. Clicking the trajectory "
                                         "in 3D jumps to the nearest step too")
            self.follow = gui.add_checkbox("Camera follows", False,
                                           hint="Keep the view on the current estimate, framing its 2σ ellipse")
        with gui.add_folder("Layers"):
            self.layers = {name: gui.add_checkbox(name, True) for name in LAYERS}
            self.magnify = gui.add_dropdown("Ellipses drawn", tuple(rp.MAGNIFICATIONS), initial_value="true size",
                                            hint="Draw every 2σ ellipse larger than it is: a centimetre ellipse "
                                                 "cannot be seen at the scale of a drive. The step table says so")
        panel = gui.add_panel()
        with panel.add_tab("Step"):
            self.step_table = gui.add_html("")
        with panel.add_tab("Timelines"):
            self.plots = timeline_plots(gui, aspect=2.2)
        with panel.add_tab("Runs"):
            self.runs_table = gui.add_html("")
        panel.dock_below(gui.main_panel)

        def on(handle, fn):
            handle.on_update(lambda _: self._locked(fn))

        on(self.run, lambda: self._open(self.labels.index(self.run.value), self._compare_index()))
        on(self.compare, lambda: self._open(self.labels.index(self.run.value), self._compare_index()))
        on(self.series, lambda: self._choose_series(self.series.value))
        on(self.step, lambda: self._show_step(int(self.step.value) - 1))
        on(self.jump, self._jumped)
        on(self.play, lambda: setattr(self.state, "play", bool(self.play.value)))
        on(self.follow, lambda: (setattr(self.state, "follow", bool(self.follow.value)), self._draw_step()))
        on(self.magnify, self._magnified)
        for name, box in self.layers.items():
            on(box, lambda n=name, b=box: self._toggle(n, b.value))
        self.move.on_click(lambda _: self._locked(lambda: self._move(-1 if "Previous" in self.move.value else 1)))

    def _locked(self, fn) -> None:
        try:
            with self._lock:
                fn()
        except visloc.VislocError as exc:
            self.status.content = status_html(str(exc), error=True)

    def _compare_index(self) -> int | None:
        return None if self.compare.value == rp.NO_COMPARISON else self.labels.index(self.compare.value)

    # -- opening runs ----------------------------------------------------------------------------------

    def _open(self, index: int, compare: int | None) -> None:
        s = self.state
        label, path = self.files[index]
        self.status.content = status_html(f"Reading {path}…")
        try:
            s.main = visloc.load_run(path)
            s.other = None if compare is None else visloc.load_run(self.files[compare][1], s.main.frame)
        except visloc.VislocError as exc:
            self.status.content = status_html(str(exc), error=True)
            return
        self.status.content = status_html(f"{label}: {s.main.n_steps} steps in {len(s.main.series)} series"
                                          + ("" if s.other is None else f"; compared with {self.labels[compare]}"))
        self.series.options = s.main.series_labels
        self.series.value = s.main.series_labels[0]
        self._choose_series(s.main.series_labels[0], force=True)
        self.runs_table.content = rp.runs_html(s.main, s.other)

    def _other_series(self) -> list[visloc.SavedStep] | None:
        """The comparison's series for the one shown: the one starting at the same frame, else the same number."""
        s = self.state
        if s.other is None:
            return None
        first = s.main.series[s.series][0].frame
        for series in s.other.series:
            if series[0].frame == first:
                return series
        return s.other.series[min(s.series, len(s.other.series) - 1)]

    def _choose_series(self, label: str, force: bool = False) -> None:
        s = self.state
        if s.main is None or label not in s.main.series_labels:
            return
        index = s.main.series_labels.index(label)
        if index == s.series and not force:
            return
        s.series = index
        series = s.main.series[index]
        self.jump.options = ["–", *rp.jump_choices(series)]
        self.jump.value = "–"
        self.step.max = max(2, len(series))
        self._draw_series()
        s.k = -1
        self._show_step(min(max(int(self.step.value) - 1, 0), len(series) - 1), force=True)
        self._frame_view()

    # -- drawing ---------------------------------------------------------------------------------------

    def _series(self) -> list[visloc.SavedStep]:
        return self.state.main.series[self.state.series]

    def _draw_series(self) -> None:
        """The whole series: truth, measurements, estimate track and ellipses, the comparison, the grid."""
        s, sc = self.state, self.scene
        series, mag = self._series(), s.magnification
        truth = scene.positions([x.truth_m for x in series])
        span_m = float(max(np.nanmax(truth, axis=0) - np.nanmin(truth, axis=0))) if len(truth) else 10.0
        self._largest_m, self._farthest_m = max(span_m, 4.0) / 4.0, 2.0 * max(span_m, 10.0) + 20.0
        typical = float(np.median([x.estimate_sigma_m or 1.0 for x in series]))
        self._marker_m = rp.marker_m(typical, rp.drawn_factor([[typical**2, 0.0], [0.0, typical**2]], mag,
                                                              self._largest_m))
        meas = scene.positions([x.measurement_m for x in series])
        est = scene.positions([x.estimate_m for x in series])
        with self.server.atomic():
            draw_grid(self.scene, np.concatenate([truth, est[np.all(np.isfinite(est), axis=1)]]))
            sc.add_line_segments("/truth/track", scene.polyline_segments(truth), colors=scene.TRUTH_RGB, thickness=2.0, thickness_units="screen")
            sc.add_point_cloud("/truth/queries", np.c_[truth, np.full(len(truth), Z)], colors=scene.TRUTH_RGB,
                               point_size=self._marker_m, point_shape="circle")
            ok = np.all(np.isfinite(meas), axis=1)
            sc.add_point_cloud("/measurement/points", np.c_[meas[ok], np.full(ok.sum(), Z + 0.02)],
                               colors=scene.MEASUREMENT_RGB, point_size=1.4 * self._marker_m, point_shape="diamond")
            sc.add_line_segments("/estimate/track", scene.polyline_segments(est, Z + 0.04),
                                 colors=scene.ESTIMATE_RGB, thickness=2.5, thickness_units="screen")
            sc.add_line_segments("/estimate/ellipses", self._ellipses(series, "estimate", mag),
                                 colors=scene.ELLIPSE_RGB, thickness=1.5, thickness_units="screen")
            sc.add_line_segments("/measurement/ellipses", self._ellipses(series, "measurement", mag),
                                 colors=scene.MEASUREMENT_ELLIPSE_RGB, thickness=1.0, thickness_units="screen")
            other = self._other_series()
            if other is not None:
                o = scene.positions([x.estimate_m for x in other])
                sc.add_line_segments("/comparison/track", scene.polyline_segments(o, Z + 0.03), colors=COMPARE_RGB,
                                     thickness=2.5, thickness_units="screen")
                sc.add_line_segments("/comparison/ellipses", self._ellipses(other, "estimate", mag),
                                     colors=COMPARE_RGB, thickness=1.5, thickness_units="screen")
            else:
                for name in ("/comparison/track", "/comparison/ellipses"):
                    sc.add_line_segments(name, np.zeros((0, 2, 3)), colors=COMPARE_RGB)
        self._apply_layers()

    def _ellipses(self, series, which: str, magnification: float) -> np.ndarray:
        out = []
        for x in series:
            centre, cov = getattr(x, f"{which}_m"), getattr(x, f"{which}_cov_m2")
            if centre is not None and cov is not None and (which == "estimate" or x.measurement_source == "geometry"):
                factor = rp.drawn_factor(cov, magnification, self._largest_m)
                loop = visloc.covariance_ellipse_m(np.asarray(centre), rp.magnified(cov, factor), n_sigma=2.0)
                out.append(scene.closed_loop_segments(loop, Z + 0.03))
        return np.concatenate(out) if out else np.zeros((0, 2, 3))

    def _apply_layers(self) -> None:
        """Each layer's checkbox shows or hides its nodes."""
        apply_layers(self.scene, LAYER_NODES, self.state.hidden)

    def _toggle(self, layer: str, on: bool) -> None:
        (self.state.hidden.discard if on else self.state.hidden.add)(layer)
        self._apply_layers()

    def _magnified(self) -> None:
        self.state.magnification = rp.MAGNIFICATIONS[self.magnify.value]
        self._draw_series()
        self._draw_step()

    def _show_step(self, k: int, force: bool = False) -> None:
        series = self._series()
        k = int(np.clip(k, 0, len(series) - 1))
        if k == self.state.k and not force:
            return
        self.state.k = k
        if int(self.step.value) != k + 1:
            self.step.value = k + 1  # its callback comes back here with the same step: nothing more to do
        self._draw_step()

    def _draw_step(self) -> None:
        s, sc = self.state, self.scene
        series = self._series()
        if not 0 <= s.k < len(series):
            return
        step, other = series[s.k], self._other_series()
        other_step = None
        if other:
            other_step = min(other, key=lambda x: abs(x.time_s - step.time_s))
        mag = s.magnification
        factor = rp.drawn_factor(step.estimate_cov_m2, mag, self._largest_m)  # the current estimate's ellipse
        marker = rp.marker_m(step.estimate_sigma_m, factor)  # inside the ellipse, whatever its size
        with self.server.atomic():
            tx, ty = step.truth_m
            sc.add_icosphere("/current/truth", radius=marker, color=scene.TRUTH_RGB, position=(tx, ty, Z))
            if step.estimate_m is not None:
                ex, ey = step.estimate_m
                sc.add_icosphere("/current/estimate", radius=marker, color=scene.ESTIMATE_RGB, position=(ex, ey, Z + 0.04))
            loops = []
            for centre, cov in ((step.estimate_m, step.estimate_cov_m2),
                                (step.measurement_m, step.measurement_cov_m2 if step.measurement_source == "geometry"
                                 else None)):
                if centre is not None and cov is not None:
                    drawn = rp.magnified(cov, rp.drawn_factor(cov, mag, self._largest_m))
                    loops.append(scene.closed_loop_segments(visloc.covariance_ellipse_m(
                        np.asarray(centre), drawn, n_sigma=2.0), Z + 0.08))
            sc.add_line_segments("/current/ellipse", np.concatenate(loops) if loops else np.zeros((0, 2, 3)),
                                 colors=scene.CURRENT_RGB, thickness=3.0, thickness_units="screen")
            sc.add_label("/current/label", f"step {s.k + 1}" + ("" if factor == 1.0 else f", ellipse ×{factor:.3g}"),
                         position=(tx, ty, 1.0), anchor="bottom-center")
        self.step_table.content = rp.step_html(step, len(series), other_step, mag)
        draw_timelines(self.plots, series, s.k, other)
        if s.follow:
            for client in self.server.get_clients().values():
                self._frame_step(client)

    def _frame_step(self, client: viser.ClientHandle) -> None:
        """Camera follows: look at the current estimate from a distance that frames its (drawn) ellipse."""
        step = self._series()[self.state.k]
        centre = np.array([*(step.estimate_m or step.truth_m), 0.0])
        factor = rp.drawn_factor(step.estimate_cov_m2, self.state.magnification, self._largest_m)
        distance = rp.follow_distance_m(step, factor, self._farthest_m)
        offset = np.asarray(client.camera.position) - np.asarray(client.camera.look_at)
        offset = offset / max(np.linalg.norm(offset), 1e-9) * distance
        with client.atomic():
            client.camera.position = centre + offset  # a position set moves look_at with it: look_at last
            client.camera.look_at = centre

    def _frame_view(self) -> None:
        """The whole series in view, from the south-west and above: for tabs opened from now on, and every tab."""
        series = self._series()
        pts = np.array([x.truth_m for x in series], float)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre = 0.5 * (lo + hi)
        span = max(float(max(hi - lo)), 10.0)
        look_at = (float(centre[0]), float(centre[1]), 0.0)
        position = (float(centre[0]) - 0.3 * span, float(centre[1]) - 0.9 * span, 0.9 * span)
        initial = self.server.initial_camera
        initial.look_at, initial.position, initial.up = look_at, position, (0.0, 0.0, 1.0)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position, client.camera.look_at = position, look_at  # look_at last (see above)

    def _move(self, delta: int) -> None:
        self._show_step(self.state.k + delta)

    def _jumped(self) -> None:
        k = rp.step_of_choice(self.jump.value)
        if k is not None:
            self._show_step(k - 1)

    def _clicked(self, event) -> None:
        point = rp.ground_point(event.ray_origin, event.ray_direction)
        if point is None or self.state.main is None:
            return
        camera = event.client.camera
        reach_m = max(2.0, 0.05 * float(np.linalg.norm(np.asarray(camera.position) - np.asarray(camera.look_at))))
        with self._lock:
            series = self._series()
            k = rp.nearest_step(series, point)
            near = series[k].estimate_m or series[k].truth_m
            if np.hypot(near[0] - point[0], near[1] - point[1]) <= reach_m:  # a click far from it only orbits
                self._show_step(k)

    # -- each tab's scale bar and north arrow --------------------------------------------------------------

    def _tab_opened(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(lambda cam: self._rescale(client))

    def _rescale(self, client: viser.ClientHandle) -> None:
        """Redraw the scale bar and the north arrow for the view the tab now has (when it changed enough)."""
        with self._lock:
            if self._scale.rescale(client):
                self._apply_layers()

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                series = self._series() if self.state.main is not None else []
                dt = np.median(np.diff([x.time_s for x in series])) if len(series) > 1 else 1.0
            self._stop.wait(float(np.clip(dt, 0.05, 2.0)))
            with self._lock:
                if self.state.play and series:
                    self._show_step((self.state.k + 1) % len(series))

    def close(self) -> None:
        self._stop.set()
        self._player.join(timeout=5)

