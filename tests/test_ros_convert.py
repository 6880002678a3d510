"""Scan.from_laserscan / Scan.from_pointcloud2: rosbags' message classes and rclpy look-alikes."""

from __future__ import annotations

import array
import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from octolgp.errors import OctolgpError
from octolgp.io.carmen import NO_RETURN_MARGIN
from octolgp.io.rosbag import RosbagReader
from octolgp.scan import Scan

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
FLOAT32, FLOAT64, UINT16 = 7, 8, 4
LASER = "sensor_msgs/msg/LaserScan"
RANGES = [1.0, math.nan, 2.0, math.inf, 0.05, -math.inf, 7.5, 3.0]  # range_min 0.1, max 5
PI = math.pi


def _load_tool() -> ModuleType:
    """tools/make_rosbag_fixtures.py, for writing a small bag."""
    path = Path(__file__).resolve().parent.parent / "tools" / "make_rosbag_fixtures.py"
    spec = importlib.util.spec_from_file_location("make_rosbag_fixtures", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)
    spec.loader.exec_module(module)
    return module


def _header(sec: int = 12, nanosec: int = 500_000_000, frame: str = "laser") -> Any:
    return T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec, nanosec), frame)


def _laser(ranges: list[float] = RANGES, **kw: Any) -> Any:
    """A rosbags LaserScan: beams from -pi/2 every pi/4 (angle_max agreeing)."""
    r = np.asarray(ranges, dtype=np.float32)
    args: dict[str, Any] = {
        "header": _header(),
        "angle_min": -PI / 2,
        "angle_max": -PI / 2 + (r.size - 1) * PI / 4,
        "angle_increment": PI / 4,
        "time_increment": 0.0,
        "scan_time": 0.0,
        "range_min": 0.1,
        "range_max": 5.0,
        "ranges": r,
        "intensities": np.zeros(0, np.float32),
    }
    args.update(kw)
    return T["sensor_msgs/msg/LaserScan"](**args)


def _rclpy_laser(ranges: list[float] = RANGES) -> SimpleNamespace:
    """What rclpy hands a callback: float32[] as array.array('f'), Time with sec/nanosec."""
    stamp = SimpleNamespace(sec=12, nanosec=500_000_000)
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp, frame_id="laser"),
        angle_min=-PI / 2,
        angle_max=-PI / 2 + (len(ranges) - 1) * PI / 4,
        angle_increment=PI / 4,
        range_min=0.1,
        range_max=5.0,
        ranges=array.array("f", ranges),
    )


def _cloud(
    xyz: np.ndarray,
    *,
    kind: str = "f4",
    bigendian: bool = False,
    height: int = 1,
    pad: int = 0,
    row_pad: int = 0,
    rosbags: bool = True,
) -> Any:
    """A PointCloud2 of ``xyz`` with an intensity (f4) and ring (u2) field after z, then
    ``pad`` bytes per point and ``row_pad`` bytes per row."""
    size = np.dtype(kind).itemsize
    order = ">" if bigendian else "<"
    names = ["ring", "x", "y", "z", "intensity"]
    offsets = [0, 4, 4 + size, 4 + 2 * size, 4 + 3 * size]
    formats = [order + "u2", order + kind, order + kind, order + kind, order + "f4"]
    step = offsets[-1] + 4 + pad
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    n = xyz.shape[0]
    pts = np.zeros(n, dtype)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["ring"] = np.arange(n) % 16
    pts["intensity"] = 100.0
    width = n // height
    rows = pts.view(np.uint8).reshape(height, width * step)
    rows = np.concatenate([rows, np.full((height, row_pad), 0xAB, np.uint8)], axis=1)
    data = np.ascontiguousarray(rows).reshape(-1)
    kinds = [UINT16] + [FLOAT32 if kind == "f4" else FLOAT64] * 3 + [FLOAT32]
    if rosbags:
        field = T["sensor_msgs/msg/PointField"]
        typed = [field(m, o, k, 1) for m, o, k in zip(names, offsets, kinds, strict=True)]
        return T["sensor_msgs/msg/PointCloud2"](
            _header(), height, width, typed, bigendian, step, width * step + row_pad, data, False
        )
    fields = [
        SimpleNamespace(name=m, offset=o, datatype=k, count=1)
        for m, o, k in zip(names, offsets, kinds, strict=True)
    ]
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=500_000_000)),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bigendian,
        point_step=step,
        row_step=width * step + row_pad,
        data=bytes(data),  # rclpy: array.array('B'); bytes as a look-alike
        is_dense=False,
    )


