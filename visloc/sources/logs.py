"""A vehicle's own log as a drive: a rosbag2 folder (sqlite3 or MCAP storage), an ``.mcap`` file or a ROS 1
``.bag``, read with the ``rosbags`` library (no ROS installation).

What visloc takes from it (topics chosen automatically when the log has one candidate, by flags otherwise):

* images: a ``sensor_msgs/Image`` or ``CompressedImage`` topic (``--camera``), each stamped by its
  header (the log's receive time when the header has none);
* geotags: a ``sensor_msgs/NavSatFix`` topic (``--fix-topic``); a fix whose status is NO_FIX is not used;
  its position covariance (east and north variances) gives the geotag's stated accuracy, as OXTS
  ``pos_accuracy`` does for KITTI. Each image takes the fix at its time, interpolated between the two
  around it when they are at most ``--max-fix-gap-s`` apart; an image further from any fix is left out;
* the camera: the ``CameraInfo`` beside the image topic (same namespace, ``--camera-info-topic``
  otherwise). Its size must be the images'. With no distortion the images are taken as rectified and
  their intrinsics are ``P``'s; with distortion, ``K`` and ``D`` (undistorted at ingest, as a CSV
  drive's). Its pose on the vehicle comes from ``/tf_static``: the transform from the vehicle frame (the
  IMU's frame when the tree holds it, else ``base_link``) to the camera's frame (its optical frame:
  x right, y down, z forward);
* attitude: a ``sensor_msgs/Imu`` orientation (``--imu-topic``), relative to east-north-up as REP 145
  has it, interpolated at each image's time the same way.

The images are written once, unchanged (a compressed image's bytes as they are, a raw one as PNG), to a
cache folder keyed by the log's path, size and modification time (``$VISLOC_CACHE``, else
``~/.cache/visloc``): the store and the dashboard read them there, as they read a KITTI drive's files.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from visloc.errors import InputError
from visloc.geo import yaw_enu_to_heading_deg
from visloc.sources.drives import Drive, Frame
from visloc.sources.imagesize import header_size_px
from visloc.sources.log_cache import cache_folder, cached_images, image_file, record_images
from visloc.sources.log_frames import (NO_FIX, Fixes, attitude_at, chain, horizontal_sigma_m, pair_fix,
                                       transform_matrix)

LOG_SUFFIXES = (".mcap", ".bag")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
FIX_TYPE = "sensor_msgs/msg/NavSatFix"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
IMU_TYPE = "sensor_msgs/msg/Imu"
TF_TYPE = "tf2_msgs/msg/TFMessage"
DEFAULT_MAX_FIX_GAP_S = 1.0  # a 1 Hz receiver's fixes are 1 s apart (visloc.params.options: --max-fix-gap-s)


def is_log(path: Path | str | None) -> bool:
    """A ROS 1 bag, an MCAP file, or a rosbag2 folder (one holding ``metadata.yaml``)."""
    if path is None:
        return False
    path = Path(path)
    return path.suffix.lower() in LOG_SUFFIXES or (path.is_dir() and (path / "metadata.yaml").is_file())


@contextmanager
def _reader(path: Path) -> Iterator[object]:
    """The log open for reading; ``InputError`` naming it when it cannot be read (missing, truncated, not a
    log)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise InputError(f"{path}: log not found")
    reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own error types, and struct or OS errors on a damaged file
        raise InputError(f"{path}: cannot read the log ({_first_line(exc)})") from None
    try:
        yield reader
    finally:
        reader.close()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:160]


def _messages(reader, path: Path, topic: str) -> Iterator[tuple[int, object]]:
    """(log time in ns, the message decoded) of every message of ``topic``; a log that breaks off while it is
    read is an ``InputError`` naming it."""
    connections = [c for c in reader.connections if c.topic == topic]
    try:
        for connection, log_ns, raw in reader.messages(connections=connections):
            yield log_ns, reader.deserialize(raw, connection.msgtype)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: cannot read {topic} ({_first_line(exc)}): is the log truncated?") from None


def _topics(reader) -> dict[str, str]:
    return {c.topic: c.msgtype for c in reader.connections}


def _listing(topics: dict[str, str]) -> str:
    return ", ".join(f"{t} ({m.replace('/msg/', '/')})" for t, m in sorted(topics.items())) or "none"


