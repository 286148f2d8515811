"""What a command uses when the user leaves it out, and the store file's life around a command.

* cameras: ``--camera`` given for a CSV drive is refused (a CSV drive has one camera, stored as
  ``camera``); a KITTI camera left out is the preferred one the drive holds; a log's, its only image
  topic;
* the database: a flag given wins; else the store's only source (or the query's own) and the
  source's only camera; an ambiguous choice is one line listing what the store holds;
* the exclusion window: left out, 1 s when the database holds images of the queries' own drive,
  else 0; 0 asked for on such a database prints a warning;
* the store file: a writing command makes its missing folder (one level, as ``out/``) and, failing
  before any image is stored in a store it created, removes the file again.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
import argparse
from pathlib import Path

from visloc.store.database import GeoDatabase, same_drive
from visloc.errors import InputError
from visloc.results.export import GEOJSON_SUFFIXES, write_trajectory
from visloc.cli.outputs import require_writable_output
from visloc.sources.drives import default_data_root, resolve_drive
from visloc.sources.logs import is_log
from visloc.store.workspace import Workspace

CSV_CAMERA = "camera"  # the one camera of a CSV drive, as the store names it (visloc.sources.drives.open_csv)
PAPER_DATABASE_CAMERA = {"image_00": ("image_01",)}  # the paper's protocol: left queries, right database


def is_csv(source: Path | str | None) -> bool:
    return source is not None and Path(source).suffix.lower() == ".csv"


def log_options(a: argparse.Namespace) -> dict:
    """What the flags say of a log's topics and fixes (None: not given), for ``open_source``."""
    return {key: getattr(a, key, None) for key in LOG_OPTIONS}


LOG_OPTIONS = ("fix_topic", "camera_info_topic", "imu_topic", "max_fix_gap_s")


def refuse_camera_for_csv(source: Path | str | None, flag: str, value: str | Sequence[str] | None) -> None:
    """A camera flag the user gave for a CSV drive is an error, not silently ignored."""
    if value is None or not is_csv(source):
        return
    value = " ".join(value) if isinstance(value, (list, tuple)) else value
    raise InputError(f"{flag} {value}: {source} is a CSV drive, which has one camera (stored as "
                     f"'{CSV_CAMERA}'); leave {flag} out")


def kitti_only_camera(source: Path | str | None, flag: str, value: str | None, default: str) -> str:
    """A camera flag: refused for a CSV drive (whose one camera this returns), else its value or ``default``."""
    refuse_camera_for_csv(source, flag, value)
    if is_log(source):
        return value  # None: the log's only image topic
    return CSV_CAMERA if is_csv(source) else value or default


def kitti_camera(root: Path | str | None, drive: str | None, camera: str | None,
                 preferred: Sequence[str] = ("image_01", "image_00")) -> str:
    """``camera`` if given; else the first of ``preferred`` the drive folder holds (the first when
    none or when the drive cannot be found, so that opening it names the problem)."""
    if camera is not None:
        return camera
    if is_csv(root):
        return CSV_CAMERA
    if is_log(root):
        return None  # the log's only image topic
    try:
        folder = resolve_drive(default_data_root() if root is None else Path(root), drive)
    except InputError:
        return preferred[0]
    return next((c for c in preferred if (folder / c / "data").is_dir()), preferred[0])


