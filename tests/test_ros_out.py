"""ROS 2 output without ROS: grid messages and updates, the OctoMap payload, markers, the tf
wait queue, and the octolgp_ros package's files."""

from __future__ import annotations

import ast
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.errors import OctolgpError
from octolgp.export.nav2 import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    TrinaryGrid,
    cell_states,
    trinary_grid,
    write_nav2_map,
)
from octolgp.export.nav2_read import read_nav2_map
from octolgp.export.octomap import bt_data, write_bt
from octolgp.export.octomap_read import read_bt_header
from octolgp.export.ros_out import (
    GridMessage,
    GridSync,
    GridUpdate,
    apply_updates,
    clip_z_range,
    grid_message,
    grid_updates,
    height_colours,
    map_grid,
    occupied_cubes,
    octomap_binary,
    trinary_voxels,
)
from octolgp.geometry.keys import coord_to_key, key_to_coord
from octolgp.io import read_kitti
from octolgp.ros_tf import TfWaitQueue

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data"
PACKAGE = ROOT / "examples" / "ros2" / "octolgp_ros"
NODE = PACKAGE / "octolgp_ros" / "mapper.py"
HP2 = Hyperparameters(
    length_scale=1.2, signal_variance=3.8, noise_variance=0.006, alpha=4.5, beta=1.0
)
HP3 = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=3.0)
RES = 0.1
STATES = np.array([UNKNOWN, FREE, OCCUPIED], dtype=np.int8)


@pytest.fixture(scope="module")
def intel_scans() -> list[Any]:
    return list(load_scans(DATA / "intel_first20.log"))[:6]


@pytest.fixture(scope="module")
def map2d(tmp_path_factory: pytest.TempPathFactory, intel_scans: list[Any]) -> Path:
    """A 2D map file of the first 3 Intel scans at 0.1 m."""
    path = tmp_path_factory.mktemp("ros") / "intel.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=RES, hyperparameters=HP2), path=path) as m:
        m.insert_scans(intel_scans[:3])
    return path


@pytest.fixture(scope="module")
def map3d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3D map file of two scans of the KITTI fixture at 0.5 m (z up)."""
    path = tmp_path_factory.mktemp("ros") / "street.octolgp"
    scans = list(read_kitti(DATA / "kitti" / "sequences" / "00", world="velodyne"))[:2]
    with OnlineMap(MapConfig(dim=3, resolution=0.5, hyperparameters=HP3), path=path) as m:
        m.insert_scans(scans)
    return path


def _voxels(path: Path) -> tuple[np.ndarray, np.ndarray, float, int]:
    with OnlineMap.open(path, read_only=True) as m:
        centres, prob = m.voxels()
        return centres, prob, m.config.resolution, m.config.tree_depth


def _random_grid(rng: np.random.Generator, shape: tuple[int, int]) -> TrinaryGrid:
    return TrinaryGrid(STATES[rng.integers(0, 3, shape)], (-1.0, 2.0), 0.05)


# ---------------------------------------------------------------- OccupancyGrid


def test_grid_message_is_row_major_from_the_lower_left() -> None:
    data = np.array([[0, 100, -1], [-1, -1, 0]], dtype=np.int8)  # row 0: smallest y
    msg = grid_message(TrinaryGrid(data, (1.5, -2.0), 0.25))
    assert (msg.width, msg.height, msg.resolution, msg.origin) == (3, 2, 0.25, (1.5, -2.0))
    assert msg.data.dtype == np.int8
    np.testing.assert_array_equal(msg.data, [0, 100, -1, -1, -1, 0])
    for row in range(2):
        for col in range(3):
            assert msg.data[row * msg.width + col] == data[row, col]
    with pytest.raises(ValueError, match="read-only"):
        msg.data[0] = 1
    with pytest.raises(OctolgpError, match=r"^grid must be a TrinaryGrid"):
        grid_message(data)  # type: ignore[arg-type]


@pytest.mark.parametrize("dim", [2, 3])
def test_published_grid_is_the_pgm_as_map_server_loads_it(
    map2d: Path, map3d: Path, tmp_path: Path, dim: int
) -> None:
    """100 % of the cells the PGM makes occupied are lethal (100) in the published grid, and
    every other cell has the PGM's state too; the padding around them is unknown."""
    centres, prob, res, _ = _voxels(map2d if dim == 2 else map3d)
    band = (-math.inf, math.inf) if dim == 2 else (-1.0, 1.0)
    option: dict[str, Any] = {} if dim == 2 else {"z_range": band}
    msg = grid_message(map_grid(centres, prob, res, tile=16, **option))
    back = read_nav2_map(write_nav2_map(tmp_path / "m.pgm", centres, prob, res, **option))
    assert msg.width % 16 == 0
    assert msg.height % 16 == 0
    for v in msg.origin:
        assert v / (16 * res) == pytest.approx(round(v / (16 * res)))
    # every PGM pixel centre, looked up in the published message as a subscriber would
    ny, nx = back.cells.shape
    iy, ix = np.mgrid[0:ny, 0:nx]
    x = back.origin[0] + (ix + 0.5) * back.resolution
    y = back.origin[1] + (iy + 0.5) * back.resolution
    col = np.floor((x - msg.origin[0]) / msg.resolution).astype(int)
    row = np.floor((y - msg.origin[1]) / msg.resolution).astype(int)
    published = msg.data[row * msg.width + col]
    occupied = back.cells == OCCUPIED
    assert occupied.sum() > 10
    assert np.all(published[occupied] == 100)  # nav2's static layer: lethal at 100
    np.testing.assert_array_equal(published, back.cells)
    assert (msg.data == OCCUPIED).sum() == occupied.sum()  # the padding is unknown
    assert (msg.data == FREE).sum() == (back.cells == FREE).sum()


