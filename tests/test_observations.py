"""Scan → voxel observations, against a per-beam brute force."""

from __future__ import annotations

import numpy as np

from octolgp import MapConfig, Scan
from octolgp.observations import merge_observations, observe


def _brute_force(
    scans: list[Scan], config: MapConfig, first: dict[tuple[int, ...], np.ndarray] | None = None
) -> dict[tuple[int, ...], list[int]]:
    """Per voxel [scans with a hit, scans with free and no hit], one beam at a time.

    ``first`` receives each voxel's first return.
    """
    res, off = config.resolution, 1 << (config.tree_depth - 1)
    counts: dict[tuple[int, ...], list[int]] = {}
    first = {} if first is None else first
    for scan in scans:
        hit_vox: set[tuple[int, ...]] = set()
        free_vox: set[tuple[int, ...]] = set()
        for p in scan.points:
            d = float(np.linalg.norm(p - scan.origin))
            if d <= 1e-9:
                continue
            u = (p - scan.origin) / d
            no_return = scan.max_range is not None and d >= scan.max_range * (1 - 1e-9)
            if not no_return:
                key = tuple(int(v) for v in np.floor(p / res).astype(int) + off)
                hit_vox.add(key)
                first.setdefault(key, p)
            length = min(d, scan.max_range) if no_return else d - config.free_margin
            if length <= 1e-9:
                continue
            end = scan.origin + u * length
            n = int(np.floor(length / (res / 2))) + 2
            for j in range(n):
                t = min(j * res / 2, length) / length
                q = scan.origin + (end - scan.origin) * t
                free_vox.add(tuple(int(v) for v in np.floor(q / res).astype(int) + off))
        for v in hit_vox:
            counts.setdefault(v, [0, 0])[0] += 1
        for v in free_vox - hit_vox:
            counts.setdefault(v, [0, 0])[1] += 1
    return counts


def _scans(rng: np.random.Generator, dim: int) -> list[Scan]:
    scans = []
    for _ in range(3):
        origin = rng.uniform(-1, 1, dim)
        direction = rng.normal(size=(25, dim))
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        r = rng.uniform(0.0, 3.0, 25)
        r[:3] = 4.0  # no-returns
        r[3] = 0.0  # a beam on its sensor
        scans.append(Scan(origin=origin, points=origin + r[:, None] * direction, max_range=4.0))
    scans.append(scans[0])  # a scan seen twice counts twice
    return scans


def test_observations_match_a_per_beam_brute_force() -> None:
    rng = np.random.default_rng(0)
    for dim in (2, 3):
        config = MapConfig(dim=dim, resolution=0.2)
        scans = _scans(rng, dim)
        obs = observe(scans, config)
        first: dict[tuple[int, ...], np.ndarray] = {}
        truth = _brute_force(scans, config, first)
        got = {
            tuple(int(v) for v in k): [int(h), int(f)]
            for k, h, f in zip(obs.keys, obs.hits, obs.frees, strict=True)
        }
        assert got == truth
        assert obs.hits.max() >= 2  # the repeated scan
        for k, h, p in zip(obs.keys, obs.hits, obs.first_hit, strict=True):
            if h:
                np.testing.assert_array_equal(p, first[tuple(int(v) for v in k)])
            else:
                assert np.isnan(p).all()


def test_observations_of_parts_add_up_to_the_whole() -> None:
    rng = np.random.default_rng(1)
    config = MapConfig(dim=3, resolution=0.1)
    scans = _scans(rng, 3)
    whole = observe(scans, config)
    parts = merge_observations([observe(scans[:1], config), observe(scans[1:], config)], 3)
    np.testing.assert_array_equal(whole.keys, parts.keys)
    np.testing.assert_array_equal(whole.hits, parts.hits)
    np.testing.assert_array_equal(whole.frees, parts.frees)
    np.testing.assert_array_equal(whole.first_hit, parts.first_hit)


def test_a_hit_voxel_is_not_free_in_the_same_scan() -> None:
    config = MapConfig(dim=2, resolution=0.1, training=MapConfig().training)
    # the second beam passes through the first beam's hit voxel
    scan = Scan(origin=[0.0, 0.05], points=[[0.55, 0.05], [1.55, 0.05]])
    obs = observe([scan], config)
    key = np.floor(np.array([0.55, 0.05]) / 0.1).astype(int) + (1 << 15)
    row = int(np.flatnonzero((obs.keys == key).all(1))[0])
    assert (obs.hits[row], obs.frees[row]) == (1, 0)


def test_a_lattice_leaf_keeps_the_first_return_of_each_voxel_it_sees_occupied() -> None:
    from octolgp import Hyperparameters, OnlineMap
    from octolgp.geometry.keys import pack_keys

    config = MapConfig(dim=2, resolution=0.2, hyperparameters=Hyperparameters(0.6))
    scans = _scans(np.random.default_rng(4), 2)
    m = OnlineMap(config)
    m.insert_scans(scans)
    obs = observe(scans, config)
    first = {int(k): p for k, p in zip(pack_keys(obs.keys), obs.first_hit, strict=True)}
    side, halo = m.grid.side, m.grid.halo_voxels
    box = side + 2 * halo
    for _, leaf in m.leaves():
        assert leaf.hit_keys.size == np.count_nonzero(leaf.counts[0])
        for key, point in zip(leaf.hit_keys.tolist(), leaf.hits, strict=True):
            np.testing.assert_array_equal(point, first[key])  # the first, in time order
            local = np.floor(point / 0.2).astype(int) + (1 << 15) - (leaf.index * side - halo)
            assert leaf.counts[0, local @ box ** np.arange(2)] > 0
