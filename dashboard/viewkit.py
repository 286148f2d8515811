"""What both 3D views share (the live page and the saved-run viewer): a scene that remembers its
nodes so a checkbox can hide a layer, a grid labelled in metres, and a scale bar and north arrow
that follow each tab's camera as it zooms.

Node names: ``/scale/grid``, ``/scale/ticks/...``, ``/scale/bar``, ``/scale/north``.
"""

from __future__ import annotations

import numpy as np
import viser

from visloc.dashboard import runpanels as rp

SCALE_NODES = ("/scale/grid", "/scale/ticks", "/scale/bar", "/scale/north")


def flat_scene(scene_api: viser.SceneApi) -> None:
    """A scene of lines, frustums and images seen from above: z up, and neither the environment map's lighting
    nor shadows, which such a scene does not show but which cost every frame; on a machine drawing WebGL in
    software (no GPU) the page then draws its frames several times cheaper (idle, the browser's drawing
    process used half as much of a core in headless Chromium with SwiftShader)."""
    scene_api.set_up_direction("+z")
    scene_api.configure_environment_map(hdri=None)
    scene_api.configure_default_lights(enabled=True, cast_shadow=False)


class KeptScene:
    """The server's scene, keeping a handle of every node added through it (by name), for the layer toggles."""

    def __init__(self, scene_api: viser.SceneApi):
        self.api, self.nodes = scene_api, {}

    def __getattr__(self, name: str):
        attr = getattr(self.api, name)
        if not name.startswith("add_"):
            return attr

        def add(*args, **kwargs):
            handle = attr(*args, **kwargs)
            self.nodes[handle.name] = handle
            return handle

        return add


def apply_layers(sc: KeptScene, layer_nodes: dict[str, tuple[str, ...]], hidden: set[str]) -> None:
    """Show or hide every node of each layer (a hidden node hides its children: labels, ticks)."""
    for name, handle in list(sc.nodes.items()):
        layer = next((layer for layer, prefixes in layer_nodes.items()
                      if any(name == p or name.startswith(p + "/") for p in prefixes)), None)
        if layer is not None and handle.visible != (layer not in hidden):
            handle.visible = layer not in hidden


def draw_grid(sc: KeptScene, points_m: np.ndarray, margin_m: float = 2.0) -> None:
    """A grid in metres around ``points_m`` (N, 2), with labelled ticks along its west and south edges."""
    points_m = np.asarray(points_m, float)
    lo, hi = points_m.min(axis=0), points_m.max(axis=0)
    extent = float(max(hi - lo)) * 1.2 + margin_m
    step = rp.grid_step_m(extent)
    centre = 0.5 * (lo + hi)
    lo, hi = centre - extent / 2, centre + extent / 2
    sc.add_grid("/scale/grid", width=extent, height=extent, plane="xy", cell_size=step, section_size=5 * step,
                position=(float(centre[0]), float(centre[1]), 0.0))
    sc.add_frame("/scale/ticks", show_axes=False)  # replaces the previous ticks, whatever their number
    for i, x in enumerate(rp.axis_ticks(lo[0], hi[0], 5 * step)):
        sc.add_label(f"/scale/ticks/e{i}", f"{x:g} m E", position=(x, lo[1], 0.0), anchor="top-center",
                     font_screen_scale=0.8)
    for i, y in enumerate(rp.axis_ticks(lo[1], hi[1], 5 * step)):
        sc.add_label(f"/scale/ticks/n{i}", f"{y:g} m N", position=(lo[0], y, 0.0), anchor="center-right",
                     font_screen_scale=0.8)
    sc.add_label("/scale/ticks/cell", f"grid: {rp.length_text(step)} cells", position=(lo[0], lo[1], 0.0),
                 anchor="bottom-left")


class ScaleFollower:
    """Each tab's scale bar and north arrow, redrawn for the view the tab has when it changed enough
    (another bar length, or the view moved by a bar's length). Call ``rescale`` from the tab's camera
    callback with the view's lock held."""

    def __init__(self, server: viser.ViserServer, sc: KeptScene):
        self.server, self.scene = server, sc
        self._drawn: dict[int, tuple] = {}  # per tab: the scale drawn for its view

    def rescale(self, client: viser.ClientHandle) -> bool:
        """Draw the marks for ``client``'s view; False when what is drawn already fits it."""
        look_at = np.asarray(client.camera.look_at, float)
        distance = float(np.linalg.norm(np.asarray(client.camera.position, float) - look_at))
        marks = rp.scale_marks(look_at, distance)
        key = (marks["length_m"], tuple(np.round(look_at[:2] / marks["length_m"])))
        if self._drawn.get(client.client_id) == key:
            return False
        self._drawn[client.client_id] = key
        sc, width = self.scene, marks["length_m"] / 100
        with self.server.atomic():
            sc.add_line_segments("/scale/bar", marks["bar"][None], colors=(20, 20, 20), thickness=4.0,
                                 thickness_units="screen")
            sc.add_label("/scale/bar/label", f"scale: {marks['label']}", position=tuple(marks["bar"].mean(axis=0)),
                         anchor="top-center")
            a = marks["arrow"]
            sc.add_arrows("/scale/north", a[None], colors=(200, 30, 30), shaft_radius=width,
                          head_radius=4 * width, head_length=12 * width)
            sc.add_label("/scale/north/label", "N", position=tuple(a[1] + [0.0, 0.1 * marks["length_m"], 0.0]),
                         anchor="bottom-center")
        return True

    def forget(self, client_id: int) -> None:
        self._drawn.pop(client_id, None)