def test_projection_with_infinite_ends_is_the_whole_height(map3d: Path) -> None:
    centres, prob, res, _ = _voxels(map3d)
    lo, hi = float(centres[:, 2].min()), float(centres[:, 2].max())
    assert clip_z_range(centres, (-math.inf, math.inf)) == (lo, hi)
    assert clip_z_range(centres, (0.0, math.inf)) == (0.0, hi)
    assert clip_z_range(centres, (-math.inf, lo - 5.0)) == (lo - 5.0, lo - 5.0)
    whole = map_grid(centres, prob, res)
    inner = trinary_grid(centres, prob, res, z_range=(lo, hi))
    assert (whole.data == OCCUPIED).sum() == (inner.data == OCCUPIED).sum() > 0
    with pytest.raises(OctolgpError, match=r"^z_range must be \(zmin, zmax\) with zmin <= zmax"):
        map_grid(centres, prob, res, z_range=(1.0, 0.0))
    with pytest.raises(OctolgpError, match=r"^no voxel centre in z_range"):
        map_grid(centres, prob, res, z_range=(lo - 9.0, lo - 8.0))


# ---------------------------------------------------------------- OccupancyGridUpdate


@given(
    seed=st.integers(0, 2**32 - 1),
    h=st.integers(1, 70),
    w=st.integers(1, 70),
    tile=st.integers(1, 24),
    max_updates=st.integers(1, 20),
    changes=st.integers(0, 60),
)
def test_updates_applied_to_the_old_grid_give_the_new_one(
    seed: int, h: int, w: int, tile: int, max_updates: int, changes: int
) -> None:
    rng = np.random.default_rng(seed)
    old = _random_grid(rng, (h, w))
    data = old.data.copy()
    if changes and rng.random() < 0.5:  # a few clustered blobs, as a scan changes a map
        y, x = rng.integers(0, h), rng.integers(0, w)
        data[y : y + rng.integers(1, 9), x : x + rng.integers(1, 9)] = STATES[rng.integers(0, 3)]
    cells = rng.integers(0, h * w, changes)
    data.reshape(-1)[cells] = STATES[rng.integers(0, 3, changes)]
    new = TrinaryGrid(data, old.origin, old.resolution)
    updates = grid_updates(old, new, tile=tile, max_updates=max_updates)
    assert updates is not None
    assert len(updates) <= max_updates
    np.testing.assert_array_equal(apply_updates(old, updates).data, new.data)
    changed = old.data != new.data
    if not changed.any():
        assert updates == []
    for u in updates:  # each rectangle is inside the grid and holds a changed cell on each edge
        assert 0 <= u.x < u.x + u.width <= w
        assert 0 <= u.y < u.y + u.height <= h
        block = changed[u.y : u.y + u.height, u.x : u.x + u.width]
        assert block[0].any()
        assert block[-1].any()
        assert block[:, 0].any()
        assert block[:, -1].any()
        assert u.data.dtype == np.int8


