"""The control panel: built once, returning its handles. Nothing here reacts to anything."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import viser

import visloc
from visloc.dashboard.explain import HINTS, help_html
from visloc.dashboard.runpanels import MAGNIFICATIONS, TIMELINE_TITLES, TIMELINES, timeline_series
from visloc.dashboard.panels import legend_html, map_legend_html, placeholder, status_html
from visloc.dashboard.scene import CURRENT_RGB, ELLIPSE_RGB, ESTIMATE_RGB, MEASUREMENT_RGB, css
from visloc.dashboard.state import CONTROLLED

RATES_HZ = ("0.5", "1", "2", "5", "10")
# the live 3D view's layers: a checkbox each, hiding the scene nodes under these paths
LAYER_NODES = {"Truth": ("/truth",), "Database geotags": ("/database",),
               "Measurements": ("/measurement/points", "/measurement/offsets"),
               "Estimate": ("/estimate/track", "/estimate/points"), "Estimate ellipses": ("/estimate/ellipses",),
               "Measurement ellipses": ("/measurement/ellipses",),
               "Cameras": ("/current/query_camera", "/current/match_camera"),
               "Grid and scale": ("/scale/grid", "/scale/ticks", "/scale/bar", "/scale/north")}
SPEEDS = ("0.5x", "1x", "2x", "5x")


def _decimals(step: float) -> int:
    return max(0, -math.floor(math.log10(step) + 1e-9))


def shown_initial(spec, default) -> float:
    """A controlled parameter's first value as its slider shows it, rounded to the slider's step."""
    c = spec.control
    value = c.initial if c.initial is not None else default
    return round(float(c.to_shown(value)), _decimals(c.step))


def paper_values() -> dict[str, object]:
    """The controls' values for the paper's parameters (Table 1): the mode, rate and start by handle
    name, and every parameter control under ``params``."""
    return {"mode": visloc.PAPER_METHOD.name, "rate": "1", "start": 0.0,
            "params": {name: shown_initial(spec, default) for _, name, spec, default in CONTROLLED}}


def mode_rate(method_name: str) -> str:
    """The query rate a mode plays at unless another is chosen: the camera-rate mode at the camera's 10 Hz,
    where its ellipses are honest (docs/dashboard.md, measured by benchmarks/dashboard_rates.py), the others at
    the paper's 1 Hz."""
    return "10" if visloc.method_named(method_name).camera_rate else "1"


def rate_after_mode_change(previous_mode: str, mode: str, rate: str) -> str:
    """The rate a change of mode leaves: the new mode's own where the rate was the previous mode's own, else the
    one chosen."""
    return mode_rate(mode) if rate == mode_rate(previous_mode) else rate


def rate_follows_mode(gui: "Handles") -> None:
    """A change of mode moves the query rate as ``rate_after_mode_change`` says (the mode's own callbacks,
    registered before, have recorded it; the rate's record the rate)."""
    shown = [gui.mode.value]

    def on_mode(_event) -> None:
        previous, shown[0] = shown[0], gui.mode.value
        gui.rate.value = rate_after_mode_change(previous, gui.mode.value, gui.rate.value)

    gui.mode.on_update(on_mode)


def saved_values(settings: visloc.LiveSettings) -> tuple[dict[str, object], list[str]]:
    """The controls' values for a saved run's settings (as ``paper_values``; the paper's where the run
    records none), and what had to move to fit a control, in words."""
    values, moved = paper_values(), []
    if settings.method in visloc.METHODS:
        values["mode"] = settings.method
    if settings.rate_hz:
        nearest = min(RATES_HZ, key=lambda r: abs(math.log(float(r) / settings.rate_hz)))
        values["rate"] = nearest
        if abs(math.log(float(nearest) / settings.rate_hz)) > 0.02:  # not a frame interval's jitter
            moved.append(f"query rate {settings.rate_hz:.3g} Hz → {nearest} Hz")
    for _, name, spec, _ in CONTROLLED:
        if name in settings.params:
            c = spec.control
            shown = float(c.to_shown(settings.params[name]))
            fitted = round(float(np.clip(shown, c.low, c.high)), _decimals(c.step))  # to the slider's step
            if not c.low <= shown <= c.high:
                moved.append(f"{c.label.split(' (')[0]} {shown:.4g} → {fitted:g}")
            values["params"][name] = fitted
    return values, moved


