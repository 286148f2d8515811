"""The dashboard's state: what the controls ask for, and what the page shows now.

``Controls`` is written by the GUI callbacks and nothing else. ``Shown`` is written by the
apply path (and the background jobs it starts): which store, data, run and step the page
shows, with the keys that say which controls they were made for. Applying compares the
two; see ``visloc.dashboard.app``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import visloc

STORE_SUFFIXES = (".sqlite", ".sqlite3", ".db")


# the parameters with a dashboard control, as declared in the engine: (class, name, spec, default)
CONTROLLED = visloc.dashboard_controls()


def short_label(spec) -> str:
    """A control's label without its parenthesis: "τ1 (Lowe ratio)" -> "τ1"."""
    return spec.control.label.split(" (")[0]


def initial_params() -> dict[str, float]:
    """Every controlled parameter's first value, in the parameter's units."""
    return {name: float(spec.control.initial if spec.control.initial is not None else default)
            for _, name, spec, default in CONTROLLED}


@dataclass
class Controls:
    """What the user asked for. ``params``: every controlled parameter by name, in its own units (a
    variance where the slider shows a standard deviation); replaced whole, never changed in place."""

    store_request: tuple[int, str]  # (how many times a store was asked for, its path)
    db_name: str | None = None
    query_name: str | None = None
    method: str = visloc.PAPER_METHOD.name
    rate_hz: float = 1.0
    start_s: float = 0.0
    params: dict[str, float] = field(default_factory=initial_params)
    step: int = 1  # the Step slider: 1..N
    play: bool = False
    speed: float = 1.0
    follow: bool = False
    latlon: bool = False  # show latitude and longitude beside the local metres
    magnification: float = 1.0  # the 3D view's ellipses drawn this many times larger (at most)
    hidden: frozenset[str] = frozenset()  # the 3D view's layers hidden
    rerun: int = 0  # "Paper's parameters" asks for a fresh run even when nothing else changed

    def _labelled(self, folder: str) -> tuple:
        return tuple((short_label(spec), self.params[name]) for _, name, spec, _ in CONTROLLED
                     if spec.control.folder == folder)

    def match_key(self, data_key: tuple) -> tuple:
        """What a drive run's retrievals and measurements depend on, as (what, value) pairs."""
        return (("data", data_key), ("mode", self.method), *self._labelled("matching"), ("rate (Hz)", self.rate_hz),
                ("start (s)", self.start_s), *self._labelled("queries"), ("rerun", self.rerun))

    def filter_key(self) -> tuple:
        """What the filter over a run's measurements depends on (besides the run)."""
        return self._labelled("filter")

    def params_for(self, base):
        """``base`` (a parameter object) with the controls' values of its fields."""
        return base.replace(**{name: self.params[name] for cls, name, _, _ in CONTROLLED if isinstance(base, cls)})

    def filter_params(self) -> visloc.FilterParams:
        return self.params_for(visloc.PAPER_FILTER.replace(dt_s=1.0 / self.rate_hz))


@dataclass
class Run:
    """A drive run as drawn: its retrievals and measurements, and the filter over them."""

    matches: visloc.DriveMatches
    match_key: tuple
    number: int  # completed runs so far, shown in the status line
    rate_hz: float  # the query rate it was matched at: the filter's time step
    n_queries: int = 0  # queries the run will have once matched
    partial: bool = False  # still being matched: the queries matched so far
    records: list[visloc.StepRecord] = field(default_factory=list)
    track_key: tuple | None = None
    # a later run being matched over the same queries: the complete run it replaces, whose steps are shown
    # beyond the ones matched so far (``shown``)
    previous: Run | None = None
    fresh_steps: int | None = None  # in a view made by ``shown``: steps before this one are the new run's

    def replaces_in_place(self, other: Run | None) -> bool:
        """Whether this run's steps can stand in for ``other``'s one by one: same queries, same method."""
        return (other is not None and other.matches.method.name == self.matches.method.name
                and np.array_equal(other.matches.query_indices[:len(self.matches)], self.matches.query_indices)
                and len(other.matches) == self.n_queries)

    def shown(self) -> Run:
        """What the page draws: the run itself, or, while it is matched in place of a previous run, its
        steps so far followed by the previous run's later steps (marked by ``fresh_steps``), so the
        trajectory and the step slider keep their length and fill in with the new run from the start."""
        p, m = self.previous, len(self.records)
        if p is None or not self.partial or m >= len(p.records) or m != len(self.matches):
            return self
        a, b = self.matches, p.matches
        latency_ms = np.concatenate([np.asarray(a.latency_ms, float), np.asarray(b.latency_ms, float)[m:]])
        matches = replace(a, query_indices=b.query_indices, retrievals=a.retrievals + b.retrievals[m:],
                          measurements=a.measurements + b.measurements[m:], latency_ms=latency_ms)
        return replace(self, matches=matches, records=self.records + p.records[m:], fresh_steps=m)

    def from_previous(self, k: int) -> bool:
        """Whether step ``k`` (0-based) of this view is the previous run's (not matched again yet)."""
        return self.fresh_steps is not None and k >= self.fresh_steps

    def match_params_of(self, k: int) -> visloc.MatchParams:
        """The matching parameters step ``k`` was matched with."""
        return (self.previous if self.from_previous(k) else self).matches.match_params


