"""visloc: localize a vehicle from one camera against a database of geotagged images.

The paper's method (Zahedian et al.): SIFT correspondences by Lowe's ratio and cosine
similarity pick the best-matching database image, whose geotag is the measurement of a
constant-velocity Kalman filter. The refined method (beyond the paper) measures a metric
position instead, from the database's own geometry, with its own covariance.

The pipeline, one subpackage per stage (docs/architecture.md): ``params`` (every parameter,
declared once), ``geometry``, ``features``, ``sources`` (KITTI and CSV drives), ``retrieval``,
``pose`` (what a retrieval tells the filter), ``store`` (building a store and the one door to it;
the SQL is in ``visloc.db``), ``tracking`` (the filter, the localizer, the named methods),
``protocols`` (the paper's evaluation, whole drives, every frame at camera rate), ``results``
and ``cli``; the browser dashboard is ``visloc.dashboard``.

Public API: the names below, what the README's Python section, the dashboard and the scripts use.
Everything else is importable from its stage's module.
"""

from visloc.errors import InputError, ParameterError, VislocError
from visloc.features.sift import Query
from visloc.features.vlad import GlobalIndex
from visloc.geo import LocalFrame, geodesic_distance_m
from visloc.params import (FAST, PAPER_EVAL_RETRIEVAL, PAPER_FILTER, PAPER_MATCH, PAPER_RETRIEVAL, PAPER_SIFT, REFINED,
                           TRACK, FastParams, FilterParams, MatchParams, RefinedParams, RetrievalParams, SiftParams,
                           TrackParams, dashboard_controls)
from visloc.pose.measurement import GEOMETRY, GEOTAG
from visloc.pose.refined import StructureCache, pose_measurement
from visloc.protocols.drive import DriveMatches, drive_query_indices, drive_summary, match_drive, track_drive
from visloc.protocols.evaluation import evaluate
from visloc.protocols.records import RecordGeotags, StepRecord, record_geotags
from visloc.protocols.track import TrackFrame, TrackRun, run_track, track_filter, track_localizer
from visloc.results.export import trajectory_csv, trajectory_geojson, trajectory_text, write_trajectory
from visloc.results.figures import correspondence_figure
from visloc.results.saved import (LiveSettings, SavedRun, SavedStep, flat_params, live_settings, load_run,
                                  params_that_differ, run_figures, run_files, steps_of_records, worst_steps)
from visloc.retrieval.matching import MatchCancelled, PairCountCache, correspondences, nearest_two
from visloc.retrieval.retrievers import Retrieval, retrieve
from visloc.sources.drives import Sequence, default_data_root, load_gray, open_csv, open_kitti, open_source
from visloc.sources.queries import extract_queries
from visloc.store.build import ingest_sequence
from visloc.store.database import GeoDatabase, QuerySet
from visloc.store.ingest import IngestReport
from visloc.store.workspace import Dataset, Workspace
from visloc.tracking.kalman import covariance_ellipse_m, run_filter
from visloc.tracking.localizer import Localizer, StepResult
from visloc.tracking.methods import (METHODS, PAPER_METHOD, REFINED_FAST_METHOD, REFINED_METHOD, Method,
                                     build_localizer, method_named)
from visloc.tracking.runs import run_queries

__version__ = "0.1.0"

__all__ = [
    # drives and the store
    "Dataset", "GeoDatabase", "IngestReport", "QuerySet", "Sequence", "Workspace", "default_data_root",
    "ingest_sequence", "load_gray", "open_csv", "open_kitti", "open_source",
    # parameters and methods
    "FAST", "METHODS", "PAPER_EVAL_RETRIEVAL", "PAPER_FILTER", "PAPER_MATCH", "PAPER_METHOD", "PAPER_RETRIEVAL",
    "PAPER_SIFT", "REFINED", "REFINED_FAST_METHOD", "REFINED_METHOD", "TRACK", "FastParams", "FilterParams",
    "MatchParams", "Method", "RefinedParams", "RetrievalParams", "SiftParams", "TrackParams", "dashboard_controls",
    "method_named",
    # the pipeline's parts
    "Query", "extract_queries", "MatchCancelled", "PairCountCache", "correspondences", "nearest_two", "GlobalIndex",
    "Retrieval", "retrieve", "GEOMETRY", "GEOTAG", "StructureCache", "pose_measurement", "covariance_ellipse_m",
    "run_filter", "Localizer", "StepResult", "build_localizer", "run_queries",
    # runs and results
    "DriveMatches", "RecordGeotags", "StepRecord", "drive_query_indices", "drive_summary", "evaluate", "match_drive",
    "record_geotags", "track_drive", "TrackFrame", "TrackRun", "run_track", "track_filter", "track_localizer",
    "trajectory_csv", "trajectory_geojson", "trajectory_text", "write_trajectory", "correspondence_figure",
    # saved runs, read back
    "SavedRun", "SavedStep", "flat_params", "load_run", "params_that_differ", "run_figures", "run_files",
    "steps_of_records", "worst_steps", "LiveSettings", "live_settings",
    # geodesy, errors
    "LocalFrame", "geodesic_distance_m", "InputError", "ParameterError", "VislocError",
]