def test_updates_cover_only_the_changed_tiles() -> None:
    old = TrinaryGrid(np.full((64, 64), UNKNOWN, dtype=np.int8), (0.0, 0.0), 0.1)
    data = old.data.copy()
    data[3, 5] = OCCUPIED  # tile (0, 0)
    data[40:42, 50] = FREE  # tile (1, 1)
    updates = grid_updates(old, TrinaryGrid(data, (0.0, 0.0), 0.1), tile=32)
    assert updates is not None
    assert [(u.x, u.y, u.width, u.height) for u in updates] == [(5, 3, 1, 1), (50, 40, 1, 2)]
    assert [u.data.tolist() for u in updates] == [[OCCUPIED], [FREE, FREE]]
    one = grid_updates(old, TrinaryGrid(data, (0.0, 0.0), 0.1), tile=32, max_updates=1)
    assert [(u.x, u.y, u.width, u.height) for u in one or []] == [(5, 3, 46, 39)]


def test_a_grid_of_another_geometry_needs_a_full_publish() -> None:
    rng = np.random.default_rng(0)
    old = _random_grid(rng, (8, 8))
    assert grid_updates(None, old) is None
    assert grid_updates(old, _random_grid(rng, (8, 9))) is None
    assert grid_updates(old, TrinaryGrid(old.data, (0.0, 2.0), old.resolution)) is None
    assert grid_updates(old, TrinaryGrid(old.data, old.origin, 0.1)) is None
    assert grid_updates(old, TrinaryGrid(old.data.copy(), old.origin, old.resolution)) == []


def test_subscribers_of_a_growing_map_hold_the_newest_grid(intel_scans: list[Any]) -> None:
    """What the node sends, applied as nav2's static layer applies it, is the map's grid after
    every scan: full grids when the map outgrows its tiles, updates in between."""
    sync = GridSync(tile=8, max_updates=4, full_period=100.0)
    held: TrinaryGrid | None = None
    kinds = []
    with OnlineMap(MapConfig(dim=2, resolution=RES, hyperparameters=HP2)) as m:
        for i, scan in enumerate(intel_scans):
            m.insert_scan(scan)
            grid = map_grid(*m.voxels(), RES, tile=8)
            out = sync.next(grid, now=float(i))
            if isinstance(out, GridMessage):
                kinds.append("full")
                held = TrinaryGrid(out.data.reshape(out.height, out.width), out.origin, RES)
            else:
                kinds.append("updates")
                assert held is not None
                held = apply_updates(held, out)
            np.testing.assert_array_equal(held.data, grid.data)
            assert held.origin == grid.origin
    assert kinds[0] == "full"
    assert "updates" in kinds  # the grid kept its geometry at least once
    # a full grid goes out again after full_period seconds, whatever changed
    assert isinstance(sync.next(grid, now=200.0), GridMessage)
    assert sync.next(grid, now=201.0) == []
    assert isinstance(GridSync(full_period=0.0).next(grid, 0.0), GridMessage)


