"""Drawing the 3D scene: pure functions from a run's records (metres) to viser scene nodes.

The scene is the engine's local metric frame: x = east m, y = north m, z = up m, origin at
the first database image's geotag. The trajectory lies at ground level. Node names are
paths: ``/truth/...``, ``/database/...``, ``/measurement/...``, ``/estimate/...``,
``/current/...`` (the grid and scale marks, under ``/scale``, are ``viewkit``'s). Ellipses are
drawn ``factor(cov)`` times their true size (1 unless the page's "Ellipses drawn" says more).
"""

from __future__ import annotations

import numpy as np
import viser
import viser.transforms as vtf

import visloc

# RGB colours, also used by the legend and the plots
TRUTH_RGB = (30, 150, 60)
MEASUREMENT_RGB = (235, 120, 0)
ESTIMATE_RGB = (40, 90, 220)
ELLIPSE_RGB = (120, 160, 245)  # the estimate's 2-sigma ellipse: the filter's covariance P
MEASUREMENT_ELLIPSE_RGB = (245, 175, 90)  # a refined measurement's own 2-sigma ellipse: its covariance R
DATABASE_RGB = (150, 150, 150)
CURRENT_RGB = (220, 30, 120)

CAMERA_HEIGHT_M = 1.65  # KITTI's cameras are about 1.65 m above the road
TRACK_HEIGHT_M = 0.05  # just above the grid, so lines do not flicker
FRUSTUM_SCALE_M = 5.0


def css(rgb: tuple[int, int, int]) -> str:
    return f"rgb({rgb[0]},{rgb[1]},{rgb[2]})"


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


def positions(values: list) -> np.ndarray:
    """(N, 2) array of (east_m, north_m) positions, NaN rows where a value is None."""
    out = np.full((len(values), 2), np.nan)
    for i, v in enumerate(values):
        if v is not None:
            out[i] = v
    return out


def initial_view(truth_m: np.ndarray, db_m: np.ndarray) -> tuple[tuple, tuple]:
    """(look_at, camera position): from behind the start, to one side, from above, so the whole track is
    in view and the frustums (facing along the track) are seen from behind, their images showing."""
    all_xy = np.concatenate([truth_m, db_m])
    lo, hi = all_xy.min(axis=0), all_xy.max(axis=0)
    center = 0.5 * (lo + hi)
    span = max(float(max(hi - lo)), 20.0)
    along = truth_m[-1] - truth_m[0]
    along = along / np.linalg.norm(along) if np.linalg.norm(along) > 0 else np.array([0.0, 1.0])
    across = np.array([along[1], -along[0]])  # to the right of the direction of travel
    eye = center + span * (-0.75 * along + 0.55 * across)
    return (float(center[0]), float(center[1]), 0.0), (float(eye[0]), float(eye[1]), 0.75 * span)


def draw_static(scene: viser.SceneApi, truth_m: np.ndarray, db_m: np.ndarray) -> None:
    """The database geotags and the whole ground-truth track."""
    scene.add_point_cloud("/database/geotags", np.c_[db_m, np.full(len(db_m), TRACK_HEIGHT_M)],
                          colors=DATABASE_RGB, point_size=0.6, point_shape="circle")
    scene.add_line_segments("/truth/track", polyline_segments(truth_m), colors=TRUTH_RGB, thickness=0.25)


def _ellipse_segments(center_m: np.ndarray, cov_m2, z_m: float, factor=lambda cov: 1.0) -> np.ndarray:
    cov = np.asarray(cov_m2, float)
    return closed_loop_segments(visloc.covariance_ellipse_m(center_m, cov * factor(cov) ** 2, n_sigma=2.0), z_m)


