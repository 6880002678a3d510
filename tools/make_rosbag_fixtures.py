"""Write the ROS bag fixtures of ``tests/test_rosbag.py`` under ``tests/data/rosbag/``.

Run from the repository root: ``python tools/make_rosbag_fixtures.py``. It overwrites:

- ``intel.bag`` (ROS 1): the 20 scans of ``tests/data/intel_first20.log`` as
  ``sensor_msgs/LaserScan`` on ``/scan`` (frame ``laser``), posed by ``/tf``
  (``map -> odom``, a constant :data:`T_MAP_ODOM`, and ``odom -> base_link``) and
  ``/tf_static`` (``base_link -> laser``, :data:`T_BASE_LASER`), such that
  ``map -> laser`` is the CARMEN laser pose.
- ``intel_ros2/`` (ROS 2, sqlite3): the same scans, posed by ``nav_msgs/Odometry`` on
  ``/odom`` (``odom -> base_link``) and ``/tf_static`` (``base_link -> laser``), such that
  ``odom -> laser`` is the CARMEN laser pose.
- ``cloud_ros2/`` (ROS 2, mcap): :data:`CLOUD_POINTS` points of 3DTK scans 1 and 2
  (``tests/data/3dtk``) as ``sensor_msgs/PointCloud2`` on ``/points`` (frame ``scanner``),
  posed by ``geometry_msgs/PoseStamped`` on ``/pose`` (frame ``map``, the 3DTK pose in
  octolgp's frame). Cloud 0: FLOAT32 little-endian, ``point_step`` 32 with an intensity
  field, plus 4 NaN points. Cloud 1: FLOAT64 big-endian, ``point_step`` 28 with a ``ring``
  field, organised as 2 rows, with 2 NaN points.

The message builders are reused by the tests to write small bags of their own.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from octolgp.io.carmen import CarmenReader, beam_angles
from octolgp.io.threedtk import ThreeDTKReader

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "rosbag"
ROS1 = get_typestore(Stores.ROS1_NOETIC)
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
# The Noetic store lacks tf2_msgs; its definition (md5 94810edda583a504dfda3829e70d7eec):
ROS1.register(
    get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
)
CLOUD_POINTS = 300
RANGE_MAX = 81.83  # the Intel log's no-return reading
NS = 1_000_000_000


def planar(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    """4x4 transform of a planar pose (plus a height)."""
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


T_MAP_ODOM = planar(1.5, -0.7, 0.3)
T_BASE_LASER = planar(0.12, -0.03, 0.05, z=0.25)


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return x, y, z, w


def header(ts: Any, stamp_ns: int, frame: str) -> Any:
    """A ``std_msgs/Header`` (ROS 1 headers have a ``seq``)."""
    stamp = ts.types["builtin_interfaces/msg/Time"](stamp_ns // NS, stamp_ns % NS)
    if ts is ROS1:
        return ts.types["std_msgs/msg/Header"](0, stamp, frame)
    return ts.types["std_msgs/msg/Header"](stamp, frame)


def pose_msg(ts: Any, T: np.ndarray) -> Any:
    """A ``geometry_msgs/Pose``."""
    point = ts.types["geometry_msgs/msg/Point"](*map(float, T[:3, 3]))
    q = ts.types["geometry_msgs/msg/Quaternion"](*quaternion(T[:3, :3]))
    return ts.types["geometry_msgs/msg/Pose"](point, q)


def tf_message(ts: Any, links: Iterable[tuple[str, str, int, np.ndarray]]) -> Any:
    """A ``tf2_msgs/TFMessage`` of ``(parent, child, stamp_ns, T_parent_child)`` links."""
    out = []
    for parent, child, stamp_ns, T in links:
        v = ts.types["geometry_msgs/msg/Vector3"](*map(float, T[:3, 3]))
        q = ts.types["geometry_msgs/msg/Quaternion"](*quaternion(T[:3, :3]))
        transform = ts.types["geometry_msgs/msg/Transform"](v, q)
        out.append(
            ts.types["geometry_msgs/msg/TransformStamped"](
                header(ts, stamp_ns, parent), child, transform
            )
        )
    return ts.types["tf2_msgs/msg/TFMessage"](out)


def odometry(ts: Any, stamp_ns: int, frame: str, child: str, T: np.ndarray) -> Any:
    """A ``nav_msgs/Odometry`` with pose ``T`` and zero twist and covariances."""
    cov = np.zeros(36)
    pose = ts.types["geometry_msgs/msg/PoseWithCovariance"](pose_msg(ts, T), cov)
    zero = ts.types["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    twist = ts.types["geometry_msgs/msg/TwistWithCovariance"](
        ts.types["geometry_msgs/msg/Twist"](zero, zero), cov
    )
    return ts.types["nav_msgs/msg/Odometry"](header(ts, stamp_ns, frame), child, pose, twist)


def pose_stamped(ts: Any, stamp_ns: int, frame: str, T: np.ndarray) -> Any:
    """A ``geometry_msgs/PoseStamped``."""
    return ts.types["geometry_msgs/msg/PoseStamped"](header(ts, stamp_ns, frame), pose_msg(ts, T))


def laser_scan(
    ts: Any,
    stamp_ns: int,
    frame: str,
    ranges: Sequence[float] | np.ndarray,
    *,
    angle_min: float = -math.pi / 2,
    angle_increment: float = math.pi / 180,
    angle_max: float | None = None,
    range_min: float = 0.0,
    range_max: float = RANGE_MAX,
) -> Any:
    """A ``sensor_msgs/LaserScan``; ``angle_max`` is the last beam's angle by default."""
    r = np.asarray(ranges, dtype=np.float32)
    if angle_max is None:
        angle_max = angle_min + (r.size - 1) * angle_increment
    return ts.types["sensor_msgs/msg/LaserScan"](
        header(ts, stamp_ns, frame),
        angle_min,
        angle_max,
        angle_increment,
        0.0,
        0.0,
        range_min,
        range_max,
        r,
        np.zeros(0, dtype=np.float32),
    )


