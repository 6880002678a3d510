"""Streaming reader for ROS 1 bags and ROS 2 bags (sqlite3 or mcap), via :mod:`rosbags`.

One scan topic is read, in bag (receive-time) order, and posed in a fixed frame:

- ``sensor_msgs/msg/LaserScan`` becomes a 2D :class:`~octolgp.scan.Scan`. Beam ``i`` points at
  ``angle_min + i * angle_increment`` in the scan's ``header.frame_id``; when ``angle_max``
  agrees with that to float32 round-off (``|(angle_max - angle_min) / (n - 1) -
  angle_increment| <= 1e-6 |angle_increment|``), the angles are interpolated from
  ``angle_min`` to ``angle_max`` in float64 instead, so the float32 increment does not
  accumulate over the fan. A reading ``r`` with ``range_min <= r < range_max`` is a hit; ``r >=
  range_max`` or ``+inf`` is a no-return, kept as a beam of length ``range_max`` with
  :attr:`Scan.max_range` set :data:`NO_RETURN_MARGIN` below it (free space to the maximum range,
  as for CARMEN logs); ``NaN``, ``-inf`` and ``r < range_min`` are dropped (REP 117). The 3D
  sensor pose is projected to the plane: ``(x, y, yaw)``.
- ``sensor_msgs/msg/PointCloud2`` becomes a 3D scan: fields ``x``, ``y``, ``z`` of type FLOAT32
  or FLOAT64, at any offsets and ``point_step``, either byte order, rows padded to ``row_step``
  or not, decoded with one numpy structured dtype. Points with a non-finite coordinate are
  dropped. A cloud has no no-returns unless ``max_range`` is given.

Messages are decoded by :mod:`octolgp.ros_msgs`, the code behind
:meth:`Scan.from_laserscan <octolgp.scan.Scan.from_laserscan>` and
:meth:`Scan.from_pointcloud2 <octolgp.scan.Scan.from_pointcloud2>`.

The sensor pose of a scan with header stamp ``t`` (the bag time when the stamp is zero) comes
from one source:

- ``tf``: ``tf2_msgs/msg/TFMessage`` (or ROS 1 ``tf/tfMessage``) topics (``/tf``, and
  ``/tf_static``: any topic whose name ends in ``tf_static`` holds static transforms, valid at
  every time; a ``tf_static`` topic alone is no pose source). The transform from the
  fixed ``frame`` to the scan's ``header.frame_id`` is composed along the tf tree through the
  frames' nearest common ancestor, each dynamic link taking its latest transform stamped at or
  before ``t`` (no interpolation, and no waiting for transforms recorded after the scan; only
  the last :data:`TF_HORIZON` seconds of each link are kept). A scan with no such chain yet is
  skipped and counted in ``unposed``.
- a pose topic: ``geometry_msgs/msg/PoseStamped``, ``geometry_msgs/msg/PoseWithCovarianceStamped``
  or ``nav_msgs/msg/Odometry`` (its ``pose.pose``), the latest pose stamped at or before ``t``,
  in the pose messages' own ``header.frame_id`` (``frame`` is not used). It is taken as the
  pose of the scan's frame, unless the message names a ``child_frame_id`` (Odometry) from which
  static transforms lead to the scan's frame: then those are composed on.
- none: the identity; the points stay in the scan's own frame.

With ``pose_topic=None`` the source is ``tf`` when the bag has a non-static TFMessage topic,
else the bag's one pose topic (several raise), else none.

Only the scan, pose and tf topics are read, one message at a time; the tf and pose history is
trimmed to :data:`TF_HORIZON` seconds.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections.abc import Generator, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.rotations import quaternion_to_matrix
from octolgp.io.base import ScanStream
from octolgp.io.carmen import NO_RETURN_MARGIN
from octolgp.ros_msgs import RosMessageError, laserscan_beams, pointcloud2_points
from octolgp.scan import FloatArray, Scan, pose_rotation

__all__ = [
    "NO_RETURN_MARGIN",
    "TF_HORIZON",
    "RosbagReader",
    "TfBuffer",
    "looks_like_rosbag",
    "read_rosbag",
]

logger = logging.getLogger(__name__)

TF_HORIZON = 10.0
"""Seconds of transform and pose history kept per tf link (the latest one is always kept)."""

LASERSCAN = "sensor_msgs/msg/LaserScan"
POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # the latter: ROS 1 before tf2
SCAN_TYPES = (LASERSCAN, POINTCLOUD2)
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "nav_msgs/msg/Odometry",
)

_ROS1_MAGIC = b"#ROSBAG V2.0"
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"
_FRAME_SNIFF = 1000  # tf messages read at construction to choose the default frame
_MAX_DEPTH = 64  # tf tree depth limit (guards against cycles)
_NS = 1_000_000_000


def _why(exc: BaseException) -> str:
    """An exception's message, or its type when it has none."""
    return str(exc) or type(exc).__name__