def _expected_2d(pose: tuple[float, float, float]) -> np.ndarray:
    """The laser endpoints: hits at 1, 2, 3 m, no-returns (inf, 7.5) at 5 m; rest dropped."""
    keep = [(0, 1.0), (2, 2.0), (3, 5.0), (6, 5.0), (7, 3.0)]
    x, y, th = pose
    return np.array(
        [
            [x + r * math.cos(th - PI / 2 + i * PI / 4), y + r * math.sin(th - PI / 2 + i * PI / 4)]
            for i, r in keep
        ]
    )


# --- LaserScan ---------------------------------------------------------------------------


@pytest.mark.parametrize("make", [_laser, _rclpy_laser], ids=["rosbags", "rclpy-like"])
def test_laserscan_beams_no_returns_and_stamp(make: Any) -> None:
    pose = (1.0, -2.0, 0.3)
    scan = Scan.from_laserscan(make(), pose)
    assert scan.dim == 2
    np.testing.assert_allclose(scan.origin, [1.0, -2.0])
    np.testing.assert_allclose(scan.points, _expected_2d(pose), atol=1e-6)
    assert scan.max_range == pytest.approx(5.0 - NO_RETURN_MARGIN)
    assert scan.stamp == pytest.approx(12.5)
    lengths = np.linalg.norm(scan.points - scan.origin, axis=1)
    assert int((lengths >= scan.max_range).sum()) == 2


def test_laserscan_pose_forms_agree() -> None:
    x, y, th = 0.5, 4.0, -2.0
    c, s = math.cos(th), math.sin(th)
    planar = Scan.from_laserscan(_laser(), (x, y, th))
    matrix3 = Scan.from_laserscan(_laser(), np.array([[c, -s, x], [s, c, y], [0, 0, 1]]))
    np.testing.assert_allclose(matrix3.points, planar.points, atol=1e-12)
    # 4x4: a 3D scan in the laser's plane; here the plane is z = 1.5, yawed by th
    T4 = np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, 1.5], [0, 0, 0, 1]])
    spatial = Scan.from_laserscan(_laser(), T4)
    assert spatial.dim == 3
    np.testing.assert_allclose(spatial.origin, [x, y, 1.5])
    np.testing.assert_allclose(spatial.points[:, :2], planar.points, atol=1e-9)
    np.testing.assert_allclose(spatial.points[:, 2], 1.5)
    assert spatial.max_range == planar.max_range
    # a laser on its side: beams sweep the world's xz plane
    on_side = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]])
    upright = Scan.from_laserscan(_laser(), on_side)
    np.testing.assert_allclose(upright.points[:, 1], 0.0, atol=1e-12)


def test_laserscan_max_range_and_stamp_override() -> None:
    scan = Scan.from_laserscan(_laser(), (0, 0, 0), max_range=2.5, stamp=99.0)
    assert scan.max_range == pytest.approx(2.5 - NO_RETURN_MARGIN)
    assert scan.stamp == 99.0
    lengths = np.linalg.norm(scan.points, axis=1)
    np.testing.assert_allclose(np.sort(lengths), [1.0, 2.0, 2.5, 2.5, 2.5], atol=1e-6)
    bare = SimpleNamespace(**{k: v for k, v in vars(_rclpy_laser()).items() if k != "header"})
    assert Scan.from_laserscan(bare, (0, 0, 0)).stamp is None


