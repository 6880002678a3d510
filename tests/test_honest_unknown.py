"""Honest unknown (``LatticeConfig.fill_voxels``): the GP fills only near what was observed."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from octolgp import Hyperparameters, LatticeConfig, MapConfig, OctolgpError, OnlineMap, Scan
from octolgp.engines import lattice
from octolgp.engines.lattice import (
    LatticeEvidence,
    fit_lattice_leaves,
    observed_near,
    tile_layout,
    tiles_seeing,
)
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.sim.scenes import ray_box_distance

HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
ROOM = np.array([[3.0, 3.0, 7.0, 7.0]])  # a closed room: no beam gets inside


@pytest.mark.parametrize(("dim", "fill"), [(2, 0), (2, 1), (2, 2), (3, 0), (3, 1)])
def test_observed_near_is_the_brute_force_neighbourhood(dim: int, fill: int) -> None:
    config = MapConfig(dim=dim, resolution=0.1).resolve()
    grid = LeafGrid.from_config(config)
    side, halo = grid.side, grid.halo_voxels
    box = side + 2 * halo
    rng = np.random.default_rng(10 * dim + fill)
    stored = (rng.random((3, 2, box**dim)) < 0.02).astype(np.uint8)
    got = observed_near(stored, grid, fill)
    seen = (stored.sum(axis=1) > 0).reshape((3,) + (box,) * dim)
    for leaf in range(3):
        want = np.zeros((side,) * dim, dtype=bool)
        for v in itertools.product(range(side), repeat=dim):  # a small leaf: brute force
            lo = [c + halo - fill for c in v]
            window = seen[(leaf, *[slice(a, a + 2 * fill + 1) for a in lo])]
            want[v] = window.any()
        np.testing.assert_array_equal(got[leaf], want.reshape(-1))


def _scans(n: int) -> list[Scan]:
    """A 2D laser circling a closed room at 2 m from its walls (beams to 8 m)."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        origin = np.array([5.0, 5.0]) + 4.5 * np.array([np.cos(a), np.sin(a)])
        ang = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
        u = np.c_[np.cos(ang), np.sin(ang)]
        r = np.minimum(ray_box_distance(np.repeat(origin[None], 360, 0), u, ROOM), 8.0)
        out.append(Scan(origin=origin, points=origin + u * r[:, None], max_range=8.0))
    return out


def _map(fill: int) -> OnlineMap:
    config = MapConfig(
        dim=2, resolution=0.1, hyperparameters=HP, lattice=LatticeConfig(fill_voxels=fill)
    )
    m = OnlineMap(config)
    m.insert_scans(_scans(24))
    return m


def test_a_room_no_beam_entered_reads_unknown() -> None:
    inside = np.stack(np.meshgrid(np.arange(3.55, 6.5, 0.1), np.arange(3.55, 6.5, 0.1)), -1)
    inside = inside.reshape(-1, 2)
    honest, filled = _map(2), _map(-1)
    p = honest.occupancy(inside)
    q = filled.occupancy(inside)
    # farther than 2 voxels (and a voxel of interpolation) from the walls: unknown
    assert np.all(p == 0.5)
    # without the rule, the leaves along the walls fill the room's edge with values
    assert np.mean(q != 0.5) > 0.1
    # observed space reads as before: free in front of the walls, occupied on them
    free = np.array([[1.5, 5.0], [5.0, 8.5], [8.4, 4.0]])
    wall = np.array([[3.0, 5.0], [7.0, 4.2], [5.5, 3.0]])
    assert np.all(honest.occupancy(free) < 0.3)
    assert np.all(honest.occupancy(wall) > 0.7)
    np.testing.assert_allclose(honest.occupancy(free), filled.occupancy(free))
    # the voxels of the map leave out what holds no value, so exports do too
    centres, prob = honest.voxels()
    assert np.isfinite(prob).all()
    assert not np.any(np.all((centres > 3.35) & (centres < 6.65), axis=1))


