"""The compiled gather loops against their numpy forms: the same arrays, in the same order."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, Scan
from octolgp.config import LatticeConfig
from octolgp.engines import gather_kernel
from octolgp.engines.known import halo_pairs_numpy
from octolgp.engines.lattice import (
    LatticeEvidence,
    _advance_chord_pairs,
    _voxel_units,
    gather_observations,
)
from octolgp.mapping.grid import LeafGrid
from octolgp.observations import advance, observe
from octolgp.sweep import swept_keys

pytestmark = pytest.mark.skipif(not gather_kernel.AVAILABLE, reason="numba is not installed")


def _scans(dim: int, n: int, seed: int, near_zero: bool = False) -> list[Scan]:
    """Random scans; ``near_zero``: around the tree's lowest corner (keys near 0)."""
    rng = np.random.default_rng(seed)
    centre = np.full(dim, -3276.78 if near_zero else 0.0)  # the tree reaches -3276.8 m
    out = []
    for _ in range(n):
        origin = centre + rng.uniform(0.5, 1.0, dim) * (1 if near_zero else rng.choice([-1, 1]))
        ends = origin + rng.uniform(-2.5, 2.5, (300, dim))
        if near_zero:
            ends = np.maximum(ends, centre + 0.001)
        out.append(Scan(origin=origin, points=ends, max_range=2.0))
    return out


@pytest.mark.parametrize(
    ("dim", "leaf_log2", "halo", "near_zero"),
    [
        (2, 4, None, False),
        (2, 4, None, True),
        (3, 3, None, False),
        (3, 3, None, True),
        (3, 4, None, False),
        (2, 3, 0.0, False),
        (3, 2, 0.45, True),
    ],
)
def test_halo_pairs_equal_the_numpy_form(
    dim: int, leaf_log2: int, halo: float | None, near_zero: bool
) -> None:
    base = MapConfig(dim=dim, resolution=0.1)
    online = OnlineConfig(leaf_depth=base.tree_depth - leaf_log2, halo=halo)
    config = dataclasses.replace(base, online=online).resolve()
    grid = LeafGrid.from_config(config)
    obs = observe(_scans(dim, 2, 3 * dim + leaf_log2, near_zero), config)
    want = halo_pairs_numpy(obs.keys, grid)
    got = gather_kernel.halo_pairs(obs.keys, grid.side, grid.halo_voxels, 1 << grid.leaf_depth)
    for a, b in zip(got[:4], want[:4], strict=True):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == np.int64
    assert got[4:] == want[4:]


def test_halo_pairs_of_no_voxel() -> None:
    voxel, leaf, flat, cell, origin, extent = gather_kernel.halo_pairs(
        np.zeros((0, 3), np.int64), 8, 1, 1 << 13
    )
    assert voxel.size == leaf.size == flat.size == cell.size == 0
    assert origin == (0, 0, 0)
    assert extent == (1, 1, 1)