def looks_like_rosbag(path: str | Path) -> bool:
    """Tell whether ``path`` is a ROS bag.

    A ROS 1 bag is a file starting with ``#ROSBAG V2.0``; a ROS 2 bag is a directory with a
    ``metadata.yaml``, that ``metadata.yaml`` itself, or a storage file: an SQLite ``.db3``
    or an ``.mcap`` (by its magic bytes).
    """
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    if not p.is_file():
        return False
    if p.name == "metadata.yaml":
        return True
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return False
    if head.startswith(_ROS1_MAGIC) or head.startswith(_MCAP_MAGIC):
        return True
    return head.startswith(_SQLITE_MAGIC) and p.suffix.lower() == ".db3"


def _stamp_ns(header: Any, fallback: int) -> int:
    """Header stamp in integer nanoseconds; ``fallback`` (the bag time) when it is zero."""
    ns = int(header.stamp.sec) * _NS + int(header.stamp.nanosec)
    return ns if ns != 0 else fallback


def _transform(translation: Any, rotation: Any) -> FloatArray:
    """4x4 homogeneous transform from a ROS ``Vector3``/``Point`` and a ``Quaternion``."""
    t = np.array([translation.x, translation.y, translation.z], dtype=np.float64)
    q = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=np.float64)
    if not (np.isfinite(t).all() and np.isfinite(q).all()):
        raise RosMessageError("NaN or inf in a transform")
    if float(np.linalg.norm(q)) < 1e-6:
        raise RosMessageError("zero quaternion")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q, order="xyzw")
    T[:3, 3] = t
    return T


def _inverse(T: FloatArray) -> FloatArray:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


@dataclass
class _History:
    """Time-stamped transforms of one link, sorted by stamp, trimmed to a horizon."""

    horizon_ns: int
    stamps: list[int] = field(default_factory=list)
    values: list[FloatArray] = field(default_factory=list)

    def add(self, stamp: int, value: FloatArray) -> None:
        i = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(i, stamp)
        self.values.insert(i, value)
        cutoff = self.stamps[-1] - self.horizon_ns
        # Keep the newest entry at or before the cutoff: it is still the one in force there.
        drop = bisect.bisect_right(self.stamps, cutoff) - 1
        if drop > 0:
            del self.stamps[:drop], self.values[:drop]

    def at(self, stamp: int) -> FloatArray | None:
        """The latest value stamped at or before ``stamp``, or ``None``."""
        i = bisect.bisect_right(self.stamps, stamp) - 1
        return self.values[i] if i >= 0 else None


