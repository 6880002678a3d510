"""Export: OctoMap .bt/.ot files checked against the real OctoMap, PLY and PNG writers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from octolgp.errors import OctolgpError
from octolgp.export.image import write_png
from octolgp.export.octomap import write_bt, write_ot
from octolgp.export.octomap_read import decode_bt, read_bt_header
from octolgp.export.ply import write_ply
from octolgp.geometry.keys import key_to_coord

RES = 0.1
CENTER = 1 << 15


@pytest.fixture
def pyoctomap() -> Any:
    return pytest.importorskip("pyoctomap", exc_type=ImportError)


def _random_voxels(
    rng: np.random.Generator, n: int, side: int = 8, dim: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` distinct voxels in a ``side``-cube straddling the origin, plus a full aligned block."""
    cells = rng.choice(side**dim, size=n, replace=False)
    keys = np.column_stack(np.unravel_index(cells, (side,) * dim)) + CENTER - side // 2
    block = np.stack(np.meshgrid(*[[0, 1]] * dim, indexing="ij"), -1).reshape(-1, dim)
    keys = np.vstack([keys, block + CENTER + 2 * side])  # aligned 2^dim block, all occupied
    occupied = rng.random(len(keys)) < 0.5
    occupied[-len(block) :] = True
    return keys.astype(np.int64), occupied


def _octomap_tree(pyoctomap: Any, keys: np.ndarray, updates: list[Any]) -> Any:
    """The same voxels inserted into OctoMap itself: one update per key (auto-pruned)."""
    tree = pyoctomap.OcTree(RES)
    for key, update in zip(keys.tolist(), updates, strict=True):
        tree.updateNode(pyoctomap.OcTreeKey(*key), update)
    return tree


def _nodes_from_bytes(path: Path) -> int:
    """Decoder-free node count: 1 (root) + every non-zero 2-bit child field in the data."""
    header = read_bt_header(path)
    data = path.read_bytes()[header["data_offset"] :]
    codes = np.frombuffer(data, dtype="<u2").astype(np.int64)
    fields = (codes[:, None] >> (2 * np.arange(8))) & 3
    return 1 + int(np.count_nonzero(fields)) if codes.size else 0


def _search(tree: Any, centre: np.ndarray) -> Any:
    return tree.search(np.asarray(centre, dtype=np.float64))


# --- .bt against OctoMap ------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bt_is_byte_identical_to_octomap(pyoctomap: Any, tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    keys, occupied = _random_voxels(rng, 300)
    path = tmp_path / "map.bt"
    size = write_bt(path, keys, occupied, RES)
    reference = _octomap_tree(pyoctomap, keys, [bool(o) for o in occupied])
    # OctoMap's writeBinary: toMaxLikelihood, prune, header, writeBinaryNode.
    assert path.read_bytes() == reference.writeBinary()
    assert size == reference.size()


@pytest.mark.parametrize("seed", [3, 4])
def test_bt_read_by_octomap(pyoctomap: Any, tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    keys, occupied = _random_voxels(rng, 200)
    path = tmp_path / "map.bt"
    size = write_bt(path, keys, occupied, RES)
    tree = pyoctomap.OcTree(RES * 3)
    assert tree.readBinary(str(path))
    assert tree.size() == size == _nodes_from_bytes(path)
    assert tree.getResolution() == RES
    leaf_keys, _, _ = decode_bt(path)
    assert tree.getNumLeafNodes() == len(leaf_keys)
    for centre, occ in zip(key_to_coord(keys, RES), occupied, strict=True):
        node = _search(tree, centre)
        assert node is not None
        assert tree.isNodeOccupied(node) == occ
    # Voxels never written are unknown: no node.
    known = {tuple(k) for k in keys.tolist()}
    box = np.column_stack(np.unravel_index(np.arange(12**3), (12,) * 3)) + CENTER - 6
    unknown = np.array([k for k in box.tolist() if tuple(k) not in known])
    assert len(unknown) > 100
    for centre in key_to_coord(unknown, RES):
        assert _search(tree, centre) is None


def test_full_block_is_pruned_to_one_leaf(pyoctomap: Any, tmp_path: Path) -> None:
    block = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3)
    path = tmp_path / "block.bt"
    # Root plus one inner node at each depth 1..14, the block a leaf at depth 15.
    assert write_bt(path, block + CENTER, np.ones(8, bool), RES) == 16
    header = read_bt_header(path)
    blob = path.read_bytes()
    offset = blob.index(b"\ndata\n") + 6
    assert header == {"kind": "bt", "id": "OcTree", "size": 16, "res": RES, "data_offset": offset}
    assert blob[:offset].decode().splitlines()[3:] == ["id OcTree", "size 16", "res 0.1", "data"]
    assert len(blob) - offset == 2 * 15  # 15 inner nodes
    assert _nodes_from_bytes(path) == 16
    keys, occupied, depth = decode_bt(path)
    np.testing.assert_array_equal(keys, [[CENTER] * 3])
    np.testing.assert_array_equal(occupied, [True])
    np.testing.assert_array_equal(depth, [15])
    tree = pyoctomap.OcTree(RES)
    assert tree.readBinary(str(path))
    assert tree.size() == 16
    assert tree.getNumLeafNodes() == 1
    for centre in key_to_coord(block + CENTER, RES):
        assert tree.isNodeOccupied(_search(tree, centre))
    # A 4^3 block prunes one level further; a mixed or misaligned block does not prune.
    big = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) + CENTER
    assert write_bt(path, big, np.ones(64, bool), RES) == 15
    mixed = np.ones(8, bool)
    mixed[3] = False
    assert write_bt(path, block + CENTER, mixed, RES) == 16 + 8
    assert write_bt(path, block + CENTER + 1, np.ones(8, bool), RES) > 16 + 8


