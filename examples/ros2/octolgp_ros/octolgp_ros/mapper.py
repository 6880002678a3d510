"""The octolgp mapping node: range scans in, a map file and nav2 / OctoMap messages out.

Topics (relative: a namespace or remapping in the launch file moves them):

- in: ``scan`` (``sensor_msgs/LaserScan``, a 2D map) or ``points``
  (``sensor_msgs/PointCloud2``, a 3D map), chosen by the ``input`` parameter.
- 2D out: ``map`` (``nav_msgs/OccupancyGrid``, transient local as ``map_server``'s) and
  ``map_updates`` (``map_msgs/OccupancyGridUpdate``: the tiles that changed since the last
  full ``map``), as nav2's static layer subscribes to them.
- 3D out: ``octomap_binary`` (``octomap_msgs/Octomap``), ``occupied_cells_vis_array``
  (``visualization_msgs/MarkerArray``) and ``projected_map`` with ``projected_map_updates``
  (the 2.5D projection), as ``octomap_server`` names them.
- service ``save`` (``std_srvs/Trigger``): writes ``MAP.bt`` and the nav2 map ``MAP.pgm`` with
  ``MAP.yaml`` beside the map file.

Each scan waits in an :class:`octolgp.ros_tf.TfWaitQueue` until tf2 gives the sensor's pose in
``frame_id`` at the scan's own stamp (at most ``tf_timeout`` seconds), then goes into an
:class:`octolgp.OnlineMap` that writes the map file in one SQLite transaction per scan: a killed
node loses at most the scan in hand, and a node started on an existing file resumes it. Every
message is stamped with the last inserted scan's stamp. The grids are trinary by the map's
thresholds (``occupied_thresh``, ``free_thresh``): 100 where the nav2 PGM export is black, so
nav2's static layer marks every wall lethal.

Publishing runs on its own timer in its own callback group under a multi-threaded executor, off
the insert path: a scan waits for it only while it copies the map's voxels
(``OnlineMap.voxels()``, which holds the map's lock); building the messages runs beside the
inserts. Messages nobody subscribes to are not built (the latched grid always is).

Parameters are documented in ``config/params.yaml``.
"""

from __future__ import annotations

import array
import dataclasses
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    import rclpy
    from geometry_msgs.msg import Point
    from map_msgs.msg import OccupancyGridUpdate
    from message_filters import Subscriber
    from nav_msgs.msg import OccupancyGrid
    from octomap_msgs.msg import Octomap
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from rclpy.time import Time
    from sensor_msgs.msg import LaserScan, PointCloud2
    from std_msgs.msg import ColorRGBA
    from std_srvs.srv import Trigger
    from tf2_ros import Buffer, TransformException, TransformListener
    from visualization_msgs.msg import Marker, MarkerArray
except ImportError as exc:  # no ROS 2 here: say what to do, without a traceback
    raise SystemExit(
        f"octolgp_ros needs ROS 2 (Humble or later) with its message packages: {exc}. "
        "Source /opt/ros/<distro>/setup.bash and the workspace's install/setup.bash, and use "
        "the same Python for octolgp."
    ) from None

from octolgp import MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.export.nav2 import TrinaryGrid, write_nav2_map
from octolgp.export.octomap import write_bt
from octolgp.export.ros_out import (
    GridMessage,
    GridSync,
    clip_z_range,
    map_grid,
    occupied_cubes,
    octomap_binary,
    trinary_voxels,
)
from octolgp.geometry.rotations import quaternion_to_matrix
from octolgp.ros_tf import TfWaitQueue

WARN_PERIOD = 5.0  # seconds between repeated warnings
TF_POLL_PERIOD = 0.05  # seconds between looks at tf for scans still waiting

PARAMETERS: dict[str, Any] = {
    "input": "scan",
    "frame_id": "map",
    "map_file": "octolgp_map.octolgp",
    "config": "",
    "resolution": 0.0,
    "downsample": 0.0,
    "occupied_thresh": 0.65,
    "free_thresh": 0.25,
    "publish_rate": 1.0,
    "full_publish_period": 10.0,
    "tile": 32,
    "max_updates": 16,
    "tf_timeout": 0.5,
    "tf_queue_size": 10,
    "projection_min_z": -math.inf,
    "projection_max_z": math.inf,
    "color_factor": 0.8,
}
"""Every parameter the node declares, with its default (``config/params.yaml`` documents them)."""