def tuned_from_html(path, settings: visloc.LiveSettings, moved: list[str]) -> str:
    """What the controls started from: the saved run's file, and what could not be taken as it was."""
    missing = [spec.control.label.split(" (")[0] for _, name, spec, _ in CONTROLLED if name not in settings.params]
    lines = [f"Started from the saved run {path}"]
    if moved:
        lines.append("moved to fit a control: " + "; ".join(moved))
    if missing:
        lines.append("not recorded by the run (the paper's): " + ", ".join(missing))
    return status_html(" · ".join(lines))


def enable_for_mode(gui: Handles, method_name: str) -> None:
    """Controls the chosen mode does not use are disabled (their hints say why)."""
    method = visloc.METHODS.get(method_name)
    if method is None:
        return
    for _, name, spec, _ in CONTROLLED:  # each parameter declares the methods that use it
        handle, unused = gui.params[name], method.name not in spec.methods
        if handle.disabled != unused:
            handle.disabled = unused


@dataclass
class Handles:
    status: viser.GuiHtmlHandle
    progress: viser.GuiInputHandle  # a progress bar (0-100)
    session: viser.GuiHtmlHandle  # how many tabs share the page, the last change and from which tab
    step: viser.GuiSliderHandle  # 1..N: "Step k of N"
    prev_next: viser.GuiButtonGroupHandle
    play: viser.GuiCheckboxHandle
    speed: viser.GuiDropdownHandle
    follow: viser.GuiCheckboxHandle
    latlon: viser.GuiCheckboxHandle
    mode: viser.GuiDropdownHandle
    rate: viser.GuiDropdownHandle
    start: viser.GuiSliderHandle
    params: dict[str, viser.GuiSliderHandle]  # every parameter control, by parameter name (state.CONTROLLED)
    reset: viser.GuiButtonHandle
    tuned_from: viser.GuiHtmlHandle  # the saved run the controls started from (``--tune-from``), if any
    layers: dict[str, viser.GuiCheckboxHandle]  # by layer name (LAYER_NODES)
    magnify: viser.GuiDropdownHandle  # "Ellipses drawn": true size, ×10, ×100
    geojson: viser.GuiButtonHandle
    csv: viser.GuiButtonHandle
    mcap: viser.GuiButtonHandle
    store: viser.GuiDropdownHandle
    store_path: viser.GuiTextHandle
    open: viser.GuiButtonHandle
    store_message: viser.GuiHtmlHandle  # store text: HTML, escaped by panels.text
    db: viser.GuiDropdownHandle
    queries: viser.GuiDropdownHandle
    store_info: viser.GuiHtmlHandle  # store text: HTML, escaped by panels.text
    step_badge: viser.GuiHtmlHandle  # "previous run … re-matching" above the step's numbers, or empty
    figure: viser.GuiImageHandle
    numbers: viser.GuiHtmlHandle  # the step table, with store text (cameras, reasons)
    counts_plot: viser.GuiUplotHandle
    error_plot: viser.GuiUplotHandle
    run_summary: viser.GuiMarkdownHandle
    map_badge: viser.GuiHtmlHandle
    map_tiles: viser.GuiHtmlHandle
    map: viser.GuiImageHandle
    timelines: dict[str, viser.GuiUplotHandle]  # error, sigma, nees, inliers, latency per step (runpanels.timeline)


def _param_sliders(gui, folder: str, shown: dict[str, float]) -> dict[str, viser.GuiSliderHandle]:
    """A slider per parameter the engine declares in ``folder``; one the paper's method does not use starts
    disabled."""
    out = {}
    for _, name, spec, _ in CONTROLLED:
        c = spec.control
        if c.folder == folder:
            out[name] = gui.add_slider(c.label, min=c.low, max=c.high, step=c.step, initial_value=shown[name],
                                       hint=c.hint or spec.help,
                                       disabled=visloc.PAPER_METHOD.name not in spec.methods)
    return out