class TfBuffer:
    """A tf tree: static links plus a bounded history of each dynamic link.

    Parameters
    ----------
    horizon : float
        Seconds of history kept per dynamic link (the newest transform at or before the
        cutoff is kept too).
    """

    def __init__(self, horizon: float = TF_HORIZON) -> None:
        self.horizon_ns = int(horizon * _NS)
        self.static: dict[str, tuple[str, FloatArray]] = {}
        self.dynamic: dict[str, tuple[str, _History]] = {}

    def add(self, parent: str, child: str, stamp_ns: int, T: FloatArray, static: bool) -> None:
        """Add ``T_parent_child`` (4x4, metres), valid from ``stamp_ns`` (always if static)."""
        if static:
            self.static[child] = (parent, T)
            return
        entry = self.dynamic.get(child)
        if entry is None or entry[0] != parent:  # new link, or re-parented: restart
            entry = (parent, _History(self.horizon_ns))
            self.dynamic[child] = entry
        entry[1].add(stamp_ns, T)

    def frames(self) -> set[str]:
        """Every frame named so far, as parent or child."""
        out = set(self.static) | set(self.dynamic)
        out |= {p for p, _ in self.static.values()} | {p for p, _ in self.dynamic.values()}
        return out

    def _parent(self, child: str, stamp_ns: int, static_only: bool) -> tuple[str, FloatArray]:
        if child in self.static:
            return self.static[child]
        if not static_only and child in self.dynamic:
            parent, history = self.dynamic[child]
            T = history.at(stamp_ns)
            if T is not None:
                return parent, T
        raise KeyError(child)

    def _ancestors(self, frame: str, stamp_ns: int, static_only: bool) -> dict[str, FloatArray]:
        """``{ancestor: T_ancestor_frame}`` from ``frame`` itself up to its root."""
        out = {frame: np.eye(4)}
        T = np.eye(4)
        for _ in range(_MAX_DEPTH):
            try:
                parent, T_parent_frame = self._parent(frame, stamp_ns, static_only)
            except KeyError:
                break
            if parent in out:  # a cycle
                break
            T = T_parent_frame @ T
            frame = parent
            out[frame] = T
        return out

    def lookup(
        self, target: str, source: str, stamp_ns: int, *, static_only: bool = False
    ) -> FloatArray | None:
        """``T_target_source`` (4x4) at ``stamp_ns``, or ``None`` when the frames do not connect.

        Each dynamic link contributes its latest transform stamped at or before ``stamp_ns``;
        the chain goes through the frames' nearest common ancestor.
        """
        up_source = self._ancestors(source, stamp_ns, static_only)
        if target in up_source:
            return up_source[target]
        up_target = self._ancestors(target, stamp_ns, static_only)
        for ancestor, T_a_source in up_source.items():  # nearest first
            if ancestor in up_target:
                return _inverse(up_target[ancestor]) @ T_a_source
        return None


def _pose_of(msg: Any, msgtype: str) -> FloatArray:
    """The 4x4 pose of a pose-topic message."""
    pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
    return _transform(pose.position, pose.orientation)


