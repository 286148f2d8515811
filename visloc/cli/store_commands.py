"""The commands on a store itself: ``visloc upgrade`` (migrate it in place), ``visloc check`` (is it whole?)
and ``visloc info`` (what it holds, or what visloc reads from a drive)."""

from __future__ import annotations

import argparse

from visloc.cli.describing import describe_drive
from visloc.db.shards import is_sharded
from visloc.params.methods import PAPER_METHOD, features_for
from visloc.progress import progress_reporter
from visloc.store.check import check_sharded, check_store
from visloc.store.sharded import sharded_summary
from visloc.store.workspace import STORE_SCHEMA_VERSION, Workspace


def cmd_upgrade(a: argparse.Namespace) -> int:
    ws = Workspace(a.db)  # opening for writing migrates in place
    if ws.migrated_from is None:
        print(f"{a.db}: already at schema version {STORE_SCHEMA_VERSION}")
    else:
        print(f"{a.db}: schema version {ws.migrated_from} -> {STORE_SCHEMA_VERSION}, every image and cached count kept; "
              "'visloc ingest' on its drives fills in what the new version adds")
        if ws.checksums_filled:
            print(f"{a.db}: computed the checksums of its {ws.checksums_filled} stored arrays as they are now (from "
                  "here on a changed byte is caught; damage from before cannot be told apart); the next 'visloc "
                  "ingest' of each drive describes its images once more to record which files they were made from")
    return 0


def cmd_check(a: argparse.Namespace) -> int:
    lines, clean = (check_sharded(a.db, progress=progress_reporter(f"check {a.db}", "tiles")) if is_sharded(a.db)
                    else check_store(a.db, progress=progress_reporter(f"check {a.db}", "images")).summary())
    print("\n".join(lines))
    return 0 if clean else 2


def cmd_info(a: argparse.Namespace) -> int:
    if a.source is not None:
        return describe_drive(a)
    ws = Workspace(a.db, read_only=True)  # reading never changes the file
    sift = ws.sift_params
    print(f"{a.db}: {ws.image_count()} images")
    if ws.sharded:
        print(sharded_summary(a.db))
    print(f"SIFT settings: {sift.as_dict() if sift else 'none yet'}")
    paper = None if sift is None else features_for(PAPER_METHOD, sift)
    if paper is not None and paper != sift:
        print(f"the paper's method, and the refined mode's retrieval, read the keypoints SIFT keeps at contrast "
              f"{paper.contrast_threshold:g}; the refined measurements and the camera-rate path read all of them")
    for d in ws.drives():
        calib = "P_rect known" if d.has_calibration else "no calibration"
        calib += ", extrinsics known" if d.has_extrinsics else ", no extrinsics"
        calib += f", {d.n_without_attitude} without attitude" if d.n_without_attitude else ", attitudes known"
        print(f"  {d.name}: {d.n_images} images over {d.duration_s:.1f} s, "
              f"{d.mean_keypoints:.0f} keypoints per image, {calib}")
    skipped = ws.skipped_frames()
    if skipped:
        print(f"{len(skipped)} frame{'s' if len(skipped) > 1 else ''} skipped at ingest (could not be described):")
        for f in skipped:
            print(f"  {f.source}/{f.camera} frame {f.frame} ({f.path}): {f.reason}")
    return 0
