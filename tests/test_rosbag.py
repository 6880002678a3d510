"""ROS bag reader: real Intel scans and 3DTK points in ROS 1/2 bags, tf, malformed messages."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io.carmen import CarmenReader
from octolgp.io.rosbag import NO_RETURN_MARGIN, RosbagReader, TfBuffer, looks_like_rosbag
from octolgp.scan import Scan

HERE = Path(__file__).resolve().parent
DATA = HERE / "data" / "rosbag"
INTEL_LOG = HERE / "data" / "intel_first20.log"


def _load_tool() -> ModuleType:
    """The fixture script, for its message builders and the truth it derived the bags from."""
    path = HERE.parent / "tools" / "make_rosbag_fixtures.py"
    spec = importlib.util.spec_from_file_location("make_rosbag_fixtures", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


fx = _load_tool()
NS = fx.NS
LASER = "sensor_msgs/msg/LaserScan"
CLOUD = "sensor_msgs/msg/PointCloud2"
TF = "tf2_msgs/msg/TFMessage"
Message = tuple[str, str, int, Any]  # topic, type, bag time (ns), message


def _carmen() -> list[Scan]:
    return list(CarmenReader(INTEL_LOG))


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to 2D or 3D points (2D: z = 0)."""
    p = np.zeros((points.shape[0], 3))
    p[:, : points.shape[1]] = points
    out: np.ndarray = (p @ T[:3, :3].T + T[:3, 3])[:, : points.shape[1]]
    return out


def _assert_same_scans(got: list[Scan], want: list[Scan], tol: float = 1e-5) -> None:
    assert len(got) == len(want) > 0
    for a, b in zip(got, want, strict=True):
        assert a.dim == b.dim == 2
        np.testing.assert_allclose(a.origin, b.origin, atol=tol, rtol=0)
        np.testing.assert_allclose(a.points, b.points, atol=tol, rtol=0)
        assert a.max_range == pytest.approx(b.max_range, abs=tol)
        assert a.stamp == pytest.approx(b.stamp, abs=1e-9)


def _no_returns(scan: Scan) -> int:
    return int(
        np.count_nonzero(np.linalg.norm(scan.points - scan.origin, axis=1) >= scan.max_range)
    )


# --- the fixtures: truths from the data they were made of ------------------------------------


def test_looks_like_rosbag(tmp_path: Path) -> None:
    assert looks_like_rosbag(DATA / "intel.bag")
    assert looks_like_rosbag(DATA / "intel_ros2")
    assert looks_like_rosbag(DATA / "intel_ros2" / "intel_ros2.db3")
    assert looks_like_rosbag(DATA / "intel_ros2" / "metadata.yaml")
    assert looks_like_rosbag(DATA / "cloud_ros2" / "cloud_ros2.mcap")
    assert not looks_like_rosbag(INTEL_LOG)
    assert not looks_like_rosbag(HERE / "data" / "3dtk")
    assert not looks_like_rosbag(tmp_path / "missing.bag")
    (tmp_path / "empty.bag").write_bytes(b"")
    assert not looks_like_rosbag(tmp_path / "empty.bag")


def test_ros1_tf_bag_equals_carmen_scans() -> None:
    reader = RosbagReader(DATA / "intel.bag")
    assert (reader.scan_topic, reader.scan_type) == ("/scan", LASER)
    assert reader.pose_source == "tf"
    assert reader.frame == "map"
    scans = list(reader)
    want = _carmen()
    _assert_same_scans(scans, want)
    # The log's 81.83 m readings are no-returns in both, beam for beam.
    assert [_no_returns(s) for s in scans] == [_no_returns(s) for s in want]
    assert sum(_no_returns(s) for s in scans) > 0
    assert reader.skipped == reader.unposed == reader.empty == 0


def test_ros1_tf_bag_in_the_odom_frame() -> None:
    """frame='odom' drops the map -> odom link: the scans move by inv(T_map_odom)."""
    scans = list(RosbagReader(DATA / "intel.bag", frame="odom"))
    T = np.linalg.inv(fx.T_MAP_ODOM)
    for got, ref in zip(scans, _carmen(), strict=True):
        np.testing.assert_allclose(got.origin, _apply(T, ref.origin[None])[0], atol=1e-5)
        np.testing.assert_allclose(got.points, _apply(T, ref.points), atol=1e-5)


