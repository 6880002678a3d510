"""Exports in bounded chunks: the streamed files equal the ones written from whole arrays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OctolgpError, OnlineMap, load_scans
from octolgp.cli.main import main
from octolgp.cli.maps import median_height
from octolgp.export.nav2 import trinary_grid, trinary_grid_chunks, write_nav2_map
from octolgp.export.octomap import write_bt, write_map_voxels, write_ot, write_tree_chunks
from octolgp.export.octree import morton, to_keys16
from octolgp.export.pcd import write_pcd, write_pcd_chunks
from octolgp.export.ply import write_ply, write_ply_chunks
from octolgp.sim.lidar3d import simulate_lidar_room

INTEL20 = Path(__file__).resolve().parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.04, alpha=5.0)


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("chunks") / "m.octolgp"
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP), path=path) as m:
        m.insert_scans(list(load_scans(INTEL20)))
    return path


def test_voxel_chunks_are_the_voxels_in_pieces(mapped: Path) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
        chunks = list(m.voxel_chunks(size=1000))
    assert len(chunks) > 3
    assert all(c.shape[0] < 1000 + m.grid.voxels_per_leaf for c, _ in chunks)
    np.testing.assert_array_equal(np.concatenate([c for c, _ in chunks]), centres)
    np.testing.assert_array_equal(np.concatenate([p for _, p in chunks]), prob)


@pytest.mark.parametrize("binary", [True, False])
def test_streamed_point_clouds_equal_the_whole_ones(
    mapped: Path, tmp_path: Path, binary: bool
) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
        chunks = list(m.voxel_chunks(size=700))
    for whole, streamed, ext in (
        (write_ply, write_ply_chunks, "ply"),
        (write_pcd, write_pcd_chunks, "pcd"),
    ):
        a, b = tmp_path / f"a.{ext}", tmp_path / f"b.{ext}"
        whole(a, centres, prob, binary=binary)
        assert streamed(b, iter(chunks), binary=binary) == centres.shape[0]
        assert a.read_bytes() == b.read_bytes()


def test_cli_export_streams_the_occupied_voxels(mapped: Path, tmp_path: Path) -> None:
    with OnlineMap.open(mapped, read_only=True) as m:
        centres, prob = m.voxels()
    keep = prob > 0.5
    for ext, whole in (("ply", write_ply), ("pcd", write_pcd)):
        out, want = tmp_path / f"m.{ext}", tmp_path / f"want.{ext}"
        assert main(["export", str(mapped), "--out", str(out)]) == 0
        whole(want, centres[keep], prob[keep])
        assert out.read_bytes() == want.read_bytes()
    leftovers = [
        p for p in tmp_path.iterdir() if p.name not in {"m.ply", "m.pcd", "want.ply", "want.pcd"}
    ]
    assert not leftovers  # the records' temporary file is gone


def _random_voxels(rng: np.random.Generator, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique keys near the tree's centre, and a 16-voxel block of one state (pruned)."""
    span = int(rng.integers(2, 40))
    keys = rng.integers(32768 - span, 32768 + span, (int(rng.integers(1, 2500)), dim))
    axes = [np.arange(32768, 32768 + 16)] * dim
    block = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim)
    keys = np.unique(np.concatenate([keys, block]), axis=0)
    occupied = rng.random(keys.shape[0]) < 0.3
    occupied[np.all((keys >= 32768) & (keys < 32768 + 16), axis=1)] = True
    return keys, occupied


@pytest.mark.parametrize("seed", range(12))
def test_octomap_trees_from_chunks_equal_the_whole_ones(tmp_path: Path, seed: int) -> None:
    """Subtrees below a split depth serialised chunk by chunk, in any chunk order, give
    the bytes of the tree built at once, including siblings pruned across chunks."""
    rng = np.random.default_rng(seed)
    dim = 2 + seed % 2
    keys, occupied = _random_voxels(rng, dim)
    log_odds = np.where(occupied, 2.0, rng.normal(size=occupied.size))
    log_odds[np.all((keys >= 32768) & (keys < 32776), axis=1)] = -1.5  # one value: pruned
    split = int(rng.integers(1, 17))
    code = morton(to_keys16(keys, 16)) >> (3 * (16 - split))  # each voxel's subtree
    subtrees, which = np.unique(code, return_inverse=True)
    chunk = rng.permutation(subtrees.size)[which] % int(rng.integers(1, 7))
    order = rng.permutation(np.unique(chunk))
    for full, whole, values in ((False, write_bt, occupied), (True, write_ot, log_odds)):
        a, b = tmp_path / f"a{full}", tmp_path / f"b{full}"
        n = whole(a, keys, values, 0.1)
        parts = [(keys[chunk == c], values[chunk == c]) for c in order]
        assert write_tree_chunks(b, parts, 0.1, 16, split, full=full) == n
        assert a.read_bytes() == b.read_bytes()


