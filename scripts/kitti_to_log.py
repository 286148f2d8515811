"""Write a KITTI raw drive as a vehicle's log: a rosbag2 folder (sqlite3 or MCAP storage) or a ROS 1 bag.

    .venv/bin/python scripts/kitti_to_log.py ROOT --drive 2011_09_26_drive_0005 --camera image_00 OUT \\
        --format mcap [--frames N]

The log is written with the ``rosbags`` writer, as a robot's recorder would write it:

* ``/kitti/<camera>/image_raw`` (``sensor_msgs/Image``, mono8 or bgr8, the PNG's pixels) and
  ``/kitti/<camera>/camera_info`` (``CameraInfo``: ``P`` = KITTI's ``P_rect_0X``, ``K`` its 3x3 part,
  no distortion, the images' size), each stamped with the camera's own time from its timestamps.txt,
  to the nanosecond;
* ``/gps/fix`` (``NavSatFix``): the geotag visloc's KITTI reader gives frame i of each camera (KITTI's synced
  OXTS record i, moved on to that camera's time of frame i), stated at that time, with the record's stated
  accuracy (``pos_accuracy``) as the east, north and up variances;
* ``/imu/data`` (``Imu``): the record's roll, pitch and yaw as the orientation of ``base_link`` (the
  OXTS frame: x forward, y left, z up, relative to east-north-up), stamped as the fixes;
* ``/tf_static``: ``base_link`` to each camera's optical frame, from KITTI's calibration.

The values are what visloc's own KITTI reader makes of the drive, so a drive read from the log is the
drive read from the folder. ``--format``: ``sqlite3`` and ``mcap`` write a rosbag2 folder OUT (its
``.mcap`` file alone is a log too), ``bag`` a ROS 1 bag OUT; an OUT that exists is kept as it is. Bad input:
one line and exit status 2.
"""

from __future__ import annotations

import argparse
import datetime as dt
import math
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from visloc.errors import InputError  # noqa: E402
from visloc.geometry.projective import quaternion_from_rotation, rotation_from_rpy  # noqa: E402
from visloc.sources.calibration import inverse_pose, read_text  # noqa: E402
from visloc.sources.drives import KITTI_CAMERAS, open_kitti, resolve_drive  # noqa: E402

FORMATS = ("sqlite3", "mcap", "bag")
FIX_TOPIC, IMU_TOPIC = "/gps/fix", "/imu/data"
VEHICLE_FRAME = "base_link"


def camera_topics(camera: str) -> tuple[str, str, str]:
    """(image topic, CameraInfo topic, optical frame id) of a KITTI camera."""
    return f"/kitti/{camera}/image_raw", f"/kitti/{camera}/camera_info", f"{camera}_optical_frame"


def stamps_ns(path: Path) -> list[int]:
    """A KITTI timestamps.txt as integer nanoseconds since the Unix epoch (UTC), digit for digit."""
    out = []
    for line in read_text(path).split("\n"):
        if line.strip():
            day, _, frac = line.strip().partition(".")
            seconds = int(dt.datetime.strptime(day, "%Y-%m-%d %H:%M:%S").replace(tzinfo=dt.timezone.utc).timestamp())
            out.append(seconds * 1_000_000_000 + int(frac.ljust(9, "0")[:9] or 0))
    return out


