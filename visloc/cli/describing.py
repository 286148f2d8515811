"""``visloc info SOURCE``: what visloc reads from a drive (a log, a KITTI root or a CSV), without a store."""

from __future__ import annotations

import argparse

from visloc.cli.choices import kitti_camera, log_options, refuse_camera_for_csv
from visloc.sources.logs import IMAGE_TYPES, is_log, log_topics
from visloc.sources.opening import open_source


def describe_drive(a: argparse.Namespace) -> int:
    """``visloc info SOURCE``: what visloc reads from a drive (a log's topics first, then each of its cameras
    unless ``--camera`` names one)."""
    cameras = [a.camera]
    if is_log(a.source):
        topics = log_topics(a.source)
        print(f"{a.source}: topics")
        for topic, (msgtype, count) in sorted(topics.items()):
            print(f"  {topic}: {msgtype.replace('/msg/', '/')}, {count} messages")
        if a.camera is None:
            cameras = sorted(t for t, (m, _) in topics.items() if m in IMAGE_TYPES) or [None]
    refuse_camera_for_csv(a.source, "--camera", a.camera)
    for camera in cameras:
        seq = open_source(a.source, drive=a.drive, camera=kitti_camera(a.source, a.drive, camera), **log_options(a))
        _describe(seq)
    return 0


def _describe(seq) -> None:
    for note in seq.notes:
        print(note)
    times = seq.timestamps_s
    accuracies = [f.position_accuracy_m for f in seq.frames if f.position_accuracy_m is not None]
    with_attitude = sum(f.yaw_rad is not None for f in seq.frames)
    print(f"{seq.name}: {len(seq)} frames over {times[-1] - times[0]:.1f} s; "
          + (f"images {seq.image_size_px[0]}x{seq.image_size_px[1]} px, " if seq.image_size_px else "")
          + ("calibration known" if seq.P_rect is not None else "no calibration")
          + (", its pose on the vehicle known" if seq.T_camera_imu is not None else ", its pose on the vehicle unknown")
          + f"; {with_attitude} of {len(seq)} frames with attitude; "
          + (f"stated geotag accuracy {min(accuracies):.3g}-{max(accuracies):.3g} m" if accuracies
             else "no stated geotag accuracy")
          + (f" (none for {len(seq) - len(accuracies)} of them: no position fix, each taken as an error of its own)"
             if accuracies and len(accuracies) < len(seq) else ""))