@pytest.mark.parametrize(
    "name", ["intel_ros2", "intel_ros2/intel_ros2.db3", "intel_ros2/metadata.yaml"]
)
def test_ros2_odometry_bag_equals_carmen_scans(name: str) -> None:
    reader = RosbagReader(DATA / name)
    assert reader.pose_source == "/odom"
    assert reader.frame is None
    _assert_same_scans(list(reader), _carmen())


@pytest.mark.parametrize("name", ["cloud_ros2", "cloud_ros2/cloud_ros2.mcap"])
def test_pointcloud2_bag_equals_source_points(name: str) -> None:
    reader = RosbagReader(DATA / name)
    assert (reader.scan_topic, reader.scan_type, reader.pose_source) == ("/points", CLOUD, "/pose")
    scans = list(reader)
    truth = fx.cloud_scans()
    assert len(scans) == len(truth) == 2
    for scan, (stamp, T, world), tol in zip(scans, truth, (1e-4, 1e-9), strict=True):
        assert scan.dim == 3
        assert scan.max_range is None
        assert scan.stamp == pytest.approx(stamp / NS)
        np.testing.assert_allclose(scan.origin, T[:3, 3], atol=1e-9)
        # NaN points dropped, order kept; cloud 0 is float32 (about 1e-6 relative).
        np.testing.assert_allclose(scan.points, world, atol=tol, rtol=0)
    with_max = list(RosbagReader(DATA / name, max_range=25.0))
    assert all(s.max_range == 25.0 for s in with_max)


# --- tf composition -----------------------------------------------------------------------