def choose_database(ws: Workspace, query_source: str, *, db_source: str | None = None, db_camera: str | None = None,
                    prefer: Sequence[str] = ()) -> tuple[str, str]:
    """(source, camera) of the database in ``ws`` for queries of ``query_source``. ``db_source`` and
    ``db_camera``, when given, win; else the query's own source if the store holds it (with
    ``db_camera``), or the only source that fits; the source's only camera, or the first of ``prefer``
    it holds. Anything else is ambiguous: an ``InputError`` listing what the store holds."""
    datasets = ws.drive_keys()  # (source, camera) pairs: a sharded store's catalogue is not read for them
    held = ", ".join(f"{s}/{c}" for s, c in datasets) or "nothing"
    if not datasets:
        raise InputError(f"{ws.path}: holds no images yet (build it with 'visloc ingest')")
    if db_source is None:
        sources = sorted({s for s, c in datasets if db_camera is None or c == db_camera})
        if query_source in sources:
            db_source = query_source
        elif len(sources) == 1:
            db_source = sources[0]
        elif not sources:
            raise InputError(f"{ws.path}: no images of camera {db_camera} (it holds {held}); "
                             "choose the database with --db-source and --db-camera")
        else:
            raise InputError(f"{ws.path}: choose the database with --db-source (it holds {held})")
    if db_camera is None:
        cameras = sorted(c for s, c in datasets if s == db_source)
        if not cameras:
            raise InputError(f"{ws.path}: no images of --db-source {db_source} (it holds {held})")
        if len(cameras) == 1:
            db_camera = cameras[0]
        else:
            db_camera = next((c for c in prefer if c in cameras), None)
            if db_camera is None:
                raise InputError(f"{ws.path}: {db_source} has cameras {', '.join(cameras)}; choose one with "
                                 f"--db-camera (it holds {held})")
    return db_source, db_camera


def only_camera(path: Path | str) -> str | None:
    """The camera of a store holding exactly one (source, camera); None otherwise or if unreadable."""
    try:
        datasets = (Workspace(path, read_only=True).drive_keys()
                    if Path(path).is_file() or Workspace.is_sharded(path) else [])
    except InputError:
        return None
    return datasets[0][1] if len(datasets) == 1 else None


# -- the store file around a writing command ---------------------------------------------------------

SIDE_FILES = ("-wal", "-shm", "-journal")


def _holds_images(path: Path) -> bool:
    try:
        return Workspace(path, read_only=True).image_count() > 0
    except InputError:
        return path.stat().st_size > 0 if path.exists() else False


@contextmanager
def store_for_writing(path: Path | str, flag: str = "--db") -> Iterator[None]:
    """Around a command that creates or extends the store at ``path``: make its folder when missing
    (the last folder only, as ``out/``); if the command fails while the store it created holds no
    image, remove the file, its side files and the folder it made. A store that existed is kept."""
    path = Path(path)
    existed = path.exists()
    parent = path.absolute().parent
    made = None
    if not parent.exists() and parent.parent.is_dir():
        try:
            parent.mkdir()
        except OSError as exc:
            raise InputError(f"{flag} {path}: cannot create folder {parent} ({exc.strerror or exc})") from None
        made = parent
    try:
        yield
    except BaseException:
        if not existed and path.exists() and not _holds_images(path):
            for suffix in ("", *SIDE_FILES):
                Path(f"{path}{suffix}").unlink(missing_ok=True)
        if made is not None:
            try:
                made.rmdir()  # only when empty
            except OSError:
                pass
        raise


def make_folder_of(path: Path | str, flag: str) -> None:
    """Make the missing last folder of an output file (as ``out/``) for a command that writes it."""
    parent = Path(path).absolute().parent
    if not parent.exists() and parent.parent.is_dir():
        try:
            parent.mkdir()
        except OSError as exc:
            raise InputError(f"{flag} {path}: cannot create folder {parent} ({exc.strerror or exc})") from None


def require_output(path: Path | str | None, flag: str, store: Path | str | None = None) -> None:
    """``require_writable_output``, except that a file in the missing folder a writing command makes
    for its ``store`` (as ``out/``) is accepted: the folder will exist when the file is written."""
    if path is not None and store is not None:
        parent = Path(path).absolute().parent
        if not parent.exists() and parent == Path(store).absolute().parent and parent.parent.is_dir():
            return
    require_writable_output(path, flag)


SAME_DRIVE_EXCLUSION_S = 1.0  # the evaluation's window: a same-drive query never sees its own second of driving


