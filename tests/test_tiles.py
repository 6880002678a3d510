"""Lattice leaves fitted in tiles: the map of tile-sized leaves, with fewer leaves to keep.

A 3D lattice leaf of 8 voxels a side is fitted as 8 tiles of 4, a 2D leaf of 16 as 16
tiles of 4, each a local GP on its own halo box with its own inducing lattice. Each tile sees exactly what a leaf of 4
voxels would see (the same counts in the same halo box, the same kept returns), so the
maps' values must be the same; only pruning, which collapses a whole leaf, differs.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineMap, load_scans
from octolgp.engines.lattice import KeptReturns, Returns, tile_layout, tile_returns
from octolgp.errors import OctolgpError
from octolgp.mapping.grid import LeafGrid
from octolgp.sim.lidar3d import simulate_lidar_room

INTEL20 = Path(__file__).parent / "data" / "intel_first20.log"
HP = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def _config(
    leaf_voxels: int | None, prune: bool, clear_scans: int | None = None, dim: int = 3
) -> MapConfig:
    config = MapConfig(dim=dim, resolution=0.2 if dim == 3 else 0.1)
    leaf_depth = None if leaf_voxels is None else config.tree_depth - int(np.log2(leaf_voxels))
    online = dataclasses.replace(
        config.online, n_jobs=1, prune=prune, leaf_depth=leaf_depth, clear_scans=clear_scans
    )
    return dataclasses.replace(config, hyperparameters=HP, online=online)


def _room(n: int) -> list:
    room = simulate_lidar_room(
        n, seed=3, n_azimuth=256, n_elevation=16, max_range=12.0, range_noise=0.02, n_heldout=1
    )
    return [s.downsample(0.2) for s in room.scans()]


def test_the_default_leaves_hold_tiles_of_four() -> None:
    config = _config(None, True).resolve()
    grid = LeafGrid.from_config(config)
    assert (grid.side, config.tile_voxels, grid.halo_voxels) == (16, 4, 1)
    config = MapConfig(dim=2, resolution=0.1).resolve()
    grid = LeafGrid.from_config(config)
    assert (grid.side, config.tile_voxels, grid.halo_voxels) == (16, 4, 2)


@pytest.mark.parametrize(("dim", "clear_scans"), [(3, None), (3, 0), (2, None)])
def test_tiled_leaves_give_the_map_of_tile_sized_leaves(
    dim: int, clear_scans: int | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Scan after scan, a changed leaf refits only the tiles whose halo boxes changed and
    keeps the others' values: the map stays that of tile-sized leaves refitted whole."""
    import octolgp.engines.lattice as lattice_module

    kept_tiles: list[int] = []
    fit = lattice_module.fit_lattice_leaves

    def spy(*args: object) -> object:
        fresh = args[4] if len(args) > 4 else None
        kept_tiles.append(0 if fresh is None else int(np.sum(fresh)))
        return fit(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(lattice_module, "fit_lattice_leaves", spy)
    scans = _room(6) if dim == 3 else list(load_scans(INTEL20))[:12]

    def fitted_at_once(config: MapConfig) -> MapConfig:
        return dataclasses.replace(
            config, online=dataclasses.replace(config.online, defer_fit=False)
        )

    tiled = OnlineMap(fitted_at_once(_config(None, False, clear_scans, dim)))
    small = OnlineMap(fitted_at_once(_config(4, False, clear_scans, dim)))
    deferred = OnlineMap(_config(None, False, clear_scans, dim))  # all tiles, at the end
    for scan in scans:  # one by one: leaves change and are refitted scan after scan
        tiled.insert_scan(scan)
        small.insert_scan(scan)
        deferred.insert_scan(scan)
    assert sum(kept_tiles) > 0  # some tiles kept their values
    assert len(tiled.store) * 4 < len(small.store)
    centres, _ = small.voxels()
    for read in ("occupancy", "latent"):
        a = getattr(tiled, read)(centres, interpolate=False)
        b = getattr(small, read)(centres, interpolate=False)
        c = getattr(deferred, read)(centres, interpolate=False)
        # the same float64 system per tile, computed in the same kernel: equal values
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(c, b)
    for m in (tiled, small, deferred):
        m.close()


def test_with_pruning_only_the_pruned_voxels_differ() -> None:
    scans = _room(4)
    tiled = OnlineMap(_config(None, True))
    small = OnlineMap(_config(4, True))
    tiled.insert_scans(scans)
    small.insert_scans(scans)
    centres, _ = small.voxels()
    a = tiled.occupancy(centres, interpolate=False)
    b = small.occupancy(centres, interpolate=False)
    # a pruned leaf reads its least confident value: confident on both sides of the bounds
    differ = a != b
    assert ((a[differ] < 0.5) == (b[differ] < 0.5)).all()
    assert (np.minimum(a, b)[differ] < 0.5).sum() + (np.maximum(a, b)[differ] > 0.5).sum() > 0
    tiled.close()
    small.close()


@pytest.mark.parametrize(
    ("dim", "side", "tile", "halo"), [(3, 8, 4, 1), (2, 16, 4, 2), (3, 8, 2, 1)]
)
def test_tile_windows_are_the_tiles_halo_boxes(dim: int, side: int, tile: int, halo: int) -> None:
    grid = LeafGrid(dim, 0.2, 16, 16 - int(np.log2(side)), halo / side)
    layout = tile_layout(grid, tile)
    box = side + 2 * halo
    rng = np.random.default_rng(dim)
    values = rng.integers(0, 1000, (box,) * dim)  # indexed [z, y, x]: flat = x fastest
    voxels = rng.integers(0, 1000, (side,) * dim)
    for q, o in enumerate(itertools.product(range(side // tile), repeat=dim)):
        o = o[::-1]  # tile numbers: x fastest
        lo = [o[a] * tile for a in range(dim)]
        window = tuple(slice(lo[a], lo[a] + tile + 2 * halo) for a in reversed(range(dim)))
        inner = tuple(slice(lo[a], lo[a] + tile) for a in reversed(range(dim)))
        np.testing.assert_array_equal(values.ravel()[layout.window[q]], values[window].ravel())
        np.testing.assert_array_equal(voxels.ravel()[layout.voxels[q]], voxels[inner].ravel())
        np.testing.assert_array_equal(layout.corner[q], lo)


def test_tile_returns_match_a_tile_by_tile_split() -> None:
    dim, side, tile, halo, res = 3, 8, 4, 1, 0.2
    grid = LeafGrid(dim, res, 16, 13, halo / side)
    layout = tile_layout(grid, tile)
    box = side + 2 * halo
    rng = np.random.default_rng(5)
    per_leaf = np.array([0, 7, 1, 30])
    coords = rng.integers(0, box, (per_leaf.sum(), dim))
    pos = (coords - halo + rng.random(coords.shape)) * res
    weights = rng.integers(1, 4, per_leaf.sum()).astype(float)
    kept = KeptReturns(Returns(pos, weights, per_leaf), coords, pos + 10.0)  # leaves at 10 m
    tile_lo = np.tile(10.0 + layout.corner * res, (per_leaf.size, 1))
    out = tile_returns(kept, layout, tile_lo)
    starts = np.r_[0, np.cumsum(per_leaf)]
    rows_out = np.r_[0, np.cumsum(out.counts)]
    n_tiles = layout.window.shape[0]
    for j in range(per_leaf.size):
        for q in range(n_tiles):
            lo = layout.corner[q]
            mine = [
                r
                for r in range(starts[j], starts[j + 1])
                if ((coords[r] >= lo) & (coords[r] < lo + tile + 2 * halo)).all()
            ]
            k = j * n_tiles + q
            got = slice(rows_out[k], rows_out[k + 1])
            np.testing.assert_array_equal(out.points[got], (pos[mine] + 10.0) - (10.0 + lo * res))
            np.testing.assert_array_equal(out.weights[got], weights[mine])


@pytest.mark.parametrize(
    ("tile", "leaf_depth", "match"),
    [
        (3, None, "tile_voxels must be a power of two"),
        (32, None, "at most the leaf's edge"),
        (0, None, "tile_voxels"),
    ],
)
def test_bad_tile_sizes_name_the_field(tile: int, leaf_depth: int | None, match: str) -> None:
    from octolgp.config import LatticeConfig

    with pytest.raises(OctolgpError, match=match):
        MapConfig(dim=3, resolution=0.2, lattice=LatticeConfig(tile_voxels=tile))
