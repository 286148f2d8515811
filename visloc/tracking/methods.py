"""The named methods: compositions of the localizer's parts.

A ``Method`` says which retriever and which measurer a localizer is made of; it holds
parameters only. ``build_localizer`` makes the parts from a database and composes them,
and refuses a composition that lacks what it needs (the refined method without calibrated
cameras) with a message that says what is missing.

===========  ======================================  ============================================
method       retriever                               measurer
===========  ======================================  ============================================
``paper``    +-window_s around the previous match    the best match's geotag, the filter's R
``refined``  the same                                a metric pose from the database's geometry,
                                                     its own covariance; the filter gates outliers
``refined-`` the filter's gate, a global-vector       the same pose on the database's stored
``fast``     shortlist, matches to 3D points only     structure (``visloc.pose.fastpose``): camera rate
===========  ======================================  ============================================

Either can take the fast retrieval (``method.replace(shortlist=FAST)``): the filter's gate,
a global-vector shortlist, exact counts on the shortlist only.
"""

from __future__ import annotations

from visloc.store.database import GeoDatabase
from visloc.pose.fastpose import FastPoseMeasurer, StructureMatcher
from visloc.geometry.projective import CameraModel
from visloc.tracking.localizer import Localizer
from visloc.retrieval.matching import Counter, PairCountCache, backend_counter, brute_force_counter
from visloc.pose.measurement import GeotagMeasurer, MemoisedMeasurer
from visloc.params import FilterParams, MatchParams, RetrievalParams
from visloc.params.methods import Method
from visloc.pose.refined import PoseMeasurer, StructureCache
from visloc.retrieval.retrievers import ContrastSelecting, ShortlistRetriever, WindowRetriever, build_global_index
from visloc.pose.structure import seeded_structure_cache
from visloc.features.vlad import GlobalIndex


def build_localizer(method: Method, db: GeoDatabase, match: MatchParams, retrieval: RetrievalParams,
                    filter_params: FilterParams, *, query_camera: CameraModel | None = None,
                    query_what: str = "the query camera", counter: Counter | None = None,
                    shortlist_index: GlobalIndex | None = None, structures: StructureCache | None = None,
                    stored: dict | None = None, memoise: bool = False) -> Localizer:
    """The localizer ``method`` describes, over ``db``.

    query_camera:     the query camera's calibration (the refined method needs it); ``query_what``
                      names the queries (source/camera) in the message when it is missing
    counter:          how retrieval counts correspondences (e.g. a ``PairCountCache`` of earlier
                      runs); default: computed afresh for every candidate
    shortlist_index:  the fast retrieval's global vectors of ``db``, if built already
    structures:       database structure triangulated by earlier refined measurements, to reuse
    stored:           the database's stored structure (``Workspace.load_structure``): the camera-rate
                      path needs it (it counts with it and ignores ``counter``); the exact refined path
                      reads it where it would triangulate the same view with the same neighbours
    memoise:          measure a query (by its key) with the same retrieval only once
    """
    if method.camera_rate:
        return _camera_rate_localizer(method, db, retrieval, filter_params, query_camera, query_what,
                                      shortlist_index, stored)
    if isinstance(counter, PairCountCache):
        counter.check_thresholds(match)
    descriptors = db.retrieval_descriptors_u8  # the paper's features, also where the store's are denser
    if method.shortlist is None:
        retriever = WindowRetriever(db.timestamps_s, counter or brute_force_counter(descriptors, match), retrieval)
    else:
        index = shortlist_index or build_global_index(descriptors, method.shortlist)
        counter = counter or backend_counter(method.shortlist.nn_backend, descriptors, match)
        retriever = ShortlistRetriever(db.timestamps_s, db.east_north_m, index, method.shortlist, counter, retrieval)
    if db.retrieval_contrast is not None:
        retriever = ContrastSelecting(retriever, db.retrieval_contrast, db.octave_layers)
    if method.pose is None:
        measurer = GeotagMeasurer(db.east_north_m)
    else:
        if structures is None and stored:
            structures = seeded_structure_cache(stored)  # the stored structure, where the views' neighbours match
        measurer = PoseMeasurer(db.east_north_m, db.geometry(), query_camera, method.pose, structures=structures,
                                query_what=query_what)
    if memoise:
        measurer = MemoisedMeasurer(measurer)
    return Localizer(retriever, measurer, filter_params, **method.filter_options)


def _camera_rate_localizer(method: Method, db: GeoDatabase, retrieval: RetrievalParams, filter_params: FilterParams,
                           query_camera: CameraModel | None, query_what: str, shortlist_index: GlobalIndex | None,
                           stored: dict | None) -> Localizer:
    stored = stored or {}
    matcher = StructureMatcher(db.descriptors_u8, stored, method.pose.ratio)
    measurer = FastPoseMeasurer(db.east_north_m, db.timestamps_s, db.geometry(camera_rate=True), stored, query_camera,
                                method.pose, exclusion_s=retrieval.exclusion_s, min_matches=method.min_matches,
                                query_what=query_what, db_name=f"{db.source}/{db.camera}")  # refuses first
    index = shortlist_index or build_global_index(db.descriptors_u8, method.shortlist)
    retriever = ShortlistRetriever(db.timestamps_s, db.east_north_m, index, method.shortlist, matcher, retrieval)
    return Localizer(retriever, measurer, filter_params, **method.filter_options)
