"""visloc: localize a vehicle from one camera against a database of geotagged images.

The paper's method (Zahedian et al.): SIFT correspondences by Lowe's ratio and cosine
similarity pick the best-matching database image, whose geotag is the measurement of a
constant-velocity Kalman filter. The refined method (beyond the paper) measures a metric
position instead, from the database's own geometry, with its own covariance.

The pipeline, one module per stage (each a set of pure functions over numpy arrays, plus
the small classes that hold a stage's state):

    features     SIFT keypoints and descriptors; ``Query``
    matching     the paper's equations (1) and (2); exact GEMM, faiss and batched backends; counters
    vlad         global descriptors (VLAD) for the fast path's shortlist
    retrieval    candidates and the best match: the paper's window, or the filter-gated shortlist
    measurement  what a retrieval tells the filter: the best match's geotag
    geometry     rigid transforms, essential matrix, triangulation, PnP
    pose         the refined measurement: a metric pose from the database's geometry
    structure    database structure made once at ingest, per image and variant
    viewpose     posing a query against views whose keypoints carry 3D points (both refined paths)
    fastpose     the refined measurement at camera rate, on stored structure
    tracking     the constant-velocity Kalman filter, its gate, the RTS smoother
    localizer    a retriever, a measurer and the filter composed; ``methods``: the named compositions
    runs         the one query loop and what each query costs

Around it: ``sources`` (KITTI drives, CSV drives), ``ingest`` and ``workspace`` (the store,
``visloc.db``, and the only door to it), ``database`` (what is loaded from it), ``evaluation``
(the paper's protocol), ``drive`` (whole-drive runs), ``track`` (every frame at camera rate), ``records``, ``report`` and ``export`` (results and
their tables, JSON and plots), ``cli`` and ``commands`` (the ``visloc`` command), and the
browser dashboard ``visloc.dashboard``.

Public API: the names below (the dashboard and scripts use only these).
"""

from visloc.store.database import GeoDatabase, QuerySet
from visloc.protocols.drive import DriveMatches, drive_query_indices, drive_summary, filter_measurements, match_drive, track_drive
from visloc.errors import InputError, ParameterError, VislocError
from visloc.protocols.evaluation import Evaluation, evaluate, series_schedule, step_labels
from visloc.results.export import (TrajectoryPoint, trajectory_csv, trajectory_format, trajectory_geojson,
                           trajectory_points, trajectory_text, write_trajectory)
from visloc.features.sift import Features, Query, extract_sift, make_sift
from visloc.results.figures import correspondence_figure
from visloc.geo import LocalFrame, geodesic_distance_m, haversine_distance_m
from visloc.geometry.projective import CameraModel, PnPResult, Triangulation, essential_inliers, solve_pnp, triangulate
from visloc.store.ingest import IngestReport
from visloc.tracking.localizer import Localizer, StepResult, StepTimings
from visloc.retrieval.matching import (MatchCancelled, NearestTwo, PairCountCache, backend_counter, brute_force_counter,
                             cancellable, correspondence_mask, correspondences, count_correspondences, count_many,
                             nearest_two, nearest_two_faiss)
from visloc.pose.measurement import GEOMETRY, GEOTAG, GeotagMeasurer, Measurement, MemoisedMeasurer, geotag_measurement
from visloc.tracking.methods import METHODS, PAPER_METHOD, REFINED_FAST_METHOD, REFINED_METHOD, Method, build_localizer, method_named
from visloc.params import (
    FAST,
    PAPER_EVAL_RETRIEVAL,
    PAPER_FILTER,
    PAPER_MATCH,
    PAPER_RETRIEVAL,
    PAPER_SIFT,
    REFINED,
    FastParams,
    FilterParams,
    MatchParams,
    RefinedParams,
    RetrievalParams,
    SiftParams,
    TRACK,
    TrackParams,
    dashboard_controls,
)
from visloc.pose.refined import PoseMeasurer, StructureCache, pose_measurement
from visloc.pose.viewpose import DatabaseGeometry
from visloc.sources.queries import extract_queries
from visloc.protocols.records import RecordGeotags, StepRecord, record_geotags, step_record
from visloc.retrieval.retrievers import (Retrieval, ShortlistRetriever, WindowRetriever, build_global_index, candidate_mask,
                              gate_mask, retrieve, shortlist_retrieve)
