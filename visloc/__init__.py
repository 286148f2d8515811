"""visloc: localize a vehicle from one camera against a database of geotagged images.

The paper's method (Zahedian et al.): SIFT correspondences by Lowe's ratio and
cosine similarity pick the best-matching database image, whose geotag is the
measurement of a constant-velocity Kalman filter.

Public API (the dashboard and scripts use only these names):
"""

from visloc.database import GeoDatabase, QuerySet, load_database, load_query_set
from visloc.drive import DriveMatches, MatchCancelled, drive_query_indices, drive_summary, match_drive, track_drive
from visloc.errors import InputError, ParameterError, VislocError
from visloc.evaluation import Evaluation, StepRecord, evaluate, series_schedule
from visloc.features import Features, extract_sift, make_sift
from visloc.figures import correspondence_figure
from visloc.geo import LocalFrame, geodesic_distance_m, haversine_distance_m
from visloc.ingest import IngestReport, ingest
from visloc.localizer import Localizer, PairCountCache, Query, StepResult
from visloc.matching import NearestTwo, correspondence_mask, correspondences, count_correspondences, nearest_two
from visloc.params import (
    PAPER_EVAL_RETRIEVAL,
    PAPER_FILTER,
    PAPER_MATCH,
    PAPER_RETRIEVAL,
    PAPER_SIFT,
    FilterParams,
    MatchParams,
    RetrievalParams,
    SiftParams,
)
from visloc.retrieval import Retrieval, candidate_mask, retrieve
from visloc.sources import Frame, Sequence, load_gray, open_csv, open_kitti, open_source
from visloc.tracking import ConstantVelocityKalman, FilterStep, covariance_ellipse_m, run_filter
from visloc.workspace import Dataset, Workspace

__version__ = "0.1.0"

__all__ = [
    "ConstantVelocityKalman", "Dataset", "DriveMatches", "MatchCancelled", "Workspace", "correspondence_figure",
    "covariance_ellipse_m", "drive_query_indices", "drive_summary", "match_drive", "track_drive", "Evaluation", "Features", "FilterParams", "FilterStep", "Frame", "GeoDatabase",
    "IngestReport", "InputError", "LocalFrame", "Localizer", "MatchParams", "NearestTwo", "PAPER_EVAL_RETRIEVAL",
    "PAPER_FILTER", "PAPER_MATCH", "PAPER_RETRIEVAL", "PAPER_SIFT", "PairCountCache", "ParameterError", "Query",
    "QuerySet", "Retrieval", "RetrievalParams", "Sequence", "SiftParams", "StepRecord", "StepResult", "VislocError",
    "candidate_mask", "correspondence_mask", "correspondences", "count_correspondences", "evaluate", "extract_sift",
    "geodesic_distance_m", "haversine_distance_m", "ingest", "load_database", "load_query_set", "load_gray", "make_sift",
    "nearest_two", "open_csv", "open_kitti", "open_source", "retrieve", "run_filter", "series_schedule",
]
