"""Observations in a region, and learning sets built from them, against the whole scans.

Oracles: :func:`octolgp.observations.observe` on every voxel, restricted to the region
afterwards; :func:`octolgp.gp.learning.sets_around` on every observed voxel with the
same seeds; a brute-force test of which blocks meet a ball.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from octolgp import MapConfig, OctolgpError, Scan
from octolgp.config import LearningConfig
from octolgp.geometry import ray_kernel
from octolgp.geometry.keys import KeyRegion, coord_to_key, key_to_coord, pack_keys
from octolgp.gp.learning import learning_voxel_sets, voxel_learning_sets, voxel_observations
from octolgp.mapping.online import OnlineMap
from octolgp.observations import VoxelObservations, observe


def _scans(dim: int, n_scans: int, n_beams: int, seed: int) -> list[Scan]:
    """Beams from a few origins to random walls, some far (the codes path) and no-returns."""
    rng = np.random.default_rng(seed)
    scans = []
    for _ in range(n_scans):
        origin = rng.uniform(-1.0, 1.0, dim)
        u = rng.normal(size=(n_beams, dim))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        length = np.where(rng.random(n_beams) < 0.2, 60.0, rng.uniform(0.5, 8.0, n_beams))
        scans.append(Scan(origin, origin + u * length[:, None], max_range=60.0))
    return scans


def _resolved(dim: int) -> MapConfig:
    return OnlineMap(MapConfig(dim=dim, resolution=0.2)).config


def _restricted(obs: VoxelObservations, keep: np.ndarray) -> dict[str, object]:
    return {
        f.name: (v[keep] if isinstance(v := getattr(obs, f.name), np.ndarray) else v)
        for f in dataclasses.fields(obs)
    }


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("dim", [2, 3])
def test_observations_in_a_region_are_the_whole_ones_there(
    dim: int, compiled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if compiled and not ray_kernel.AVAILABLE:
        pytest.skip("numba is not installed")
    monkeypatch.setattr(ray_kernel, "AVAILABLE", compiled)
    config = _resolved(dim)
    scans = _scans(dim, 3, 300, seed=dim)
    rng = np.random.default_rng(7)
    centres = np.concatenate([s.points for s in scans])[rng.choice(900, 3)]
    region = KeyRegion.around(centres, np.array([0.5, 1.5, 3.0]), 0.2, config.tree_depth)
    whole = observe(scans, config)
    part = observe(scans, config, region)
    keep = region.contains(pack_keys(whole.keys))
    assert 0 < keep.sum() < whole.n_voxels
    expected = _restricted(whole, keep)
    for name, value in _restricted(part, np.ones(part.n_voxels, dtype=bool)).items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, expected[name], err_msg=name)
        else:
            assert value == expected[name]


@pytest.mark.parametrize("dim", [2, 3])
def test_a_region_holds_exactly_the_blocks_that_meet_its_balls(dim: int) -> None:
    rng = np.random.default_rng(dim)
    centres = rng.uniform(-5.0, 5.0, (4, dim))
    radii = np.array([0.0, 0.3, 1.0, 2.5])
    region = KeyRegion.around(centres, radii, 0.1, 16, shift=2)
    points = rng.uniform(-9.0, 9.0, (60_000, dim))
    keys = coord_to_key(points, 0.1, 16)
    inside = region.contains(pack_keys(keys))
    # brute force: a voxel is in when its block (4 voxels on an edge) meets a ball
    corner = key_to_coord((keys >> 2) << 2, 0.1, 16) - 0.05  # the block's lower corner
    nearest = np.clip(centres[:, None, :], corner[None], corner[None] + 0.4)
    meets = np.any(np.sum((nearest - centres[:, None, :]) ** 2, axis=2) <= radii[:, None] ** 2, 0)
    np.testing.assert_array_equal(inside, meets)
    centre_in = np.any(
        np.linalg.norm(key_to_coord(keys, 0.1, 16)[None] - centres[:, None], axis=2)
        <= radii[:, None],
        axis=0,
    )
    assert np.all(inside[centre_in])  # every voxel whose centre is in a ball


def _assert_same_sets(a: list, b: list) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.items.nodes, y.items.nodes)
        np.testing.assert_array_equal(x.y, y.y)
        np.testing.assert_array_equal(x.noise_scale, y.noise_scale)


@pytest.mark.parametrize("dim", [2, 3])
def test_learning_sets_from_regions_are_those_of_every_voxel(dim: int) -> None:
    config = _resolved(dim)
    scans = _scans(dim, 4, 400, seed=10 + dim)
    points, y, weights = voxel_observations(scans, config)
    _assert_same_sets(
        learning_voxel_sets(scans, config), voxel_learning_sets(points, y, weights, config)
    )


def test_learning_sets_from_regions_where_returns_were_forgotten() -> None:
    """A wall seen once, then seen through scan after scan: its returns are forgotten,
    so they seed no set and sit in no set (the occupied voxels come from the region of
    the returns' blocks, as from every voxel)."""
    small = LearningConfig(max_clusters=8, max_items_per_cluster=20)  # 10 returns a set
    config = dataclasses.replace(_resolved(2), learning=small)
    angles = np.linspace(-0.6, 0.6, 200)
    u = np.c_[np.cos(angles), np.sin(angles)]
    origin = np.zeros(2)
    wall = Scan(origin, u * (2.0 / u[:, :1]))  # a wall at x = 2
    through = Scan(origin, u * (6.0 / u[:, :1]))  # later: gone, a wall at x = 6
    scans = [wall] + [through] * (config.clear_scans + 2)
    points, y, weights = voxel_observations(scans, config)
    assert not np.any((y > 0) & (points[:, 0] < 3.0))  # the first wall is forgotten
    sets = learning_voxel_sets(scans, config)
    _assert_same_sets(sets, voxel_learning_sets(points, y, weights, config))
    assert all(np.all(part.items.nodes[part.y > 0, 0] > 3.0) for part in sets)


def test_learning_in_a_region_refuses_scans_without_data_or_returns() -> None:
    config = _resolved(2)
    with pytest.raises(OctolgpError, match="no training data"):
        learning_voxel_sets([Scan(np.zeros(2), np.zeros((3, 2)))], config)
    blind = Scan(np.zeros(2), np.array([[5.0, 0.0], [0.0, 5.0]]), max_range=5.0)
    with pytest.raises(OctolgpError, match="no return"):
        learning_voxel_sets([blind], config)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_region_holding_keys_holds_exactly_their_blocks(dim: int) -> None:
    rng = np.random.default_rng(dim)
    keys = rng.integers(30000, 30100, (50, dim))
    region = KeyRegion.holding(np.unique(pack_keys(keys)), dim, shift=2)
    probe = rng.integers(29990, 30110, (20000, dim))
    blocks = {tuple(k) for k in (keys >> 2).tolist()}
    expected = np.array([tuple(k) in blocks for k in (probe >> 2).tolist()])
    np.testing.assert_array_equal(region.contains(pack_keys(probe)), expected)