def _plots(gui) -> tuple[viser.GuiUplotHandle, viser.GuiUplotHandle]:
    """The two plots. Their legends are static (no values until hovered: uPlot's live legend reads
    "--" before the cursor is on the plot, which looks like missing data)."""
    static = {"live": False}
    counts_plot = gui.add_uplot(
        (np.zeros(1), np.zeros(1), np.zeros(1), np.full(1, np.nan)),
        ({"label": "database image time (s)"},
         {"label": "images before the query", "stroke": "rgb(120,120,120)", "width": 1.5,
          "points": {"show": True, "size": 4}},
         {"label": "images after it", "stroke": "rgb(150,90,200)", "width": 1.5, "points": {"show": True, "size": 4}},
         {"label": "best match", "stroke": css(CURRENT_RGB), "width": 0,
          "points": {"show": True, "size": 9, "fill": css(CURRENT_RGB)}}),
        title="Correspondences per candidate", aspect=1.6, scales={"x": {"time": False}}, legend=static,
        axes=({"label": "database image time (s)"}, {"label": "correspondences"}))
    error_plot = gui.add_uplot(
        (np.zeros(1),) + tuple(np.full(1, np.nan) for _ in range(4)),
        ({"label": "query time (s)"},
         {"label": "measurement error", "stroke": css(MEASUREMENT_RGB), "width": 2,
          "points": {"show": True, "size": 5}},
         {"label": "estimate error", "stroke": css(ESTIMATE_RGB), "width": 2, "points": {"show": True, "size": 5}},
         {"label": "estimate 2σ", "stroke": css(ELLIPSE_RGB), "width": 1.5, "dash": (5.0, 4.0)},
         {"label": "current step", "stroke": css(CURRENT_RGB), "width": 0,
          "points": {"show": True, "size": 10, "fill": css(CURRENT_RGB)}}),
        title="Error per step (m), the paper's Figure 4", aspect=1.6, scales={"x": {"time": False}}, legend=static,
        axes=({"label": "query time (s)"}, {"label": "error (m)"}))
    return counts_plot, error_plot


def timeline_plots(gui, aspect: float = 2.0) -> dict[str, viser.GuiUplotHandle]:
    """One plot per timeline (``runpanels.TIMELINES``), empty until a run is drawn."""
    plots = {}
    for kind in TIMELINES:
        columns = len(timeline_series(kind))
        plots[kind] = gui.add_uplot((np.zeros(1),) + tuple(np.full(1, np.nan) for _ in range(columns - 1)),
                                    timeline_series(kind), title=TIMELINE_TITLES[kind], aspect=aspect,
                                    legend={"live": False}, scales={"x": {"time": False}},
                                    axes=({"label": "time since the run's first query (s)"}, {}))
    return plots