def test_bad_update_input_names_the_field() -> None:
    grid = _random_grid(np.random.default_rng(1), (4, 4))
    with pytest.raises(OctolgpError, match=r"^tile must be a positive integer"):
        grid_updates(grid, grid, tile=0)
    with pytest.raises(OctolgpError, match=r"^max_updates must be a positive integer"):
        grid_updates(grid, grid, max_updates=True)
    with pytest.raises(OctolgpError, match=r"^old\.data must be int8"):
        grid_updates(TrinaryGrid(grid.data.astype(np.int16), grid.origin, 0.05), grid)  # type: ignore[arg-type]
    with pytest.raises(OctolgpError, match=r"^updates\[1\]: .* reach outside the 4 x 4 grid"):
        apply_updates(
            grid,
            [GridUpdate(0, 0, 1, 1, np.zeros(1, np.int8)), GridUpdate(3, 0, 2, 1, np.zeros(2))],  # type: ignore[arg-type]
        )
    with pytest.raises(OctolgpError, match=r"^updates\[0\]\.data must have 4 cells"):
        apply_updates(grid, [GridUpdate(0, 0, 2, 2, np.zeros(3, np.int8))])
    with pytest.raises(OctolgpError, match=r"^full_period must be a number >= 0"):
        GridSync(full_period=-1.0)


# ---------------------------------------------------------------- Octomap and markers


@pytest.mark.parametrize("dim", [2, 3])
def test_octomap_payload_is_the_bt_tree(map2d: Path, map3d: Path, tmp_path: Path, dim: int) -> None:
    centres, prob, res, depth = _voxels(map2d if dim == 2 else map3d)
    msg = octomap_binary(centres, prob, res, depth)
    assert (msg.id, msg.binary, msg.resolution) == ("OcTree", True, res)
    keys, occupied = trinary_voxels(centres, prob, res, depth)
    states = cell_states(prob)
    assert occupied.sum() == (states == OCCUPIED).sum() > 0
    assert len(keys) == (states != UNKNOWN).sum()
    path = tmp_path / "m.bt"
    assert write_bt(path, keys, occupied, res, depth) == msg.size
    blob = path.read_bytes()
    assert blob[read_bt_header(path)["data_offset"] :] == msg.data
    assert bt_data(keys, occupied, res, depth) == (msg.data, msg.size)


def test_octomap_payload_round_trips_through_octomap(map3d: Path, tmp_path: Path) -> None:
    """The message's bytes after a .bt header read back in OctoMap itself (as
    octomap_msgs::binaryMsgToMap does) with the same occupied voxels."""
    pyoctomap = pytest.importorskip("pyoctomap", exc_type=ImportError)
    centres, prob, res, depth = _voxels(map3d)
    msg = octomap_binary(centres, prob, res, depth)
    path = tmp_path / "msg.bt"
    header = (
        "# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the "
        f"first line as it is!)\n#\nid {msg.id}\nsize {msg.size}\nres {msg.resolution!r}\ndata\n"
    )
    path.write_bytes(header.encode("ascii") + msg.data)
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    assert tree.size() == msg.size
    assert tree.getResolution() == res
    occupied_centres = centres[cell_states(prob) == OCCUPIED]
    for c in occupied_centres:
        node = tree.search(np.asarray(c, dtype=np.float64))
        assert node is not None
        assert tree.isNodeOccupied(node)
    # the tree's occupied volume is exactly the occupied voxels (pruned nodes hold 8^k)
    volume = 0.0
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            volume += leaf.getSize() ** 3
    assert volume == pytest.approx(len(occupied_centres) * res**3)