class RosbagReader(ScanStream):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over a ROS 1 or ROS 2 bag.

    Parameters
    ----------
    path : str or Path
        A ROS 1 ``.bag`` file, or a ROS 2 bag directory (with ``metadata.yaml``), its
        ``metadata.yaml``, or one of its ``.db3``/``.mcap`` storage files.
    scan_topic : str, optional
        The LaserScan or PointCloud2 topic; the bag's only one when ``None``.
    pose_topic : str, optional
        A TFMessage topic (``"/tf"``: pose from tf) or a PoseStamped, PoseWithCovarianceStamped
        or Odometry topic; chosen as the module docstring says when ``None``.
    frame : str, optional
        With tf: the fixed (world) frame. Default: ``"map"`` if the first tf messages name
        it, else ``"odom"`` if they name it, else the tf tree's single root.
    max_range : float, optional
        Metres. LaserScan: no-return threshold used instead of a message's ``range_max`` when
        smaller. PointCloud2: points at least this far from the sensor are no-returns
        (:attr:`Scan.max_range`); clouds have none when ``None``.
    skip_bad : bool
        Skip and count malformed scan, pose or tf messages instead of raising.

    Attributes
    ----------
    scan_topic : str
        The scan topic read.
    scan_type : str
        Its message type, ``sensor_msgs/msg/LaserScan`` or ``sensor_msgs/msg/PointCloud2``.
    pose_source : str or None
        ``"tf"``, the pose topic, or ``None`` (identity).
    frame : str or None
        The fixed frame (tf), else ``None``.
    skipped : int
        Malformed messages skipped so far (``skip_bad=True``); ``bad_messages`` holds their
        ``(topic, index)``, the index counting from 0 among that topic's messages.
    unposed : int
        Scans skipped so far because no pose was known at their stamp.
    empty : int
        Scans skipped so far because no beam or point was left after filtering.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, if ``path`` is not a readable bag, on a missing or ambiguous topic,
        or an undeterminable frame; while iterating, on a malformed message (``file: topic
        'name' message i: why``), or at the end if scans were read but none could be posed.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        scan_topic: str | None = None,
        pose_topic: str | None = None,
        frame: str | None = None,
        max_range: float | None = None,
        skip_bad: bool = False,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise MapFileNotFound(f"ROS bag {str(self.path)!r} does not exist")
        if self.path.name == "metadata.yaml":
            self.path = self.path.parent
        if not looks_like_rosbag(self.path):
            raise OctolgpError(f"{str(self.path)!r} is not a ROS bag")
        if self.path.is_file() and self.path.suffix.lower() not in (".bag", ".db3", ".mcap"):
            raise OctolgpError(
                f"ROS bag {str(self.path)!r}: name must end in .bag (ROS 1), .db3 or .mcap"
            )
        if max_range is not None and not (np.isfinite(max_range) and max_range > 0):
            raise OctolgpError(f"RosbagReader.max_range must be finite and > 0, got {max_range!r}")
        self.max_range = None if max_range is None else float(max_range)
        self.skip_bad = skip_bad
        self.skipped = 0
        self.bad_messages: list[tuple[str, int]] = []
        self.unposed = 0
        self.empty = 0
        self.frame: str | None = None
        self._counts: dict[str, int] = {}
        try:
            with self._open() as reader:
                types = self._topic_types(reader)
                self.scan_topic = self._choose_scan_topic(types, scan_topic)
                self.scan_type = types[self.scan_topic]
                self.pose_source = self._choose_pose_source(types, pose_topic)
                self._types = types
                self._tf_topics = sorted(t for t, m in types.items() if m in TF_TYPES)
                if self.pose_source == "tf":
                    self.frame = frame if frame is not None else self._default_frame(reader)
        except OctolgpError:
            raise
        except Exception as exc:  # rosbags raises many types on a corrupt bag
            raise OctolgpError(f"ROS bag {self.path}: unreadable: {_why(exc)}") from None
        self._scans = self._generate()

    def _open(self) -> Any:
        """An :class:`rosbags.highlevel.AnyReader` on the bag (not yet opened)."""
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        default = None if self.path.suffix == ".bag" else get_typestore(Stores.ROS2_HUMBLE)
        return AnyReader([self.path], default_typestore=default)

    @staticmethod
    def _topic_types(reader: Any) -> dict[str, str]:
        return {name: info.msgtype for name, info in reader.topics.items() if info.msgtype}

    def _choose_scan_topic(self, types: dict[str, str], wanted: str | None) -> str:
        scans = sorted(t for t, m in types.items() if m in SCAN_TYPES)
        listing = ", ".join(f"{t} ({types[t].rsplit('/', 1)[-1]})" for t in scans) or "none"
        if wanted is not None:
            if types.get(wanted) not in SCAN_TYPES:
                raise OctolgpError(
                    f"ROS bag {self.path}: {wanted!r} is not a LaserScan or PointCloud2 topic "
                    f"(scan topics: {listing})"
                )
            return wanted
        if len(scans) != 1:
            why = "no" if not scans else "several"
            raise OctolgpError(
                f"ROS bag {self.path}: {why} LaserScan/PointCloud2 topics ({listing}); "
                "choose one with scan_topic="
            )
        return scans[0]

    def _choose_pose_source(self, types: dict[str, str], wanted: str | None) -> str | None:
        if wanted is not None:
            if types.get(wanted) in TF_TYPES:
                return "tf"
            if types.get(wanted) not in POSE_TYPES:
                raise OctolgpError(
                    f"ROS bag {self.path}: {wanted!r} is not a tf, PoseStamped, "
                    "PoseWithCovarianceStamped or Odometry topic"
                )
            return wanted
        if any(m in TF_TYPES and not t.endswith("tf_static") for t, m in types.items()):
            return "tf"
        poses = sorted(t for t, m in types.items() if m in POSE_TYPES)
        if len(poses) > 1:
            raise OctolgpError(
                f"ROS bag {self.path}: several pose topics ({', '.join(poses)}); "
                "choose one with pose_topic="
            )
        return poses[0] if poses else None

    def _default_frame(self, reader: Any) -> str:
        """``map``, else ``odom``, else the single root of the first tf messages' tree."""
        connections = [c for c in reader.connections if c.msgtype in TF_TYPES]
        parents: set[str] = set()
        children: set[str] = set()
        messages = reader.messages(connections=connections)
        for _, (connection, _, raw) in zip(range(_FRAME_SNIFF), messages, strict=False):
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception:
                continue  # reported when iterating
            for tf in msg.transforms:
                parents.add(tf.header.frame_id.lstrip("/"))
                children.add(tf.child_frame_id.lstrip("/"))
        frames = parents | children
        for name in ("map", "odom"):
            if name in frames:
                return name
        roots = sorted(parents - children)
        if len(roots) != 1:
            raise OctolgpError(
                f"ROS bag {self.path}: cannot choose the fixed frame (tf roots: "
                f"{', '.join(roots) or 'none'}); pass frame="
            )
        return roots[0]

    def _bad(self, topic: str, index: int, why: str) -> None:
        """Raise on a malformed message, or count it with ``skip_bad``."""
        if not self.skip_bad:
            raise OctolgpError(f"ROS bag {self.path}: topic {topic!r} message {index}: {why}")
        self.skipped += 1
        self.bad_messages.append((topic, index))
        logger.info("ROS bag %s: topic %r message %d: skipped: %s", self.path, topic, index, why)

    def _read(
        self, reader: Any, connections: Iterable[Any]
    ) -> Generator[tuple[str, int, int, Any]]:
        """Yield ``(topic, index, bag_time_ns, message)``; bad data is raised or counted."""
        counts = self._counts
        for connection, bag_ns, raw in reader.messages(connections=list(connections)):
            topic = connection.topic
            index = counts.get(topic, 0)
            counts[topic] = index + 1
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as exc:
                self._bad(topic, index, f"cannot deserialize {connection.msgtype}: {_why(exc)}")
                continue
            yield topic, index, bag_ns, msg

    def _generate(self) -> Generator[Scan]:
        """Stream the scans, keeping only the tf and pose history."""
        tf = TfBuffer()
        poses = _History(int(TF_HORIZON * _NS))
        pose_child = ""
        no_pose = ""
        yielded = 0
        reader = self._open_reader()
        try:
            for topic, index, bag_ns, msg in self._read(reader, self._connections(reader)):
                if topic != self.scan_topic:
                    pose_child = self._note_pose(tf, poses, pose_child, topic, index, bag_ns, msg)
                    continue
                try:
                    stamp = _stamp_ns(msg.header, bag_ns)
                    source = msg.header.frame_id.lstrip("/")
                    T_world, why = self._world_pose(tf, poses, pose_child, source, stamp)
                    if T_world is None:
                        self.unposed += 1
                        no_pose = why
                        continue
                    scan = self._to_scan(msg, T_world, stamp)
                except RosMessageError as exc:
                    self._bad(topic, index, str(exc))
                    continue
                if scan is None:
                    self.empty += 1
                    continue
                yielded += 1
                yield scan
        except OctolgpError:
            raise
        except Exception as exc:
            raise OctolgpError(f"ROS bag {self.path}: unreadable: {_why(exc)}") from None
        finally:
            reader.close()
        if yielded == 0 and self.unposed:
            frames = ", ".join(sorted(tf.frames())) or "none"
            raise OctolgpError(
                f"ROS bag {self.path}: none of {self.unposed} scans on {self.scan_topic!r} "
                f"could be posed: {no_pose} (tf frames: {frames})"
            )

    def _open_reader(self) -> Any:
        """The bag's reader, opened; a bag that cannot be opened raises :class:`OctolgpError`."""
        try:
            reader = self._open()
            reader.open()
        except Exception as exc:
            raise OctolgpError(f"ROS bag {self.path}: unreadable: {_why(exc)}") from None
        return reader

    def _connections(self, reader: Any) -> list[Any]:
        """The connections to read: the scan topic, the pose source and the tf it needs.

        Without ``pose_source="tf"`` only the static tf topics are read, which still
        place the scan frame relative to a pose topic's child frame.
        """
        wanted = {self.scan_topic}
        wanted.update(t for t in self._tf_topics if self.pose_source == "tf" or _static(t))
        if self.pose_source not in (None, "tf"):
            wanted.add(self.pose_source)
        return [c for c in reader.connections if c.topic in wanted]

    def _note_pose(
        self,
        tf: TfBuffer,
        poses: _History,
        pose_child: str,
        topic: str,
        index: int,
        bag_ns: int,
        msg: Any,
    ) -> str:
        """Add a pose or tf message to the history; return the pose topic's child frame.

        The child frame is the one of this message when it is a pose, else
        ``pose_child`` unchanged; a bad message is raised or counted (:meth:`_bad`).
        """
        try:
            if topic == self.pose_source:
                T = _pose_of(msg, self._types[topic])
                poses.add(_stamp_ns(msg.header, bag_ns), T)
                return str(getattr(msg, "child_frame_id", "").lstrip("/"))
            self._add_tf(tf, msg, bag_ns, static=_static(topic))
        except RosMessageError as exc:
            self._bad(topic, index, str(exc))
        return pose_child

    def _world_pose(
        self, tf: TfBuffer, poses: _History, pose_child: str, source: str, stamp: int
    ) -> tuple[FloatArray | None, str]:
        """The pose of frame ``source`` in the world at ``stamp``, or ``None`` and why not.

        With no pose source the scans are already in the world frame; with ``"tf"`` the
        pose is the tf chain from :attr:`frame`; with a pose topic it is the latest pose
        at or before ``stamp``, times the static tf from the pose's child frame to
        ``source`` when there is one.
        """
        if self.pose_source is None:
            return np.eye(4), ""
        if self.pose_source == "tf":
            assert self.frame is not None
            found = tf.lookup(self.frame, source, stamp)
            if found is None:
                return None, f"no tf chain from {self.frame!r} to {source!r}"
            return found, ""
        pose = poses.at(stamp)
        if pose is None:
            return None, f"no {self.pose_source} pose at or before the scans"
        offset = None
        if pose_child and pose_child != source:
            offset = tf.lookup(pose_child, source, stamp, static_only=True)
        return (pose if offset is None else pose @ offset), ""

    @staticmethod
    def _add_tf(tf: TfBuffer, msg: Any, bag_ns: int, static: bool) -> None:
        for t in msg.transforms:
            T = _transform(t.transform.translation, t.transform.rotation)
            parent, child = t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/")
            if not parent or not child or parent == child:
                raise RosMessageError(f"bad tf link {parent!r} -> {child!r}")
            tf.add(parent, child, _stamp_ns(t.header, bag_ns), T, static)

    def _to_scan(self, msg: Any, T_world: FloatArray, stamp: int) -> Scan | None:
        """The scan in the world frame, or ``None`` when no beam is left."""
        seconds = stamp / _NS
        if self.scan_type == LASERSCAN:  # posed in the plane: (x, y, yaw)
            yaw = math.atan2(T_world[1, 0], T_world[0, 0])
            pose = np.array([T_world[0, 3], T_world[1, 3], yaw])
            beams = laserscan_beams(msg, pose, max_range=self.max_range)
            rotation = pose_rotation(pose, 2)
        else:
            beams = pointcloud2_points(msg, T_world, max_range=self.max_range)
            rotation = pose_rotation(T_world, 3)
        return None if beams is None else Scan(*beams, seconds, rotation)


def _static(topic: str) -> bool:
    return topic.endswith("tf_static")


def read_rosbag(
    path: str | Path,
    *,
    scan_topic: str | None = None,
    pose_topic: str | None = None,
    frame: str | None = None,
    max_range: float | None = None,
    skip_bad: bool = False,
) -> RosbagReader:
    """Open a ROS 1/2 bag as a stream of scans in the world frame; see :class:`RosbagReader`."""
    return RosbagReader(
        path,
        scan_topic=scan_topic,
        pose_topic=pose_topic,
        frame=frame,
        max_range=max_range,
        skip_bad=skip_bad,
    )