def point_cloud(
    ts: Any,
    stamp_ns: int,
    frame: str,
    xyz: np.ndarray,
    *,
    kind: str = "f4",
    bigendian: bool = False,
    point_step: int | None = None,
    extra: Sequence[tuple[str, int, str]] = (),
    height: int = 1,
    fields: Sequence[str] = ("x", "y", "z"),
    data: np.ndarray | None = None,
) -> Any:
    """A ``sensor_msgs/PointCloud2`` of ``xyz`` (n, 3) as packed ``kind`` fields.

    ``extra`` adds ``(name, offset, numpy kind)`` fields after x, y, z (filled with the
    point index); ``data`` replaces the encoded bytes (to write malformed clouds).
    """
    size = np.dtype(kind).itemsize
    datatypes = {"f4": 7, "f8": 8, "u2": 4, "u4": 6}
    order = ">" if bigendian else "<"
    names = list(fields) + [e[0] for e in extra]
    offsets = [i * size for i in range(len(fields))] + [e[1] for e in extra]
    kinds = [kind] * len(fields) + [e[2] for e in extra]
    step = point_step or max(o + np.dtype(k).itemsize for o, k in zip(offsets, kinds, strict=True))
    dtype = np.dtype(
        {
            "names": names,
            "formats": [order + k for k in kinds],
            "offsets": offsets,
            "itemsize": step,
        }
    )
    n = xyz.shape[0]
    arr = np.zeros(n, dtype=dtype)
    for i, name in enumerate(fields):
        arr[name] = xyz[:, i]
    for name, _, _ in extra:
        arr[name] = np.arange(n)
    raw = arr.view(np.uint8).reshape(-1) if data is None else data
    field_type = ts.types["sensor_msgs/msg/PointField"]
    msg_fields = [
        field_type(name, off, datatypes[k], 1)
        for name, off, k in zip(names, offsets, kinds, strict=True)
    ]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header(ts, stamp_ns, frame),
        height,
        n // height,
        msg_fields,
        bigendian,
        step,
        step * (n // height),
        np.ascontiguousarray(raw, dtype=np.uint8),
        False,
    )


Message = tuple[str, str, int, Any]  # topic, msgtype, bag time (ns), message


def write_bag(path: Path, messages: Sequence[Message], *, ros1: bool, mcap: bool = False) -> None:
    """Write ``messages`` (in any order: bag time orders them) to a new ROS 1 or 2 bag."""
    ts = ROS1 if ros1 else ROS2
    writer: Any = (
        Writer1(path)
        if ros1
        else Writer2(
            path,
            version=9,
            storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3,
        )
    )
    with writer:
        connections: dict[str, Any] = {}
        for topic, msgtype, _, _ in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, bag_ns, msg in sorted(messages, key=lambda m: m[2]):
            raw = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
            writer.write(connections[topic], bag_ns, raw)


