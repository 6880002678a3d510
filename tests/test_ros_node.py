"""The octolgp_ros node driven through stand-ins for rclpy, tf2_ros and the message packages.

ROS 2 is not installed here, so these modules are replaced by small fakes that record what
the node publishes and let the test play tf and the clock. What is checked is the node's own
logic: scans wait for their pose at their stamp and leave in order, outputs carry the last
scan's stamp, the map file is written as scans come and resumed, updates reproduce the grid,
the save service writes its files, 3D maps publish the octomap, markers and projection.
"""

from __future__ import annotations

import importlib
import math
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineMap, Scan
from octolgp.export.nav2 import TrinaryGrid
from octolgp.export.ros_out import (
    GridUpdate,
    apply_updates,
    map_grid,
    occupied_cubes,
    octomap_binary,
)
from octolgp.io import read_kitti

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "examples" / "ros2" / "octolgp_ros"
HP2 = Hyperparameters(
    length_scale=1.2, signal_variance=3.8, noise_variance=0.006, alpha=4.5, beta=1.0
)
HP3 = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=3.0)


# ---------------------------------------------------------------- fakes


class Msg:
    """Any ROS message: keyword fields, nested fields made on first access."""

    def __init__(self, **fields: Any) -> None:
        self.__dict__.update(fields)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        child = Msg()
        setattr(self, name, child)
        return child


class Marker(Msg):
    CUBE_LIST = 6
    ADD = 0


class Stamp(Msg):
    def __eq__(self, other: object) -> bool:
        return isinstance(other, Stamp) and (self.sec, self.nanosec) == (other.sec, other.nanosec)

    __hash__ = None  # type: ignore[assignment]


def stamp(t: float) -> Stamp:
    return Stamp(sec=int(t), nanosec=round((t - int(t)) * 1e9))