from visloc.tracking.runs import TimedStep, latency_ms, run_queries
from visloc.pose.fastpose import FastPoseMeasurer, StructureMatcher
from visloc.pose.structure import ViewStructure, choose_variant, view_structures
from visloc.protocols.track import TrackFrame, TrackRun, run_track, track_filter, track_localizer
from visloc.sources.drives import Frame, Sequence, default_data_root, load_gray, open_csv, open_kitti, open_source
from visloc.tracking.kalman import (ConstantVelocityKalman, FilterStep, SmoothedStep, covariance_ellipse_m, rts_smooth,
                             run_filter)
from visloc.features.vlad import GlobalEncoder, GlobalIndex, shortlist
from visloc.store.build import build_global_vectors, build_self_check, build_structure, ingest_sequence
from visloc.store.workspace import Dataset, Workspace

__version__ = "0.1.0"

__all__ = [
    # data and the store
    "Dataset", "Frame", "GeoDatabase", "IngestReport", "QuerySet", "Sequence", "Workspace", "default_data_root",
    "build_global_vectors", "build_self_check", "build_structure", "ingest_sequence",
    "load_gray", "open_csv", "open_kitti", "open_source",
    # parameters and methods
    "FAST", "METHODS", "PAPER_EVAL_RETRIEVAL", "PAPER_FILTER", "PAPER_MATCH", "PAPER_METHOD", "PAPER_RETRIEVAL",
    "PAPER_SIFT", "REFINED", "REFINED_FAST_METHOD", "REFINED_METHOD", "TRACK", "TrackParams", "FastParams", "FilterParams", "MatchParams", "Method", "RefinedParams",
    "RetrievalParams", "SiftParams", "dashboard_controls", "method_named",
    # pipeline stages
    "Features", "Query", "extract_sift", "make_sift", "extract_queries",
    "MatchCancelled", "NearestTwo", "PairCountCache", "backend_counter", "brute_force_counter", "cancellable",
    "correspondence_mask", "correspondences", "count_correspondences", "count_many", "nearest_two",
    "nearest_two_faiss",
    "GlobalEncoder", "GlobalIndex", "shortlist",
    "Retrieval", "ShortlistRetriever", "WindowRetriever", "build_global_index", "candidate_mask", "gate_mask",
    "retrieve", "shortlist_retrieve",
    "GEOMETRY", "GEOTAG", "GeotagMeasurer", "Measurement", "MemoisedMeasurer", "geotag_measurement",
    "CameraModel", "PnPResult", "Triangulation", "essential_inliers", "solve_pnp", "triangulate",
    "DatabaseGeometry", "PoseMeasurer", "StructureCache", "pose_measurement",
    "FastPoseMeasurer", "StructureMatcher", "ViewStructure", "choose_variant", "view_structures",
    "ConstantVelocityKalman", "FilterStep", "SmoothedStep", "covariance_ellipse_m", "rts_smooth", "run_filter",
    "Localizer", "StepResult", "StepTimings", "build_localizer",
    "TimedStep", "latency_ms", "run_queries",
    # runs and results
    "DriveMatches", "Evaluation", "RecordGeotags", "StepRecord", "drive_query_indices", "drive_summary", "evaluate",
    "filter_measurements", "match_drive", "record_geotags", "series_schedule", "step_labels", "step_record",
    "track_drive", "TrajectoryPoint", "trajectory_csv", "trajectory_format", "trajectory_geojson",
    "trajectory_points", "trajectory_text", "write_trajectory", "TrackFrame", "TrackRun", "run_track", "track_filter", "track_localizer",
    # geodesy, figures, errors
    "LocalFrame", "geodesic_distance_m", "haversine_distance_m", "correspondence_figure",
    "InputError", "ParameterError", "VislocError",
]