@pytest.mark.parametrize("dim", [2, 3])
def test_markers_sit_at_occupied_voxel_centres(map2d: Path, map3d: Path, dim: int) -> None:
    centres, prob, res, depth = _voxels(map2d if dim == 2 else map3d)
    cubes = occupied_cubes(centres, prob, res)
    expected = centres[cell_states(prob) == OCCUPIED]
    if dim == 2:
        expected = np.c_[expected, np.full(len(expected), res / 2)]
    assert cubes.scale == res
    assert cubes.points.shape == expected.shape
    assert len(expected) > 0
    order = np.lexsort(cubes.points.T)
    np.testing.assert_array_equal(cubes.points[order], expected[np.lexsort(expected.T)])
    # each cube is its voxel's centre: key and back
    again = key_to_coord(coord_to_key(cubes.points, res, depth), res, depth)
    np.testing.assert_allclose(again, cubes.points, atol=1e-9)
    assert cubes.colours.shape == (len(expected), 4)
    assert cubes.colours.dtype == np.float32
    assert np.all((cubes.colours >= 0) & (cubes.colours <= 1))
    np.testing.assert_array_equal(cubes.colours[:, 3], 1.0)


def test_height_colours_are_octomap_servers_hsv_ramp() -> None:
    from matplotlib.colors import hsv_to_rgb

    z = np.random.default_rng(2).uniform(-3.0, 5.0, 500)
    for factor in (0.8, 1.0, 0.3):
        hue = (1.0 - (z - z.min()) / (z.max() - z.min())) * factor
        expected = hsv_to_rgb(np.c_[hue % 1.0, np.ones_like(z), np.ones_like(z)])
        np.testing.assert_allclose(height_colours(z, factor)[:, :3], expected, atol=1e-6)
    top = height_colours(np.array([0.0, 1.0]))
    np.testing.assert_allclose(top[1], [1.0, 0.0, 0.0, 1.0])  # the highest cube is red
    assert height_colours(np.array([2.0, 2.0])).shape == (2, 4)  # one height: no division
    with pytest.raises(OctolgpError, match=r"^z must be finite"):
        height_colours(np.array([0.0, np.nan]))
    with pytest.raises(OctolgpError, match=r"^color_factor must be a number in \[0, 1\]"):
        height_colours(np.zeros(2), 1.5)
    with pytest.raises(OctolgpError, match=r"^resolution must be finite and > 0"):
        occupied_cubes(np.zeros((1, 3)), [0.9], 0.0)


# ---------------------------------------------------------------- tf wait queue


def test_tf_queue_keeps_arrival_order_and_times_out() -> None:
    q: TfWaitQueue[str] = TfWaitQueue(queue_size=3, timeout=0.5)
    posed = {"b"}
    assert q.push("a", 0.0) is None
    assert q.push("b", 0.1) is None
    out = q.drain(lambda m: m in posed, now=0.2)
    assert out.ready == ()  # b waits behind a
    assert out.timed_out == ()
    posed.add("a")
    out = q.drain(lambda m: m in posed, now=0.3)
    assert out.ready == ("a", "b")
    assert len(q) == 0
    q.push("c", 1.0)
    q.push("d", 1.2)
    out = q.drain(lambda m: m in posed, now=1.5)  # c timed out, d still in time
    assert out.timed_out == ("c",)
    assert out.ready == ()
    assert len(q) == 1
    q.push("e", 1.6)
    q.push("f", 1.7)
    assert q.push("g", 1.8) == "d"  # queue_size 3: the oldest goes
    posed.update("efg")
    assert q.drain(lambda m: m in posed, now=1.9).ready == ("e", "f", "g")
    with pytest.raises(OctolgpError, match=r"^queue_size must be an integer >= 1"):
        TfWaitQueue(0, 1.0)
    with pytest.raises(OctolgpError, match=r"^timeout must be a finite number >= 0"):
        TfWaitQueue(1, math.inf)


# ---------------------------------------------------------------- the package


def _node_parameters() -> dict[str, Any]:
    """The node's PARAMETERS dict, read from its source (rclpy is not needed)."""
    tree = ast.parse(NODE.read_text())
    for node in tree.body:
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "PARAMETERS":
            assert isinstance(node.value, ast.Dict)
            out = {}
            for k, v in zip(node.value.keys, node.value.values, strict=True):
                assert isinstance(k, ast.Constant)
                src = ast.unparse(v).replace("math.inf", "float('inf')")
                out[k.value] = eval(src)
            return out
    raise AssertionError("no PARAMETERS in the node")


