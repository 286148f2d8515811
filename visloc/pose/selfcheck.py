"""How well a database poses its own images: the measurement its lever gain is fitted on.

Every other database image (``self_checked_indices``) is treated as a query of its own drive: the images
closer to it in time than ``SELF_CHECK_EXCLUSION_S`` (the evaluation's exclusion window) are left out, the
``top_k`` allowed images most like it by global vector are its candidates, and the refined measurement
(``visloc.pose.refined``: verification, structure with refined database poses, PnP) poses it as it poses a
query, with the same settings: the same views posed apart and averaged, the same guided matching. Its error
against its own geotag, with the covariance the measurement gives without the lever term, says how
far this database's poses are off per metre of lever (``visloc.pose.uncertainty.fit_lever_gain``). Each pose
is the mean of views posed apart, as a query's measurement is, with their spread in its covariance: the gain is
then what such views share beyond their spread, the lever term a query's measurement carries. A cheaper
stand-in (two views in one PnP) was tried and does not speak for the queries: a tighter
position prior in the structure made the queries' poses better and the stand-in's worse on drive 0001, so its
gain rose while the queries' errors fell and their ellipses came out twice too large
(``benchmarks/self_check_agreement.py``).

Only the database's own data is used: its images, geotags, attitudes and calibration. The
retrieval is shortcut (global vectors instead of the paper's counts) because it is not what is
checked: the verification re-ranks the candidates as it does for any query.

The camera-rate path poses a query differently: against the stored structure's variants, matched to their
3D-carrying keypoints only (``visloc.pose.fastpose``), where the exact path triangulates each view with the
neighbours the query's window leaves it. The two paths' poses need not carry the same error per metre of
lever: denser structure makes the exact path's self-poses better while the stored variants, triangulated
with neighbours on one side only wherever the window holds the others, gain less. So the camera-rate path has
a self-check of its own (``camera_rate=True``: the same images, the same candidates, posed as
``FastPoseMeasurer`` poses), and its own gain.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from visloc.db import SelfCheckRecord
from visloc.features.sift import Query
from visloc.geometry.projective import CameraModel
from visloc.pose.fastpose import FastPoseMeasurer, StoredStructures, StructureMatcher
from visloc.pose.measurement import GEOMETRY, Measurement
from visloc.params import TRACK, RefinedParams
from visloc.params.methods import REFINED_FAST_METHOD
from visloc.pose.refined import StructureCache, pose_measurement
from visloc.retrieval.retrievers import Retrieval
from visloc.pose.structure import structure_settings_json
from visloc.pose.uncertainty import DEFAULT_LEVER_GAIN, SIDES, LeverGain, fit_lever_gain, fit_lever_gains
from visloc.pose.viewpose import DatabaseGeometry

SELF_CHECK_EXCLUSION_S = 1.0  # as the evaluation's: a same-drive query never sees its own second of driving
SELF_CHECK_PROBABILITY = 0.8  # the level at which the lever gain matches the errors (see fit_lever_gain)
MIN_POSES_PER_SIDE = 10  # fewer: that side keeps the default gain (never below the other side's)
SELF_CHECK_VERSION = 4  # bump when what a self-check measures changes: older rows are then not used (3: the
# spread of fewer than 4 views is round; 4: each pose says how many views it is the mean of)
CAMERA_RATE_SELF_CHECK_VERSION = 2  # the same, for the camera-rate path's (2: its two views posed apart)
BASE_TERMS = ("pnp", "views", "views_round")  # what a self-check pose's gain is fitted beyond
# what of a query's pose settings a stored self-check depends on beyond the structure's, top_k and pnp_px
POSE_SETTINGS = ("n_views", "fuse_views", "guided_radius_px", "thin_support_pnp_px", "other_side_candidates")
# every other image of a drive is checked: adjacent frames' poses share nearly all their errors (the same views,
# the same structure), so half of them give the same gain at half the cost (on every shared drive the even and
# the odd images' gains lie within 13 % of their mean)
SELF_CHECK_STRIDE = 2
CAMERA_RATE_PARAMS = REFINED_FAST_METHOD.pose  # the camera-rate path's pose settings: its self-check's too


@dataclass(frozen=True)
class SelfCheckPose:
    """One database image posed from its allowed neighbours.

    index: database index; error_m: (2,) pose minus the image's geotag, metres (None: no pose);
    base_cov_m2: (2, 2) the pose's covariance without the lever term; lever_m, side: as the
    measurement's; reason: why there is no pose (None otherwise); heading_deg: the image's compass heading
    (its geotag's attitude; None where it states none), along which the lever gain is told from across;
    views_posed_apart: how many views the pose is the mean of (None: not recorded)."""

    index: int
    error_m: np.ndarray | None
    base_cov_m2: np.ndarray | None
    lever_m: float | None
    side: str | None
    reason: str | None = None
    heading_deg: float | None = None
    views_posed_apart: int | None = None


def self_check_params(params: RefinedParams) -> RefinedParams:
    """The pose the camera-rate path's self-check makes (``FastPoseMeasurer``): ``params`` with two views and no
    guided matching, as that path poses a frame (each view alone and averaged where ``params.fuse_views``). No
    second, looser pose where support is thin, and no search for views on the other side: the gain's one-sided
    poses are the database's own extrapolation over the lever."""
    return params.replace(n_views=2, guided_radius_px=0.0, thin_support_pnp_px=0.0, other_side_candidates=0)


def self_check_settings_json(params: RefinedParams, exclusion_s: float = SELF_CHECK_EXCLUSION_S, *,
                             camera_rate: bool = False) -> str:
    """What a stored self-check was made with: the structure's settings, the exclusion, ``top_k``, ``pnp_px``,
    the version, and for the exact path's, the query's pose settings (``POSE_SETTINGS``); for the camera-rate
    path's, ``"path": "camera-rate"`` and the frames' SIFT scale and keypoints."""
    settings = {"structure": json.loads(structure_settings_json(params)), "exclusion_s": exclusion_s,
                "top_k": params.top_k, "pnp_px": params.pnp_px}
    if camera_rate:
        settings.update(path="camera-rate", query_image_scale=TRACK.query_image_scale,
                        query_max_keypoints=TRACK.query_max_keypoints, version=CAMERA_RATE_SELF_CHECK_VERSION)
    else:
        d = params.as_dict()
        settings.update(pose={k: d[k] for k in POSE_SETTINGS}, version=SELF_CHECK_VERSION)
    return json.dumps(settings, sort_keys=True)


def self_checked_indices(n_images: int) -> range:
    """The database indices (time order) a store's self-check poses: every ``SELF_CHECK_STRIDE``-th."""
    return range(0, n_images, SELF_CHECK_STRIDE)


def _candidates(k: int, db_timestamps_s: np.ndarray, global_vectors_f32: np.ndarray, top_k: int,
                exclusion_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(the ``top_k`` images allowed to image ``k`` most like it by global vector, every allowed image)."""
    t = np.asarray(db_timestamps_s, float)
    allowed = np.flatnonzero(np.abs(t - t[k]) >= exclusion_s)
    similarity = global_vectors_f32[allowed] @ global_vectors_f32[k]
    return allowed[np.argsort(-similarity, kind="stable")[:top_k]], allowed


def self_check_pose(k: int, geometry: DatabaseGeometry, db_east_north_m: np.ndarray, db_timestamps_s: np.ndarray,
                    keypoints_f32: np.ndarray, descriptors_u8: np.ndarray, global_vectors_f32: np.ndarray,
                    params: RefinedParams, *, exclusion_s: float = SELF_CHECK_EXCLUSION_S,
                    cache: StructureCache | None = None) -> SelfCheckPose:
    """Database image ``k`` posed as a query of its own drive (module docstring); ``geometry`` without
    a lever gain (the base covariance is what is kept)."""
    chosen, allowed = _candidates(k, db_timestamps_s, global_vectors_f32, params.top_k, exclusion_s)
    if allowed.size == 0:
        return SelfCheckPose(k, None, None, None, None, f"no image at least {exclusion_s:g} s away")
    retrieval = Retrieval(candidates=chosen, counts=np.arange(len(chosen), 0, -1, dtype=np.int64),
                          best_index=int(chosen[0]), allowed=allowed)
    camera: CameraModel = geometry.camera
    m = pose_measurement(keypoints_f32, descriptors_u8, retrieval, db_east_north_m, geometry, camera, params, cache)
    return _pose_of(k, m, db_east_north_m)


def camera_rate_self_check_pose(k: int, query: Query, measurer: FastPoseMeasurer, matcher: StructureMatcher,
                                global_vectors_f32: np.ndarray, top_k: int) -> SelfCheckPose:
    """Database image ``k`` posed as the camera-rate path poses a query of its own drive: ``query`` (its
    features as the camera-rate path describes a frame), the same ``top_k`` candidates as ``self_check_pose``
    ranked by their matches to stored structure (``matcher``), posed by ``measurer`` (a ``FastPoseMeasurer`` on a
    geometry without a lever gain, with the self-check's exclusion)."""
    chosen, allowed = _candidates(k, measurer.db_timestamps_s, global_vectors_f32, top_k, measurer.exclusion_s)
    if allowed.size == 0:
        return SelfCheckPose(k, None, None, None, None, f"no image at least {measurer.exclusion_s:g} s away")
    counts_of = matcher(query.descriptors_u8)
    counts = counts_of(chosen)
    retrieval = Retrieval(candidates=chosen, counts=counts,
                          best_index=int(chosen[int(np.argmax(counts))]) if counts.max() > 0 else None,
                          allowed=allowed, pairs=counts_of.pairs)
    return _pose_of(k, measurer.measure(query, retrieval), measurer.db_east_north_m)


def _pose_of(k: int, m: Measurement, db_east_north_m: np.ndarray) -> SelfCheckPose:
    """A measurement of database image ``k`` as a self-check pose: its base covariance is the measurement's without
    the lever and the geotags' terms, as its path states it (the exact path's with a few views' spread round)."""
    if m.source != GEOMETRY:
        return SelfCheckPose(k, None, None, None, None, m.fallback_reason)
    error = np.asarray(m.east_north_m, float) - np.asarray(db_east_north_m[k], float)
    base = sum(v for name, v in m.cov_terms_m2.items() if name in BASE_TERMS)
    return SelfCheckPose(k, error, base, float(m.lever_m), m.side, views_posed_apart=int(m.views_posed_apart))


def self_check(geometry: DatabaseGeometry, db_east_north_m: np.ndarray, db_timestamps_s: np.ndarray,
               keypoints_f32: Sequence[np.ndarray], descriptors_u8: Sequence[np.ndarray],
               global_vectors_f32: np.ndarray, params: RefinedParams, *, indices: Sequence[int] | None = None,
               exclusion_s: float = SELF_CHECK_EXCLUSION_S, cache: StructureCache | None = None,
               stored: StoredStructures | None = None, queries: Mapping[int, Query] | None = None,
               progress: Callable[[int, int], None] | None = None) -> list[SelfCheckPose]:
    """Every database image (or ``indices``) posed as a query of its own drive. Structure is shared
    between them through ``cache`` (one view serves many neighbours). With ``stored`` (the store's structure,
    database index -> variant -> structure), posed as the camera-rate path poses (module docstring): database
    index ``k`` as ``queries[k]``, its image described as the camera-rate path describes a frame (an image
    without one is not posed, and says so)."""
    bare = replace(geometry, lever_gain=None)
    wanted = range(len(db_timestamps_s)) if indices is None else indices
    if stored is None:
        cache = cache if cache is not None else StructureCache()

        def pose(k: int) -> SelfCheckPose:
            return self_check_pose(k, bare, db_east_north_m, db_timestamps_s, keypoints_f32[k], descriptors_u8[k],
                                   global_vectors_f32, params, exclusion_s=exclusion_s, cache=cache)
    else:
        matcher = StructureMatcher(descriptors_u8, stored, params.ratio)
        measurer = FastPoseMeasurer(db_east_north_m, db_timestamps_s, bare, stored, geometry.camera,
                                    self_check_params(params), exclusion_s=exclusion_s)

        def pose(k: int) -> SelfCheckPose:
            query = (queries or {}).get(k)
            if query is None:
                return SelfCheckPose(k, None, None, None, None, "no frame of the drive to describe as a camera frame")
            return camera_rate_self_check_pose(k, query, measurer, matcher, global_vectors_f32, params.top_k)
    out = []
    for n, k in enumerate(wanted, 1):
        out.append(pose(int(k)))
        if progress:
            progress(n, len(wanted))
    return out


def _side_gains(chosen: list[SelfCheckPose]) -> tuple[float, float]:
    """(along, across) the heading for one side's poses: ``fit_lever_gains`` where every pose states its
    heading, else one round gain (``fit_lever_gain``) both ways."""
    errors = np.array([p.error_m for p in chosen])
    base = np.array([p.base_cov_m2 for p in chosen])
    lever = np.array([p.lever_m for p in chosen])
    headings = np.array([np.nan if p.heading_deg is None else p.heading_deg for p in chosen], float)
    if np.all(np.isfinite(headings)):
        return fit_lever_gains(errors, base, lever, headings, probability=SELF_CHECK_PROBABILITY)
    gain = fit_lever_gain(errors, base, lever, probability=SELF_CHECK_PROBABILITY)
    return gain, gain


def lever_gain_from(poses: Sequence[SelfCheckPose], source: str = "self-check", *, min_views: int = 0) -> LeverGain:
    """The lever gain per side, along the heading and across it, that the self-check's poses call for
    (``_side_gains`` at ``SELF_CHECK_PROBABILITY``), fitted on a side's poses on at least ``min_views`` views
    posed apart where it has ``MIN_POSES_PER_SIDE`` of them, else on all its poses. The exact path states the
    spread of fewer than ``SHAPED_SPREAD_VIEWS`` views round (``visloc.pose.refined.round_spread``): those poses'
    own term already holds most of their error, so fitted among the others they lower the gain that a query on
    more views needs, and the more of them a store's self-check has the lower it goes (a store whose images keep
    fewer keypoints poses more of its own images on few views than its queries). The one-side gain is never
    below the both-sides one, either way: a query with views on one side only extrapolates the database's
    errors where one with views on both sides interpolates them, and is never better off (a self-check with
    few one-sided poses can say otherwise by chance). A side with fewer than ``MIN_POSES_PER_SIDE`` poses keeps the default gain (round),
    again never below the other side's; with no pose on either side, the defaults."""
    gains, counts = {}, {}
    for side in SIDES:
        chosen = [p for p in poses if p.error_m is not None and p.side == side]
        counts[side] = len(chosen)
        shaped = [p for p in chosen if p.views_posed_apart is not None and p.views_posed_apart >= min_views]
        chosen = shaped if len(shaped) >= MIN_POSES_PER_SIDE else chosen
        if len(chosen) >= MIN_POSES_PER_SIDE:
            gains[side] = _side_gains(chosen)
    default_one = (DEFAULT_LEVER_GAIN.one_side, DEFAULT_LEVER_GAIN.one_side)
    if "both" in gains:
        both = gains["both"]
        one = np.maximum(gains.get("one", default_one), both)
    elif "one" in gains:
        both = one = gains["one"]
    else:
        both = (DEFAULT_LEVER_GAIN.both_sides, DEFAULT_LEVER_GAIN.both_sides)
        one = default_one
    return LeverGain(both_sides=float(both[0]), one_side=float(one[0]), n_both=counts["both"], n_one=counts["one"],
                     source=source, both_sides_across=float(both[1]), one_side_across=float(one[1]))


def pose_record(p: SelfCheckPose, image_id: int, settings_json: str) -> SelfCheckRecord:
    """A self-check pose as the store keeps it (``visloc.db.SelfCheckRecord``)."""
    if p.error_m is None:
        return SelfCheckRecord(image_id, settings_json, None, None, None, None, None, None, None, p.reason)
    C = p.base_cov_m2
    return SelfCheckRecord(image_id, settings_json, float(p.error_m[0]), float(p.error_m[1]), float(C[0, 0]),
                           float(C[0, 1]), float(C[1, 1]), float(p.lever_m), p.side, None, p.views_posed_apart)


def record_pose(r: SelfCheckRecord, index: int, heading_deg: float | None = None) -> SelfCheckPose:
    """A stored self-check as a pose of database index ``index``, whose geotag's heading is ``heading_deg``."""
    if r.error_east_m is None:
        return SelfCheckPose(index, None, None, None, None, r.reason)
    heading = None if heading_deg is None or not np.isfinite(heading_deg) else float(heading_deg)
    return SelfCheckPose(index, np.array([r.error_east_m, r.error_north_m]),
                         np.array([[r.cov_ee_m2, r.cov_en_m2], [r.cov_en_m2, r.cov_nn_m2]]), r.lever_m, r.side,
                         heading_deg=heading, views_posed_apart=r.views_posed_apart)