def test_tf_buffer_composes_chains_by_hand() -> None:
    P = fx.planar
    buf = TfBuffer()
    T_bl = P(0.2, 0.1, 0.3, z=0.4)
    buf.add("base", "laser", 0, T_bl, static=True)
    buf.add("map", "odom", 1 * NS, P(1.0, 0.0, 0.0), static=False)
    buf.add("map", "odom", 2 * NS, P(2.0, 0.0, 0.0), static=False)
    buf.add("odom", "base", 1 * NS, P(0.0, 1.0, math.pi / 2), static=False)
    buf.add("odom", "base", 3 * NS, P(0.0, 3.0, math.pi), static=False)
    # At 2.5 s: map->odom of 2 s, odom->base of 1 s, base->laser static.
    got = buf.lookup("map", "laser", int(2.5 * NS))
    assert got is not None
    # Hand computation: base at (2, 1) facing +y; laser 0.2 ahead (+y), 0.1 left (-x), 0.4 up.
    np.testing.assert_allclose(got[:3, 3], [2.0 - 0.1, 1.0 + 0.2, 0.4], atol=1e-12)
    yaw = math.atan2(got[1, 0], got[0, 0])
    assert yaw == pytest.approx(math.pi / 2 + 0.3)
    np.testing.assert_allclose(got, P(2.0, 0.0, 0.0) @ P(0.0, 1.0, math.pi / 2) @ T_bl, atol=1e-12)
    # Through the common ancestor, and inverted.
    odom_laser = buf.lookup("odom", "laser", 4 * NS)
    assert odom_laser is not None
    np.testing.assert_allclose(odom_laser, P(0.0, 3.0, math.pi) @ T_bl, atol=1e-12)
    inv = buf.lookup("laser", "map", int(2.5 * NS))
    assert inv is not None
    np.testing.assert_allclose(inv @ got, np.eye(4), atol=1e-12)
    sibling = buf.lookup("laser", "odom", 4 * NS)
    assert sibling is not None
    np.testing.assert_allclose(sibling @ odom_laser, np.eye(4), atol=1e-12)
    # Before the first dynamic transform, or between unconnected frames: none.
    assert buf.lookup("map", "laser", NS // 2) is None
    assert buf.lookup("map", "camera", 2 * NS) is None
    assert buf.lookup("base", "laser", 0, static_only=True) is not None
    assert buf.frames() == {"map", "odom", "base", "laser"}


def test_tf_buffer_keeps_a_bounded_history() -> None:
    buf = TfBuffer(horizon=10.0)
    for i in range(1000):  # 100 s at 10 Hz
        buf.add("odom", "base", i * NS // 10, fx.planar(i, 0, 0), static=False)
    history = buf.dynamic["base"][1]
    assert len(history.stamps) <= 102
    found = buf.lookup("odom", "base", 95 * NS + 1)
    assert found is not None
    assert found[0, 3] == 950


def _scan_bag(tmp_path: Path, messages: list[Message], name: str = "b", **kw: Any) -> Path:
    path = tmp_path / name
    fx.write_bag(path, messages, ros1=False, **kw)
    return path


def _beam(stamp: int, frame: str = "laser", r: float = 2.0) -> Message:
    """One beam straight ahead of the laser."""
    return (
        "/scan",
        LASER,
        stamp,
        fx.laser_scan(fx.ROS2, stamp, frame, [r], angle_min=0.0, range_max=20.0),
    )


def test_tf_chain_from_a_bag_with_static_offset_and_3d_pose(tmp_path: Path) -> None:
    P, R = fx.planar, fx.ROS2
    tilt = np.eye(4)  # base tilted 0.2 rad about x: the planar projection keeps x, y, yaw
    tilt[1:3, 1:3] = [[math.cos(0.2), -math.sin(0.2)], [math.sin(0.2), math.cos(0.2)]]
    static = [("base_link", "laser", 0, P(0.5, 0.0, math.pi / 2))]
    msgs = [
        ("/tf_static", TF, 0, fx.tf_message(R, static)),
        ("/tf", TF, 1 * NS, fx.tf_message(R, [("odom", "base_link", 1 * NS, P(1.0, 2.0, 0.0))])),
        _beam(1 * NS + 5),
        (
            "/tf",
            TF,
            2 * NS,
            fx.tf_message(R, [("odom", "base_link", 2 * NS, P(3.0, 2.0, math.pi) @ tilt)]),
        ),
        _beam(3 * NS),
    ]
    reader = RosbagReader(_scan_bag(tmp_path, msgs))
    assert reader.frame == "odom"  # no map: odom
    s1, s2 = list(reader)
    # Hand computation: laser at base + 0.5 along base x, facing base +y; beam 2 m ahead.
    np.testing.assert_allclose(s1.origin, [1.5, 2.0], atol=1e-6)
    np.testing.assert_allclose(s1.points, [[1.5, 4.0]], atol=1e-6)
    np.testing.assert_allclose(s2.origin, [2.5, 2.0], atol=1e-6)
    # Tilted about x then yawed by pi: laser facing -y, rotated by the tilt; yaw stays -pi/2.
    assert s2.points[0, 0] == pytest.approx(2.5, abs=1e-6)
    assert s2.points[0, 1] == pytest.approx(0.0, abs=1e-6)
    assert s2.stamp == 3.0


def test_default_frame_is_the_tf_root(tmp_path: Path) -> None:
    msgs = [
        ("/tf", TF, NS, fx.tf_message(fx.ROS2, [("world", "laser", NS, fx.planar(1, 1, 0))])),
        _beam(2 * NS),
    ]
    reader = RosbagReader(_scan_bag(tmp_path, msgs))
    assert reader.frame == "world"
    np.testing.assert_allclose(next(reader).points, [[3.0, 1.0]], atol=1e-6)


def test_unposed_scans_are_skipped_and_counted(tmp_path: Path) -> None:
    tf = fx.tf_message(fx.ROS2, [("odom", "laser", 2 * NS, fx.planar(1, 0, 0))])
    msgs = [_beam(1 * NS), ("/tf", TF, 2 * NS, tf), _beam(3 * NS)]
    reader = RosbagReader(_scan_bag(tmp_path, msgs))
    scans = list(reader)
    assert len(scans) == 1
    assert reader.unposed == 1
    # A frame that never connects: nothing could be posed, which is an error.
    lost = [("/tf", TF, 2 * NS, tf), _beam(3 * NS, frame="camera")]
    with pytest.raises(OctolgpError, match=r"none of 1 scans.*'odom' to 'camera'"):
        list(RosbagReader(_scan_bag(tmp_path, lost, name="c")))


def test_pose_topics_and_identity(tmp_path: Path) -> None:
    R = fx.ROS2
    pose = fx.pose_stamped(R, NS, "map", fx.planar(1.0, 0.0, math.pi / 2))
    odom = fx.odometry(R, NS, "odom", "base", fx.planar(0.0, 0.0, 0.0))
    msgs = [
        ("/pose", "geometry_msgs/msg/PoseStamped", NS, pose),
        ("/odom", "nav_msgs/msg/Odometry", NS, odom),
        _beam(2 * NS),
    ]
    path = _scan_bag(tmp_path, msgs)
    with pytest.raises(OctolgpError, match=r"several pose topics.*/odom, /pose"):
        RosbagReader(path)
    scan = next(RosbagReader(path, pose_topic="/pose"))
    np.testing.assert_allclose(scan.points, [[1.0, 2.0]], atol=1e-6)
    with pytest.raises(OctolgpError, match="not a tf, PoseStamped"):
        RosbagReader(path, pose_topic="/scan")
    # No pose source: the scan's own frame.
    alone = RosbagReader(_scan_bag(tmp_path, [_beam(NS)], name="c"))
    assert alone.pose_source is None
    np.testing.assert_allclose(next(alone).points, [[2.0, 0.0]], atol=1e-6)


# --- decoding -------------------------------------------------------------------------------


def test_laser_scan_special_ranges(tmp_path: Path) -> None:
    ranges = [1.0, np.nan, -np.inf, np.inf, 0.05, 30.0, 5.0]
    msg = fx.laser_scan(
        fx.ROS2,
        NS,
        "laser",
        ranges,
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.1,
        range_max=20.0,
    )
    path = _scan_bag(tmp_path, [("/scan", LASER, NS, msg)])
    scan = next(RosbagReader(path))
    # NaN, -inf and the short reading are dropped; inf and 30 (>= range_max) are no-returns.
    kept = np.array([0, 3, 5, 6])
    lengths = np.array([1.0, 20.0, 20.0, 5.0])
    want = lengths[:, None] * np.stack([np.cos(0.1 * kept), np.sin(0.1 * kept)], axis=1)
    np.testing.assert_allclose(scan.points, want, atol=1e-5)
    assert scan.max_range == pytest.approx(20.0 - NO_RETURN_MARGIN)
    capped = next(RosbagReader(path, max_range=4.0))
    np.testing.assert_allclose(
        np.linalg.norm(capped.points, axis=1), [1.0, 4.0, 4.0, 4.0], atol=1e-6
    )
    assert capped.max_range == pytest.approx(4.0 - NO_RETURN_MARGIN)
    # A scan with nothing left is skipped and counted.
    void = fx.laser_scan(fx.ROS2, NS, "laser", [np.nan, 0.0], range_min=0.1, range_max=20.0)
    reader = RosbagReader(_scan_bag(tmp_path, [("/scan", LASER, NS, void)], name="c"))
    assert list(reader) == []
    assert reader.empty == 1


def test_pointcloud2_layouts(tmp_path: Path) -> None:
    R = fx.ROS2
    xyz = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [-4.0, 5.5, 0.25], [7.0, 8.0, 9.0]])
    plain = fx.point_cloud(R, NS, "s", xyz, kind="f8", bigendian=True, extra=[("t", 24, "u4")])
    padded = fx.point_cloud(R, 2 * NS, "s", xyz, kind="f4", height=2, point_step=16)
    data = np.asarray(padded.data).reshape(2, 32)
    padded.data = np.concatenate([data, np.full((2, 8), 255, np.uint8)], axis=1).reshape(-1)
    padded.row_step = 40
    msgs = [("/points", CLOUD, NS, plain), ("/points", CLOUD, 2 * NS, padded)]
    a, b = list(RosbagReader(_scan_bag(tmp_path, msgs)))
    np.testing.assert_array_equal(a.points, xyz[[0, 2, 3]])
    np.testing.assert_allclose(b.points, xyz[[0, 2, 3]], atol=1e-6)
    np.testing.assert_array_equal(a.origin, [0.0, 0.0, 0.0])