def test_octomap_trees_from_chunks_refuse_a_split_subtree(tmp_path: Path) -> None:
    keys = np.array([[32768, 32768, 32768], [32769, 32768, 32768]])
    parts = [(keys[:1], np.array([True])), (keys[1:], np.array([False]))]
    with pytest.raises(OctolgpError, match="whole subtrees of depth 15"):
        write_tree_chunks(tmp_path / "m.bt", parts, 0.1, 16, 15, full=False)
    with pytest.raises(OctolgpError, match="split must be"):
        write_tree_chunks(tmp_path / "m.bt", parts, 0.1, 16, 0, full=False)
    assert not (tmp_path / "m.bt").exists()
    assert write_tree_chunks(tmp_path / "e.bt", [], 0.1, 16, 13, full=False) == 0
    write_bt(tmp_path / "w.bt", np.zeros((0, 3), np.int64), np.zeros(0, bool), 0.1)
    assert (tmp_path / "e.bt").read_bytes() == (tmp_path / "w.bt").read_bytes()


@pytest.mark.parametrize("suffix", [".bt", ".ot"])
def test_maps_export_octomap_in_chunks_as_from_whole_arrays(
    mapped: Path, tmp_path: Path, suffix: str
) -> None:
    room = simulate_lidar_room(3, seed=1, n_azimuth=128, n_elevation=8, max_range=10.0)
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    with OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp)) as m3:
        m3.insert_scans([s.downsample(0.2) for s in room.scans()])
        maps = [(m3, 3)]
        with OnlineMap.open(mapped, read_only=True) as m2:
            maps.append((m2, 2))
            for m, dim in maps:
                out, ref = tmp_path / f"m{dim}{suffix}", tmp_path / f"r{dim}{suffix}"
                centres, prob = m.voxels()
                res, depth = m.config.resolution, m.config.tree_depth
                n = write_map_voxels(ref, centres, prob, res, depth, 0.4)
                assert m.export_octomap(out, threshold=0.4) == n > 0
                assert out.read_bytes() == ref.read_bytes()


@pytest.mark.parametrize(
    ("dim", "z", "z_range"), [(2, None, None), (3, 0.3, None), (3, None, (0.0, 1.0))]
)
def test_nav2_grids_from_chunks_equal_the_whole_ones(
    dim: int, z: float | None, z_range: tuple[float, float] | None
) -> None:
    rng = np.random.default_rng(dim)
    centres = (np.floor(rng.uniform(-3, 3, (5000, dim)) / 0.1) + 0.5) * 0.1
    centres = np.unique(centres, axis=0)
    prob = rng.choice([0.1, 0.5, 0.4, 0.9], centres.shape[0])
    whole = trinary_grid(centres, prob, 0.1, z=z, z_range=z_range)
    cut = np.sort(rng.choice(centres.shape[0], 6, replace=False))
    chunks = list(zip(np.split(centres, cut), np.split(prob, cut), strict=True))
    chunks.append((np.zeros((0, dim)), np.zeros(0)))  # a chunk without voxels
    parts = trinary_grid_chunks(chunks[::-1], 0.1, z=z, z_range=z_range)
    np.testing.assert_array_equal(parts.data, whole.data)
    assert (parts.origin, parts.resolution) == (whole.origin, whole.resolution)
    with pytest.raises(OctolgpError, match="no voxel"):
        trinary_grid_chunks([(c[:0], p[:0]) for c, p in chunks], 0.1, z=z, z_range=z_range)


def test_median_height_is_numpys_median_over_the_chunks() -> None:
    rng = np.random.default_rng(3)
    for n in (1, 2, 7, 1000):
        centres = np.c_[rng.normal(size=(n, 2)), (rng.integers(-5, 9, n) + 0.5) * 0.2]
        cut = np.sort(rng.choice(n + 1, 3))
        chunks = [(c, np.zeros(len(c))) for c in np.split(centres, cut)]
        assert median_height(chunks) == float(np.median(centres[:, 2]))
    with pytest.raises(OctolgpError, match="no voxel"):
        median_height([])


@pytest.mark.parametrize("args", [["--z-range", "0", "2"], ["--z", "0.5"]])
def test_cli_nav2_and_png_exports_of_a_3d_map_read_chunks(tmp_path: Path, args: list[str]) -> None:
    room = simulate_lidar_room(3, seed=1, n_azimuth=128, n_elevation=8, max_range=10.0)
    path = tmp_path / "room.octolgp"
    hp = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)
    with OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=hp), path=path) as m:
        m.insert_scans([s.downsample(0.2) for s in room.scans()])
        centres, prob = m.voxels()
    z = float(args[1]) if args[0] == "--z" else None
    z_range = (float(args[1]), float(args[2])) if args[0] == "--z-range" else None
    write_nav2_map(tmp_path / "ref.pgm", centres, prob, 0.2, z=z, z_range=z_range)
    assert main(["export", str(path), "--out", str(tmp_path / "m.pgm"), *args]) == 0
    assert (tmp_path / "m.pgm").read_bytes() == (tmp_path / "ref.pgm").read_bytes()
    if z is not None:  # the PNG's slice: the layer holding z (a figure: compare its input)
        assert main(["export", str(path), "--out", str(tmp_path / "m.png"), *args]) == 0
        assert (tmp_path / "m.png").stat().st_size > 0