def test_laserscan_matches_the_bag_reader(tmp_path: Path) -> None:
    """One decoder: a bag read without a pose source gives the converter's scans exactly."""
    fx = _load_tool()
    msgs = [("/scan", LASER, (i + 1) * 10**9, _laser()) for i in range(3)]
    fx.write_bag(tmp_path / "b", msgs, ros1=False)
    got = list(RosbagReader(tmp_path / "b"))
    wire = TS.deserialize_cdr(TS.serialize_cdr(_laser(), LASER), LASER)  # float32 angles
    want = Scan.from_laserscan(wire, (0.0, 0.0, 0.0))
    assert len(got) == 3
    for scan in got:
        np.testing.assert_array_equal(scan.points, want.points)
        assert scan.max_range == want.max_range


# --- PointCloud2 --------------------------------------------------------------------------

XYZ = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0], [4.0, -3.0, 1.0], [0.0, 0.0, 9.0]])


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"kind": "f8"},
        {"bigendian": True},
        {"bigendian": True, "kind": "f8", "pad": 5},
        {"height": 2, "row_pad": 7},
        {"rosbags": False},
        {"rosbags": False, "bigendian": True, "height": 2, "row_pad": 3},
    ],
    ids=["f4", "f8", "big-endian", "big-f8-padded", "organised-row-step", "bytes", "bytes-all"],
)
def test_pointcloud2_layouts(kw: dict[str, Any]) -> None:
    T4 = np.eye(4)
    T4[:3, 3] = [10.0, 20.0, 1.0]
    scan = Scan.from_pointcloud2(_cloud(XYZ, **kw), T4)
    assert scan.dim == 3
    np.testing.assert_allclose(scan.origin, [10.0, 20.0, 1.0])
    np.testing.assert_allclose(scan.points, XYZ + np.array([10.0, 20.0, 1.0]), atol=1e-6)
    assert scan.stamp == pytest.approx(12.5)
    assert scan.max_range is None


def test_pointcloud2_drops_nan_holes_and_takes_planar_pose() -> None:
    xyz = np.vstack([XYZ, [[math.nan, math.nan, math.nan], [1.0, math.inf, 0.0]]])
    msg = _cloud(xyz, height=2)
    msg.data = array.array("B", bytes(msg.data))  # as rclpy hands uint8[]
    scan = Scan.from_pointcloud2(msg, (1.0, 0.0, PI / 2), max_range=8.0)
    rotated = np.stack([1.0 - XYZ[:, 1], XYZ[:, 0], XYZ[:, 2]], axis=1)
    np.testing.assert_allclose(scan.points, rotated, atol=1e-6)
    np.testing.assert_allclose(scan.origin, [1.0, 0.0, 0.0])
    assert scan.max_range == 8.0


# --- malformed messages and poses -------------------------------------------------------------


def _mutated(make: Any, **changes: Any) -> Any:
    msg = make()
    for name, value in changes.items():
        setattr(msg, name, value)
    return msg


def _no_x_cloud() -> Any:
    msg = _cloud(XYZ)
    msg.fields = [f for f in msg.fields if f.name != "x"]
    return msg


def _uint_x_cloud() -> Any:
    msg = _cloud(XYZ)
    msg.fields[1].datatype = UINT16
    return msg


LASER_CASES = [
    ({"angle_increment": 0.0}, r"angle_increment must be > 0"),
    ({"angle_min": math.nan}, r"NaN or inf in angle_min"),
    ({"range_min": 6.0}, r"range_min/range_max"),
    ({"range_max": math.inf}, r"range_min/range_max"),
    ({"ranges": np.zeros((2, 2), np.float32)}, r"ranges must be 1D"),
    ({"ranges": ["a", "b"]}, r"ranges must be a sequence of numbers"),
    ({"range_min": "far"}, r"range_min must be a number"),
]