def test_scan_topic_auto_detection_and_choice(tmp_path: Path) -> None:
    cloud = fx.point_cloud(fx.ROS2, NS, "laser", np.ones((3, 3)))
    path = _scan_bag(tmp_path, [_beam(NS), ("/points", CLOUD, NS, cloud)])
    with pytest.raises(
        OctolgpError, match=r"several.*/points \(PointCloud2\), /scan \(LaserScan\)"
    ):
        RosbagReader(path)
    assert next(RosbagReader(path, scan_topic="/points")).dim == 3
    assert next(RosbagReader(path, scan_topic="/scan")).dim == 2
    with pytest.raises(OctolgpError, match="'/nope' is not a LaserScan"):
        RosbagReader(path, scan_topic="/nope")
    odom = fx.odometry(fx.ROS2, NS, "odom", "base", np.eye(4))
    with pytest.raises(OctolgpError, match="no LaserScan/PointCloud2 topics"):
        RosbagReader(_scan_bag(tmp_path, [("/odom", "nav_msgs/msg/Odometry", NS, odom)], name="c"))


def test_malformed_messages_name_topic_and_index(tmp_path: Path) -> None:
    R = fx.ROS2

    def laser(t: int, **kw: Any) -> Message:
        return ("/scan", LASER, t, fx.laser_scan(R, t, "laser", [1.0, 2.0], range_max=20.0, **kw))

    msgs = [
        laser(1),
        laser(2, angle_increment=0.0),
        laser(3, angle_min=math.nan),
        laser(4, angle_increment=-0.1),
        laser(5),
    ]
    path = _scan_bag(tmp_path, msgs)
    with pytest.raises(
        OctolgpError, match=r"b: topic '/scan' message 1: angle_increment must be > 0"
    ):
        list(RosbagReader(path))
    reader = RosbagReader(path, skip_bad=True)
    assert len(list(reader)) == 2
    assert reader.skipped == 3
    assert reader.bad_messages == [("/scan", 1), ("/scan", 2), ("/scan", 3)]

    good = np.ones((4, 3))
    bad = {
        "data has 40 bytes, width\\*height\\*point_step = 48": fx.point_cloud(
            R, 2, "s", good, data=np.zeros(40, np.uint8)
        ),
        "no z field": fx.point_cloud(R, 2, "s", good[:, :2], fields=("x", "y")),
        "field 'x' has datatype 6, not FLOAT32/64": fx.point_cloud(R, 2, "s", good, kind="u4"),
        "field .z. at offset 8 overruns point_step 8": fx.point_cloud(R, 2, "s", good),
    }
    bad["field .z. at offset 8 overruns point_step 8"].point_step = 8
    for i, (why, cloud) in enumerate(bad.items()):
        msgs = [
            ("/points", CLOUD, 1, fx.point_cloud(R, 1, "s", good)),
            ("/points", CLOUD, 2, cloud),
        ]
        path = _scan_bag(tmp_path, msgs, name=f"c{i}")
        with pytest.raises(OctolgpError, match=f"topic '/points' message 1: {why}"):
            list(RosbagReader(path))
    msgs = [("/points", CLOUD, i + 1, c) for i, c in enumerate(bad.values())]
    reader = RosbagReader(_scan_bag(tmp_path, msgs, name="call"), skip_bad=True)
    assert list(reader) == []
    assert reader.skipped == 4
    assert reader.bad_messages == [("/points", i) for i in range(4)]

    bad_tf = fx.tf_message(R, [("odom", "laser", 1, np.eye(4))])
    bad_tf.transforms[0].transform.rotation = R.types["geometry_msgs/msg/Quaternion"](0, 0, 0, 0)
    ok_tf = fx.tf_message(R, [("odom", "laser", 1, np.eye(4))])
    path = _scan_bag(tmp_path, [("/tf", TF, 1, ok_tf), ("/tf", TF, 2, bad_tf), laser(3)], name="d")
    with pytest.raises(OctolgpError, match="topic '/tf' message 1: zero quaternion"):
        list(RosbagReader(path))
    reader = RosbagReader(path, skip_bad=True)
    assert len(list(reader)) == 1
    assert reader.skipped == 1