def test_package_xml_names_the_dependencies() -> None:
    root = ET.parse(PACKAGE / "package.xml").getroot()
    assert root.tag == "package"
    assert root.get("format") == "3"
    assert root.findtext("name") == "octolgp_ros"
    deps = {e.text for e in root.findall("exec_depend")}
    assert {
        "rclpy",
        "tf2_ros",
        "message_filters",
        "sensor_msgs",
        "nav_msgs",
        "map_msgs",
        "octomap_msgs",
        "visualization_msgs",
        "std_msgs",
        "std_srvs",
        "geometry_msgs",
    } <= deps
    assert root.findtext("export/build_type") == "ament_python"
    assert (PACKAGE / "resource" / "octolgp_ros").is_file()
    # every message package the node imports is a dependency
    imported = {
        n.module.split(".")[0]
        for n in ast.walk(ast.parse(NODE.read_text()))
        if isinstance(n, ast.ImportFrom) and n.module and n.module.endswith((".msg", ".srv"))
    }
    assert imported
    assert imported <= deps


def test_setup_has_the_entry_point_and_files() -> None:
    tree = ast.parse((PACKAGE / "setup.py").read_text())
    call = next(
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup"
    )
    kw = {k.arg: k.value for k in call.keywords}
    scripts = ast.literal_eval(kw["entry_points"])["console_scripts"]
    assert scripts == ["octolgp_mapper = octolgp_ros.mapper:main"]
    assert ast.unparse(kw["name"]) == "PACKAGE"
    assert 'PACKAGE = "octolgp_ros"' in (PACKAGE / "setup.py").read_text()
    main = [n for n in ast.parse(NODE.read_text()).body if isinstance(n, ast.FunctionDef)]
    assert "main" in {f.name for f in main}
    assert "install_scripts=$base/lib/octolgp_ros" in (PACKAGE / "setup.cfg").read_text()


@pytest.mark.parametrize(
    "path",
    [
        NODE,
        PACKAGE / "launch" / "octolgp.launch.py",
        PACKAGE / "setup.py",
        PACKAGE / "octolgp_ros" / "__init__.py",
        ROOT / "examples" / "ros2_node.py",
    ],
    ids=lambda p: p.name,
)
def test_package_python_compiles(path: Path) -> None:
    compile(path.read_text(), str(path), "exec")


def test_params_yaml_matches_the_node() -> None:
    yaml = pytest.importorskip("yaml")
    text = (PACKAGE / "config" / "params.yaml").read_text()
    params = yaml.safe_load(text)["octolgp_mapper"]["ros__parameters"]
    declared = _node_parameters()
    assert set(params) == set(declared)
    for name, value in declared.items():
        assert params[name] == value, name
        assert type(params[name]) is type(value), name  # ROS parameter types are strict
    # every parameter has a comment above it (parameters documented together share one)
    lines = [line.strip() for line in text.splitlines()]
    for name in params:
        at = next(i for i, line in enumerate(lines) if line.startswith(f"{name}:"))
        while lines[at - 1].split(":")[0] in params:
            at -= 1
        assert lines[at - 1].startswith("#"), name
    # the node declares its parameters from PARAMETERS
    assert "self.declare_parameter(name, value)" in NODE.read_text()


def test_node_topics_are_relative() -> None:
    source = NODE.read_text()
    tree = ast.parse(source)
    names = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and getattr(n.func, "attr", "") in (
            "create_publisher",
            "create_service",
        ):
            arg = n.args[1]
            if isinstance(arg, ast.Constant):
                names.append(arg.value)
    assert {"octomap_binary", "occupied_cells_vis_array", "save"} <= set(names)
    assert all(not name.startswith("/") for name in names)
    for topic in ('"scan"', '"points"', '"map"', '"projected_map"', 'f"{name}_updates"'):
        assert topic in source
    assert "now()" not in source.replace("get_clock().now().nanoseconds", "")
