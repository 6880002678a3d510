"""The lattice engine's per-leaf fast paths give the maps of the straightforward ones.

The gather, the fitted leaves and the store's accounting each have a plain reference
here (a loop per leaf, the rule run on every voxel copy, byte counts recomputed from the
leaves); maps built with the package's paths and with these agree in every leaf field,
the store's LRU order, dirty set and byte count, after every insert.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable

import numpy as np
import pytest

import octolgp.engines.lattice as lattice_module
import octolgp.mapping.online as online_module
from octolgp import Hyperparameters, MapConfig, OnlineMap, Scan
from octolgp.config import LatticeConfig
from octolgp.engines.base import Evidence, LeafFit, Lookup, evidence_arrays, with_values
from octolgp.engines.lattice import (
    LatticeEvidence,
    _moved_returns,
    gather_observations,
    halo_copies,
    lattice_evidence,
    map_tables,
    return_points,
)
from octolgp.geometry import ray_kernel
from octolgp.geometry.keys import unpack_keys
from octolgp.gp.lattice import Returns, lattice_posterior
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf, LeafStore
from octolgp.observations import (
    VoxelObservations,
    advance,
    advance_chord,
    effective_counts,
    observe,
)
from octolgp.sim.lidar3d import simulate_lidar_room

HP = Hyperparameters(
    length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0, beta=0.0
)
SMALL_LEAVES = MapConfig(dim=3).tree_depth - 3
"""Leaves of 8³ voxels: a scan there touches leaves whose GP inputs stay the same (kept),
the path these tests need besides the refitted one."""


def reference_gather(
    obs: VoxelObservations,
    grid: LeafGrid,
    config: MapConfig,
    lookup: Lookup,
    *,
    fresh: bool = True,
    swept: np.ndarray | None = None,
) -> Evidence:
    """The gather done plainly: the rule on every voxel copy, one leaf at a time.

    It works out no fresh tiles (``fresh`` is unused): its leaves are refitted whole.
    The scenes here sweep no voxel between beams (``swept`` is empty).
    """
    if swept is not None and swept.size:
        raise NotImplementedError("the reference gather takes no swept voxels")
    voxel, leaf_key, flat = halo_copies(obs, grid)
    touched = np.unique(leaf_key)
    inverse = np.searchsorted(touched, leaf_key)
    n_halo = (grid.side + 2 * grid.halo_voxels) ** grid.dim
    old = np.zeros((touched.size, 2, n_halo), dtype=np.uint8)
    old_w = np.zeros((touched.size, n_halo), dtype=np.uint16)  # summed chord shares
    current: list[Leaf | None] = []
    for j, key in enumerate(touched.tolist()):
        leaf = lookup(key)
        current.append(leaf)
        counts = None if leaf is None else lattice_evidence(leaf).counts
        if counts is not None and counts.shape[1] == n_halo:
            old[j] = counts
        chord = None if leaf is None else lattice_evidence(leaf).chord
        if chord is not None and chord.size == n_halo:
            old_w[j] = chord
    cap = config.lattice.evidence_cap
    at_h = inverse * (2 * n_halo) + flat
    before_h = old.reshape(-1)[at_h].astype(np.int64)
    before_f = old.reshape(-1)[at_h + n_halo].astype(np.int64)
    state = advance(before_h, before_f, obs, voxel, cap)
    new = old.copy()
    new.reshape(-1)[at_h] = state.hits
    new.reshape(-1)[at_h + n_halo] = state.frees
    eh0, ef0 = effective_counts(before_h, before_f, cap, obs.clear_scans)
    eh1, ef1 = effective_counts(state.hits, state.frees, cap, obs.clear_scans)
    d_h, d_f = eh1 != eh0, ef1 != ef0
    moves = state.replace | state.drop
    effective = d_h | d_f | moves
    stored = effective | (state.hits != before_h) | (state.frees != before_f)
    new_w = old_w.copy()
    if obs.chord is not None:  # the rule on every copy's summed shares
        at_w = inverse * n_halo + flat
        w0 = old_w.reshape(-1)[at_w].astype(np.int64)
        w1 = advance_chord(w0, before_h, before_f, obs, voxel)
        new_w.reshape(-1)[at_w] = w1
        w_input = np.where(ef1 > 0, w1, 0) != np.where(ef0 > 0, w0, 0)
        effective = effective | w_input
        stored = stored | w_input | (w1 != w0)
    refit = np.zeros(touched.size, dtype=bool)
    refit[inverse[effective]] = True
    mv = np.flatnonzero(moves)
    returns = _moved_returns(
        current,
        inverse[mv],
        voxel[mv],
        state.drop[mv],
        state.replace[mv],
        state.position[mv],
        obs.keys,
        grid.dim,
    )
    changed: list[tuple[int, Leaf]] = []
    kept: list[tuple[int, Leaf]] = []
    index = unpack_keys(touched, grid.dim)
    for j in np.unique(inverse[stored]).tolist():
        leaf = current[j]
        if leaf is None:
            leaf = Leaf(index[j].copy(), LatticeEvidence.empty(grid.dim))
        ev = lattice_evidence(leaf)
        hit_keys, hits = returns.get(j, (ev.hit_keys, ev.hits))
        chord = new_w[j].copy() if obs.chord is not None else ev.chord
        evidence = LatticeEvidence(new[j].copy(), hit_keys, hits, ev.swept, chord)
        leaf = leaf.evolve(evidence=evidence)
        (changed if refit[j] else kept).append((int(touched[j]), leaf))
    return Evidence(changed, touched.tolist(), int(d_h.sum() + d_f.sum()), kept)


def reference_return_points(leaves: list[Leaf], grid: LeafGrid, evidence_cap: int) -> Returns:
    """The kept returns of leaves, read leaf by leaf."""
    box, halo, d = grid.side + 2 * grid.halo_voxels, grid.halo_voxels, grid.dim
    evidence = [lattice_evidence(leaf) for leaf in leaves]
    n_kept = np.array([ev.hit_keys.size for ev in evidence], dtype=np.int64)
    if not n_kept.sum():
        return Returns(np.zeros((0, d)), np.zeros(0), n_kept)
    index = np.stack([leaf.index for leaf in leaves])
    owner = np.repeat(np.arange(len(leaves)), n_kept)
    keys = np.concatenate([ev.hit_keys for ev in evidence])
    corner = index[owner] * grid.side - halo
    flat = (unpack_keys(keys, d) - corner) @ (box ** np.arange(d, dtype=np.int64))
    counts = np.stack([ev.counts[0] for ev in evidence])
    weights = np.minimum(counts[owner, flat], evidence_cap).astype(np.float64)
    lo, _ = grid.box(index)
    pos = np.concatenate([ev.hits for ev in evidence]) - lo[owner]
    return Returns(pos, weights, n_kept)


def reference_fit(
    leaves: list[Leaf],
    config: MapConfig,
    hp: Hyperparameters,
    pool: object = None,
    fresh: object = None,
) -> list[LeafFit]:
    """The lattice fit on one thread, tile by tile, its inputs read and its leaves made one
    by one: each tile's halo box sliced out of its leaf's, its returns picked one by one.
    Every tile is refitted (``fresh`` is ignored): keeping fresh tiles must not matter."""
    if not leaves:
        return []
    lc = config.lattice
    grid = LeafGrid.from_config(config)
    side, halo, d, t = grid.side, grid.halo_voxels, grid.dim, config.tile_voxels
    box, per_axis = side + 2 * halo, side // t
    tile_grid = dataclasses.replace(grid, leaf_depth=grid.leaf_depth + int(np.log2(per_axis)))
    tiles = [o[::-1] for o in itertools.product(range(per_axis), repeat=d)]  # x fastest
    hit_rows, free_rows, tile_points = [], [], []
    chord_mode = config.free_evidence == "chord"
    weight = lc.chord_weight / ray_kernel.CHORD_UNITS if chord_mode else lc.free_weight
    for leaf in leaves:
        ev = lattice_evidence(leaf)
        h, f = effective_counts(ev.counts[0], ev.counts[1], lc.evidence_cap, config.clear_scans)
        if chord_mode:  # a free voxel weighs its summed chord shares
            f = np.where(f > 0, ev.chord, 0)
        h, f = h.reshape((box,) * d), f.reshape((box,) * d)  # [z, y, x]
        coords = unpack_keys(ev.hit_keys, d) - (leaf.index * side - halo)
        flat = coords @ (box ** np.arange(d))
        for o in tiles:
            lo = np.array(o) * t
            window = tuple(slice(lo[a], lo[a] + t + 2 * halo) for a in reversed(range(d)))
            hit_rows.append(h[window].ravel())
            free_rows.append(f[window].ravel())
            inside = [
                i
                for i in range(coords.shape[0])
                if ((coords[i] >= lo) & (coords[i] < lo + t + 2 * halo)).all()
            ]
            corner, _ = tile_grid.box((leaf.index * per_axis + np.array(o))[None])
            weights = np.minimum(ev.counts[0][flat[inside]], lc.evidence_cap).astype(float)
            tile_points.append((ev.hits[inside] - corner[0], weights))
    tables = map_tables(config, hp)
    tile_mean, tile_var = lattice_posterior(
        tables,
        np.array(hit_rows),
        np.array(free_rows),
        weight,
        Returns.from_list(tile_points, d),
    )
    mean = np.empty((len(leaves),) + (side,) * d)
    var = np.empty_like(mean)
    for j, q in itertools.product(range(len(leaves)), range(len(tiles))):
        lo = np.array(tiles[q]) * t
        inner = (j, *(slice(lo[a], lo[a] + t) for a in reversed(range(d))))
        mean[inner] = tile_mean[j * len(tiles) + q].reshape((t,) * d)
        var[inner] = tile_var[j * len(tiles) + q].reshape((t,) * d)
    mean, var = mean.reshape(len(leaves), -1), var.reshape(len(leaves), -1)
    prob = latent_occupancy(mean, var, hp)
    k = config.fill_voxels
    if k >= 0:  # no value where no voxel within k was observed, voxel by voxel
        for j, leaf in enumerate(leaves):
            seen = (lattice_evidence(leaf).counts.sum(axis=0) > 0).reshape((box,) * d)
            for v in itertools.product(range(side), repeat=d):  # v in [z, y, x] order
                window = tuple(slice(c + halo - k, c + halo + k + 1) for c in v)
                if not seen[window].any():
                    flat = sum(c * side**a for a, c in enumerate(reversed(v)))
                    mean[j, flat] = var[j, flat] = prob[j, flat] = np.nan
    prune = config.prune
    return [
        LeafFit(with_values(leaf, mean[j], var[j], prob[j], prune), 0)
        for j, leaf in enumerate(leaves)
    ]


class ReferenceStore(LeafStore):
    """The store with its byte count recomputed from the leaves at every change."""

    def get(self, key: int) -> Leaf | None:
        key = int(key)
        leaf = self._leaves.get(key)
        if leaf is not None:
            self._leaves.move_to_end(key)
            return leaf
        if key not in self._keys or self.backing is None:
            return None
        leaf = self.backing.read_leaf(key)
        self._leaves[key] = leaf
        self._nbytes += leaf.nbytes
        self.loads += 1
        return leaf

    def apply(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        touched: Iterable[int] = (),
        scan: int | None = None,
    ) -> None:
        if scan is not None:
            for key in touched:
                leaf = self.get(key)
                if leaf is not None:
                    leaf.touched = scan
        for key, leaf in leaves:
            key = int(key)
            if scan is not None:
                leaf.touched = scan
            old = self._leaves.get(key)
            self._nbytes += leaf.nbytes - (old.nbytes if old is not None else 0)
            self._leaves[key] = leaf
            self._leaves.move_to_end(key)
            self._keys.add(key)
            self._dirty.add(key)
            if leaf.pending:
                self._pending.add(key)
            else:
                self._pending.discard(key)

    def remove(self, keys: Iterable[int]) -> None:
        for key in keys:
            key = int(key)
            old = self._leaves.pop(key, None)
            if old is not None:
                self._nbytes -= old.nbytes
            self._keys.discard(key)
            self._dirty.discard(key)
            self._pending.discard(key)

    def trim(self) -> int:
        if self.budget_bytes is None or self.backing is None:
            return 0
        evicted, room = 0, max(self.budget_bytes - self.reserve_bytes, 0)
        for key in list(self._leaves):
            if self._nbytes <= room:
                break
            if key in self._dirty:
                continue
            self._nbytes -= self._leaves.pop(key).nbytes
            self._pending.discard(key)  # the file gives it back to be fitted as it is read
            evicted += 1
        self.evictions += evicted
        return evicted


def _scans(n: int) -> list[Scan]:
    room = simulate_lidar_room(
        n, seed=4, n_azimuth=256, n_elevation=16, max_range=12.0, range_noise=0.02, n_heldout=1
    )
    return [s.downsample(0.2) for s in room.scans()]


def _config(
    clear_scans: int | None,
    budget: float | None,
    prune: bool | None = None,
    defer: bool = True,
    leaf_depth: int | None = SMALL_LEAVES,
    free_evidence: str | None = None,
) -> MapConfig:
    lattice = LatticeConfig(free_evidence=free_evidence)
    config = MapConfig(dim=3, resolution=0.2, memory_budget_mb=budget, lattice=lattice)
    online = dataclasses.replace(
        config.online,
        n_jobs=1,
        clear_scans=clear_scans,
        prune=prune,
        defer_fit=defer,
        leaf_depth=leaf_depth,
    )
    return dataclasses.replace(config, hyperparameters=HP, online=online)


def _leaf_state(leaf: Leaf) -> tuple[object, ...]:
    arrays = (leaf.index, leaf.mean, leaf.var, leaf.prob, *evidence_arrays(leaf.evidence))
    return (
        type(leaf.evidence),
        tuple((a.dtype.str, a.shape, a.tobytes()) for a in arrays),
        leaf.pruned,
        leaf.refits,
        leaf.touched,
        leaf.pending,
    )


def _store_state(store: LeafStore) -> tuple[object, ...]:
    resident = list(store._leaves.items())
    return (
        [k for k, _ in resident],  # LRU order
        [_leaf_state(leaf) for _, leaf in resident],
        sorted(store),
        store.dirty,
        store.nbytes,
        store.loads,
        store.evictions,
    )


def _evidence_state(evidence: Evidence) -> tuple[object, ...]:
    return (
        [(k, _leaf_state(leaf)) for k, leaf in evidence.changed],
        [(k, _leaf_state(leaf)) for k, leaf in evidence.kept],
        evidence.touched,
        evidence.new_items,
    )


@pytest.mark.parametrize(
    ("clear_scans", "budget", "prune", "defer", "leaf_depth", "free_evidence"),
    [
        (None, None, None, False, SMALL_LEAVES, None),
        (None, None, None, True, SMALL_LEAVES, None),
        (None, None, None, True, None, None),  # the default leaves
        (None, None, None, True, None, "looks"),
        (0, None, True, False, SMALL_LEAVES, None),
        (0, None, None, True, SMALL_LEAVES, "looks"),
        (2, 0.05, True, True, SMALL_LEAVES, None),  # a budget's spill file: fitted at every insert
    ],
)
def test_maps_equal_those_of_the_straightforward_path(
    monkeypatch: pytest.MonkeyPatch,
    clear_scans: int | None,
    budget: float | None,
    prune: bool | None,
    defer: bool,
    leaf_depth: int | None,
    free_evidence: str | None,
) -> None:
    scans = _scans(6)
    config = _config(clear_scans, budget, prune, defer, leaf_depth, free_evidence)
    fast = OnlineMap(config)
    with monkeypatch.context() as m:
        m.setattr(lattice_module, "gather_observations", reference_gather)
        m.setattr(online_module, "LeafStore", ReferenceStore)
        plain = OnlineMap(config)
        assert type(plain.store) is ReferenceStore
    for scan in scans:
        a = fast.insert_scan(scan)
        with monkeypatch.context() as m:
            m.setattr(lattice_module, "gather_observations", reference_gather)
            m.setattr(lattice_module, "fit_lattice_leaves", reference_fit)
            b = plain.insert_scan(scan)
        assert (a.touched_leaves, a.refit_leaves, a.new_items, a.pruned_leaves, a.n_leaves) == (
            b.touched_leaves,
            b.refit_leaves,
            b.new_items,
            b.pruned_leaves,
            b.n_leaves,
        )
        assert _store_state(fast.store) == _store_state(plain.store)
        resident = fast.store._leaves.values()
        assert fast.store.nbytes == sum(leaf.nbytes for leaf in resident)
    assert a.refit_leaves
    if leaf_depth == SMALL_LEAVES:
        assert a.touched_leaves > a.refit_leaves  # kept leaves too
    if budget is None:  # under a tiny budget every written leaf is evicted, pending or not
        assert bool(fast.store.pending) == fast.defers_fit
    fast.settle()
    with monkeypatch.context() as m:
        m.setattr(lattice_module, "fit_lattice_leaves", reference_fit)
        plain.settle()
    assert _store_state(fast.store) == _store_state(plain.store)
    if budget is not None:
        assert fast.store.evictions
        assert fast.store.loads
    fast.close()
    plain.close()


def _stored_leaves(config: MapConfig, scans: list[Scan]) -> dict[int, Leaf]:
    m = OnlineMap(config)
    for scan in scans:
        m.insert_scan(scan)
    leaves = dict(m.store.items())
    m.close()
    return leaves


def test_gather_equals_the_straightforward_path_when_copies_differ() -> None:
    """Stored counts that disagree between a voxel's copies, or are not sized yet."""
    scans = _scans(4)
    config = _config(2, None)
    grid = LeafGrid.from_config(config)
    leaves = _stored_leaves(config, scans[:2])
    rng = np.random.default_rng(5)
    for key in list(leaves)[::3]:  # random counts: copies of shared voxels differ
        leaf = leaves[key]
        ev = lattice_evidence(leaf)
        counts = rng.integers(0, 3, ev.counts.shape).astype(np.uint8)
        leaves[key] = leaf.evolve(evidence=LatticeEvidence(counts, ev.hit_keys, ev.hits))
    for key in list(leaves)[1::7]:  # never sized: counts of zero length
        leaves[key] = leaves[key].evolve(evidence=LatticeEvidence.empty(3))
    obs = observe(scans[2:], config)
    a = gather_observations(obs, grid, config, leaves.get)
    b = reference_gather(obs, grid, config, leaves.get)
    assert a.changed
    assert a.kept
    assert _evidence_state(a) == _evidence_state(b)
    # each leaf owns its counts (and chord sums): one buffer of its own, of just them
    evs = [lattice_evidence(leaf) for _, leaf in [*a.changed, *a.kept]]
    owners = [ev.counts if ev.counts.base is None else ev.counts.base for ev in evs]
    assert len({id(o) for o in owners}) == len(owners)
    for ev, owner in zip(evs, owners, strict=True):
        assert owner.nbytes == ev.counts.nbytes + ev.chord.nbytes
        assert ev.chord.size == 0 or np.shares_memory(ev.chord, owner)