@dataclass
class Shown:
    """What the page shows, and the requests in flight."""

    store_request: tuple[int, str] | None = None  # the last store request acted on
    store_path: str | None = None
    workspace: visloc.Workspace | None = None
    datasets: list[visloc.StoredDrive] = field(default_factory=list)
    data_key: tuple | None = None  # (store path, database name, queries name) of the loaded data
    loading_key: tuple | None = None
    db: visloc.GeoDatabase | None = None
    queries: visloc.QuerySet | None = None
    # the paper's own features (database, queries), where the store's were described at a lower contrast
    paper_features: tuple[visloc.GeoDatabase, visloc.QuerySet] | None = None
    # counts per (tau1, tau2, the contrast the features were selected at)
    caches: dict[tuple, visloc.PairCountCache] = field(default_factory=dict)
    structures: visloc.StructureCache = field(default_factory=visloc.StructureCache)
    stored: dict = field(default_factory=dict)  # the database's stored structure (the camera-rate path)
    index: visloc.GlobalIndex | None = None  # its stored global vectors
    # (queries' name, their images read again as a drive or None, why not): what the camera-rate mode follows
    series_images: tuple | None = None
    run: Run | None = None
    matching_key: tuple | None = None  # a match running in the background for these controls
    failed_key: tuple | None = None  # controls whose match failed: not tried again until they change
    step_key: tuple | None = None
    drawn_key: tuple | None = None  # the run drawn in 3D: (its track key, the ellipses' magnification)
    image_key: tuple | None = None  # the step whose pictures are shown or being read
    runs_done: int = 0

    def features(self, method: visloc.Method) -> tuple[visloc.GeoDatabase, visloc.QuerySet]:
        """The database and queries ``method`` matches: the store's features, or the paper's own for its method."""
        if self.paper_features is not None and method.pose is None:
            return self.paper_features
        return self.db, self.queries


def load_features(workspace: visloc.Workspace, db_drive: visloc.StoredDrive, query_drive: visloc.StoredDrive):
    """The database and the queries as the store holds them, and the paper's own features where the store's
    were described at a lower SIFT contrast threshold than the paper's (else None)."""
    db = workspace.load_database(db_drive.source, db_drive.camera)
    queries = workspace.load_queries(query_drive.source, query_drive.camera)
    paper_sift = visloc.features_for(visloc.PAPER_METHOD, workspace.sift_params)
    if paper_sift == workspace.sift_params:
        return db, queries, None
    return db, queries, (workspace.load_database(db_drive.source, db_drive.camera, paper_sift, frame=db.frame),
                         workspace.load_queries(query_drive.source, query_drive.camera, paper_sift))


@dataclass(frozen=True)
class Allowed:
    """What the page may open: store files inside ``folders`` (``visloc dashboard --allow``), and the
    store it was started on wherever that is. Paths are compared resolved (``..`` and symbolic links
    followed), so neither climbs out of a folder."""

    folders: tuple[Path, ...]
    start: Path | None = None  # the store named on the command line, resolved

    @classmethod
    def of(cls, folders, start: Path | str | None = None) -> Allowed:
        return cls(tuple(dict.fromkeys(Path(f).resolve() for f in folders)),
                   Path(start).resolve() if start is not None else None)

    def admits(self, path: Path | str) -> bool:
        try:
            resolved = Path(path).resolve()
        except (OSError, RuntimeError, ValueError):  # a loop of links, a NUL byte: nothing to open
            return False
        return resolved == self.start or any(resolved.is_relative_to(f) for f in self.folders)

    def refusal(self, path: str) -> str:
        """The one line a path outside is refused with (the path as typed: where it leads is not said)."""
        folders = ", ".join(str(f) for f in self.folders) or "none"
        return f"{path}: outside the folders this dashboard may open ({folders}); restart it with --allow to add one"