def test_2d_layer(pyoctomap: Any, tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    keys, occupied = _random_voxels(rng, 40, side=10, dim=2)
    path = tmp_path / "layer.bt"
    size = write_bt(path, keys, occupied, RES)
    decoded, decoded_occ, _ = decode_bt(path, expand=True)
    np.testing.assert_array_equal(decoded[:, 2], CENTER)
    got = dict(zip(map(tuple, decoded[:, :2].tolist()), decoded_occ.tolist(), strict=True))
    assert got == dict(zip(map(tuple, keys.tolist()), occupied.tolist(), strict=True))
    tree = pyoctomap.OcTree(RES)
    assert tree.readBinary(str(path))
    assert tree.size() == size
    for (x, y), occ in zip(key_to_coord(keys, RES), occupied, strict=True):
        assert tree.isNodeOccupied(_search(tree, [x, y, 0.5 * RES])) == occ  # z in [0, res)
        assert _search(tree, [x, y, -0.5 * RES]) is None
        assert _search(tree, [x, y, 1.5 * RES]) is None


def test_shallow_tree_keys_are_recentred(pyoctomap: Any, tmp_path: Path) -> None:
    keys = np.array([[128, 128, 128], [0, 255, 7]])  # depth 8: coordinate 0 has key 128
    path = tmp_path / "d8.bt"
    write_bt(path, keys, [True, False], 0.5, tree_depth=8)
    tree = pyoctomap.OcTree(0.5)
    assert tree.readBinary(str(path))
    assert tree.isNodeOccupied(_search(tree, [0.25, 0.25, 0.25]))
    corner = key_to_coord(keys[1:], 0.5, tree_depth=8)[0]
    assert not tree.isNodeOccupied(_search(tree, corner))
    decoded, occupied, _ = decode_bt(path, tree_depth=8)  # depth-first order
    np.testing.assert_array_equal(decoded, keys[::-1])
    np.testing.assert_array_equal(occupied, [False, True])
    with pytest.raises(OctolgpError, match="outside"):
        decode_bt(path, tree_depth=4)


def test_empty_map(pyoctomap: Any, tmp_path: Path) -> None:
    path = tmp_path / "empty.bt"
    assert write_bt(path, np.zeros((0, 3), np.int64), np.zeros(0, bool), RES) == 0
    assert read_bt_header(path)["size"] == 0
    keys, occupied, depth = decode_bt(path)
    assert keys.shape == (0, 3)
    assert occupied.shape == depth.shape == (0,)
    tree = pyoctomap.OcTree(RES)
    assert tree.readBinary(str(path))
    assert tree.size() == 0


@given(
    st.sets(st.tuples(*[st.integers(CENTER - 4, CENTER + 3)] * 3), min_size=1, max_size=80),
    st.integers(0, 2**32 - 1),
)
def test_decode_round_trip(
    tmp_path_factory: pytest.TempPathFactory, cells: set[Any], seed: int
) -> None:
    keys = np.array(sorted(cells), dtype=np.int64)
    occupied = np.random.default_rng(seed).random(len(keys)) < 0.7
    path = tmp_path_factory.mktemp("rt") / "map.bt"
    size = write_bt(path, keys, occupied, RES)
    assert size == read_bt_header(path)["size"] == _nodes_from_bytes(path)
    decoded, decoded_occ, depth = decode_bt(path, expand=True)
    assert (depth == 16).all()
    got = dict(zip(map(tuple, decoded.tolist()), decoded_occ.tolist(), strict=True))
    assert got == dict(zip(map(tuple, keys.tolist()), occupied.tolist(), strict=True))


# --- .ot against OctoMap ------------------------------------------------------------


@pytest.mark.parametrize("seed", [6, 7])
def test_ot_matches_octomap(pyoctomap: Any, tmp_path: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    keys, _ = _random_voxels(rng, 250)
    # Within OctoMap's clamping range, so that one update sets the value exactly.
    log_odds = rng.choice([-1.5, -0.4, 0.3, 2.0], size=len(keys)).astype(np.float32)
    log_odds[-8:] = 2.0  # the aligned block prunes
    path = tmp_path / "map.ot"
    size = write_ot(path, keys, log_odds, RES)
    reference = _octomap_tree(pyoctomap, keys, [float(v) for v in log_odds])
    assert path.read_bytes() == reference.write()  # OctoMap's AbstractOcTree::write
    assert read_bt_header(path)["kind"] == "ot"
    tree = pyoctomap.OcTree(RES).read(str(path))
    assert tree is not None
    assert tree.size() == size
    assert tree.getRoot().getLogOdds() == log_odds.max()  # inner nodes: max of children
    for centre, value in zip(key_to_coord(keys, RES), log_odds, strict=True):
        node = _search(tree, centre)
        assert node.getLogOdds() == value
        assert node.getOccupancy() == pytest.approx(1.0 / (1.0 + np.exp(-value)), rel=1e-6)
        assert tree.isNodeOccupied(node) == (value > 0)


def test_ot_empty_and_2d(tmp_path: Path) -> None:
    path = tmp_path / "map.ot"
    assert write_ot(path, np.zeros((0, 2), np.int64), [], RES) == 0
    assert read_bt_header(path)["size"] == 0
    assert write_ot(path, [[CENTER, CENTER]], [0.5], RES) == 17  # root + 16 levels
    with pytest.raises(OctolgpError, match="binary"):
        decode_bt(path)


# --- bad input ----------------------------------------------------------------------


GOOD_KEYS = np.array([[CENTER, CENTER, CENTER], [CENTER + 1, CENTER, CENTER]])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"keys": GOOD_KEYS.astype(float)}, "keys"),
        ({"keys": np.zeros((2, 4), np.int64)}, "keys"),
        ({"keys": GOOD_KEYS[:, 0]}, "keys"),
        ({"keys": GOOD_KEYS + CENTER}, "keys"),
        ({"keys": -GOOD_KEYS}, "keys"),
        ({"keys": GOOD_KEYS[[0, 0]]}, "keys"),
        ({"keys": GOOD_KEYS, "tree_depth": 8}, "keys"),
        ({"occupied": [True]}, "occupied"),
        ({"occupied": [0.5, 1.0]}, "occupied"),
        ({"resolution": 0.0}, "resolution"),
        ({"resolution": float("nan")}, "resolution"),
        ({"tree_depth": 17}, "tree_depth"),
    ],
)
def test_write_bt_rejects(tmp_path: Path, kwargs: dict[str, Any], field: str) -> None:
    args: dict[str, Any] = {"keys": GOOD_KEYS, "occupied": [True, False], "resolution": RES}
    args.update(kwargs)
    with pytest.raises(OctolgpError, match=field):
        write_bt(tmp_path / "x.bt", **args)
    assert not (tmp_path / "x.bt").exists()