def _choose(path: Path, topics: dict[str, str], types: tuple[str, ...], asked: str | None, flag: str,
            what: str, *, required: bool = True) -> str | None:
    """The topic of one of ``types``: ``asked`` (with or without its leading /), else the only one."""
    candidates = sorted(t for t, m in topics.items() if m in types)
    kind = " or ".join(m.replace("/msg/", "/") for m in types)
    if asked is not None:
        by_name = {n: t for t, n in camera_names(candidates).items()} if types == IMAGE_TYPES else {}
        name = by_name.get(asked, "/" + asked.lstrip("/"))  # a topic, or the camera name visloc gave it
        if name not in candidates:
            raise InputError(f"{flag} {asked}: {path} has no {kind} topic of that name (its {what} topics: "
                             f"{', '.join(candidates) or 'none'})")
        return name
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        if required:
            raise InputError(f"{path}: no {what}: the log has no {kind} topic (its topics: {_listing(topics)})")
        return None
    raise InputError(f"{path}: holds {len(candidates)} {what} topics, choose one with {flag} "
                     f"({', '.join(candidates)})")


IMAGE_LEAVES = ("image_raw", "image_rect", "image_color", "image_mono", "image_rect_color", "image_rect_mono",
                "image", "compressed")  # what ROS names the last part of an image topic


def camera_names(image_topics: list[str]) -> dict[str, str]:
    """The name the store gives each image topic's camera: the part of the topic that names the camera
    (``/kitti/image_01/image_raw``: ``image_01``, ``/cam0/image_raw``: ``cam0``) when no other image topic of
    the log has the same; else the whole topic, its / as dots (a drive's name is source/camera, and ROS names
    hold no dots)."""
    def short(topic: str) -> str:
        parts = topic.strip("/").split("/")
        while len(parts) > 1 and parts[-1] in IMAGE_LEAVES:
            parts.pop()
        return parts[-1]

    shorts = [short(t) for t in image_topics]
    return {t: s if shorts.count(s) == 1 else t.strip("/").replace("/", ".") for t, s in zip(image_topics, shorts)}


def _stamp_ns(message, log_ns: int) -> int:
    stamp = message.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns > 0 else int(log_ns)


def _field(message, name: str):
    """A field ROS 2 spells in lower case and ROS 1 in upper case (``CameraInfo``'s k, d, r, p)."""
    return getattr(message, name) if hasattr(message, name) else getattr(message, name.upper())


def _read_fixes(reader, path: Path, topic: str) -> tuple[Fixes, int]:
    """The topic's valid fixes, and how many it holds in all."""
    rows = []
    n = 0
    for log_ns, m in _messages(reader, path, topic):
        n += 1
        values = (m.latitude, m.longitude, m.altitude)
        if int(m.status.status) == NO_FIX or not all(math.isfinite(v) for v in values[:2]):
            continue
        if not (-90 <= m.latitude <= 90 and -180 <= m.longitude <= 180):
            raise InputError(f"{path}: {topic}: latitude/longitude out of range ({m.latitude}, {m.longitude})")
        sigma = horizontal_sigma_m(np.asarray(m.position_covariance, float), int(m.position_covariance_type))
        rows.append((_stamp_ns(m, log_ns), float(m.latitude), float(m.longitude), float(m.altitude), sigma))
    if not rows:
        raise InputError(f"{path}: {topic}: none of its {n} fixes has a position (each has status NO_FIX)"
                         if n else f"{path}: {topic}: holds no fixes")
    rows.sort(key=lambda r: r[0])
    stamps = np.array([r[0] for r in rows], np.int64)
    keep = np.r_[True, np.diff(stamps) > 0]  # a fix repeated at the same time: the first
    table = np.array([r[1:] for r in rows], float)[keep]
    return Fixes(stamps[keep], table[:, 0], table[:, 1], table[:, 2], table[:, 3]), n


