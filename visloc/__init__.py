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

import importlib

__version__ = "0.1.0"  # the one place the version is written: pyproject.toml reads it from here

# Each public name and the module it comes from. They are imported when first used (PEP 562), so that
# ``import visloc`` and the command line's parsing, help and refusals load none of OpenCV, faiss, pyproj
# or SQLite's wrappers; ``from visloc import X`` and ``visloc.X`` work as with plain imports.
_EXPORTS = {
    "visloc.errors": ("InputError", "ParameterError", "VislocError"),
    "visloc.features.sift": ("Query",),
    "visloc.features.vlad": ("GlobalIndex",),
    "visloc.geo": ("LocalFrame", "geodesic_distance_m"),
    "visloc.params": ("FAST", "PAPER_EVAL_RETRIEVAL", "PAPER_FILTER", "PAPER_MATCH", "PAPER_RETRIEVAL", "PAPER_SIFT",
                      "REFINED", "STORE_SIFT", "TRACK", "FastParams", "FilterParams", "MatchParams", "RefinedParams",
                      "RetrievalParams", "SiftParams", "TrackParams", "dashboard_controls"),
    "visloc.params.methods": ("METHODS", "PAPER_METHOD", "REFINED_FAST_METHOD", "REFINED_METHOD", "Method",
                              "features_for", "method_named"),
    "visloc.pose.measurement": ("GEOMETRY", "GEOTAG"),
    "visloc.pose.refined": ("StructureCache", "pose_measurement"),
    "visloc.protocols.drive": ("DriveMatches", "drive_query_indices", "drive_summary", "match_drive", "track_drive"),
    "visloc.protocols.evaluation": ("evaluate",),
    "visloc.protocols.records": ("RecordGeotags", "StepRecord", "record_geotags"),
    "visloc.protocols.following": ("drive_indices", "follow_drive", "follows_points", "open_series"),
    "visloc.protocols.track": ("TrackFrame", "TrackRun", "run_track", "track_filter", "track_localizer"),
    "visloc.results.export": ("trajectory_csv", "trajectory_geojson", "trajectory_text", "write_trajectory"),
    "visloc.results.figures": ("correspondence_figure",),
    "visloc.results.mcap_export": ("write_run_mcap",),
    "visloc.results.saved": ("LiveSettings", "SavedRun", "SavedStep", "flat_params", "live_settings", "load_run",
                             "params_that_differ", "run_figures", "run_files", "steps_of_records", "worst_steps"),
    "visloc.retrieval.matching": ("MatchCancelled", "PairCountCache", "correspondences", "nearest_two"),
    "visloc.retrieval.retrievers": ("Retrieval", "retrieve"),
    "visloc.sources.drives": ("Drive", "default_data_root", "load_gray", "open_csv", "open_kitti"),
    "visloc.sources.opening": ("open_source",),
    "visloc.sources.logs": ("is_log", "log_topics", "open_log"),
    "visloc.sources.queries": ("extract_queries",),
    "visloc.store.build": ("ingest_sequence",),
    "visloc.store.database": ("GeoDatabase", "QuerySet"),
    "visloc.store.ingest": ("IngestReport",),
    "visloc.store.workspace": ("StoredDrive", "Workspace"),
    "visloc.tracking.kalman": ("covariance_ellipse_m", "run_filter"),
    "visloc.tracking.localizer": ("Localizer", "StepResult"),
    "visloc.tracking.methods": ("build_localizer",),
    "visloc.tracking.runs": ("run_queries",),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module 'visloc' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # imported once
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULE_OF])


__all__ = [
    # drives and the store
    "StoredDrive", "GeoDatabase", "IngestReport", "QuerySet", "Drive", "Workspace", "default_data_root",
    "ingest_sequence", "load_gray", "open_csv", "open_kitti", "open_source", "is_log", "log_topics", "open_log",
    # parameters and methods
    "FAST", "METHODS", "PAPER_EVAL_RETRIEVAL", "PAPER_FILTER", "PAPER_MATCH", "PAPER_METHOD", "PAPER_RETRIEVAL",
    "PAPER_SIFT", "REFINED", "REFINED_FAST_METHOD", "REFINED_METHOD", "STORE_SIFT", "TRACK", "FastParams", "FilterParams",
    "MatchParams", "Method", "RefinedParams", "RetrievalParams", "SiftParams", "TrackParams", "dashboard_controls",
    "features_for", "method_named",
    # the pipeline's parts
    "Query", "extract_queries", "MatchCancelled", "PairCountCache", "correspondences", "nearest_two", "GlobalIndex",
    "Retrieval", "retrieve", "GEOMETRY", "GEOTAG", "StructureCache", "pose_measurement", "covariance_ellipse_m",
    "run_filter", "Localizer", "StepResult", "build_localizer", "run_queries",
    # runs and results
    "DriveMatches", "RecordGeotags", "StepRecord", "drive_query_indices", "drive_summary", "evaluate", "match_drive",
    "follow_drive", "follows_points", "open_series", "drive_indices",
    "record_geotags", "write_run_mcap", "track_drive", "TrackFrame", "TrackRun", "run_track", "track_filter", "track_localizer",
    "trajectory_csv", "trajectory_geojson", "trajectory_text", "write_trajectory", "correspondence_figure",
    # saved runs, read back
    "SavedRun", "SavedStep", "flat_params", "load_run", "params_that_differ", "run_figures", "run_files",
    "steps_of_records", "worst_steps", "LiveSettings", "live_settings",
    # geodesy, errors
    "LocalFrame", "geodesic_distance_m", "InputError", "ParameterError", "VislocError",
]