def test_gather_equals_the_straightforward_path_on_one_short_beam() -> None:
    config = _config(None, None)
    grid = LeafGrid.from_config(config)
    obs = observe([Scan(np.zeros(3), np.array([[0.5, 0.1, 0.0]]), 12.0)], config)
    a = gather_observations(obs, grid, config, lambda _: None)
    b = reference_gather(obs, grid, config, lambda _: None)
    assert _evidence_state(a) == _evidence_state(b)


def test_gather_refuses_another_engines_evidence() -> None:
    config = _config(None, None)
    grid = LeafGrid.from_config(config)
    scans = _scans(2)
    leaves = _stored_leaves(config, scans[:1])
    key = next(iter(leaves))
    leaves[key] = leaves[key].evolve(evidence=object())
    with pytest.raises(TypeError, match="not the lattice engine's evidence"):
        gather_observations(observe(scans, config), grid, config, leaves.get)


def test_leaf_fast_copies_equal_evolve() -> None:
    leaf = Leaf(np.array([1, 2, 3]), LatticeEvidence.empty(3), refits=4, touched=9)
    ev = LatticeEvidence.empty(3)
    values = [np.full(2, x, np.float32) for x in (1.0, 2.0, 3.0)]
    pairs = [
        (leaf.with_evidence(ev), leaf.evolve(evidence=ev)),
        (
            leaf.refitted(*values, True),
            leaf.evolve(mean=values[0], var=values[1], prob=values[2], pruned=True, refits=5),
        ),
    ]
    for fast, plain in pairs:
        for f in dataclasses.fields(Leaf):
            assert getattr(fast, f.name) is getattr(plain, f.name) or (
                getattr(fast, f.name) == getattr(plain, f.name)
            )
    with pytest.raises(TypeError, match="no field 'colour'"):
        leaf.evolve(colour=1)


def test_return_points_equal_those_read_leaf_by_leaf() -> None:
    config = _config(None, None)
    grid = LeafGrid.from_config(config)
    leaves = list(_stored_leaves(config, _scans(2)).values())
    a = return_points(leaves, grid, 2)
    b = reference_return_points(leaves, grid, 2)
    assert a.counts.sum()
    for name in ("points", "weights", "counts"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
