"""Scan → voxel observations, against a per-beam brute force."""

from __future__ import annotations

import numpy as np
import pytest

from octolgp import LatticeConfig, MapConfig, Scan
from octolgp.engines.lattice import LatticeEvidence
from octolgp.geometry.keys import return_steps, step_points
from octolgp.geometry.raycast import traverse_voxels
from octolgp.mapping.evidence import map_scans
from octolgp.observations import advance, merge_observations, newer_evidence_wins, observe


def _brute_force(
    scans: list[Scan], config: MapConfig, first: dict[tuple[int, ...], np.ndarray] | None = None
) -> dict[tuple[int, ...], list[int]]:
    """Per voxel [scans with a hit, scans with free and no hit], one beam at a time.

    A beam's free voxels are those of OctoMap's ray traversal (``traverse_voxels``) from
    the sensor to its free segment's end, and the end's own voxel.

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
            # every voxel the segment passes through: the traversal, and the end's own
            _, keys = traverse_voxels(scan.origin[None], end[None], res, config.tree_depth)
            free_vox.update(tuple(int(v) for v in k) for k in keys)
            free_vox.add(tuple(int(v) for v in np.floor(end / res).astype(int) + off))
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
            if h:  # the first return, at the cell of its voxel a leaf keeps it at
                point = first[tuple(int(v) for v in k)][None]
                key = k[None].astype(np.int64)
                kept = step_points(return_steps(point, key, 0.2, 16), key, 0.2, 16)[0]
                np.testing.assert_array_equal(p, kept)
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
    obs = observe(map_scans(scans, config), config)  # the scans as the map rounds them
    first = {int(k): p for k, p in zip(pack_keys(obs.keys), obs.first_hit, strict=True)}
    side, halo = m.grid.side, m.grid.halo_voxels
    box = side + 2 * halo
    for _, leaf in m.leaves():
        ev = leaf.evidence
        assert isinstance(ev, LatticeEvidence)
        assert ev.hit_keys.size == np.count_nonzero(ev.counts[0])
        for key, point in zip(ev.hit_keys.tolist(), ev.hits, strict=True):
            np.testing.assert_array_equal(point, first[key])  # the first, in time order
            local = np.floor(point / 0.2).astype(int) + (1 << 15) - (leaf.index * side - halo)
            assert ev.counts[0, local @ box ** np.arange(2)] > 0


def _flicker_scans(rng: np.random.Generator, dim: int, n: int) -> list[Scan]:
    """Scans whose beams end at one of two ranges at random: voxels seen hit, then free."""
    direction = rng.normal(size=(30, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    scans = []
    for _ in range(n):
        origin = rng.normal(scale=0.02, size=dim)
        r = np.where(rng.random(30) < 0.5, 1.0, 2.0) + rng.uniform(-0.05, 0.05, 30)
        scans.append(Scan(origin=origin, points=origin + r[:, None] * direction, max_range=4.0))
    return scans


def _one_by_one(
    scans: list[Scan], config: MapConfig, clear: int, cap: int
) -> dict[int, tuple[int, int, np.ndarray | None]]:
    """The rule's specification, ``newer_evidence_wins``, applied scan by scan."""
    from octolgp.geometry.keys import pack_keys

    state: dict[int, tuple[int, int, np.ndarray | None]] = {}
    for scan in scans:
        obs = observe([scan], config)  # one scan: per voxel, a return, free, or weakly free
        keys = pack_keys(obs.keys).tolist()
        before = [state.get(k, (0, 0, None)) for k in keys]
        hits, frees, renewed, forgotten = newer_evidence_wins(
            np.array([b[0] for b in before], dtype=np.int64),
            np.array([b[1] for b in before], dtype=np.int64),
            obs.hits > 0,
            obs.frees > 0,
            obs.weak_frees > 0,
            clear,
            cap,
        )
        for i, key in enumerate(keys):
            pos = obs.first_hit[i] if renewed[i] else None if forgotten[i] else before[i][2]
            state[key] = (int(hits[i]), int(frees[i]), pos)
    return state