def _read_orientations(reader, path: Path, topic: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(stamps ns, quaternions (N, 4) x y z w, frame id) of an ``Imu`` topic's orientations (those it states:
    an orientation covariance starting with -1 means none)."""
    stamps, quaternions, frame = [], [], ""
    for log_ns, m in _messages(reader, path, topic):
        q = m.orientation
        if float(m.orientation_covariance[0]) == -1.0 or not (q.x or q.y or q.z or q.w):
            continue
        stamps.append(_stamp_ns(m, log_ns))
        quaternions.append((q.x, q.y, q.z, q.w))
        frame = frame or m.header.frame_id
    order = np.argsort(np.array(stamps, np.int64), kind="stable")
    return np.array(stamps, np.int64)[order], np.array(quaternions, float).reshape(-1, 4)[order], frame


VEHICLE_FRAME = "base_link"  # REP 105's name of the vehicle's frame


def _tf_orientations(reader, path: Path, topics: dict[str, str]) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(stamps ns, quaternions (N, 4), child frame, parent frame) of the transform tree's moving transforms to
    the vehicle frame (``/tf``: e.g. map to base_link), the attitude when the log has no IMU orientation."""
    stamps, quaternions, parent = [], [], ""
    for topic in sorted(t for t, m in topics.items() if m == TF_TYPE and not t.endswith("tf_static")):
        for log_ns, m in _messages(reader, path, topic):
            for ts in m.transforms:
                if ts.child_frame_id.lstrip("/") == VEHICLE_FRAME:
                    r = ts.transform.rotation
                    stamps.append(_stamp_ns(ts, log_ns))
                    quaternions.append((r.x, r.y, r.z, r.w))
                    parent = parent or ts.header.frame_id.lstrip("/")
    order = np.argsort(np.array(stamps, np.int64), kind="stable")
    return (np.array(stamps, np.int64)[order], np.array(quaternions, float).reshape(-1, 4)[order],
            VEHICLE_FRAME if stamps else "", parent)