class Time:
    def __init__(self, nanoseconds: int = 0) -> None:
        self.nanoseconds = nanoseconds

    @classmethod
    def from_msg(cls, s: Any) -> Time:
        return cls(s.sec * 10**9 + s.nanosec)

    def to_msg(self) -> Stamp:
        return Stamp(sec=self.nanoseconds // 10**9, nanosec=self.nanoseconds % 10**9)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> Time:
        return Time(round(self.t * 1e9))


class Publisher:
    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.sent: list[Any] = []

    def publish(self, msg: Any) -> None:
        self.sent.append(msg)

    def get_subscription_count(self) -> int:
        return 1


class Logger:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def _log(self, text: str, **_: Any) -> None:
        self.lines.append(text)

    info = warning = debug = _log


class Node:
    overrides: ClassVar[dict[str, Any]] = {}

    def __init__(self, name: str) -> None:
        self.name = name
        self.publishers: dict[str, Publisher] = {}
        self.timers: list[Any] = []
        self.services: dict[str, Any] = {}
        self.clock = Clock()
        self.logger = Logger()

    def declare_parameter(self, name: str, value: Any) -> Any:
        return Msg(value=self.overrides.get(name, value))

    def create_publisher(self, msg_type: Any, topic: str, qos: Any) -> Publisher:
        self.publishers[topic] = Publisher(topic)
        return self.publishers[topic]

    def create_timer(self, period: float, callback: Any, callback_group: Any = None) -> None:
        self.timers.append(callback)

    def create_service(
        self, srv: Any, name: str, callback: Any, callback_group: Any = None
    ) -> None:
        self.services[name] = callback

    def get_logger(self) -> Logger:
        return self.logger

    def get_clock(self) -> Clock:
        return self.clock

    def destroy_node(self) -> None:
        pass


class Subscriber:
    def __init__(self, node: Node, msg_type: Any, topic: str, **kwargs: Any) -> None:
        self.topic = topic
        self.sub = Msg(topic_name="/" + topic)
        self.callbacks: list[Any] = []

    def registerCallback(self, callback: Any) -> None:  # noqa: N802  # message_filters' name
        self.callbacks.append(callback)


class TransformException(Exception):  # noqa: N818  # tf2_ros' name
    pass


class Buffer:
    """tf: the sensor's pose per stamp (nanoseconds), as the test publishes it."""

    poses: ClassVar[dict[int, np.ndarray]] = {}

    def can_transform(self, target: str, source: str, time: Time) -> bool:
        return target == "map" and source == "laser" and time.nanoseconds in self.poses

    def lookup_transform(self, target: str, source: str, time: Time) -> Any:
        if not self.can_transform(target, source, time):
            raise TransformException(f"no {source} in {target} at {time.nanoseconds}")
        T = self.poses[time.nanoseconds]
        w = math.sqrt(max(0.0, 1.0 + np.trace(T[:3, :3]))) / 2.0
        q = (  # rotation matrix to quaternion (w > 0 here: yaw below pi)
            (T[2, 1] - T[1, 2]) / (4 * w),
            (T[0, 2] - T[2, 0]) / (4 * w),
            (T[1, 0] - T[0, 1]) / (4 * w),
            w,
        )
        return Msg(
            transform=Msg(
                rotation=Msg(x=q[0], y=q[1], z=q[2], w=q[3]),
                translation=Msg(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            )
        )


def _module(name: str, **attrs: Any) -> types.ModuleType:
    m = types.ModuleType(name)
    m.__dict__.update(attrs)
    return m


@pytest.fixture
def mapper(monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """The node module, imported against the fakes."""
    fakes = {
        "rclpy": _module("rclpy", init=lambda args=None: None, try_shutdown=lambda: None),
        "rclpy.callback_groups": _module(
            "rclpy.callback_groups", MutuallyExclusiveCallbackGroup=Msg
        ),
        "rclpy.executors": _module(
            "rclpy.executors", ExternalShutdownException=RuntimeError, MultiThreadedExecutor=Msg
        ),
        "rclpy.node": _module("rclpy.node", Node=Node),
        "rclpy.qos": _module(
            "rclpy.qos",
            QoSProfile=Msg,
            DurabilityPolicy=Msg(TRANSIENT_LOCAL=1),
            ReliabilityPolicy=Msg(RELIABLE=1),
            qos_profile_sensor_data=Msg(),
        ),
        "rclpy.time": _module("rclpy.time", Time=Time),
        "message_filters": _module("message_filters", Subscriber=Subscriber),
        "tf2_ros": _module(
            "tf2_ros",
            Buffer=Buffer,
            TransformException=TransformException,
            TransformListener=lambda *a, **k: None,
        ),
    }
    messages = {
        "geometry_msgs.msg": ["Point"],
        "map_msgs.msg": ["OccupancyGridUpdate"],
        "nav_msgs.msg": ["OccupancyGrid"],
        "octomap_msgs.msg": ["Octomap"],
        "sensor_msgs.msg": ["LaserScan", "PointCloud2"],
        "std_msgs.msg": ["ColorRGBA"],
        "std_srvs.srv": ["Trigger"],
        "visualization_msgs.msg": ["MarkerArray"],
    }
    for name, classes in messages.items():
        fakes[name.split(".")[0]] = _module(name.split(".")[0])
        fakes[name] = _module(name, **{c: type(c, (Msg,), {}) for c in classes})
    fakes["visualization_msgs.msg"].Marker = Marker
    for name, module in fakes.items():
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.syspath_prepend(str(PACKAGE))
    monkeypatch.delitem(sys.modules, "octolgp_ros.mapper", raising=False)
    monkeypatch.setattr(Buffer, "poses", {})
    yield importlib.import_module("octolgp_ros.mapper")
    sys.modules.pop("octolgp_ros.mapper", None)
    sys.modules.pop("octolgp_ros", None)


# ---------------------------------------------------------------- scans


def pose2d(x: float, y: float, yaw: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = (x, y)
    return T


def laserscan(T: np.ndarray, t: float, n: int = 181) -> Msg:
    """A LaserScan taken at pose ``T`` inside the box [-4, 6] x [-3, 5] (walls all round)."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, n)
    world = angles + math.atan2(T[1, 0], T[0, 0])
    d = np.c_[np.cos(world), np.sin(world)]
    with np.errstate(divide="ignore"):
        tx = np.where(d[:, 0] > 0, (6 - T[0, 3]) / d[:, 0], (-4 - T[0, 3]) / d[:, 0])
        ty = np.where(d[:, 1] > 0, (5 - T[1, 3]) / d[:, 1], (-3 - T[1, 3]) / d[:, 1])
    ranges = np.minimum(np.abs(tx), np.abs(ty)).astype(np.float32)
    return Msg(
        header=Msg(frame_id="laser", stamp=stamp(t)),
        angle_min=-math.pi / 2,
        angle_max=math.pi / 2,
        angle_increment=math.pi / (n - 1),
        range_min=0.1,
        range_max=30.0,
        ranges=ranges,
    )


def _start(mapper: Any, tmp_path: Path, **params: Any) -> Any:
    config = tmp_path / "config.toml"
    if not config.exists():
        dim = 3 if params.get("input") == "points" else 2
        hp = HP3 if dim == 3 else HP2
        res = 0.5 if dim == 3 else 0.1
        config.write_text(MapConfig(dim=dim, resolution=res, hyperparameters=hp).to_toml())
    Node.overrides = {"map_file": str(tmp_path / "m.octolgp"), "config": str(config), **params}
    return mapper.OctolgpMapper()


def _grid_of(msg: Any) -> TrinaryGrid:
    data = np.frombuffer(msg.data.tobytes(), dtype=np.int8).reshape(msg.info.height, -1)
    origin = (msg.info.origin.position.x, msg.info.origin.position.y)
    return TrinaryGrid(data.copy(), origin, msg.info.resolution)


def _update_of(msg: Any) -> GridUpdate:
    data = np.frombuffer(msg.data.tobytes(), dtype=np.int8)
    return GridUpdate(msg.x, msg.y, msg.width, msg.height, data)


# ---------------------------------------------------------------- tests


def test_scans_wait_for_their_pose_and_outputs_carry_their_stamp(
    mapper: Any, tmp_path: Path
) -> None:
    node = _start(mapper, tmp_path, tf_timeout=0.5, full_publish_period=100.0, tile=8)
    (on_message,) = node.subscriber.callbacks
    drain, publish = node.timers
    poses = {i: pose2d(0.3 * i, 0.1 * i, 0.2 * i) for i in range(8)}
    msgs = {i: laserscan(poses[i], 100.0 + i) for i in range(8)}
    ns = {i: Time.from_msg(msgs[i].header.stamp).nanoseconds for i in range(8)}

    # scan 0 posed at once; scan 1 arrives before its tf, scan 2 (posed) waits behind it
    Buffer.poses[ns[0]] = poses[0]
    node.clock.t = 1.0
    on_message(msgs[0])
    assert node.map.n_scans == 1
    on_message(msgs[1])
    Buffer.poses[ns[2]] = poses[2]
    on_message(msgs[2])
    assert node.map.n_scans == 1
    Buffer.poses[ns[1]] = poses[1]  # tf catches up
    node.clock.t = 1.2
    drain()
    assert node.map.n_scans == 3
    # scan 3 never gets a pose: skipped after tf_timeout; scan 4 behind it goes in then
    on_message(msgs[3])
    Buffer.poses[ns[4]] = poses[4]
    on_message(msgs[4])
    node.clock.t = 1.6
    drain()
    assert node.map.n_scans == 3
    node.clock.t = 1.8
    drain()
    assert node.map.n_scans == 4
    assert node.skipped == 1
    assert any("no pose for 'laser'" in line for line in node.logger.lines)

    # the map is the scans inserted with the poses at their own stamps, in order
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2)) as ref:
        for i in (0, 1, 2, 4):
            T = poses[i]
            ref.insert_scan(
                Scan.from_laserscan(msgs[i], (T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])))
            )
        centres, prob = ref.voxels()
    got_c, got_p = node.map.voxels()
    np.testing.assert_array_equal(got_c, centres)
    np.testing.assert_allclose(got_p, prob, rtol=0, atol=1e-12)

    # the grid: stamped with the last scan's stamp, the map's trinary grid
    publish()
    (full,) = node.publishers["map"].sent
    assert full.header.stamp == msgs[4].header.stamp
    assert full.header.frame_id == "map"
    held = _grid_of(full)
    expected = map_grid(centres, prob, 0.1, tile=8)
    np.testing.assert_array_equal(held.data, expected.data)
    assert held.origin == expected.origin
    publish()  # nothing new: nothing sent
    assert len(node.publishers["map"].sent) == 1
    assert node.publishers["map_updates"].sent == []

    # more scans: the updates bring subscribers to the new grid
    kinds = []
    for i in (5, 6, 7):
        Buffer.poses[ns[i]] = poses[i]
        on_message(msgs[i])
        fulls = len(node.publishers["map"].sent)
        publish()
        grid = map_grid(*node.map.voxels(), 0.1, tile=8)
        if len(node.publishers["map"].sent) > fulls:
            kinds.append("full")
            held = _grid_of(node.publishers["map"].sent[-1])
            assert node.publishers["map"].sent[-1].header.stamp == msgs[i].header.stamp
        else:
            kinds.append("updates")
            updates = node.publishers["map_updates"].sent
            held = apply_updates(held, [_update_of(u) for u in updates])
            node.publishers["map_updates"].sent = []
            assert all(u.header.stamp == msgs[i].header.stamp for u in updates)
        np.testing.assert_array_equal(held.data, grid.data)
    assert "updates" in kinds
    node.close()


def test_map_file_is_written_as_scans_come_and_resumed(mapper: Any, tmp_path: Path) -> None:
    node = _start(mapper, tmp_path)
    (on_message,) = node.subscriber.callbacks
    for i in range(3):
        T = pose2d(0.2 * i, 0.0, 0.0)
        msg = laserscan(T, 10.0 + i)
        Buffer.poses[Time.from_msg(msg.header.stamp).nanoseconds] = T
        on_message(msg)
    # another reader sees every scan already, while the node runs (nothing saved on exit)
    with OnlineMap.open(tmp_path / "m.octolgp", read_only=True) as m:
        assert m.n_scans == 3
        centres, prob = m.voxels()
    assert (tmp_path / "m.octolgp.toml").is_file()

    response = node.services["save"](Msg(), Msg())
    assert response.success, response.message
    for suffix in (".bt", ".pgm", ".yaml"):
        assert (tmp_path / f"m{suffix}").is_file()
    node.close()  # as a kill would leave it: the file holds every scan

    again = _start(mapper, tmp_path, resolution=0.3)  # resumes; its own config wins
    assert again.map.n_scans == 3
    assert again.map.config.resolution == 0.1
    assert any("resuming an existing map file" in line for line in again.logger.lines)
    again.timers[1]()  # a resumed map is published at once, stamped 0
    (full,) = again.publishers["map"].sent
    assert (full.header.stamp.sec, full.header.stamp.nanosec) == (0, 0)
    np.testing.assert_array_equal(_grid_of(full).data, map_grid(centres, prob, 0.1).data)
    again.close()
    with pytest.raises(Exception, match="holds a 2D map"):
        _start(mapper, tmp_path, input="points")


def test_3d_map_publishes_octomap_markers_and_projection(mapper: Any, tmp_path: Path) -> None:
    scans = list(
        read_kitti(ROOT / "tests" / "data" / "kitti" / "sequences" / "00", world="velodyne")
    )[:2]
    node = _start(mapper, tmp_path, input="points", projection_min_z=-1.0, projection_max_z=1.0)
    (on_message,) = node.subscriber.callbacks
    for i, scan in enumerate(scans):
        T = pose2d(1.5 * i, 0.0, 0.0)  # the cloud in the sensor frame, posed by tf
        local = (scan.points - scan.origin) @ np.eye(3)
        data = local.astype("<f4").tobytes()
        msg = Msg(
            header=Msg(frame_id="laser", stamp=stamp(50.0 + i)),
            height=1,
            width=len(local),
            fields=[Msg(name=c, offset=4 * k, datatype=7, count=1) for k, c in enumerate("xyz")],
            is_bigendian=False,
            point_step=12,
            row_step=12 * len(local),
            data=data,
            is_dense=True,
        )
        Buffer.poses[Time.from_msg(msg.header.stamp).nanoseconds] = T
        on_message(msg)
    assert node.map.n_scans == 2
    node.timers[1]()
    centres, prob = node.map.voxels()
    (tree,) = node.publishers["octomap_binary"].sent
    expected = octomap_binary(centres, prob, 0.5, node.map.config.tree_depth)
    assert (tree.id, tree.binary, tree.resolution) == ("OcTree", True, 0.5)
    assert tree.data.tobytes() == expected.data
    assert tree.header.stamp == stamp(51.0)
    (markers,) = node.publishers["occupied_cells_vis_array"].sent
    (marker,) = markers.markers
    cubes = occupied_cubes(centres, prob, 0.5)
    assert marker.type == Marker.CUBE_LIST
    assert marker.scale.x == 0.5
    np.testing.assert_allclose([(p.x, p.y, p.z) for p in marker.points], cubes.points)
    np.testing.assert_allclose(
        [(c.r, c.g, c.b, c.a) for c in marker.colors], cubes.colours, atol=1e-7
    )
    (projected,) = node.publishers["projected_map"].sent
    grid = map_grid(centres, prob, 0.5, z_range=(-1.0, 1.0))
    np.testing.assert_array_equal(_grid_of(projected).data, grid.data)
    assert "map" not in node.publishers
    assert node.services["save"](Msg(), Msg()).success
    node.close()


def test_main_spins_until_ctrl_c_and_closes_the_map(
    mapper: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []

    class Executor:
        def __init__(self, num_threads: int) -> None:
            calls.append(f"threads {num_threads}")

        def add_node(self, node: Any) -> None:
            self.node = node

        def spin(self) -> None:
            raise KeyboardInterrupt

        def shutdown(self) -> None:
            calls.append("shutdown")

    monkeypatch.setattr(mapper, "MultiThreadedExecutor", Executor)
    config = tmp_path / "config.toml"
    config.write_text(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2).to_toml())
    Node.overrides = {"map_file": str(tmp_path / "m.octolgp"), "config": str(config)}
    mapper.main([])
    assert calls == ["threads 2", "shutdown"]
    # the map file was closed: another writer can open it
    with OnlineMap.open(tmp_path / "m.octolgp") as m:
        assert m.n_scans == 0