@pytest.mark.parametrize("bad", [[np.nan, 1.0], [np.inf, 1.0], [1e39, 0.0], [1.0]])
def test_write_ot_rejects_log_odds(tmp_path: Path, bad: list[float]) -> None:
    with pytest.raises(OctolgpError, match="log_odds"):
        write_ot(tmp_path / "x.ot", GOOD_KEYS, bad, RES)


def test_unwritable_and_unreadable_paths(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir" / "x.bt"
    with pytest.raises(OctolgpError, match="path"):
        write_bt(missing, GOOD_KEYS, [True, True], RES)
    with pytest.raises(OctolgpError, match="path"):
        write_ot(missing, GOOD_KEYS, [1.0, 1.0], RES)
    with pytest.raises(OctolgpError, match="path"):
        write_ply(missing, [[0.0, 0.0, 0.0]], [0.5])
    with pytest.raises(OctolgpError, match="path"):
        write_png(tmp_path / "no" / "x.png", [[0.0, 0.0]], [0.5], RES)
    with pytest.raises(OctolgpError, match="path"):
        read_bt_header(missing)


def test_decode_rejects_corrupt_files(tmp_path: Path) -> None:
    foreign = tmp_path / "foreign.bt"
    foreign.write_bytes(b"ply\nformat ascii 1.0\n")
    with pytest.raises(OctolgpError, match="not an OctoMap file"):
        read_bt_header(foreign)
    path = tmp_path / "map.bt"
    write_bt(path, GOOD_KEYS, [True, False], RES)
    blob = path.read_bytes()
    truncated = tmp_path / "truncated.bt"
    truncated.write_bytes(blob[:-2])
    with pytest.raises(OctolgpError, match="truncated"):
        decode_bt(truncated)
    wrong_size = tmp_path / "size.bt"
    wrong_size.write_bytes(blob.replace(b"size 18", b"size 19"))
    with pytest.raises(OctolgpError, match="corrupt"):
        decode_bt(wrong_size)
    no_data = tmp_path / "nodata.bt"
    no_data.write_bytes(blob[: blob.index(b"data")])
    with pytest.raises(OctolgpError, match="data"):
        read_bt_header(no_data)


# --- PLY and PNG ----------------------------------------------------------------------


def _read_ply(path: Path) -> tuple[str, np.ndarray]:
    blob = path.read_bytes()
    end = blob.index(b"end_header\n") + len(b"end_header\n")
    header = blob[:end].decode("ascii")
    count = int(header.split("element vertex ")[1].split()[0])
    fmt = header.split("format ")[1].split()[0]
    if fmt == "ascii":
        rows = np.loadtxt(blob[end:].decode("ascii").splitlines(), ndmin=2)
    else:
        rows = np.frombuffer(blob[end:], dtype="<f4").reshape(count, 4)
    assert rows.shape == (count, 4)
    return fmt, rows


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip(tmp_path: Path, binary: bool) -> None:
    rng = np.random.default_rng(8)
    centres = rng.uniform(-5.0, 5.0, size=(50, 3))
    prob = rng.uniform(size=50)
    path = tmp_path / "cloud.ply"
    write_ply(path, centres, prob, binary=binary)
    fmt, rows = _read_ply(path)
    assert fmt == ("binary_little_endian" if binary else "ascii")
    rows = rows.astype(np.float32)  # ASCII keeps 9 digits: float32 round-trips exactly
    np.testing.assert_array_equal(rows[:, :3], centres.astype(np.float32))
    np.testing.assert_array_equal(rows[:, 3], prob.astype(np.float32))
    write_ply(path, centres[:, :2], prob, binary=binary)  # 2D: z = 0
    _, rows = _read_ply(path)
    np.testing.assert_array_equal(rows[:, 2], 0.0)


@pytest.mark.parametrize(
    ("centres", "prob", "field"),
    [
        (np.zeros((2, 4)), [0.5, 0.5], "centres"),
        ([[np.nan, 0.0, 0.0]], [0.5], "centres"),
        (np.zeros((2, 3)), [0.5], "prob"),
        (np.zeros((2, 3)), [0.5, np.nan], "prob"),
        (np.zeros((2, 3)), [0.5, 1.5], "prob"),
    ],
)
def test_ply_rejects(tmp_path: Path, centres: Any, prob: Any, field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        write_ply(tmp_path / "x.ply", centres, prob)


def test_png(tmp_path: Path) -> None:
    from matplotlib.image import imread

    xs, ys = np.meshgrid(np.arange(40), np.arange(20), indexing="ij")
    centres = (np.column_stack([xs.ravel(), ys.ravel()]) + 0.5) * RES
    prob = np.where(xs.ravel() < 10, 0.95, 0.05)
    keep = xs.ravel() % 7 != 3  # unknown columns
    path = tmp_path / "map.png"
    write_png(path, centres[keep], prob[keep], RES, dpi=50)
    image = imread(path)
    assert image.ndim == 3
    assert image.shape[2] in (3, 4)
    assert image.shape[0] > 50
    assert image.shape[1] == 400  # 8 in at 50 dpi
    with pytest.raises(OctolgpError, match="centres"):
        write_png(path, np.zeros((0, 2)), [], RES)
    with pytest.raises(OctolgpError, match="centres"):
        write_png(path, np.zeros((3, 3)), [0.5] * 3, RES)
    with pytest.raises(OctolgpError, match="prob"):
        write_png(path, centres, prob[:-1], RES)
    with pytest.raises(OctolgpError, match="resolution"):
        write_png(path, centres, prob, -1.0)
