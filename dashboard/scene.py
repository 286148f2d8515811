"""Small presentation helpers for the 3D scene: segments, camera orientation, colours.

The scene is the engine's local metric frame: x = east m, y = north m, z = up m,
origin at the first database image's geotag. The trajectory lies at ground level.
"""

from __future__ import annotations

import numpy as np
import viser.transforms as vtf

# RGB colours, also used by the legend
TRUTH_RGB = (30, 150, 60)
MEASUREMENT_RGB = (235, 120, 0)
ESTIMATE_RGB = (40, 90, 220)
ELLIPSE_RGB = (120, 160, 245)
DATABASE_RGB = (150, 150, 150)
CURRENT_RGB = (220, 30, 120)

CAMERA_HEIGHT_M = 1.65  # KITTI's cameras are about 1.65 m above the road
TRACK_HEIGHT_M = 0.05  # just above the grid, so lines do not flicker


def polyline_segments(points_xy: np.ndarray, z_m: float = TRACK_HEIGHT_M) -> np.ndarray:
    """(N-1, 2, 3) segments joining consecutive finite points (N, 2); gaps at NaN rows."""
    p = np.asarray(points_xy, float).reshape(-1, 2)
    if len(p) < 2:
        return np.zeros((0, 2, 3))
    seg = np.stack([p[:-1], p[1:]], axis=1)
    seg = seg[np.all(np.isfinite(seg), axis=(1, 2))]
    return np.concatenate([seg, np.full(seg.shape[:2] + (1,), z_m)], axis=2)


def closed_loop_segments(points_xy: np.ndarray, z_m: float = TRACK_HEIGHT_M) -> np.ndarray:
    """(N, 2, 3) segments of a closed loop through N points."""
    p = np.asarray(points_xy, float).reshape(-1, 2)
    return polyline_segments(np.concatenate([p, p[:1]]), z_m)


def camera_wxyz(heading_deg: float) -> np.ndarray:
    """Orientation of a level, forward-looking camera with compass heading ``heading_deg``
    (0 = north, clockwise), as a wxyz quaternion of R_world_camera. Camera axes follow
    OpenCV (x right, y down, z forward), as viser's frustums do."""
    h = np.radians(heading_deg if np.isfinite(heading_deg) else 0.0)
    forward = np.array([np.sin(h), np.cos(h), 0.0])
    right = np.array([np.cos(h), -np.sin(h), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return vtf.SO3.from_matrix(np.stack([right, down, forward], axis=1)).wxyz


def swatch_html(rgb: tuple[int, int, int], text: str) -> str:
    r, g, b = rgb
    return (f'<span style="display:inline-block;width:11px;height:11px;border-radius:2px;margin:0 5px 0 2px;'
            f'background:rgb({r},{g},{b});vertical-align:-1px"></span>{text}')