class Messages:
    """Builds messages of one typestore (ROS 2 for rosbag2, ROS 1 for a bag) and serializes them."""

    def __init__(self, ros1: bool):
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # ROS 1's typestore lacks it; tf2_msgs is in ROS 1 too
            from rosbags.typesys import get_types_from_msg
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        self.t = self.store.types

    def serialize(self, message) -> bytes:
        if self.ros1:
            return self.store.serialize_ros1(message, message.__msgtype__)
        return self.store.serialize_cdr(message, message.__msgtype__)

    def header(self, stamp_ns: int, frame_id: str):
        time = self.t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        fields = {"stamp": time, "frame_id": frame_id}
        if self.ros1:
            fields["seq"] = 0
        return self.t["std_msgs/msg/Header"](**fields)

    def image(self, stamp_ns: int, frame_id: str, pixels: np.ndarray):
        channels = 1 if pixels.ndim == 2 else pixels.shape[2]
        return self.t["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, frame_id), height=pixels.shape[0], width=pixels.shape[1],
            encoding="mono8" if channels == 1 else "bgr8", is_bigendian=0, step=pixels.shape[1] * channels,
            data=np.ascontiguousarray(pixels).reshape(-1))

    def camera_info(self, stamp_ns: int, frame_id: str, P: np.ndarray, size: tuple[int, int]):
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, frame_id), height=size[1], width=size[0], distortion_model="plumb_bob",
            **{names[0]: np.zeros(5), names[1]: P[:, :3].reshape(-1).copy(), names[2]: np.eye(3).reshape(-1),
               names[3]: P.reshape(-1).copy()}, binning_x=0, binning_y=0, roi=roi)

    def fix(self, stamp_ns: int, frame, status: int = 0) -> object:
        """The frame's geotag; ``status`` -1 says NO_FIX."""
        status = self.t["sensor_msgs/msg/NavSatStatus"](status=status, service=1)
        sigma = frame.position_accuracy_m
        covariance = np.zeros(9) if sigma is None else np.diag([sigma * sigma] * 3).reshape(-1)
        return self.t["sensor_msgs/msg/NavSatFix"](
            header=self.header(stamp_ns, "gps"), status=status, latitude=frame.lat_deg, longitude=frame.lon_deg,
            altitude=math.nan if frame.alt_m is None else frame.alt_m,  # NaN: no altitude, as NavSatFix has it
            position_covariance=covariance, position_covariance_type=0 if sigma is None else 2)

    def imu(self, stamp_ns: int, frame) -> object:
        x, y, z, w = quaternion_from_rotation(rotation_from_rpy(frame.roll_rad, frame.pitch_rad, frame.yaw_rad))
        vector = self.t["geometry_msgs/msg/Vector3"]
        return self.t["sensor_msgs/msg/Imu"](
            header=self.header(stamp_ns, VEHICLE_FRAME), orientation=self.t["geometry_msgs/msg/Quaternion"](
                x=x, y=y, z=z, w=w), orientation_covariance=np.zeros(9), angular_velocity=vector(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=np.full(9, -1.0) * np.r_[1, np.zeros(8)],
            linear_acceleration=vector(x=0.0, y=0.0, z=0.0),
            linear_acceleration_covariance=np.full(9, -1.0) * np.r_[1, np.zeros(8)])

    def static_transforms(self, stamp_ns: int, poses: dict[str, np.ndarray]) -> object:
        out = []
        for child, T in poses.items():
            x, y, z, w = quaternion_from_rotation(T[:3, :3])
            transform = self.t["geometry_msgs/msg/Transform"](
                translation=self.t["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
            out.append(self.t["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp_ns, VEHICLE_FRAME), child_frame_id=child, transform=transform))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=out)


class LogWriter:
    """A log being written: ``write(topic, msgtype, log time ns, message)``, connections made as topics come."""

    def __init__(self, out: Path, fmt: str):
        if fmt not in FORMATS:
            raise InputError(f"--format {fmt!r}: must be one of {', '.join(FORMATS)}")
        self.messages = Messages(ros1=fmt == "bag")
        if fmt == "bag":
            from rosbags.rosbag1 import Writer
            self.writer = Writer(out)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            self.writer = Writer(out, version=9,
                                 storage_plugin=StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3)
        self.connections: dict[str, object] = {}

    def __enter__(self) -> "LogWriter":
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    def write(self, topic: str, msgtype: str, t_ns: int, message) -> None:
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.messages.store)
        self.writer.write(self.connections[topic], t_ns, self.messages.serialize(message))


def write_log(root: Path, drive: str, cameras: list[str], out: Path, fmt: str, frames: int | None = None) -> Path:
    """Write the log (see the module docstring); returns ``out``."""
    if out.exists():
        raise InputError(f"{out}: already exists; give a new name")
    folder = resolve_drive(root, drive)
    drives = [open_kitti(root, drive, camera) for camera in cameras]
    # the camera's own times, else the OXTS records' (as visloc's KITTI reader takes them)
    times = {camera: stamps_ns(next(p for p in (folder / camera / "timestamps.txt", folder / "oxts" / "timestamps.txt")
                                    if p.is_file() or p.parent.name == "oxts")) for camera in cameras}
    n = min(len(d) for d in drives) if frames is None else min(frames, *(len(d) for d in drives))
    records = []  # (log time ns, topic, message type, message)
    with LogWriter(out, fmt) as log:
        messages = log.messages
        first = min(times[c][0] for c in cameras)
        poses = {camera_topics(d.camera)[2]: inverse_pose(d.T_camera_imu) for d in drives}
        log.write("/tf_static", "tf2_msgs/msg/TFMessage", first, messages.static_transforms(first, poses))
        for i in range(n):
            for d in drives:
                image_topic, info_topic, optical = camera_topics(d.camera)
                t = times[d.camera][i]
                pixels = cv2.imread(str(d.frames[i].image_path), cv2.IMREAD_UNCHANGED)
                records.append((t, image_topic, "sensor_msgs/msg/Image", messages.image(t, optical, pixels)))
                records.append((t, info_topic, "sensor_msgs/msg/CameraInfo",
                                messages.camera_info(t, optical, d.P_rect, d.image_size_px)))
            fixes = {times[d.camera][i]: d.frames[i] for d in drives}  # each camera's geotag at its own time
            for t, frame in sorted(fixes.items()):
                records.append((t, FIX_TOPIC, "sensor_msgs/msg/NavSatFix", messages.fix(t, frame)))
                records.append((t, IMU_TOPIC, "sensor_msgs/msg/Imu", messages.imu(t, frame)))
            for t, topic, msgtype, message in sorted(records, key=lambda r: r[0]):
                log.write(topic, msgtype, t, message)
            records.clear()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Write a KITTI raw drive as a rosbag2 folder (sqlite3 or MCAP) or a "
                                            "ROS 1 bag.")
    p.add_argument("root", type=Path, help="KITTI raw root")
    p.add_argument("--drive", required=True, help="e.g. 2011_09_26_drive_0005")
    p.add_argument("--camera", action="append", choices=KITTI_CAMERAS, help="camera to write (repeatable; "
                                                                             "default image_00)")
    p.add_argument("out", type=Path, help="the log to write (a folder for sqlite3 and mcap, a .bag file for bag)")
    p.add_argument("--format", choices=FORMATS, default="mcap", help="default %(default)s")
    p.add_argument("--frames", type=int, default=None, help="only the first N frames")
    a = p.parse_args(argv)
    if a.out.exists():  # the walk-through run a second time: the log it wrote is kept
        print(f"{a.out} exists: kept (remove it to write it again)")
        return 0
    try:
        write_log(a.root, a.drive, a.camera or ["image_00"], a.out, a.format, a.frames)
    except BaseException as exc:  # a log written part way is removed: it is not a log of the drive
        if a.out.is_dir():
            shutil.rmtree(a.out)
        a.out.unlink(missing_ok=True)
        if not isinstance(exc, InputError):
            raise
        print(f"kitti_to_log: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