def discover_stores(path: Path, allowed: Allowed) -> list[str]:
    """Stores to offer: ``path`` plus the SQLite files beside it, those the page may open (a sharded
    store is a folder: offered when it is ``path``)."""
    found: list[str] = []
    candidates = [path] + (sorted(path.parent.glob("*")) if path.parent.is_dir() else [])
    for c in candidates:
        if (c == path or c.suffix in STORE_SUFFIXES) and str(c) not in found and allowed.admits(c) \
                and (not c.is_dir() or visloc.Workspace.is_sharded(c)):
            found.append(str(c))
    return found


def first_choices(datasets, db: tuple[str | None, str | None],
                  queries: tuple[str | None, str | None]) -> tuple[str, str]:
    """The database and queries a store opens on, as dataset names: the first that fits each
    (source, camera) asked for (None: any). Queries no camera or source was asked for, and none
    fits, are another series than the database's when the store has one (a store of two CSV
    drives opens on one against the other, not on one against itself)."""
    def fits(d, want) -> bool:
        return (want[0] is None or d.source == want[0]) and (want[1] is None or d.camera == want[1])

    names = [d.name for d in datasets]
    db_choice = next((d.name for d in datasets if fits(d, db)), names[0])
    q_choice = next((d.name for d in datasets if fits(d, queries) and d.name != db_choice), None)
    if q_choice is None:
        q_choice = next((d.name for d in datasets if fits(d, queries)), None)
    if q_choice is None:
        q_choice = next((n for n in names if n != db_choice), db_choice)
    return db_choice, q_choice



def series_images(s: Shown, queries: visloc.QuerySet, query_images: Path | None) -> tuple[visloc.Drive | None,
                                                                                          str | None]:
    """The query series' images, read again to follow points (``visloc.open_series`` from ``query_images``, None:
    the data root), or None and why not; looked for once per series loaded."""
    if s.series_images is None or s.series_images[0] != queries.name:
        try:
            drive = visloc.open_series(query_images, queries.source, queries.camera)
            visloc.drive_indices(drive, queries)
            s.series_images = (queries.name, drive, None)
        except visloc.VislocError as exc:
            s.series_images = (queries.name, None, str(exc))
    return s.series_images[1], s.series_images[2]


def measure_drive(s: Shown, queries: visloc.QuerySet, db: visloc.GeoDatabase, method: visloc.Method, match: visloc.MatchParams, retrieval: visloc.RetrievalParams,
                  indices: np.ndarray, rate_hz: float, cache: visloc.PairCountCache, query_images: Path | None,
                  **callbacks) -> tuple[visloc.DriveMatches, str | None]:
    """A live run's measurements of ``queries`` against ``db`` (the loaded data), and why a camera-rate run does not follow points (None when
    it does, or is no camera-rate run): at the camera's rate the camera-rate method follows points on the series'
    images as ``visloc track`` does (``visloc.follow_drive``); otherwise every query is measured in full
    (``visloc.match_drive``). ``callbacks``: ``progress``, ``cancelled`` and ``on_step``, as both take them."""
    # the camera-rate path's gate follows the paper's filter at the query rate
    filter_params = visloc.PAPER_FILTER.replace(dt_s=1.0 / rate_hz)
    drive, not_following = None, None
    if visloc.follows_points(method, indices):
        drive, not_following = series_images(s, queries, query_images)
    elif method.camera_rate:
        not_following = f"at {rate_hz:g} Hz, below the camera's rate, each query is localized in full"
    if drive is not None:
        return visloc.follow_drive(drive, queries, db, s.workspace.sift_params, retrieval, indices, method=method,
                                   match_params=match, filter_params=filter_params, stored=s.stored,
                                   shortlist_index=s.index, **callbacks), None
    return visloc.match_drive(queries, db, match, retrieval, indices, method=method, cache=cache,
                              structures=s.structures, stored=s.stored, shortlist_index=s.index,
                              filter_params=filter_params, **callbacks), not_following