def exclusion_for(asked_s: float | None, db: GeoDatabase, timestamps_s, lat_deg, lon_deg, what: str) -> float:
    """The exclusion window of queries (``timestamps_s`` and their geotags) against ``db``: ``asked_s``
    when given, else 1 s when the database holds images of the queries' own drive
    (``visloc.store.database.same_drive``) and 0 otherwise. Says so on stdout; warns when a window of 0
    was asked for on such a database."""
    same = same_drive(db, timestamps_s, lat_deg, lon_deg)
    if asked_s is None:
        if not same:
            return 0.0
        print(f"exclusion {SAME_DRIVE_EXCLUSION_S:g} s: the database {db.source}/{db.camera} holds images of "
              f"{what}'s own drive; a query must not be posed from its own image or its twin "
              "(--exclusion-s 0 turns this off)")
        return SAME_DRIVE_EXCLUSION_S
    if same and asked_s == 0:
        print(f"warning: --exclusion-s 0 with a database ({db.source}/{db.camera}) that holds images of {what}'s "
              "own drive: a query may be posed from its own image or its twin, and its error then says nothing of "
              "how well visloc localizes")
    return float(asked_s)


# -- trajectory files: --geojson FILE and --csv FILE ----------------------------------------------------

def require_exports(a: argparse.Namespace, store: Path | None = None) -> None:
    """``--geojson`` and ``--csv``: the right suffix and a writable place, before any work (``store``: of a
    command that makes the store's missing folder, where the files may go)."""
    for flag, path, suffixes in (("--geojson", a.geojson, GEOJSON_SUFFIXES), ("--csv", a.csv, (".csv",)),
                                 ("--mcap", a.mcap, (".mcap",))):
        if path is not None and Path(path).suffix.lower() not in suffixes:
            raise InputError(f"{flag} {path}: the file name must end in {' or '.join(suffixes)}")
        require_output(path, flag, store)
    if a.mcap_images and a.mcap is None:
        raise InputError("--mcap-images: give the file with --mcap")


def write_exports(a: argparse.Namespace, run, frame, name: str, *, queries=None, db=None) -> None:
    """The run's trajectories to the files ``--geojson``, ``--csv`` and ``--mcap`` name (``run``: series of
    records, or a track's frames; ``queries``, the query drive, and ``db``, the database, give the images
    ``--mcap-images`` asks for)."""
    for path in (a.geojson, a.csv):
        if path is not None:
            write_trajectory(path, run, frame, name=name)
            print(f"wrote {path}")
    if a.mcap is not None:
        from visloc.results.mcap_export import write_run_mcap

        images = None
        if a.mcap_images and queries is not None and db is not None:
            query_files = {f.frame: f.image_path for f in queries.frames}
            db_files = {int(f): image.path for f, image in zip(db.frames, db.images)}

            def images(point):
                return query_files.get(point.frame), db_files.get(point.best_db_frame)
        n = write_run_mcap(a.mcap, run, frame, name=name, images=images)
        print(f"wrote {a.mcap} ({n} messages)")


def start_indices(a: argparse.Namespace, query_seq, schedule: list[list[int]]) -> set[int] | None:
    """The start frames ``--start-frames`` asks for, checked against the series that fit."""
    if not a.start_frames:
        return None
    try:
        wanted = {int(v) for v in a.start_frames.split(",")}
    except ValueError:
        raise InputError(f"--start-frames {a.start_frames!r}: expected comma-separated frame numbers") from None
    allowed = {query_seq.frames[s[0]].frame for s in schedule}
    if wanted - allowed:
        raise InputError(f"--start-frames {a.start_frames}: no series of {a.steps} queries starts at "
                         f"{sorted(wanted - allowed)[:5]} (this drive's series start at frames {min(allowed)}.."
                         f"{max(allowed)}: pick start frames there, or leave out --start-frames for every series)")
    return wanted
