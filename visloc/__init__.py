"""visloc: localize a vehicle from one camera against a database of geotagged images.

The paper's method (Zahedian et al.): SIFT correspondences by Lowe's ratio and
cosine similarity pick the best-matching database image, whose geotag is the
measurement of a constant-velocity Kalman filter.

The refined mode (beyond the paper) measures a metric position instead: the
query's pose against structure triangulated from posed database images, with its
own covariance (``measurement_from_retrieval``). A caller holding retrievals can
make measurements once and re-run only the filter with other R/Q/P0 or gate
(``filter_measurements``), and smooth a run offline (``rts_smooth``).

Public API (the dashboard and scripts use only these names):
"""

from visloc.database import GeoDatabase, QuerySet, load_database, load_query_set
from visloc.drive import DriveMatches, MatchCancelled, drive_query_indices, drive_summary, match_drive, track_drive
from visloc.errors import InputError, ParameterError, VislocError
from visloc.evaluation import Evaluation, StepRecord, evaluate, series_schedule
from visloc.fast import FAST, FastDatabase, FastParams, FastRetrieval, count_many, fast_retrieve, nearest_two_faiss
from visloc.features import Features, extract_sift, make_sift
from visloc.figures import correspondence_figure
from visloc.geo import LocalFrame, geodesic_distance_m, haversine_distance_m
from visloc.geometry import CameraModel, PnPResult, Triangulation, essential_inliers, solve_pnp, triangulate
from visloc.ingest import IngestReport, ingest
from visloc.localizer import Localizer, PairCountCache, Query, StepResult
from visloc.matching import NearestTwo, correspondence_mask, correspondences, count_correspondences, nearest_two
from visloc.params import (
    PAPER_EVAL_RETRIEVAL,
    PAPER_FILTER,
    PAPER_MATCH,
    PAPER_RETRIEVAL,
    PAPER_SIFT,
    MODES,
    REFINED,
    FilterParams,
    MatchParams,
    RefinedParams,
    RetrievalParams,
    SiftParams,
)
from visloc.refined import (
    DatabaseGeometry,
    Measurement,
    StructureCache,
    filter_measurements,
    measurement_from_retrieval,
    paper_measurement,
)
from visloc.retrieval import Retrieval, candidate_mask, retrieve
from visloc.sources import Frame, Sequence, load_gray, open_csv, open_kitti, open_source
from visloc.tracking import (ConstantVelocityKalman, FilterStep, SmoothedStep, covariance_ellipse_m,
                             rts_smooth, run_filter)
from visloc.workspace import Dataset, Workspace

__version__ = "0.1.0"

__all__ = [
    "FAST", "FastDatabase", "FastParams", "FastRetrieval", "count_many", "fast_retrieve", "nearest_two_faiss",
    "Dataset", "DriveMatches", "MatchCancelled", "Workspace", "correspondence_figure",
    "covariance_ellipse_m", "drive_query_indices", "drive_summary", "match_drive", "track_drive",
    "CameraModel", "DatabaseGeometry", "MODES", "Measurement", "PnPResult", "REFINED", "RefinedParams",
    "SmoothedStep", "StructureCache", "Triangulation", "essential_inliers", "filter_measurements",
    "measurement_from_retrieval", "paper_measurement", "rts_smooth", "solve_pnp", "triangulate",
    "ConstantVelocityKalman", "Evaluation", "Features", "FilterParams", "FilterStep", "Frame", "GeoDatabase",
    "IngestReport", "InputError", "LocalFrame", "Localizer", "MatchParams", "NearestTwo", "PAPER_EVAL_RETRIEVAL",
    "PAPER_FILTER", "PAPER_MATCH", "PAPER_RETRIEVAL", "PAPER_SIFT", "PairCountCache", "ParameterError", "Query",
    "QuerySet", "Retrieval", "RetrievalParams", "Sequence", "SiftParams", "StepRecord", "StepResult", "VislocError",
    "candidate_mask", "correspondence_mask", "correspondences", "count_correspondences", "evaluate", "extract_sift",
    "geodesic_distance_m", "haversine_distance_m", "ingest", "load_database", "load_query_set", "load_gray", "make_sift",
    "nearest_two", "open_csv", "open_kitti", "open_source", "retrieve", "run_filter", "series_schedule",
]