def test_fill_voxels_is_checked_against_the_tile_halo() -> None:
    too_far = MapConfig(dim=3, resolution=0.2, lattice=LatticeConfig(fill_voxels=2))
    with pytest.raises(OctolgpError, match=r"LatticeConfig\.fill_voxels"):
        too_far.resolve()  # a config file may set the dimension later: checked at use
    with pytest.raises(OctolgpError, match=r"LatticeConfig\.fill_voxels"):
        OnlineMap(too_far)
    assert dataclasses.replace(too_far, dim=2).resolve().fill_voxels == 2
    with pytest.raises(OctolgpError, match=r"LatticeConfig\.fill_voxels"):
        LatticeConfig(fill_voxels=-2)
    assert MapConfig(dim=3, lattice=LatticeConfig(fill_voxels=1)).fill_voxels == 1


@pytest.mark.parametrize(("dim", "fill", "leaf_log2"), [(2, 2, 4), (2, 0, 4), (3, 1, 3), (3, 1, 4)])
def test_tiles_that_see_nothing_are_not_fitted_and_read_as_if_fitted(
    dim: int, fill: int, leaf_log2: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fit that leaves out the tiles without an observed voxel in their halo boxes
    equals the fit of every tile with the voxels far from every observation masked."""

    base = MapConfig(dim=dim, resolution=0.2, hyperparameters=HP)
    depth = base.tree_depth - leaf_log2
    online = dataclasses.replace(base.online, leaf_depth=depth, prune=None)
    skip = dataclasses.replace(
        base, online=online, lattice=LatticeConfig(fill_voxels=fill)
    ).resolve()
    every = dataclasses.replace(skip, lattice=dataclasses.replace(skip.lattice, fill_voxels=-1))
    rng = np.random.default_rng(7 * dim + fill + leaf_log2)
    grid = LeafGrid.from_config(skip)
    box = grid.side + 2 * grid.halo_voxels
    leaves = []
    swept_only = np.zeros(box**dim, dtype=bool)
    swept_only[rng.choice(box**dim, size=3, replace=False)] = True
    for j in range(6):  # sparse leaves: one seeing nothing, one swept only
        counts = np.zeros((2, box**dim), np.uint8)
        if 0 < j < 5:
            where = rng.choice(box**dim, size=int(0.01 * box**dim) + 1, replace=False)
            counts[1, where] = rng.integers(1, 4, where.size)
            counts[0, where[:2]] = 2
            counts[1, where[:2]] = 0
        swept = swept_only if j == 5 else np.zeros(0, dtype=bool)
        ev = LatticeEvidence(counts, np.zeros(0, np.int64), np.zeros((0, dim)), swept)
        leaves.append(Leaf(np.full(dim, 100 + j, np.int64), ev))
    layout = tile_layout(grid, skip.tile_voxels)
    stored = np.stack([leaf.evidence.counts for leaf in leaves])
    swept_all = np.zeros((len(leaves), box**dim), dtype=bool)
    swept_all[5] = swept_only
    seeing = tiles_seeing(stored, layout, swept_all)
    assert seeing[5].any()  # a swept voxel is seen
    assert not seeing.all()  # there are tiles to leave out
    fitted: list[int] = []
    posterior = lattice.lattice_posterior

    def counting(tables, hits, *args):  # type: ignore[no-untyped-def]
        fitted.append(hits.shape[0])
        return posterior(tables, hits, *args)

    monkeypatch.setattr(lattice, "lattice_posterior", counting)
    got = fit_lattice_leaves(leaves, skip, HP)
    assert sum(fitted) == int(seeing.sum())  # only the tiles that see something
    ref = fit_lattice_leaves(leaves, every, HP)
    far = ~observed_near(stored, grid, fill, swept_all)
    for g, r, mask in zip(got, ref, far, strict=True):
        for name in ("mean", "var", "prob"):
            want = getattr(r.leaf, name).copy()
            want[mask] = np.nan
            np.testing.assert_array_equal(getattr(g.leaf, name), want)
    assert np.isnan(got[0].leaf.prob).all()  # the leaf that saw nothing
    assert np.isfinite(got[5].leaf.prob).any()  # the swept one holds values near its voxels
