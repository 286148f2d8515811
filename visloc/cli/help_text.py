"""What ``visloc --help`` and each command's ``--help`` teach: the default store and worked examples.

Every example is a real command, run from the repository's folder on the shared KITTI drives
(2011_09_26_drive_0001 has both gray cameras, 2011_09_26_drive_0005 the left one only) or on a
drive of your own given as a CSV of geotagged images.
"""

from __future__ import annotations

DEFAULT_DB = "out/visloc.sqlite"  # every command's store unless --db says otherwise
DEFAULT_FAST_DB = "out/visloc_s05.sqlite"  # bench's store of the fast path (SIFT at half scale)

KITTI = "../shared/data/kitti"
CSV_FORMAT = ("A CSV drive (my_drive/geotags.csv above): the header file,timestamp,lat,lon (optional columns: alt, "
              "heading, roll_deg, pitch_deg, accuracy_m), one row per image, each file name relative to the "
              "CSV's folder; timestamp in seconds or ISO 8601. A calibration.json beside it enables the refined "
              "method.")

_EXAMPLES = {
    None: f"""\
getting started (the store is {DEFAULT_DB} unless --db says otherwise):
  visloc ingest {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --camera image_01
  visloc info
  visloc localize {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --db-camera image_01 --start-frame 40
  visloc evaluate {KITTI} --drive 2011_09_26_drive_0001 --json out/evaluation.json
  visloc dashboard

'visloc COMMAND --help' shows each command's options and examples.""",
    "ingest": f"""\
examples:
  # both gray cameras of a KITTI drive
  visloc ingest {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --camera image_01
  # a drive with the left camera only
  visloc ingest {KITTI} --drive 2011_09_26_drive_0005 --camera image_00
  # a drive of your own, into a store of its own
  visloc ingest my_drive/geotags.csv --db out/my_drive.sqlite
  # what the store holds now
  visloc info

{CSV_FORMAT}""",
    "localize": f"""\
examples:
  # the paper's Tables 2 and 3: left-camera queries from frame 40 against the right camera's database
  visloc localize {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --db-camera image_01 --start-frame 40
  # the same series as JSON and as a trajectory for GIS tools
  visloc localize {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --db-camera image_01 --start-frame 40 \\
      --json out/series_40.json --geojson out/series_40.geojson
  # a single-camera drive against its own images: the 1 s exclusion keeps a query off its own image (automatic)
  visloc localize {KITTI} --drive 2011_09_26_drive_0005 --db-camera image_00 --start-frame 20
  # a CSV drive against the store holding it alone: no --db-source or --db-camera needed
  visloc localize my_drive/geotags.csv --db out/my_drive.sqlite --steps 4 --csv out/my_drive.csv

The database defaults to the store's only drive (or the queries' own) and its only camera; with
several, name it with --db-source and --db-camera.""",
    "evaluate": f"""\
examples:
  # the paper's protocol on drive 0001: left queries, right database (ingests both cameras first)
  visloc evaluate {KITTI} --drive 2011_09_26_drive_0001 --json out/evaluation.json
  # a single-camera drive against itself, the refined method, smoothed, with a GeoJSON of every series
  visloc evaluate {KITTI} --drive 2011_09_26_drive_0005 --mode refined --smooth --json out/refined_0005.json \\
      --geojson out/refined_0005.geojson
  # a few series only, and every step as CSV
  visloc evaluate {KITTI} --drive 2011_09_26_drive_0001 --start-frames 0,20,40 --csv out/steps.csv
  # a CSV drive against itself
  visloc evaluate my_drive/geotags.csv --db out/my_drive.sqlite --json out/my_drive_eval.json""",
    "evaluate-drives": f"""\
examples:
  # every drive of the data root, both methods, every protocol each drive supports
  visloc evaluate-drives {KITTI} --out-dir out/drives
  # the paper's method only
  visloc evaluate-drives {KITTI} --modes paper --out-dir out/drives_paper""",
    "track": f"""\
examples:
  # every frame of a single-camera drive against its own images (the 1 s exclusion is automatic), at camera
  # rate, with a trajectory file
  visloc track {KITTI} --drive 2011_09_26_drive_0005 --camera image_00 --json out/track.json \\
      --geojson out/track.geojson
  # left frames against the right camera's database, first 50 frames, the exact (slow) path
  visloc track {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --db-camera image_01 --frames 50 --exact
  # by default the map's points are followed between relocalizations, each frame read once the one asked
  # for before it has come (the JSON splits latency by tracked and relocalized frames); frames delivered at a
  # camera's 10 Hz instead, to see the share of the processor a live run takes:
  visloc track {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --pace-hz 10 --json out/track_live.json
  # every frame localized in full instead, read as fast as possible:
  visloc track {KITTI} --drive 2011_09_26_drive_0001 --camera image_00 --no-follow-points \\
      --json out/track_full.json

The refined measurement needs a calibrated camera: a KITTI drive, or a CSV drive with a
calibration.json beside its CSV.""",
    "dashboard": """\
examples:
  visloc dashboard                                  # the default store, http://127.0.0.1:8080
  visloc dashboard --db out/my_drive.sqlite --port 8090
  visloc dashboard --run out/results/track_2011_09_26_drive_0001_stereo.json      # a saved run, no store needed
  visloc dashboard --run out/a.json --run out/b.json   # two runs compared""",
    "bench": f"""\
examples:
  visloc bench {KITTI} --drive 2011_09_26_drive_0001 --json out/bench.json
  # a quicker run: one live series, no synthetic database, no refined paths
  visloc bench {KITTI} --drive 2011_09_26_drive_0001 --series 1 --skip-synthetic --skip-refined""",
    "upgrade": """\
examples:
  visloc upgrade                                    # the default store
  visloc upgrade --db out/my_drive.sqlite""",
    "info": """\
examples:
  visloc info                                       # the default store
  visloc info --db out/my_drive.sqlite""",
    "check": """\
examples:
  visloc check                                      # the default store
  visloc check --db out/my_drive.sqlite && echo whole
  visloc ingest my_drive/geotags.csv --db out/my_drive.sqlite   # repairs the damaged images check named""",
}


def examples(command: str | None = None) -> str:
    """The epilog of ``visloc COMMAND --help`` (of ``visloc --help`` for None)."""
    return _EXAMPLES[command]