def build_gui(server: viser.ViserServer, store_path: str) -> Handles:
    gui = server.gui
    gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False,
                        titlebar_content=None, show_logo=False)
    gui.set_panel_label("visloc")
    paper, h = paper_values(), HINTS
    status = gui.add_html(status_html("Starting…"))
    progress = gui.add_progress_bar(0.0, visible=False, animated=True)
    session = gui.add_html("")
    with gui.add_folder("What am I looking at?", expand_by_default=False):
        gui.add_html(help_html())
    gui.add_html(legend_html())
    with gui.add_folder("Time"):
        step = gui.add_slider("Step", min=1, max=2, step=1, initial_value=1, hint=h["step"])
        prev_next = gui.add_button_group("Move", ["◀ Previous", "Next ▶"], hint=h["prev_next"])
        play = gui.add_checkbox("Play", False, hint=h["play"])
        speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x", hint=h["speed"])
        follow = gui.add_checkbox("Camera follows", False, hint=h["follow"])
        latlon = gui.add_checkbox("Show lat/lon", False, hint=h["latlon"])
    with gui.add_folder("3D view layers", expand_by_default=False):
        magnify = gui.add_dropdown("Ellipses drawn", tuple(MAGNIFICATIONS), initial_value="true size",
                                   hint="Draw every 2σ ellipse larger than it is: a refined run's are centimetres, "
                                        "invisible at the scale of a drive. The current step's label says so")
        layers = {name: gui.add_checkbox(name, True, hint="Show or hide this layer of the 3D view")
                  for name in LAYER_NODES}
    with gui.add_folder("Matching (re-matches in the background)"):
        mode = gui.add_dropdown("Mode", tuple(visloc.METHODS), initial_value=paper["mode"], hint=h["mode"])
        params = _param_sliders(gui, "matching", paper["params"])
    with gui.add_folder("Filter (instant)"):
        params |= _param_sliders(gui, "filter", paper["params"])
    with gui.add_folder("Queries"):
        rate = gui.add_dropdown("Query rate (Hz)", RATES_HZ, initial_value=paper["rate"], hint=h["rate"])
        start = gui.add_slider("Start time (s)", min=0.0, max=1.0, step=0.1, initial_value=paper["start"],
                               hint=h["start"])
        params |= _param_sliders(gui, "queries", paper["params"])
    reset = gui.add_button("Paper's parameters", hint=h["reset"])
    tuned_from = gui.add_html("")
    with gui.add_folder("Export this run"):
        geojson = gui.add_button("Download GeoJSON", hint=h["geojson"], disabled=True)
        csv = gui.add_button("Download CSV", hint=h["csv"], disabled=True)
        mcap = gui.add_button("Download MCAP", hint=h["mcap"], disabled=True)
    with gui.add_folder("Data", expand_by_default=False):
        store = gui.add_dropdown("Store file", [store_path], initial_value=store_path, hint=h["store"])
        store_path_box = gui.add_text("Other store", "", hint=h["store_path"])
        # the path typed, then what opening it gave (stays until the next open): above Open, so it is in
        # view where the user clicks
        store_message = gui.add_html("")
        open_button = gui.add_button("Open", hint="Open the store file typed above (read only)")
        db = gui.add_dropdown("Database", ["–"], hint=h["db"])
        queries = gui.add_dropdown("Queries", ["–"], hint=h["queries"])
        store_info = gui.add_html("")

    panel = gui.add_panel()
    with panel.add_tab("Current step"):
        step_badge = gui.add_html("")
        figure = gui.add_image(placeholder("No step yet"), label="query (top) and best match (bottom)",
                               format="jpeg", jpeg_quality=85)
        numbers = gui.add_html("")
        counts_plot, error_plot = _plots(gui)
        run_summary = gui.add_markdown("")
        gui.add_html('<div style="height:48px"></div>')  # room below the last plot: nothing ends at the edge
    with panel.add_tab("Timelines"):
        timelines = timeline_plots(gui)
        gui.add_html('<div style="height:48px"></div>')
    with panel.add_tab("Map"):
        map_badge = gui.add_html("")
        map_image = gui.add_image(placeholder("No run yet"), label="top-down map (north up, east right)",
                                  format="png")
        map_tiles = gui.add_html("")  # the web map's attribution, or why it has no tiles (--tiles)
        gui.add_html(map_legend_html())
    panel.dock_below(gui.main_panel)
    return Handles(status=status, progress=progress, session=session, step=step, prev_next=prev_next, play=play,
                   speed=speed, follow=follow, latlon=latlon, mode=mode, rate=rate, start=start, params=params,
                   reset=reset, tuned_from=tuned_from, layers=layers, magnify=magnify, geojson=geojson, csv=csv, mcap=mcap, store=store, store_path=store_path_box, open=open_button,
                   store_message=store_message, db=db, queries=queries, store_info=store_info, step_badge=step_badge,
                   figure=figure, numbers=numbers, counts_plot=counts_plot, error_plot=error_plot,
                   run_summary=run_summary, map_badge=map_badge, map=map_image, map_tiles=map_tiles,
                   timelines=timelines)
