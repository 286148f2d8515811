"""The control panel: built once, returning its handles. Nothing here reacts to anything."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import viser

import visloc
from visloc.dashboard.panels import legend_html, placeholder, status_html
from visloc.dashboard.scene import CURRENT_RGB, ELLIPSE_RGB, ESTIMATE_RGB, MEASUREMENT_RGB, css

RATES_HZ = ("0.5", "1", "2", "5", "10")
SPEEDS = ("0.5x", "1x", "2x", "5x")
PANEL_WIDTH_PX = 460


def paper_values() -> dict[str, object]:
    """The controls' values for the paper's parameters (Table 1), by handle name."""
    m, f = visloc.PAPER_MATCH, visloc.PAPER_FILTER
    return {
        "mode": visloc.PAPER_METHOD.name, "gate": visloc.REFINED.gate_chi2, "tau1": m.tau1, "tau2": m.tau2,
        "r": round(float(np.sqrt(f.meas_var_m2)), 2), "q": round(float(np.sqrt(f.accel_var_m2_s4)), 2),
        "p0": round(float(np.sqrt(f.init_var)), 1), "rate": "1", "start": 0.0,
        "exclusion": visloc.PAPER_EVAL_RETRIEVAL.exclusion_s, "window": visloc.PAPER_RETRIEVAL.window_s,
    }


@dataclass
class Handles:
    status: viser.GuiHtmlHandle
    progress: viser.GuiInputHandle  # a progress bar (0-100)
    step: viser.GuiSliderHandle
    prev_next: viser.GuiButtonGroupHandle
    play: viser.GuiCheckboxHandle
    speed: viser.GuiDropdownHandle
    follow: viser.GuiCheckboxHandle
    mode: viser.GuiDropdownHandle
    tau1: viser.GuiSliderHandle
    tau2: viser.GuiSliderHandle
    r: viser.GuiSliderHandle
    q: viser.GuiSliderHandle
    p0: viser.GuiSliderHandle
    gate: viser.GuiSliderHandle
    rate: viser.GuiDropdownHandle
    start: viser.GuiSliderHandle
    exclusion: viser.GuiSliderHandle
    window: viser.GuiSliderHandle
    reset: viser.GuiButtonHandle
    store: viser.GuiDropdownHandle
    store_path: viser.GuiTextHandle
    open: viser.GuiButtonHandle
    store_message: viser.GuiHtmlHandle  # store text: HTML, escaped by panels.text
    db: viser.GuiDropdownHandle
    queries: viser.GuiDropdownHandle
    store_info: viser.GuiHtmlHandle  # store text: HTML, escaped by panels.text
    figure: viser.GuiImageHandle
    numbers: viser.GuiHtmlHandle  # the step table, with store text (cameras, reasons)
    counts_plot: viser.GuiUplotHandle
    error_plot: viser.GuiUplotHandle
    run_summary: viser.GuiMarkdownHandle


def build_gui(server: viser.ViserServer, store_path: str) -> Handles:
    gui = server.gui
    gui.configure_theme(control_layout="fixed", control_width="medium", show_share_button=False,
                        titlebar_content=None, show_logo=False)
    gui.set_panel_label("visloc")
    paper = paper_values()
    gui.add_html(legend_html())
    status = gui.add_html(status_html("Starting…"))
    progress = gui.add_progress_bar(0.0, visible=False, animated=True)
    with gui.add_folder("Time"):
        step = gui.add_slider("Step", min=0, max=1, step=1, initial_value=0,
                              hint="Query step of the drive run; everything follows it")
        prev_next = gui.add_button_group("Move", ["◀ Previous", "Next ▶"])
        play = gui.add_checkbox("Play", False, hint="Step through the drive")
        speed = gui.add_dropdown("Speed", SPEEDS, initial_value="1x",
                                 hint="1x: one step per query interval, as the car drove")
        follow = gui.add_checkbox("Camera follows", False, hint="Keep the 3D view centred on the current step")
    with gui.add_folder("Matching (re-matches in the background)"):
        mode = gui.add_dropdown("Mode", tuple(visloc.METHODS), initial_value=paper["mode"],
                                hint="paper: the best match's geotag; refined: a metric pose from the "
                                     "database's geometry (PnP), geotag as fallback; refined-fast: the same pose "
                                     "at camera rate, on the structure stored at ingest (choose 10 Hz and Play)")
        tau1 = gui.add_slider("τ1 (Lowe ratio)", min=0.5, max=1.0, step=0.01, initial_value=paper["tau1"],
                              hint="Equation (1): d1²/d2² < τ1²")
        tau2 = gui.add_slider("τ2 (cosine)", min=0.8, max=1.0, step=0.005, initial_value=paper["tau2"],
                              hint="Equation (2): cosine similarity > τ2")
    with gui.add_folder("Filter (instant)"):
        r = gui.add_slider("R: meas. σ (m)", min=0.1, max=40.0, step=0.01, initial_value=paper["r"],
                           hint="R = σ² I for geotag measurements (the paper's 0.0001° is 11.12 m); "
                                "refined poses bring their own R")
        q = gui.add_slider("Q: accel. σ (m/s²)", min=0.0, max=5.0, step=0.05, initial_value=paper["q"],
                           hint="White-acceleration process noise")
        p0 = gui.add_slider("P0: initial σ", min=1.0, max=100.0, step=0.1, initial_value=paper["p0"],
                            hint="P0 = σ² I (m, m/s); the paper's 1000·I is σ = 31.6")
        gate = gui.add_slider("Gate χ² (refined)", min=0.0, max=50.0, step=0.01, initial_value=paper["gate"],
                              hint="Refined mode: skip a measurement whose squared Mahalanobis distance "
                                   "to the prediction exceeds this (13.82 = 99.9 %); 0 = off")
    with gui.add_folder("Queries"):
        rate = gui.add_dropdown("Query rate (Hz)", RATES_HZ, initial_value=paper["rate"],
                                hint="One query every 1/rate s; also the filter's Δt")
        start = gui.add_slider("Start time (s)", min=0.0, max=1.0, step=0.1, initial_value=paper["start"])
        exclusion = gui.add_slider("Exclusion (s)", min=0.0, max=3.0, step=0.1, initial_value=paper["exclusion"],
                                   hint="Ignore database images closer in time to the query")
        window = gui.add_slider("Search window ± (s)", min=1.0, max=60.0, step=1.0, initial_value=paper["window"])
    reset = gui.add_button("Paper's parameters", hint="τ1 0.8, τ2 0.97, R 0.0001°, P0 1000·I, 1 Hz")
    with gui.add_folder("Data", expand_by_default=False):
        store = gui.add_dropdown("Store file", [store_path], initial_value=store_path)
        store_path_box = gui.add_text("Other store", "", hint="Path of another store file")
        open_button = gui.add_button("Open")
        store_message = gui.add_html("")  # the path typed, then what opening it gave; stays until the next
        db = gui.add_dropdown("Database", ["–"])
        queries = gui.add_dropdown("Queries", ["–"])
        store_info = gui.add_html("")

    panel = gui.add_panel()
    with panel.add_tab("Current step"):
        figure = gui.add_image(placeholder("No step yet"), label="query (top) and best match (bottom)",
                               format="jpeg", jpeg_quality=85)
        numbers = gui.add_html("")
        counts_plot = gui.add_uplot(
            (np.zeros(1), np.zeros(1), np.zeros(1), np.full(1, np.nan)),
            ({"label": "database time (s)"},
             {"label": "earlier images", "stroke": "rgb(120,120,120)", "width": 1.5, "points": {"show": True, "size": 4}},
             {"label": "later images", "stroke": "rgb(150,90,200)", "width": 1.5, "points": {"show": True, "size": 4}},
             {"label": "best match", "stroke": css(CURRENT_RGB), "width": 0,
              "points": {"show": True, "size": 9, "fill": css(CURRENT_RGB)}}),
            title="Correspondences per candidate", aspect=2.0, scales={"x": {"time": False}})
        error_plot = gui.add_uplot(
            (np.zeros(1),) + tuple(np.full(1, np.nan) for _ in range(4)),
            ({"label": "query time (s)"},
             {"label": "measurement", "stroke": css(MEASUREMENT_RGB), "width": 2, "points": {"show": True, "size": 5}},
             {"label": "estimate", "stroke": css(ESTIMATE_RGB), "width": 2, "points": {"show": True, "size": 5}},
             {"label": "2σ", "stroke": css(ELLIPSE_RGB), "width": 1.5, "dash": (5.0, 4.0)},
             {"label": "current", "stroke": css(CURRENT_RGB), "width": 0,
              "points": {"show": True, "size": 10, "fill": css(CURRENT_RGB)}}),
            title="Error per step (m), the paper's Figure 4", aspect=2.0, scales={"x": {"time": False}})
        run_summary = gui.add_markdown("")
    panel.dock_left()
    panel.set_width(PANEL_WIDTH_PX)
    return Handles(status, progress, step, prev_next, play, speed, follow, mode, tau1, tau2, r, q, p0, gate, rate,
                   start, exclusion, window, reset, store, store_path_box, open_button, store_message, db, queries,
                   store_info,
                   figure, numbers, counts_plot, error_plot, run_summary)
