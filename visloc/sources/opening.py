"""A drive from whatever the user points at: a vehicle's log, a CSV of geotagged images, or a KITTI raw root;
and a calibration fitted to the images it is for."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from visloc.errors import InputError
from visloc.sources.drives import Drive, default_data_root, open_csv, open_kitti
from visloc.sources.imagesize import header_size_px
from visloc.sources.logs import is_log, open_log


def open_source(path: Path | None, *, drive: str | None = None, camera: str | None = None,
                camera_flag: str = "--camera", **log_options) -> Drive:
    """A CSV file gives a generic sequence; a log (a ROS bag, an MCAP file or a rosbag2 folder) the frames of
    its image topic ``camera`` (None: its only one) with ``log_options`` (``visloc.sources.logs.open_log``);
    a folder is read as a KITTI raw root (None: the default data root, ``default_data_root()``), its camera
    ``camera`` (None: image_01)."""
    path = default_data_root() if path is None else Path(path)
    if is_log(path):
        return open_log(path, camera=camera, camera_flag=camera_flag, **log_options)
    given = sorted(k for k, v in log_options.items() if v is not None)
    if given:
        raise InputError(f"--{given[0].replace('_', '-')}: only for a log (a ROS bag, an MCAP file or a rosbag2 "
                         f"folder); {path} is not one")
    if path.suffix.lower() == ".csv":
        return fit_calibration(open_csv(path))
    return fit_calibration(open_kitti(path, drive, camera or "image_01"))


def fit_calibration(sequence: Drive) -> Drive:
    """``sequence`` with a calibration that fits its images, judged from the first image's header.

    Images of the calibration's size: unchanged. Images resized from it (the same aspect ratio, to a
    pixel): the intrinsics scaled to their size, and a note saying so (``Drive.notes``). Any other
    size: ``InputError`` naming the image, both sizes and the calibration."""
    if sequence.image_size_px is None or sequence.P_rect is None or not sequence.frames:
        return sequence
    first = sequence.frames[0].image_path
    size = header_size_px(first)
    if size is None or tuple(size) == tuple(sequence.image_size_px):
        return sequence
    (w, h), (w0, h0) = size, sequence.image_size_px
    if abs(h0 * w / w0 - h) > 1.0:
        raise InputError(f"{first}: image is {w}x{h} px but the calibration of {sequence.name} is for {w0}x{h0} px, "
                         "another aspect ratio: give the calibration of these images")
    sx, sy = w / w0, h / h0
    # pixel centres: x + 0.5 = sx (x0 + 0.5), as a resize maps them
    S = np.array([[sx, 0.0, (sx - 1.0) / 2.0], [0.0, sy, (sy - 1.0) / 2.0], [0.0, 0.0, 1.0]])
    note = (f"{sequence.name}: images are {w}x{h} px, the calibration is for {w0}x{h0} px: its intrinsics are "
            f"scaled by {sx:.4g} x {sy:.4g} to fit them")
    return replace(sequence, P_rect=S @ np.asarray(sequence.P_rect, float), image_size_px=(w, h),
                   notes=(*sequence.notes, note))