def draw_run(scene: viser.SceneApi, records: list[visloc.StepRecord], factor=lambda cov: 1.0) -> None:
    """Every step of a run: truths, measurements (joined to their truth), the estimate track with its
    2-sigma ellipses, and the refined measurements' own 2-sigma ellipses."""
    truth = positions([r.truth_m for r in records])
    meas = positions([r.measurement_m for r in records])
    est = positions([r.estimate_m for r in records])
    z = TRACK_HEIGHT_M
    scene.add_point_cloud("/truth/queries", np.c_[truth, np.full(len(records), z)], colors=TRUTH_RGB,
                          point_size=0.9, point_shape="circle")
    ok = np.all(np.isfinite(meas), axis=1)
    scene.add_point_cloud("/measurement/points", np.c_[meas[ok], np.full(ok.sum(), z + 0.02)],
                          colors=MEASUREMENT_RGB, point_size=1.4, point_shape="diamond")
    links = np.stack([np.c_[truth[ok], np.full(ok.sum(), z)], np.c_[meas[ok], np.full(ok.sum(), z)]], axis=1)
    scene.add_line_segments("/measurement/offsets", links, colors=MEASUREMENT_RGB, thickness=0.05)
    scene.add_line_segments("/estimate/track", polyline_segments(est, z + 0.04), colors=ESTIMATE_RGB, thickness=0.25)
    ok_est = np.all(np.isfinite(est), axis=1)
    scene.add_point_cloud("/estimate/points", np.c_[est[ok_est], np.full(ok_est.sum(), z + 0.04)],
                          colors=ESTIMATE_RGB, point_size=1.0, point_shape="circle")
    ellipses = [_ellipse_segments(e, r.estimate_cov_m2, z + 0.03, factor) for r, e in zip(records, est)
                if np.all(np.isfinite(e)) and r.estimate_cov_m2 is not None]
    if ellipses:
        scene.add_line_segments("/estimate/ellipses", np.concatenate(ellipses), colors=ELLIPSE_RGB, thickness=0.08)
    own = [_ellipse_segments(m, r.measurement_cov_m2, z + 0.05, factor) for r, m in zip(records, meas)
           if r.measurement_source == visloc.GEOMETRY and r.measurement_cov_m2]
    scene.add_line_segments("/measurement/ellipses", np.concatenate(own) if own else np.zeros((0, 2, 3)),
                            colors=MEASUREMENT_ELLIPSE_RGB, thickness=0.05)


def draw_current(scene: viser.SceneApi, record: visloc.StepRecord, factor=lambda cov: 1.0, marker_m: float = 0.9,
                 label: str = "") -> None:
    """The current step: its truth, measurement and estimate as spheres (``marker_m`` across), the estimate's
    2-sigma ellipse (the filter's covariance) and a refined measurement's own (its covariance R), drawn with a
    line of constant width on screen so a small one stays visible; ``label`` over it."""
    z = TRACK_HEIGHT_M
    tx, ty = record.truth_m
    scene.add_icosphere("/current/truth", radius=marker_m, color=TRUTH_RGB, position=(tx, ty, z))
    if record.measurement_m is not None:
        mx, my = record.measurement_m
        scene.add_icosphere("/current/measurement", radius=marker_m, color=MEASUREMENT_RGB, position=(mx, my, z))
    else:
        scene.add_icosphere("/current/measurement", radius=marker_m, color=MEASUREMENT_RGB, visible=False)
    if record.estimate_m is not None and record.estimate_cov_m2 is not None:
        ex, ey = record.estimate_m
        scene.add_line_segments("/current/ellipse", _ellipse_segments(np.array(record.estimate_m),
                                                                      record.estimate_cov_m2, z + 0.06, factor),
                                colors=CURRENT_RGB, thickness=3.0, thickness_units="screen")
        scene.add_icosphere("/current/estimate", radius=marker_m, color=ESTIMATE_RGB, position=(ex, ey, z + 0.04))
    own = (record.measurement_source == visloc.GEOMETRY and record.measurement_m is not None
           and record.measurement_cov_m2 is not None)
    segments = (_ellipse_segments(np.array(record.measurement_m), record.measurement_cov_m2, z + 0.07, factor)
                if own else np.zeros((0, 2, 3)))
    scene.add_line_segments("/current/measurement_ellipse", segments, colors=MEASUREMENT_ELLIPSE_RGB, thickness=2.0,
                            thickness_units="screen")
    scene.add_label("/current/label", label, position=(tx, ty, 1.0), anchor="bottom-center", visible=bool(label))


def draw_cameras(scene: viser.SceneApi, fov_rad: float, aspect: float, query_xy: tuple[float, float],
                 query_heading_deg: float, query_image: np.ndarray | None, match_xy: tuple[float, float] | None,
                 match_heading_deg: float, match_image: np.ndarray | None) -> None:
    """The query camera at its true pose and the best match's camera at its geotag (the paper's
    measurement), each showing its image when there is one."""
    scene.add_camera_frustum("/current/query_camera", fov=fov_rad, aspect=aspect, scale=FRUSTUM_SCALE_M,
                             color=TRUTH_RGB, image=query_image, wxyz=camera_wxyz(query_heading_deg),
                             position=(query_xy[0], query_xy[1], CAMERA_HEIGHT_M), thickness=0.08)
    if match_xy is None:
        scene.add_camera_frustum("/current/match_camera", fov=fov_rad, aspect=aspect, visible=False)
        return
    scene.add_camera_frustum("/current/match_camera", fov=fov_rad, aspect=aspect, scale=FRUSTUM_SCALE_M,
                             color=MEASUREMENT_RGB, image=match_image, wxyz=camera_wxyz(match_heading_deg),
                             position=(match_xy[0], match_xy[1], CAMERA_HEIGHT_M), thickness=0.08)