@pytest.mark.parametrize(("dim", "clear_scans"), [(2, 0), (2, 2), (3, 0), (3, 3)])
def test_advance_equals_the_numpy_rule(dim: int, clear_scans: int) -> None:
    """Every branch of the rule: random stored counts against runs of scans that see
    voxels occupied, free, free again (forgetting) and occupied again (restarts)."""
    config = MapConfig(dim=dim, resolution=0.1)
    config = dataclasses.replace(
        config, online=dataclasses.replace(config.online, clear_scans=clear_scans)
    ).resolve()
    rng = np.random.default_rng(dim + 10 * clear_scans)
    scans = _scans(dim, 6, 5 * dim + clear_scans)
    for lo, hi in ((0, 1), (0, 6), (2, 5)):
        obs = observe(scans[lo:hi], config)
        at = rng.integers(0, obs.n_voxels, 3 * obs.n_voxels)
        hits = rng.integers(0, 6, at.size)
        frees = rng.integers(0, 6, at.size)
        for cap in (1, 3, 255):
            want = advance(hits, frees, obs, at, cap)
            got = gather_kernel.advance(hits, frees, obs, at, cap)
            for name in ("hits", "frees", "position", "replace", "drop"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
            assert got.replace.any() or not want.replace.any()
    assert obs.clear_scans == clear_scans


@pytest.mark.parametrize(
    ("dim", "clear_scans", "fresh", "free_evidence", "reopened"),
    [
        (2, 0, True, "looks", False),
        (2, 2, False, "looks", False),
        (3, 3, True, "looks", False),
        (2, 0, True, "chord", False),
        (3, 3, True, "chord", False),
        (3, 3, True, "chord", True),
        (2, 2, True, "looks", True),
    ],
)
def test_the_gather_with_compiled_loops_equals_the_numpy_gather(
    dim: int,
    clear_scans: int,
    fresh: bool,
    free_evidence: str,
    reopened: bool,
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    """The gather's compiled form (each leaf's buffers read and written where they are)
    against its numpy form (the rows stacked): the same leaves, evidence and fresh
    tiles; ``reopened``: the leaves read back from a map file (counts and sums in
    arrays of their own)."""

    hp = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
    base = MapConfig(dim=dim, resolution=0.1, hyperparameters=hp)
    config = dataclasses.replace(
        base,
        online=dataclasses.replace(base.online, clear_scans=clear_scans),
        lattice=dataclasses.replace(base.lattice, free_evidence=free_evidence),
    )
    scans = _scans(dim, 5, 40 + dim)
    m = OnlineMap(config)
    m.insert_scans(scans[:4])
    m.settle()
    if reopened:
        m.save(tmp_path / "m.octolgp")
        m.close()
        m = OnlineMap.open(tmp_path / "m.octolgp")
    obs = observe(scans[4:], m.config)
    swept = swept_keys(scans[4:], m.config)
    out = []
    for compiled in (True, False):
        monkeypatch.setattr(gather_kernel, "AVAILABLE", compiled)
        out.append(
            gather_observations(obs, m.grid, m.config, m.store.get, fresh=fresh, swept=swept)
        )
    a, b = out
    assert a.touched == b.touched
    assert a.new_items == b.new_items
    for part in ("changed", "kept"):
        pa, pb = getattr(a, part), getattr(b, part)
        assert [k for k, _ in pa] == [k for k, _ in pb]
        for (_, la), (_, lb) in zip(pa, pb, strict=True):
            ea, eb = la.evidence, lb.evidence
            assert isinstance(ea, LatticeEvidence)
            assert isinstance(eb, LatticeEvidence)
            np.testing.assert_array_equal(ea.counts, eb.counts)
            np.testing.assert_array_equal(ea.hit_keys, eb.hit_keys)
            np.testing.assert_array_equal(ea.hits, eb.hits)
            np.testing.assert_array_equal(ea.swept, eb.swept)
            np.testing.assert_array_equal(ea.chord, eb.chord)
            assert ea.chord.size == (ea.counts.shape[1] if free_evidence == "chord" else 0)
            np.testing.assert_array_equal(la.index, lb.index)
    assert len(a.changed) > 0
    if fresh:
        assert a.fresh is not None
        assert b.fresh is not None
        np.testing.assert_array_equal(a.fresh, b.fresh)


@pytest.mark.parametrize("differ", ["none", "counts", "sums"])
def test_unit_values_read_each_leafs_buffers(differ: str) -> None:
    """The compiled read of each voxel's counts and sums from the leaves' own buffers
    (some leaves without counts or sums) against _voxel_units on the stacked rows: the
    same values for every voxel with copies, and None exactly where copies differ."""
    from octolgp.engines import leaf_buffers

    rng = np.random.default_rng(7)
    n, n_halo, n_leaves = 300, 50, 40
    counts = rng.integers(0, 6, (n_leaves, 2, n_halo)).astype(np.uint8)
    sums = rng.integers(0, 65535, (n_leaves, n_halo)).astype(np.uint16)
    no_counts, no_sums = [3, 17], [5, 17, 30]  # leaves without them: zero
    voxel = np.sort(rng.integers(0, n, 700))  # some voxels without a copy
    slot = rng.permutation(n_leaves * n_halo)[: voxel.size]  # each copy its own place
    inverse, flat = slot // n_halo, slot % n_halo
    first = np.r_[0, np.flatnonzero(np.diff(voxel)) + 1]  # each voxel's first copy
    owner = np.repeat(first, np.diff(np.r_[first, voxel.size]))
    counts[inverse, 0, flat] = counts[inverse[owner], 0, flat[owner]]
    counts[inverse, 1, flat] = counts[inverse[owner], 1, flat[owner]]
    sums[inverse, flat] = sums[inverse[owner], flat[owner]]
    # a voxel with a copy in a leaf without counts (sums) holds none in every copy
    for missing, values in ((no_counts, counts[:, 0]), (no_counts, counts[:, 1]), (no_sums, sums)):
        bare = np.isin(voxel, voxel[np.isin(inverse, missing)])
        values[inverse[bare], flat[bare]] = 0
    if differ != "none":  # one copy of a voxel with several copies disagrees
        bare = np.isin(voxel, voxel[np.isin(inverse, no_counts + no_sums)])
        i = int(np.flatnonzero((owner != np.arange(voxel.size)) & ~bare)[0])
        if differ == "counts":
            counts[inverse[i], 1, flat[i]] += 1
        else:
            sums[inverse[i], flat[i]] ^= 1
    leaf_counts = [None if j in no_counts else counts[j].copy() for j in range(n_leaves)]
    leaf_sums = [None if j in no_sums else sums[j].copy() for j in range(n_leaves)]
    sources = leaf_buffers.addresses(leaf_counts), leaf_buffers.addresses(leaf_sums)
    got = leaf_buffers.unit_values(voxel, inverse, flat, n_halo, *sources, n)
    h_p, f_p = counts[inverse, 0, flat].astype(np.int64), counts[inverse, 1, flat].astype(np.int64)
    w_p = sums[inverse, flat].astype(np.int64)
    unit, _, h, f = _voxel_units(h_p, f_p, voxel, n)
    w_unit, _, w, _ = _voxel_units(w_p, w_p, voxel, n)
    assert (got is None) == (differ != "none") == (unit is None or w_unit is None)
    if got is not None:
        held_voxels = np.unique(voxel)
        for a, b in zip(got, (h, f, w), strict=True):
            np.testing.assert_array_equal(a[held_voxels], b[held_voxels])
            assert not a[np.setdiff1d(np.arange(n), held_voxels)].any()


@pytest.mark.parametrize("clear_scans", [0, 3])
@pytest.mark.parametrize("n_scans", [1, 3])
def test_chord_rule_and_flags_equal_the_numpy_form(clear_scans: int, n_scans: int) -> None:
    """The compiled chord step (the rule per voxel, the leaves' flags per pair, the new
    sums written to each pair's leaf) against its numpy form: the same sums, the same
    leaves refitted and stored, the same pairs whose input moved."""
    from octolgp.engines import leaf_buffers

    config = MapConfig(
        dim=2,
        resolution=0.1,
        online=OnlineConfig(clear_scans=clear_scans),
        lattice=LatticeConfig(free_evidence="chord"),
    ).resolve()
    obs = observe(_scans(2, n_scans, 11 + clear_scans), config)
    n = obs.n_voxels
    rng = np.random.default_rng(3 + clear_scans)
    n_halo, n_leaves = 60, 80
    chord = rng.integers(0, 3000, (n_leaves, n_halo)).astype(np.uint16)
    chord[rng.random(chord.shape) < 0.1] = 65535  # some saturated
    voxel = np.sort(rng.integers(0, n, 2 * n))  # some voxels without a copy
    slot = rng.permutation(n_leaves * n_halo)[: voxel.size]  # each copy its own place
    inverse, flat = slot // n_halo, slot % n_halo
    at_w = inverse * n_halo + flat
    first = np.r_[0, np.flatnonzero(np.diff(voxel)) + 1]  # each voxel's first copy
    owner = np.repeat(first, np.diff(np.r_[first, voxel.size]))
    flat_chord = chord.reshape(-1)
    flat_chord[at_w] = flat_chord[at_w[owner]]  # every copy holds its voxel's sum
    ef0 = rng.integers(0, 2, n) * rng.integers(1, 4, n)
    ef1 = rng.integers(0, 2, n) * rng.integers(1, 4, n)
    counts0 = rng.integers(0, 2, n), rng.integers(0, max(clear_scans, 1) + 1, n)
    refit = rng.random(n_leaves) < 0.1  # leaves the counts already change
    new_counts = refit | (rng.random(n_leaves) < 0.1)
    # numpy
    want_sums = flat_chord.copy()
    want_refit, want_new = refit.copy(), new_counts.copy()
    want_moved = _advance_chord_pairs(
        voxel, at_w, inverse, want_sums, obs, voxel, counts0, (ef0, ef1), want_refit, want_new
    )
    # compiled: each voxel's sum once, the flags, then the sums into each leaf's copy
    w0 = np.zeros(n, dtype=np.int64)
    w0[voxel] = flat_chord[at_w]
    w1, flag = gather_kernel.chord_rule(obs, w0, counts0, (ef0, ef1))
    none = np.zeros(n, dtype=bool)
    got_refit, got_new, gained, got_moved = gather_kernel.leaf_flags(
        voxel, inverse, (none, none, none, none), flag, n_leaves
    )
    assert gained == 0
    buffers = [chord[j].copy() for j in range(n_leaves)]
    at = leaf_buffers.addresses(buffers)
    zero = np.zeros(n, dtype=np.int64)
    leaf_buffers.write_pairs(voxel, inverse, flat, n_halo, np.zeros_like(at), at, zero, zero, w1)
    np.testing.assert_array_equal(np.stack(buffers).reshape(-1), want_sums)
    np.testing.assert_array_equal(got_refit | refit, want_refit)
    np.testing.assert_array_equal(got_new | new_counts, want_new)
    np.testing.assert_array_equal(got_moved, want_moved)
    assert got_moved.any()
    assert not np.array_equal(want_sums, flat_chord)