def _latched(depth: int = 1) -> QoSProfile:
    """Reliable, transient local: late subscribers get the last message, as ``map_server``'s."""
    return QoSProfile(
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


class GridTopic:
    """A trinary grid on ``NAME`` (latched) with its changed tiles on ``NAME_updates``."""

    def __init__(self, node: OctolgpMapper, name: str) -> None:
        self.node = node
        self.full = node.create_publisher(OccupancyGrid, name, _latched())
        depth = max(10, node.max_updates)
        self.updates = node.create_publisher(OccupancyGridUpdate, f"{name}_updates", depth)
        self.sync = GridSync(
            tile=node.tile, max_updates=node.max_updates, full_period=node.full_publish_period
        )

    def publish(self, grid: TrinaryGrid, stamp: Any) -> str:
        """Publish ``grid`` in full or as updates to the last one sent; say which."""
        frame = self.node.frame_id
        out = self.sync.next(grid, time.monotonic())
        if isinstance(out, GridMessage):
            msg = OccupancyGrid()
            msg.header.stamp = stamp
            msg.header.frame_id = frame
            msg.info.map_load_time = stamp
            msg.info.resolution = out.resolution
            msg.info.width, msg.info.height = out.width, out.height
            msg.info.origin.position.x, msg.info.origin.position.y = out.origin
            msg.info.origin.orientation.w = 1.0
            msg.data = array.array("b", out.data.tobytes())
            self.full.publish(msg)
            return f"full {out.width} x {out.height}"
        for u in out:
            up = OccupancyGridUpdate()
            up.header.stamp = stamp
            up.header.frame_id = frame
            up.x, up.y, up.width, up.height = u.x, u.y, u.width, u.height
            up.data = array.array("b", u.data.tobytes())
            self.updates.publish(up)
        return f"{len(out)} update(s), {sum(u.data.size for u in out)} cells"


class OctolgpMapper(Node):  # type: ignore[misc]  # rclpy is untyped without ROS installed
    """Feeds scans into an :class:`~octolgp.OnlineMap` backed by a file and publishes it."""

    def __init__(self) -> None:
        super().__init__("octolgp_mapper")
        p = {name: self.declare_parameter(name, value).value for name, value in PARAMETERS.items()}
        if p["input"] not in ("scan", "points"):
            raise OctolgpError(f"input must be 'scan' or 'points', got {p['input']!r}")
        self.cloud = p["input"] == "points"
        self.frame_id = str(p["frame_id"])
        self.map_file = Path(str(p["map_file"])).expanduser()
        self.downsample = float(p["downsample"])
        self.occupied_thresh = float(p["occupied_thresh"])
        self.free_thresh = float(p["free_thresh"])
        self.full_publish_period = float(p["full_publish_period"])
        self.tile = int(p["tile"])
        self.max_updates = int(p["max_updates"])
        self.z_range = (float(p["projection_min_z"]), float(p["projection_max_z"]))
        self.color_factor = float(p["color_factor"])
        if float(p["publish_rate"]) <= 0:
            raise OctolgpError(f"publish_rate must be > 0 Hz, got {p['publish_rate']!r}")

        self.map = self._open_map(str(p["config"]), float(p["resolution"]))
        # stamp of the last inserted scan; a resumed map is published at once, stamped 0
        self.last_stamp: Any = Time().to_msg() if self.map.n_scans else None
        self.inserted = 0  # scans inserted by this node
        self.published = -1  # value of ``inserted`` at the last publish
        self.skipped = 0
        # an insert and its stamp, or the voxels and the stamp they go out with, as one
        self.stamp_lock = threading.Lock()

        # scans and tf polling take turns in one group; publishing and saving in another
        inserts = MutuallyExclusiveCallbackGroup()
        outputs = MutuallyExclusiveCallbackGroup()
        self.tf_buffer = Buffer()
        self.tf_listener = TransformListener(self.tf_buffer, self, spin_thread=True)
        self.waiting: TfWaitQueue[Any] = TfWaitQueue(
            int(p["tf_queue_size"]), float(p["tf_timeout"])
        )
        msg_type, topic = (PointCloud2, "points") if self.cloud else (LaserScan, "scan")
        self.subscriber = Subscriber(
            self, msg_type, topic, qos_profile=qos_profile_sensor_data, callback_group=inserts
        )
        self.subscriber.registerCallback(self.on_message)
        self.create_timer(TF_POLL_PERIOD, self.drain, callback_group=inserts)

        if self.cloud:
            self.grid_topic = GridTopic(self, "projected_map")
            self.octomap_pub = self.create_publisher(Octomap, "octomap_binary", _latched())
            self.marker_pub = self.create_publisher(
                MarkerArray, "occupied_cells_vis_array", _latched()
            )
        else:
            self.grid_topic = GridTopic(self, "map")
        self.create_timer(1.0 / float(p["publish_rate"]), self.publish_all, callback_group=outputs)
        self.create_service(Trigger, "save", self.on_save, callback_group=outputs)
        self.get_logger().info(
            f"mapping {self.subscriber.sub.topic_name} ({self.map.config.dim}D, "
            f"{self.map.config.resolution:g} m) in {self.frame_id!r} into {self.map_file} "
            f"({self.map.n_scans} scans there)"
        )

    def _open_map(self, config_file: str, resolution: float) -> OnlineMap:
        """Resume the map file if it exists, else create it from the config and parameters."""
        dim = 3 if self.cloud else 2
        if self.map_file.exists():
            m = OnlineMap.open(self.map_file)
            if m.config.dim != dim:
                m.close()
                raise OctolgpError(
                    f"map_file {str(self.map_file)!r} holds a {m.config.dim}D map; "
                    f"input {'points' if self.cloud else 'scan'!r} makes {dim}D maps"
                )
            if config_file or resolution > 0:
                self.get_logger().warning(
                    "resuming an existing map file: its own config is used; "
                    "'config' and 'resolution' apply to new files only"
                )
            return m
        config = MapConfig.from_toml(config_file) if config_file else MapConfig()
        config = dataclasses.replace(config, dim=dim)
        if resolution > 0:
            config = dataclasses.replace(config, resolution=resolution)
        self.map_file.parent.mkdir(parents=True, exist_ok=True)
        m = OnlineMap(config, path=self.map_file)  # every scan written as it is inserted
        self.map_file.with_name(self.map_file.name + ".toml").write_text(m.config.to_toml())
        return m

    # --- input ----------------------------------------------------------------------------

    def now_s(self) -> float:
        """The node's clock in seconds (simulated time when ``use_sim_time`` is set)."""
        return float(self.get_clock().now().nanoseconds) * 1e-9

    def on_message(self, msg: Any) -> None:
        """Queue a scan until tf can pose it; insert whatever is ready."""
        dropped = self.waiting.push(msg, self.now_s())
        if dropped is not None:
            self.skip("tf queue full (raise tf_queue_size or check tf)")
        self.drain()

    def posable(self, msg: Any) -> bool:
        """Whether tf2 can give the sensor's pose in ``frame_id`` at the scan's stamp."""
        return bool(
            self.tf_buffer.can_transform(
                self.frame_id, msg.header.frame_id, Time.from_msg(msg.header.stamp)
            )
        )

    def drain(self) -> None:
        """Insert the waiting scans tf can pose, in arrival order; drop those timed out."""
        out = self.waiting.drain(self.posable, self.now_s())
        for msg in out.timed_out:
            self.skip(f"no pose for {msg.header.frame_id!r} in {self.frame_id!r} at its stamp")
        for msg in out.ready:
            self.insert(msg)

    def sensor_pose(self, msg: Any) -> np.ndarray:
        """The 4x4 pose of ``msg.header.frame_id`` in ``frame_id`` at the message's stamp."""
        t = self.tf_buffer.lookup_transform(
            self.frame_id, msg.header.frame_id, Time.from_msg(msg.header.stamp)
        )
        q, v = t.transform.rotation, t.transform.translation
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix([q.x, q.y, q.z, q.w], order="xyzw")
        T[:3, 3] = (v.x, v.y, v.z)
        return T

    def insert(self, msg: Any) -> None:
        """Pose one scan at its stamp and insert it (written to the map file at once)."""
        try:
            T = self.sensor_pose(msg)
            if self.cloud:
                scan = Scan.from_pointcloud2(msg, T)
                if self.downsample > 0:
                    scan = scan.downsample(self.downsample)
            else:  # posed in the plane (x, y, yaw)
                scan = Scan.from_laserscan(msg, (T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])))
            with self.stamp_lock:
                update = self.map.insert_scan(scan)
                self.last_stamp = msg.header.stamp
                self.inserted += 1
        except (OctolgpError, TransformException) as exc:
            self.skip(str(exc))
            return
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

    def publish_all(self) -> None:
        """Publish the map's messages if scans went in since the last time.

        Nothing is published while the map buffers its first scans to learn its
        hyperparameters (``online.learn_scans``): a read then fits every buffered scan
        into a map that is thrown away, holding the inserts for seconds.
        """
        if self.last_stamp is None or self.inserted == self.published:
            return
        if self.map.provisional:  # a throw-away fit of every buffered scan: not worth a stall
            return
        t0 = time.perf_counter()
        with self.stamp_lock:  # the only part that holds the map (and its inserts)
            centres, prob = self.map.voxels()
            stamp, self.published = self.last_stamp, self.inserted
        held = time.perf_counter() - t0
        if centres.shape[0] == 0:
            return
        thresholds = {"occupied_thresh": self.occupied_thresh, "free_thresh": self.free_thresh}
        try:
            grid = map_grid(
                centres,
                prob,
                self.map.config.resolution,
                z_range=self.z_range,
                tile=self.tile,
                **thresholds,
            )
            sent = self.grid_topic.publish(grid, stamp)
            if self.cloud:
                self.publish_3d(centres, prob, stamp, thresholds)
        except OctolgpError as exc:  # e.g. no voxel in the projection's height band
            self.get_logger().warning(f"not published: {exc}", throttle_duration_sec=WARN_PERIOD)
            return
        self.get_logger().debug(
            f"published {centres.shape[0]} voxels ({sent}): map held {held:.3f} s, "
            f"{time.perf_counter() - t0:.3f} s in all"
        )

    def publish_3d(
        self, centres: np.ndarray, prob: np.ndarray, stamp: Any, thresholds: dict[str, float]
    ) -> None:
        """The OctoMap tree and the occupied-cell markers, for their subscribers only."""
        res = self.map.config.resolution
        if self.octomap_pub.get_subscription_count():
            tree = octomap_binary(centres, prob, res, self.map.config.tree_depth, **thresholds)
            msg = Octomap()
            msg.header.stamp = stamp
            msg.header.frame_id = self.frame_id
            msg.binary, msg.id, msg.resolution = tree.binary, tree.id, tree.resolution
            msg.data = array.array("b", tree.data)
            self.octomap_pub.publish(msg)
        if self.marker_pub.get_subscription_count():
            cubes = occupied_cubes(centres, prob, res, color_factor=self.color_factor, **thresholds)
            marker = Marker()
            marker.header.stamp = stamp
            marker.header.frame_id = self.frame_id
            marker.ns, marker.id = "occupied_cells", 0
            marker.type, marker.action = Marker.CUBE_LIST, Marker.ADD
            marker.pose.orientation.w = 1.0
            marker.scale.x = marker.scale.y = marker.scale.z = cubes.scale
            marker.points = [Point(x=x, y=y, z=z) for x, y, z in cubes.points.tolist()]
            marker.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in cubes.colours.tolist()]
            self.marker_pub.publish(MarkerArray(markers=[marker]))

    def on_save(self, request: Any, response: Any) -> Any:
        """Write ``MAP.bt`` and ``MAP.pgm`` / ``MAP.yaml`` beside the map file."""
        try:
            centres, prob = self.map.voxels()
            res, depth = self.map.config.resolution, self.map.config.tree_depth
            thresholds = {"occupied_thresh": self.occupied_thresh, "free_thresh": self.free_thresh}
            keys, occupied = trinary_voxels(centres, prob, res, depth, **thresholds)
            bt = self.map_file.with_suffix(".bt")
            write_bt(bt, keys, occupied, res, depth)
            option = {"z_range": clip_z_range(centres, self.z_range)} if self.cloud else {}
            yaml = write_nav2_map(
                self.map_file.with_suffix(".pgm"), centres, prob, res, **thresholds, **option
            )
        except OctolgpError as exc:
            response.success, response.message = False, str(exc)
            return response
        response.success = True
        response.message = f"wrote {bt} and {yaml} ({self.map.n_scans} scans)"
        self.get_logger().info(response.message)
        return response

    def close(self) -> None:
        """Close the map file (every inserted scan is in it already)."""
        self.get_logger().info(
            f"{self.map_file}: {self.map.n_scans} scans ({self.skipped} skipped this run)"
        )
        self.map.close()


def main(args: list[str] | None = None) -> None:
    """Spin the mapper on two threads until Ctrl-C or a ROS shutdown, then close the map."""
    rclpy.init(args=args)
    node = OctolgpMapper()
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