def _static_transforms(reader, path: Path, topics: dict[str, str]) -> dict[tuple[str, str], np.ndarray]:
    out: dict[tuple[str, str], np.ndarray] = {}
    for topic in sorted(t for t, m in topics.items() if m == TF_TYPE and t.endswith("tf_static")):
        for _, m in _messages(reader, path, topic):
            for ts in m.transforms:
                t, r = ts.transform.translation, ts.transform.rotation
                out[(ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/"))] = transform_matrix(
                    (t.x, t.y, t.z), (r.x, r.y, r.z, r.w))
    return out


def _camera_info_topic(path: Path, topics: dict[str, str], image_topic: str, asked: str | None) -> str | None:
    """``asked``; else the ``CameraInfo`` beside the image topic (same namespace), else the only one."""
    infos = sorted(t for t, m in topics.items() if m == INFO_TYPE)
    if asked is not None:
        return _choose(path, topics, (INFO_TYPE,), asked, "--camera-info-topic", "camera calibration")
    namespace = image_topic.rsplit("/", 1)[0]
    beside = [t for t in infos if t.rsplit("/", 1)[0] == namespace]
    if len(beside) == 1:
        return beside[0]
    return infos[0] if len(infos) == 1 else None


def _images(reader, path: Path, topic: str, msgtype: str) -> list[tuple[int, Path]]:
    """(stamp ns, image file) of every message of the image topic, in the log's order, the files written to the
    cache once (an index records them, so that a later command reads no image message)."""
    folder = cache_folder(path, topic)
    done = cached_images(folder)
    if done is not None:
        return done
    out = [(_stamp_ns(m, log_ns), image_file(folder, n, m, msgtype, f"{path}: {topic} message {n}"))
           for n, (log_ns, m) in enumerate(_messages(reader, path, topic))]
    if not out:
        raise InputError(f"{path}: {topic}: holds no images")
    record_images(folder, out)
    return out


def _calibration(reader, path: Path, info_topic: str, image_size: tuple[int, int]
                 ) -> tuple[np.ndarray, np.ndarray | None, str]:
    """(P_rect 3x4, distortion or None, camera frame id) from the first ``CameraInfo`` of the topic."""
    info = next((m for _, m in _messages(reader, path, info_topic)), None)
    if info is None:
        raise InputError(f"{path}: {info_topic}: holds no CameraInfo")
    size = (int(info.width), int(info.height))
    if size != tuple(image_size):
        raise InputError(f"{path}: {info_topic}: calibration is for {size[0]}x{size[1]} px but the images are "
                         f"{image_size[0]}x{image_size[1]} px: give the CameraInfo of these images")
    P = np.asarray(_field(info, "p"), float).reshape(3, 4)
    K = np.asarray(_field(info, "k"), float).reshape(3, 3)
    d = np.asarray(_field(info, "d"), float).reshape(-1)
    R = np.asarray(_field(info, "r"), float).reshape(3, 3)
    if not np.all(np.isfinite(P)) or abs(P[0, 0]) < 1e-9 or abs(P[1, 1]) < 1e-9:
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0:
            raise InputError(f"{path}: {info_topic}: neither P nor K is a camera's projection")
        P = np.c_[K, np.zeros(3)]
    if d.size and np.any(d != 0):
        if d.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
            raise InputError(f"{path}: {info_topic}: distortion of {d.size} coefficients (OpenCV takes 4, 5, 8, "
                             "12 or 14)")
        if np.any(R.ravel()) and not np.allclose(R, np.eye(3), atol=1e-9):
            raise InputError(f"{path}: {info_topic}: distorted images with a rectification rotation R: record the "
                             "rectified images (image_rect) and their CameraInfo")
        return np.c_[K, np.zeros(3)], d, info.header.frame_id.lstrip("/")
    return P, None, info.header.frame_id.lstrip("/")


@dataclass(frozen=True)
class LogCamera:
    """What a log says of its camera: its calibration and its pose on the vehicle (None: unknown)."""

    P_rect: np.ndarray | None  # (3, 4), pixels
    image_size_px: tuple[int, int] | None
    distortion: np.ndarray | None
    T_camera_imu: np.ndarray | None  # (4, 4): X_camera = T_camera_imu @ X_vehicle, metres
    notes: tuple[str, ...] = ()


def _camera(reader, path: Path, topics: dict[str, str], image_topic: str, info_topic: str | None,
            image_size: tuple[int, int] | None, imu_frame: str) -> LogCamera:
    if info_topic is None:
        return LogCamera(None, None, None, None,
                         (f"{path.name}: no CameraInfo for {image_topic}: the refined mode is not available",))
    P, distortion, camera_frame = _calibration(reader, path, info_topic, image_size)
    transforms = _static_transforms(reader, path, topics)
    imu_frame = imu_frame.lstrip("/")
    vehicle = next((f for f in (imu_frame, VEHICLE_FRAME) if f and chain(transforms, f, camera_frame) is not None),
                   None)
    if vehicle is None:
        return LogCamera(P, image_size, distortion, None, (
            f"{path.name}: no static transform from the vehicle frame (the IMU's, or base_link) to the camera's "
            f"frame {camera_frame!r}: the camera's pose on the vehicle is unknown, so the refined mode is not "
            "available",))
    T_camera_imu = np.linalg.inv(chain(transforms, vehicle, camera_frame))
    T_camera_imu[3] = (0.0, 0.0, 0.0, 1.0)
    notes = ((f"{path.name}: the IMU's frame {imu_frame!r} is not in the transform tree: its orientation is taken "
              f"as {vehicle}'s",) if imu_frame and vehicle != imu_frame else ())
    return LogCamera(P, image_size, distortion, T_camera_imu, notes)


def read_log_camera(path: Path | str, *, camera: str | None = None, camera_info_topic: str | None = None,
                    imu_topic: str | None = None) -> LogCamera:
    """The camera of a log's image topic ``camera`` (None: its only one), read without its geotags: what
    ``open_log`` takes from the log's ``CameraInfo`` and transform tree."""
    path = Path(path)
    with _reader(path) as reader:
        topics = _topics(reader)
        image_topic = _choose(path, topics, IMAGE_TYPES, camera, "--camera", "image")
        imu = _choose(path, topics, (IMU_TYPE,), imu_topic, "--imu-topic", "orientation", required=False)
        first = next((m for _, m in _messages(reader, path, image_topic)), None)
        if first is None:
            raise InputError(f"{path}: {image_topic}: holds no images")
        if hasattr(first, "format"):  # a CompressedImage: its size from the decoded image
            decoded = cv2.imdecode(np.asarray(first.data, np.uint8), cv2.IMREAD_UNCHANGED)
            size = None if decoded is None else (decoded.shape[1], decoded.shape[0])
        else:
            size = (int(first.width), int(first.height))
        return _camera(reader, path, topics, image_topic,
                       _camera_info_topic(path, topics, image_topic, camera_info_topic), size,
                       _read_orientations(reader, path, imu)[2] if imu else "")


def open_log(path: Path | str, *, camera: str | None = None, camera_flag: str = "--camera", fix_topic: str | None = None,
             camera_info_topic: str | None = None, imu_topic: str | None = None,
             max_fix_gap_s: float | None = DEFAULT_MAX_FIX_GAP_S) -> Drive:
    """The drive a log holds (see the module docstring): one image topic's frames with their geotags, the
    camera's calibration when the log has it, and attitudes when it has orientations. ``InputError``, one line
    naming the log and what is missing (with the topics it has), for a log that cannot be a drive."""
    path = Path(path)
    max_fix_gap_s = DEFAULT_MAX_FIX_GAP_S if max_fix_gap_s is None else max_fix_gap_s
    if not (isinstance(max_fix_gap_s, (int, float)) and math.isfinite(max_fix_gap_s) and max_fix_gap_s >= 0):
        raise InputError(f"--max-fix-gap-s {max_fix_gap_s!r}: must be a number of seconds >= 0")
    max_gap_ns = int(round(max_fix_gap_s * 1e9))
    notes: list[str] = []
    with _reader(path) as reader:
        topics = _topics(reader)
        image_topic = _choose(path, topics, IMAGE_TYPES, camera, camera_flag, "image")
        fix = _choose(path, topics, (FIX_TYPE,), fix_topic, "--fix-topic", "geotags")
        imu = _choose(path, topics, (IMU_TYPE,), imu_topic, "--imu-topic", "orientation", required=False)
        info_topic = _camera_info_topic(path, topics, image_topic, camera_info_topic)
        fixes, _ = _read_fixes(reader, path, fix)
        images = _images(reader, path, image_topic, topics[image_topic])
        orientations = _read_orientations(reader, path, imu) if imu else (np.zeros(0, np.int64), np.zeros((0, 4)), "")
        if not len(orientations[0]):  # no IMU orientation: the transform tree's, where it moves the vehicle
            *orientations, parent = _tf_orientations(reader, path, topics)
            if len(orientations[0]):
                notes.append(f"{path.name}: attitude from the transform {parent} -> {VEHICLE_FRAME} of /tf, taken "
                             "as relative to east-north-up")
        size = header_size_px(images[0][1]) if info_topic is not None else None
        if info_topic is not None and size is None:
            raise InputError(f"{images[0][1]}: cannot read the image's size")
        camera_model = _camera(reader, path, topics, image_topic, info_topic, size, orientations[2])
    notes += camera_model.notes
    frames, largest_gap_s, left_out = [], 0.0, 0
    for n, (t_ns, image_path) in enumerate(images):
        geotag = pair_fix(fixes, t_ns, max_gap_ns)
        if geotag is None:
            left_out += 1
            continue
        largest_gap_s = max(largest_gap_s, geotag.gap_s)
        attitude = attitude_at(orientations[0], orientations[1], t_ns, max_gap_ns) if len(orientations[0]) else None
        roll, pitch, yaw = attitude if attitude is not None else (None, None, None)
        frames.append(Frame(frame=n, image_path=image_path, timestamp_s=(t_ns // 1_000_000_000) + (
            t_ns % 1_000_000_000) / 1e9, lat_deg=geotag.lat_deg, lon_deg=geotag.lon_deg, alt_m=geotag.alt_m,
            heading_deg=None if yaw is None else yaw_enu_to_heading_deg(yaw), roll_rad=roll, pitch_rad=pitch,
            yaw_rad=yaw, position_accuracy_m=geotag.sigma_m))
    if not frames:
        raise InputError(f"{path}: none of the {len(images)} images of {image_topic} lies within "
                         f"{max_fix_gap_s:g} s of fixes of {fix} (--max-fix-gap-s): no image has a geotag")
    if left_out:
        notes.append(f"{path.name}: {left_out} of {len(images)} images of {image_topic} left out: no fixes of {fix} "
                     f"within {max_fix_gap_s:g} s around them (--max-fix-gap-s)")
    gap = (f"largest gap between the two fixes an image's geotag was interpolated from: {largest_gap_s:.3f} s"
           if largest_gap_s else "every image has a fix at its own time")
    notes.append(f"{path.name}: {len(frames)} images of {image_topic} with geotags from {fix}; {gap}")
    name = camera_names(sorted(t for t, m in topics.items() if m in IMAGE_TYPES))[image_topic]
    return Drive(source=path.stem if path.is_file() else path.name, camera=name,
                 frames=tuple(frames), P_rect=camera_model.P_rect, image_size_px=camera_model.image_size_px,
                 T_camera_imu=camera_model.T_camera_imu, distortion=camera_model.distortion, notes=tuple(notes))


def log_topics(path: Path | str) -> dict[str, tuple[str, int]]:
    """{topic: (message type, message count)} of a log."""
    path = Path(path)
    with _reader(path) as reader:
        counts: dict[str, tuple[str, int]] = {}
        for c in reader.connections:
            previous = counts.get(c.topic, (c.msgtype, 0))[1]
            counts[c.topic] = (c.msgtype, previous + int(c.msgcount))
        return counts