def test_garbage_empty_and_missing_files(tmp_path: Path) -> None:
    with pytest.raises(MapFileNotFound):
        RosbagReader(tmp_path / "missing.bag")
    (tmp_path / "empty.bag").write_bytes(b"")
    (tmp_path / "garbage.bag").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "cut.bag").write_bytes((DATA / "intel.bag").read_bytes()[:200])
    (tmp_path / "fake.db3").write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    (tmp_path / "fake.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x01" * 100)
    (tmp_path / "nometa").mkdir()
    for name in ("empty.bag", "garbage.bag", "cut.bag", "fake.db3", "fake.mcap", "nometa"):
        with pytest.raises(OctolgpError, match=r"ROS bag|not a ROS bag"):
            list(RosbagReader(tmp_path / name))
    with pytest.raises(OctolgpError, match="not a ROS bag"):
        RosbagReader(INTEL_LOG)
    with pytest.raises(OctolgpError, match="max_range"):
        RosbagReader(DATA / "intel.bag", max_range=-1.0)


def test_stream_is_lazy_and_closable() -> None:
    reader = RosbagReader(DATA / "intel.bag")
    first = next(reader)
    assert first.stamp == pytest.approx(_carmen()[0].stamp)
    reader.close()
    with pytest.raises(StopIteration):
        next(reader)
