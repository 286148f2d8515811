"""A run as an MCAP file that Foxglove opens as it is, written with Foxglove's own SDK (``foxglove-sdk``).

Topics (each message at its query's time; the series of an evaluation overlap in time, and each message
says its series):

* ``/visloc/truth``, ``/visloc/measurement``, ``/visloc/estimate`` (``foxglove.LocationFix``): the
  geotag, the measurement and the Kalman estimate in WGS84, the last two with their east/north
  covariance (m², ENU order); Foxglove's Map panel draws them;
* ``/visloc/scene`` (``foxglove.SceneUpdate``): in the local frame ``visloc_local`` (metres east and north of
  the database's origin, z up), the truth, measurement and estimate tracks of each series as lines and the
  estimate's 2σ ellipse at each step; Foxglove's 3D panel draws them (display frame ``visloc_local``);
* ``/visloc/step`` (JSON, with its JSON schema): each step's figures: series, step, frame, errors, the
  measurement's source and the sigmas of both covariances;
* ``/visloc/image/query`` and ``/visloc/image/match`` (``foxglove.CompressedImage``), when asked for: the
  query image and the database image its best match came from.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from visloc.errors import InputError
from visloc.geo import LocalFrame
from visloc.results.export import (ELLIPSE_POINTS, ELLIPSE_SIGMA, TrajectoryPoint, finite_or_none, sigmas_m,
                                   trajectory_points)
from visloc.tracking.kalman import covariance_ellipse_m

LOCAL_FRAME_ID = "visloc_local"
STEP_SCHEMA = {
    "title": "visloc.Step", "type": "object",
    "properties": {
        "series": {"type": "integer"}, "step": {"type": "integer"}, "frame": {"type": "integer"},
        "timestamp_s": {"type": "number"},
        "measurement_source": {"type": ["string", "null"], "description": "geotag, geometry, or null: none"},
        "measurement_error_m": {"type": ["number", "null"]}, "estimate_error_m": {"type": ["number", "null"]},
        "measurement_sigma_major_m": {"type": ["number", "null"]}, "measurement_sigma_minor_m": {"type": ["number", "null"]},
        "estimate_sigma_major_m": {"type": ["number", "null"]}, "estimate_sigma_minor_m": {"type": ["number", "null"]},
    },
    "required": ["series", "step", "frame", "timestamp_s"],
}
COLORS = {"truth": (0.2, 0.8, 0.3), "measurement": (1.0, 0.55, 0.1), "estimate": (0.2, 0.5, 1.0)}


def _ns(timestamp_s: float) -> int:
    return int(round(timestamp_s * 1e9))


def step_json(p: TrajectoryPoint) -> dict:
    """What ``/visloc/step`` says of one step."""
    m_major, m_minor = sigmas_m(p.measurement_cov_m2)
    e_major, e_minor = sigmas_m(p.estimate_cov_m2)
    return {"series": p.series, "step": p.step, "frame": p.frame, "timestamp_s": float(p.timestamp_s),
            "measurement_source": p.measurement_source, "measurement_error_m": finite_or_none(p.measurement_error_m),
            "estimate_error_m": finite_or_none(p.estimate_error_m), "measurement_sigma_major_m": m_major,
            "measurement_sigma_minor_m": m_minor, "estimate_sigma_major_m": e_major, "estimate_sigma_minor_m": e_minor}


def write_run_mcap(path: Path | str, run, frame: LocalFrame, *, name: str,
                   images: Callable[[TrajectoryPoint], tuple[Path | None, Path | None]] | None = None) -> int:
    """Write ``run`` (series of step records, or a track's frames) to ``path``; returns the number of messages.
    ``images``: the (query, best match) image files of a step, when the images are asked for."""
    import foxglove
    from foxglove import Channel, Context
    from foxglove.channels import CompressedImageChannel, LocationFixChannel, SceneUpdateChannel
    from foxglove.messages import (Color, CompressedImage, LinePrimitive, LinePrimitiveLineType, LocationFix,
                                   LocationFixPositionCovarianceType, Point3, SceneEntity, SceneUpdate, Timestamp)

    points = trajectory_points(run)
    context = Context()
    count = 0

    def stamp(t_s: float) -> Timestamp:
        ns = _ns(t_s)
        return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)

    def fix(p: TrajectoryPoint, kind: str, position_m, cov) -> LocationFix | None:
        if position_m is None or not np.all(np.isfinite(position_m)):
            return None
        lat, lon = frame.to_geo(np.asarray(position_m, float))
        covariance = [0.0] * 9
        if cov is not None:
            covariance = [cov[0][0], cov[0][1], 0.0, cov[1][0], cov[1][1], 0.0, 0.0, 0.0, 0.0]
        r, g, b = COLORS[kind]
        return LocationFix(timestamp=stamp(p.timestamp_s), frame_id=f"series {p.series}", latitude=float(lat),
                           longitude=float(lon), altitude=0.0, position_covariance=covariance,
                           position_covariance_type=(LocationFixPositionCovarianceType.Known if cov is not None
                                                     else LocationFixPositionCovarianceType.Unknown),
                           color=Color(r=r, g=g, b=b, a=1.0))

    def line(points_m, kind: str, loop: bool = False) -> LinePrimitive:
        r, g, b = COLORS[kind]
        return LinePrimitive(type=LinePrimitiveLineType.LineLoop if loop else LinePrimitiveLineType.LineStrip,
                             thickness=2.0, scale_invariant=True, color=Color(r=r, g=g, b=b, a=1.0),
                             points=[Point3(x=float(x), y=float(y), z=0.0) for x, y in points_m])

    try:
        writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=context)
    except Exception as exc:  # the SDK raises its own error for a path it cannot write
        raise InputError(f"--mcap {path}: cannot write ({str(exc).splitlines()[0][:120]})") from None
    with writer:
        fixes = {kind: LocationFixChannel(f"/visloc/{kind}", context=context) for kind in COLORS}
        scene = SceneUpdateChannel("/visloc/scene", context=context)
        steps = Channel("/visloc/step", schema=STEP_SCHEMA, context=context, metadata={"run": name})
        pictures = ({kind: CompressedImageChannel(f"/visloc/image/{kind}", context=context)
                     for kind in ("query", "match")} if images is not None else {})
        tracks: dict[tuple[int, str], list] = {}
        for p in sorted(points, key=lambda q: (q.timestamp_s, q.series, q.step)):
            t_ns = _ns(p.timestamp_s)
            for kind, position, cov in (("truth", p.truth_m, None), ("measurement", p.measurement_m,
                                                                      p.measurement_cov_m2),
                                        ("estimate", p.estimate_m, p.estimate_cov_m2)):
                message = fix(p, kind, position, cov)
                if message is not None:
                    fixes[kind].log(message, log_time=t_ns)
                    count += 1
                    tracks.setdefault((p.series, kind), []).append(position)
            entities = [SceneEntity(timestamp=stamp(p.timestamp_s), frame_id=LOCAL_FRAME_ID,
                                    id=f"series {p.series} {kind} track", lines=[line(track, kind)])
                        for (series, kind), track in tracks.items() if series == p.series and len(track) >= 2]
            major, _ = sigmas_m(p.estimate_cov_m2)
            if major and p.estimate_m is not None:
                ring = covariance_ellipse_m(np.asarray(p.estimate_m), np.asarray(p.estimate_cov_m2), ELLIPSE_SIGMA,
                                            ELLIPSE_POINTS)
                entities.append(SceneEntity(timestamp=stamp(p.timestamp_s), frame_id=LOCAL_FRAME_ID,
                                            id=f"series {p.series} estimate {ELLIPSE_SIGMA:g} sigma ellipse",
                                            lines=[line(ring, "estimate", loop=True)]))
            if entities:
                scene.log(SceneUpdate(entities=entities), log_time=t_ns)
                count += 1
            steps.log(step_json(p), log_time=t_ns)
            count += 1
            if images is not None:
                for kind, file in zip(("query", "match"), images(p)):
                    if file is not None and Path(file).is_file():
                        data = Path(file).read_bytes()
                        fmt = "png" if data[:4] == b"\x89PNG" else "jpeg"
                        pictures[kind].log(CompressedImage(timestamp=stamp(p.timestamp_s), frame_id=kind, data=data,
                                                           format=fmt), log_time=t_ns)
                        count += 1
    return count
