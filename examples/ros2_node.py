"""A ROS 2 node that maps live scans with octolgp and serves the map as a nav_msgs/OccupancyGrid.

It subscribes to a ``sensor_msgs/LaserScan`` topic (a 2D map) or a ``sensor_msgs/PointCloud2``
topic (a 3D map), looks up each scan's sensor pose in the fixed frame with tf2 at the scan's
stamp, converts it with :meth:`octolgp.Scan.from_laserscan` / :meth:`octolgp.Scan.from_pointcloud2`
and inserts it into an :class:`octolgp.OnlineMap`. Once a second it publishes a 2D map as a
``nav_msgs/OccupancyGrid`` on ``/octolgp/map`` (transient local, as ``map_server`` does, so RViz
and nav2 get the latest map when they subscribe): P(occupied) as 0..100, unknown as -1. On
shutdown (Ctrl-C) it saves the map file and its resolved config (``MAP.octolgp.toml``) beside it.

Run it with ROS 2 sourced (Humble or later; rclpy, tf2_ros, sensor_msgs, nav_msgs)::

    python examples/ros2_node.py --ros-args -p scan_topic:=/scan -p resolution:=0.05
    python examples/ros2_node.py --ros-args -p cloud_topic:=/points -p downsample:=0.2

Parameters (``--ros-args -p name:=value``):

- ``scan_topic`` (``/scan``): the LaserScan topic, used unless ``cloud_topic`` is set.
- ``cloud_topic`` (empty): a PointCloud2 topic; maps in 3D.
- ``fixed_frame`` (empty): the world frame; empty tries ``map``, then ``odom``, and keeps the
  first that tf2 can reach.
- ``config`` (empty): a MapConfig TOML file (``octolgp dump-config`` writes one).
- ``resolution`` (0.0): metres; overrides the config's when > 0.
- ``downsample`` (0.0): a voxel-grid filter for clouds, metres; off when 0.
- ``out`` (``ros2.octolgp``): the map file written on shutdown.

Scans whose pose tf2 cannot give yet, and malformed or empty scans, are skipped and counted
(logged at most every 5 s). Callbacks run one at a time (the default single-threaded executor);
a scan arriving while the map refits waits in the subscription's queue (sensor-data QoS: keep the
last 5, best effort), so a slow update drops old scans rather than falling behind.
"""

from __future__ import annotations

import array
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

try:
    import rclpy
    from nav_msgs.msg import OccupancyGrid
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.time import Time
    from sensor_msgs.msg import LaserScan, PointCloud2
    from tf2_ros import Buffer, TransformException, TransformListener
except ImportError as exc:  # no ROS 2 here: say what to do, without a traceback
    raise SystemExit(
        f"examples/ros2_node.py needs ROS 2 (rclpy, tf2_ros, sensor_msgs, nav_msgs): {exc}. "
        "Install ROS 2 (Humble or later), run `source /opt/ros/<distro>/setup.bash` and use the "
        "same Python for octolgp."
    ) from None

from octolgp import MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.export.nav2 import trinary_grid
from octolgp.geometry.rotations import quaternion_to_matrix

MAP_TOPIC = "/octolgp/map"
PUBLISH_PERIOD = 1.0  # seconds between OccupancyGrid messages
WARN_PERIOD = 5.0  # seconds between repeated warnings