@pytest.mark.parametrize(("changes", "why"), LASER_CASES)
def test_malformed_laserscan_names_the_field(changes: dict[str, Any], why: str) -> None:
    for make in (_laser, _rclpy_laser):
        with pytest.raises(OctolgpError, match=r"^Scan\.from_laserscan: " + why):
            Scan.from_laserscan(_mutated(make, **changes), (0, 0, 0))


def test_laserscan_missing_field_and_empty_scan() -> None:
    msg = _rclpy_laser()
    del msg.ranges
    with pytest.raises(OctolgpError, match=r"from_laserscan: ranges: missing"):
        Scan.from_laserscan(msg, (0, 0, 0))
    with pytest.raises(OctolgpError, match="no beam left"):
        Scan.from_laserscan(_laser([math.nan, 0.01, -math.inf]), (0, 0, 0))


CLOUD_CASES = [
    (
        lambda: _mutated(lambda: _cloud(XYZ), point_step=8),
        r"field 'y' at offset 8 overruns point_step 8",
    ),
    (lambda: _mutated(lambda: _cloud(XYZ), point_step=0), r"point_step must be > 0"),
    (_no_x_cloud, r"no x field \(fields: 'ring', 'y', 'z', 'intensity'\)"),
    (_uint_x_cloud, r"field 'x' has datatype 4, not FLOAT32/64"),
    (lambda: _mutated(lambda: _cloud(XYZ), data=np.zeros(40, np.uint8)), r"data has 40 bytes"),
    (lambda: _mutated(lambda: _cloud(XYZ, rosbags=False), data=b"\x00" * 7), r"data has 7 bytes"),
    (lambda: _mutated(lambda: _cloud(XYZ, rosbags=False), data=[1, 300]), r"data holds values"),
    (lambda: _mutated(lambda: _cloud(XYZ, rosbags=False), data=1.5), r"data is not a byte"),
    (lambda: _mutated(lambda: _cloud(XYZ, rosbags=False), width=-1), r"width/height"),
    (lambda: _mutated(lambda: _cloud(XYZ, rosbags=False), fields=None), r"fields"),
]


@pytest.mark.parametrize(("make", "why"), CLOUD_CASES)
def test_malformed_pointcloud2_names_the_field(make: Any, why: str) -> None:
    with pytest.raises(OctolgpError, match=r"^Scan\.from_pointcloud2: .*" + why):
        Scan.from_pointcloud2(make(), np.eye(4))


def test_pointcloud2_of_only_nans_is_refused() -> None:
    msg = _cloud(np.full((2, 3), math.nan))
    with pytest.raises(OctolgpError, match="no finite point"):
        Scan.from_pointcloud2(msg, np.eye(4))


@pytest.mark.parametrize(
    ("pose", "why"),
    [
        ((0.0, math.nan, 0.0), "pose contains NaN or inf"),
        (np.diag([1.0, 1.0, 1.0, math.inf]), "pose contains NaN or inf"),
        ((1.0, 2.0), r"pose must be \(x, y, theta\) or a 3x3 / 4x4"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "pose is not a rigid transform"),
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "pose is not a rigid transform"),
        ("north", "pose must be numbers"),
    ],
)
def test_bad_pose_is_refused(pose: Any, why: str) -> None:
    with pytest.raises(OctolgpError, match=r"^Scan\.from_pointcloud2: " + why):
        Scan.from_pointcloud2(_cloud(XYZ), pose)
    with pytest.raises(OctolgpError, match=r"^Scan\.from_laserscan: " + why):
        Scan.from_laserscan(_laser(), pose)


def test_cloud_refuses_a_3x3_pose() -> None:
    with pytest.raises(OctolgpError, match="PointCloud2 needs a 4x4"):
        Scan.from_pointcloud2(_cloud(XYZ), np.eye(3))