@pytest.mark.parametrize(("clear", "cap"), [(0, 1), (0, 3), (1, 1), (2, 1), (3, 2), (5, 1)])
def test_the_newer_evidence_summary_is_the_rule_applied_scan_by_scan(clear: int, cap: int) -> None:
    from octolgp.config import OnlineConfig
    from octolgp.geometry.keys import pack_keys

    for dim in (2, 3):
        rng = np.random.default_rng(10 * clear + dim)
        scans = _flicker_scans(rng, dim, 14)
        config = MapConfig(dim=dim, resolution=0.1, online=OnlineConfig(clear_scans=clear))
        truth = _one_by_one(scans, config, clear, cap)
        # the whole run at once, and in parts merged, and in parts applied in turn
        whole = observe(scans, config)
        merged = merge_observations(
            [observe(scans[:5], config), observe(scans[5:6], config), observe(scans[6:], config)],
            dim,
        )
        for obs in (whole, merged):
            np.testing.assert_array_equal(obs.keys, whole.keys)
            zero = np.zeros(obs.hits.size, dtype=np.int64)
            got = advance(zero, zero, obs, np.arange(obs.hits.size), cap)
            for i, key in enumerate(pack_keys(obs.keys).tolist()):
                hits, frees, pos = truth[key]
                assert (got.hits[i], got.frees[i]) == (hits, frees)
                assert got.replace[i] == (pos is not None)
                if pos is not None:
                    np.testing.assert_array_equal(got.position[i], pos)
        # in parts applied in turn; one scan at a time, each with its own summary
        for parts in ((scans[:4], scans[4:9], scans[9:]), [[s] for s in scans]):
            state: dict[int, tuple[int, int, np.ndarray | None]] = {}
            for part in parts:
                obs = observe(part, config)
                keys = pack_keys(obs.keys).tolist()
                h0 = np.array([state.get(k, (0, 0, None))[0] for k in keys], dtype=np.int64)
                f0 = np.array([state.get(k, (0, 0, None))[1] for k in keys], dtype=np.int64)
                got = advance(h0, f0, obs, np.arange(len(keys)), cap)
                for i, k in enumerate(keys):
                    pos = state.get(k, (0, 0, None))[2]
                    if got.drop[i]:
                        pos = None
                    if got.replace[i]:
                        pos = got.position[i]
                    state[k] = (int(got.hits[i]), int(got.frees[i]), pos)
            assert state.keys() == truth.keys()
            for k, (hits, frees, pos) in truth.items():
                assert state[k][:2] == (hits, frees)
                assert (state[k][2] is None) == (pos is None)
                if pos is not None:
                    np.testing.assert_array_equal(state[k][2], pos)
        if clear:  # the runs exercise the rule: returns forgotten, frees near returns
            assert any(v[0] == 0 and v[1] >= clear for v in truth.values())
            assert whole.weak_frees.sum() > 0
        else:  # static: counts only add
            assert any(v[0] > 0 and v[1] > 0 for v in truth.values())


def test_frees_near_a_return_are_weak() -> None:
    """Weak: within clear_margin of the beam's own return, or on a no-return beam."""
    from octolgp.config import OnlineConfig
    from octolgp.geometry.keys import pack_keys

    config = MapConfig(
        dim=2,
        resolution=0.1,
        online=OnlineConfig(clear_scans=4),
        lattice=LatticeConfig(clear_margin=0.35),
    )
    # beam 0 ends at x = 3.05 (a return); beam 1 passes just above it to a return at 5.05;
    # beam 2 is a no-return along y = -0.15
    scan = Scan(
        origin=[0.05, 0.05], points=[[3.05, 0.05], [5.05, 0.15], [6.05, -0.15]], max_range=6.0
    )
    obs = observe([scan], config)
    weak = {int(k): int(w) for k, w in zip(pack_keys(obs.keys), obs.weak_frees, strict=True)}
    frees = {int(k): int(f) for k, f in zip(pack_keys(obs.keys), obs.frees, strict=True)}

    def key(x: float, y: float) -> int:
        return int(pack_keys((np.floor(np.array([[x, y]]) / 0.1) + (1 << 15)).astype(int))[0])

    assert frees[key(1.05, 0.05)] == 1
    assert weak[key(1.05, 0.05)] == 0  # far from any return
    assert frees[key(2.75, 0.05)] == 1
    assert weak[key(2.75, 0.05)] == 1  # 0.3 m before its return
    assert weak[key(4.05, 0.15)] == 0  # beam 1, far from its return
    assert weak[key(4.95, 0.15)] == 1  # beam 1, just before its return
    assert frees[key(4.05, -0.05)] == 1
    assert weak[key(4.05, -0.05)] == 1  # beam 2, a no-return
    static = observe([scan], MapConfig(dim=2, resolution=0.1, online=OnlineConfig(clear_scans=0)))
    assert static.weak_frees.sum() == 0
    np.testing.assert_array_equal(static.frees, obs.frees)  # weak or not, a free is a free


def test_effective_counts_count_free_looks_up_to_clear_scans() -> None:
    """Static: both counts up to evidence_cap. Newer evidence winning: a voxel holding a
    return is occupied only; one without counts its free looks up to clear_scans."""
    from octolgp.observations import effective_counts

    hits = np.array([0, 0, 0, 0, 1, 2])
    frees = np.array([0, 1, 3, 5, 2, 0])
    h, f = effective_counts(hits, frees, 1, 0)
    np.testing.assert_array_equal(h, [0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(f, [0, 1, 1, 1, 1, 0])
    h, f = effective_counts(hits, frees, 1, 4)
    np.testing.assert_array_equal(h, [0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(f, [0, 1, 3, 4, 0, 0])
    h, f = effective_counts(hits, frees, 8, 4)  # a larger cap wins
    np.testing.assert_array_equal(f, [0, 1, 3, 5, 0, 0])