class OctolgpMapper(Node):  # type: ignore[misc]  # rclpy is untyped without ROS installed
    """Feeds scans from one topic into an :class:`~octolgp.OnlineMap` and publishes it."""

    def __init__(self) -> None:
        super().__init__("octolgp_mapper")
        scan_topic = str(self.declare_parameter("scan_topic", "/scan").value)
        cloud_topic = str(self.declare_parameter("cloud_topic", "").value)
        self.fixed_frame = str(self.declare_parameter("fixed_frame", "").value)
        config_file = str(self.declare_parameter("config", "").value)
        resolution = float(self.declare_parameter("resolution", 0.0).value)
        self.downsample = float(self.declare_parameter("downsample", 0.0).value)
        self.out = Path(str(self.declare_parameter("out", "ros2.octolgp").value))
        # the map's thresholds on P(occupied), as the nav2 PGM export applies them
        self.occupied_thresh = float(self.declare_parameter("occupied_thresh", 0.65).value)
        self.free_thresh = float(self.declare_parameter("free_thresh", 0.25).value)

        self.cloud = bool(cloud_topic)
        config = MapConfig.from_toml(config_file) if config_file else MapConfig()
        config = dataclasses.replace(config, dim=3 if self.cloud else 2)
        if resolution > 0:
            config = dataclasses.replace(config, resolution=resolution)
        self.map = OnlineMap(config)  # in memory; saved on shutdown
        self.skipped = 0

        self.tf_buffer = Buffer()
        self.tf_listener = TransformListener(self.tf_buffer, self)
        if self.cloud:
            self.create_subscription(
                PointCloud2, cloud_topic, self.on_cloud, qos_profile_sensor_data
            )
        else:
            self.create_subscription(LaserScan, scan_topic, self.on_scan, qos_profile_sensor_data)
        latched = QoSProfile(
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        self.grid_pub = self.create_publisher(OccupancyGrid, MAP_TOPIC, latched)
        self.create_timer(PUBLISH_PERIOD, self.publish_map)
        topic = cloud_topic or scan_topic
        self.get_logger().info(
            f"mapping {topic} at {config.resolution:g} m ({config.dim}D), "
            f"publishing {MAP_TOPIC}, saving {self.out} on shutdown"
        )

    # --- input ----------------------------------------------------------------------------

    def sensor_pose(self, msg: Any) -> np.ndarray | None:
        """The 4x4 pose of ``msg.header.frame_id`` in the fixed frame at the message's stamp."""
        frames = [self.fixed_frame] if self.fixed_frame else ["map", "odom"]
        stamp = Time.from_msg(msg.header.stamp)
        why = ""
        for frame in frames:
            try:
                t = self.tf_buffer.lookup_transform(frame, msg.header.frame_id, stamp)
            except TransformException as exc:
                why = str(exc)
                continue
            if not self.fixed_frame:
                self.fixed_frame = frame  # keep one world frame for the whole map
                self.get_logger().info(f"fixed frame: {frame}")
            q, p = t.transform.rotation, t.transform.translation
            T = np.eye(4)
            T[:3, :3] = quaternion_to_matrix([q.x, q.y, q.z, q.w], order="xyzw")
            T[:3, 3] = (p.x, p.y, p.z)
            return T
        self.skip(f"no pose for {msg.header.frame_id!r} in {' or '.join(frames)}: {why}")
        return None

    def on_scan(self, msg: LaserScan) -> None:
        """A LaserScan: posed in the plane ``(x, y, yaw)``, inserted into the 2D map."""
        T = self.sensor_pose(msg)
        if T is None:
            return
        pose = (T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0]))
        try:
            self.insert(Scan.from_laserscan(msg, pose))
        except OctolgpError as exc:
            self.skip(str(exc))

    def on_cloud(self, msg: PointCloud2) -> None:
        """A PointCloud2: posed in 3D, optionally downsampled, inserted into the 3D map."""
        T = self.sensor_pose(msg)
        if T is None:
            return
        try:
            scan = Scan.from_pointcloud2(msg, T)
            if self.downsample > 0:
                scan = scan.downsample(self.downsample)
            self.insert(scan)
        except OctolgpError as exc:
            self.skip(str(exc))

    def insert(self, scan: Scan) -> None:
        """Insert one world-frame scan into the map."""
        update = self.map.insert_scan(scan)
        self.get_logger().debug(
            f"scan {update.scan}: {update.refit_leaves} leaves refitted in {update.seconds:.3f} s"
        )

    def skip(self, why: str) -> None:
        """Count a skipped scan and say why (throttled)."""
        self.skipped += 1
        self.get_logger().warning(
            f"skipped {self.skipped} scan(s); last: {why}", throttle_duration_sec=WARN_PERIOD
        )

    # --- output ---------------------------------------------------------------------------

    def publish_map(self) -> None:
        """Publish a 2D map as an OccupancyGrid (3D maps: export a slice with octolgp export)."""
        if self.map.config.dim != 2 or not self.fixed_frame:
            return
        centres, prob = self.map.voxels()
        if centres.shape[0] == 0:
            return  # still buffering the first scans to learn hyperparameters on
        resolution = self.map.config.resolution
        # trinary, as nav2's static layer reads it: 100 lethal, 0 free, -1 unknown
        grid = trinary_grid(
            centres,
            prob,
            resolution,
            occupied_thresh=self.occupied_thresh,
            free_thresh=self.free_thresh,
        )
        xmin, ymin = grid.origin
        cells = grid.data

        msg = OccupancyGrid()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.fixed_frame
        msg.info.map_load_time = msg.header.stamp
        msg.info.resolution = float(resolution)
        msg.info.height, msg.info.width = (int(n) for n in cells.shape)
        msg.info.origin.position.x = float(xmin)  # the corner of cell (0, 0)
        msg.info.origin.position.y = float(ymin)
        msg.info.origin.orientation.w = 1.0
        msg.data = array.array("b", cells.tobytes())  # row-major from (xmin, ymin), rows along y
        self.grid_pub.publish(msg)

    def save(self) -> None:
        """Write the map file and its resolved config beside it."""
        if self.map.n_scans == 0 and self.map.buffered_scans == 0:
            self.get_logger().info("no scans mapped; nothing saved")
            return
        self.map.flush()  # learn now if the run was shorter than learn_scans
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.map.save(self.out)
        self.out.with_name(self.out.name + ".toml").write_text(self.map.config.to_toml())
        self.get_logger().info(
            f"saved {self.out}: {self.map.n_scans} scans, {len(self.map.store)} leaves "
            f"({self.skipped} skipped)"
        )


def main(args: list[str] | None = None) -> None:
    """Spin the mapper until Ctrl-C or a ROS shutdown, then save the map."""
    rclpy.init(args=args)
    node = OctolgpMapper()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.save()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