def intel_scans() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(stamp_ns, T_world_laser, ranges)`` of the Intel scans, ranges rounded to the log's cm."""
    out = []
    for scan in CarmenReader(ROOT / "tests" / "data" / "intel_first20.log"):
        d = scan.points - scan.origin
        ranges = np.round(np.hypot(d[:, 0], d[:, 1]), 2)
        first = np.arctan2(d[0, 1], d[0, 0]) - beam_angles(len(scan))[0]
        assert scan.stamp is not None
        pose = planar(scan.origin[0], scan.origin[1], float(first))
        out.append((round(scan.stamp * NS), pose, ranges))
    return out


def cloud_scans() -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(stamp_ns, T_world_scanner, world points)``: every k-th point of 3DTK scans 1, 2."""
    reader = ThreeDTKReader(ROOT / "tests" / "data" / "3dtk", first=1, last=2)
    out = []
    for i, (scan, T) in enumerate(zip(reader, reader.transforms, strict=True)):
        step = max(1, len(scan) // CLOUD_POINTS)
        out.append(((i + 1) * NS, T, scan.points[::step][:CLOUD_POINTS]))
    return out


def intel_messages(ros1: bool) -> list[Message]:
    """Messages of ``intel.bag`` (ROS 1: tf) or ``intel_ros2`` (ROS 2: odometry)."""
    ts = ROS1 if ros1 else ROS2
    scans = intel_scans()
    t0 = scans[0][0] - NS // 1000
    msgs: list[Message] = [
        (
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            t0,
            tf_message(ts, [("base_link", "laser", t0, T_BASE_LASER)]),
        )
    ]
    for stamp, T_laser, ranges in scans:
        scan = laser_scan(ts, stamp, "laser", ranges)
        msgs.append(("/scan", "sensor_msgs/msg/LaserScan", stamp + NS // 1000, scan))
        if ros1:
            T_odom_base = np.linalg.inv(T_MAP_ODOM) @ T_laser @ np.linalg.inv(T_BASE_LASER)
            links = [("map", "odom", stamp, T_MAP_ODOM), ("odom", "base_link", stamp, T_odom_base)]
            msgs.append(("/tf", "tf2_msgs/msg/TFMessage", stamp, tf_message(ts, links)))
        else:
            T_odom_base = T_laser @ np.linalg.inv(T_BASE_LASER)
            odom = odometry(ts, stamp, "odom", "base_link", T_odom_base)
            msgs.append(("/odom", "nav_msgs/msg/Odometry", stamp, odom))
    return msgs


def cloud_messages() -> list[Message]:
    """Messages of ``cloud_ros2``."""
    msgs: list[Message] = []
    nan = np.full((1, 3), np.nan)
    for i, (stamp, T, world) in enumerate(cloud_scans()):
        local = (world - T[:3, 3]) @ T[:3, :3]
        msgs.append(
            ("/pose", "geometry_msgs/msg/PoseStamped", stamp, pose_stamped(ROS2, stamp, "map", T))
        )
        if i == 0:
            xyz = np.concatenate([local[:100], nan, nan, local[100:200], nan, nan, local[200:]])
            cloud = point_cloud(
                ROS2, stamp, "scanner", xyz, point_step=32, extra=[("intensity", 16, "f4")]
            )
        else:
            xyz = np.concatenate([local, nan, nan])
            if xyz.shape[0] % 2:
                xyz = xyz[1:]  # keep 2 equal rows
            cloud = point_cloud(
                ROS2,
                stamp,
                "scanner",
                xyz,
                kind="f8",
                bigendian=True,
                extra=[("ring", 24, "u2")],
                height=2,
            )
        msgs.append(("/points", "sensor_msgs/msg/PointCloud2", stamp + NS // 1000, cloud))
    return msgs


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    for name in ("intel.bag", "intel_ros2", "cloud_ros2"):
        target = OUT / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    write_bag(OUT / "intel.bag", intel_messages(ros1=True), ros1=True)
    write_bag(OUT / "intel_ros2", intel_messages(ros1=False), ros1=False)
    write_bag(OUT / "cloud_ros2", cloud_messages(), ros1=False, mcap=True)
    total = sum(f.stat().st_size for f in OUT.rglob("*") if f.is_file())
    print(f"wrote {OUT} ({total} bytes)")


if __name__ == "__main__":
    main()
