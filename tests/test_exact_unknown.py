"""Honest unknown in the exact engine: its seen masks know what the lattice engine knows."""

from __future__ import annotations

import dataclasses
import itertools
import json
import sqlite3
import zlib
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, LatticeConfig, MapConfig, OnlineConfig, OnlineMap, Scan
from octolgp.engines import engine_for
from octolgp.engines.base import Evidence, evidence_arrays
from octolgp.engines.exact import ExactEvidence, gather_evidence
from octolgp.engines.known import halo_pairs, near_leaf, seen_near
from octolgp.geometry.keys import pack_keys, unpack_keys
from octolgp.mapping.evidence import map_scans
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.observations import observe
from octolgp.persist.mapfile import VERSION
from octolgp.sweep import swept_keys
from octolgp.training import TrainingData

HP = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
RES = {2: 0.1, 3: 0.2}
ROOM = {2: (np.zeros(2), np.array([8.0, 8.0])), 3: (np.zeros(3), np.array([8.0, 8.0, 3.0]))}
CRATE = {2: (np.array([3.0, 3.0]), np.array([5.0, 5.0])), 3: (np.array([3.0, 3.0, 0.0]), np.array([5.0, 5.0, 2.0]))}  # fmt: skip
"""A closed crate in the room: no beam gets inside it."""


def _ranges(origin: np.ndarray, u: np.ndarray, dim: int) -> np.ndarray:
    """Distance along the unit rays ``u`` (n, d) from ``origin`` to the room's walls or the crate."""
    lo, hi = ROOM[dim]
    with np.errstate(divide="ignore", invalid="ignore"):
        wall = np.where(u > 0, (hi - origin) / u, np.where(u < 0, (lo - origin) / u, np.inf))
        t_wall = wall.min(axis=1)
        c_lo, c_hi = CRATE[dim]
        t1, t2 = (c_lo - origin) / u, (c_hi - origin) / u
        near = np.nanmax(np.where(u != 0, np.minimum(t1, t2), -np.inf), axis=1)
        far = np.nanmin(np.where(u != 0, np.maximum(t1, t2), np.inf), axis=1)
    inside = (u == 0) & ((origin < c_lo) | (origin > c_hi))  # parallel rays outside a slab
    hits = (near <= far) & (far > 0) & ~inside.any(axis=1)
    return np.where(hits, np.minimum(near, t_wall), t_wall)


def _scans(dim: int, n: int, max_range: float = 5.0) -> list[Scan]:
    """A sensor circling the crate inside the room; beams past ``max_range`` return nothing."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        if dim == 2:
            origin = np.array([4.0, 4.0]) + 2.6 * np.array([np.cos(a), np.sin(a)])
            ang = np.linspace(0.0, 2 * np.pi, 240, endpoint=False) + 0.01 * k
            u = np.c_[np.cos(ang), np.sin(ang)]
        else:
            origin = np.array([4.0, 4.0, 1.2]) + 2.6 * np.array([np.cos(a), np.sin(a), 0.0])
            az, el = np.meshgrid(
                np.linspace(0.0, 2 * np.pi, 120, endpoint=False) + 0.02 * k,
                np.radians(np.linspace(-25.0, 25.0, 9)),
            )
            az, el = az.ravel(), el.ravel()
            u = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
        r = np.minimum(_ranges(origin, u, dim), max_range)
        out.append(Scan(origin=origin, points=origin + u * r[:, None], max_range=max_range))
    return out


def _config(dim: int, engine: str, fill: int, **online: object) -> MapConfig:
    return MapConfig(
        dim=dim,
        resolution=RES[dim],
        hyperparameters=HP,
        lattice=LatticeConfig(fill_voxels=fill),
        online=OnlineConfig(engine=engine, **online),  # type: ignore[arg-type]
    )


def _known(m: OnlineMap) -> np.ndarray:
    """Packed keys of the voxels of a map that hold a value, ascending."""
    centres, prob = m.voxels()
    assert np.isfinite(prob).all()
    return np.unique(LeafGrid.from_config(m.config).voxel_keys(centres))


def _brute_known(scans: list[Scan], config: MapConfig) -> np.ndarray:
    """The known voxels by the rule's definition: within ``fill_voxels`` (every axis) of a
    voxel some scan observed or swept, each scan on its own (rounded as the map rounds it)."""
    d, fill = config.dim, config.fill_voxels
    scans = map_scans(scans, config)
    seen = [observe([s], config).keys for s in scans]
    seen += [unpack_keys(swept_keys([s], config), d) for s in scans]
    keys = unpack_keys(np.unique(pack_keys(np.concatenate(seen))), d)
    near = [
        pack_keys(keys + np.array(o)) for o in itertools.product(range(-fill, fill + 1), repeat=d)
    ]
    return np.unique(np.concatenate(near))


def _leaf_bytes(m: OnlineMap) -> dict[int, tuple[bytes, ...]]:
    """Every leaf's evidence arrays and values, as bytes, by key."""
    return {
        k: (
            *(a.tobytes() for a in evidence_arrays(leaf.evidence)),
            *(getattr(leaf, f).tobytes() for f in ("mean", "var", "prob")),
            bytes([leaf.pruned]),
        )
        for k, leaf in m.leaves()
    }


@pytest.mark.parametrize(("dim", "fill"), [(2, 2), (2, 1), (2, 0), (3, 1), (3, 0)])
def test_both_engines_know_the_brute_force_set(dim: int, fill: int) -> None:
    scans = _scans(dim, 6)
    known = {}
    for engine in ("lattice", "exact"):
        m = OnlineMap(_config(dim, engine, fill))
        m.insert_scans(scans)
        known[engine] = _known(m)
    config = OnlineMap(_config(dim, "exact", fill)).config
    want = _brute_known(scans, config)
    if (dim, fill) == (2, 0):  # beams far enough apart to sweep voxels between them
        assert swept_keys(scans, config).size
    np.testing.assert_array_equal(known["exact"], want)
    np.testing.assert_array_equal(known["lattice"], want)
    if dim == 2:  # some space is unknown: inside the crate, and beyond the beams' reach
        inside = np.stack(np.meshgrid(*[np.arange(3.55, 4.5, 0.1)] * 2), -1).reshape(-1, 2)
        m = OnlineMap(_config(dim, "exact", fill))
        m.insert_scans(scans)
        assert np.all(m.occupancy(inside) == 0.5)


@pytest.mark.parametrize("dim", [2, 3])
def test_known_voxels_read_as_without_the_rule_bit_for_bit(dim: int) -> None:
    """Where a voxel is known, its values are exactly those of ``fill_voxels = -1``, whose
    leaves keep no seen mask; elsewhere NaN."""
    scans = _scans(dim, 4)
    maps = {}
    for fill in (-1, 1):
        maps[fill] = OnlineMap(_config(dim, "exact", fill, prune=False))
        maps[fill].insert_scans(scans)
    every, honest = dict(maps[-1].leaves()), dict(maps[1].leaves())
    assert all(leaf.evidence.seen.size == 0 for leaf in every.values())
    assert set(every) <= set(honest)
    grid = LeafGrid.from_config(maps[1].config)
    unknown = 0
    for key, leaf in honest.items():
        seen = leaf.evidence.seen
        known = seen_near(seen[None], grid, 1)[0]
        for name in ("mean", "var", "prob"):
            values = getattr(leaf, name)
            assert np.isnan(values[~known]).all()
            if key in every:
                assert values[known].tobytes() == getattr(every[key], name)[known].tobytes()
            else:  # a leaf only seen near: no items, the prior
                assert leaf.evidence.n_items == 0
        unknown += int((~known).sum())
    assert unknown > 0


def test_a_step_that_grows_the_seen_mask_changes_the_leaf() -> None:
    config = OnlineMap(_config(2, "exact", 1)).config
    grid = LeafGrid.from_config(config)
    box = grid.side + 2 * grid.halo_voxels
    index = np.array([2048, 2048])
    corner = index * grid.side - grid.halo_voxels  # the halo box's lowest voxel key
    c = box // 2  # the leaf's middle voxel, in its halo box
    seen = np.zeros((box, box), dtype=bool)
    seen[c - 1 : c + 2, c - 1 : c + 2] = True
    seen[c, c] = False  # a ring: its known voxels are the 5 x 5 block around the middle
    seen = seen.reshape(-1)
    hits = grid.key_centres((corner + c)[None])
    leaf = Leaf(
        index,
        ExactEvidence(
            hits,
            grid.voxel_keys(hits),
            np.zeros((0, 2)),
            np.zeros((0, 2)),
            np.zeros(0, np.int64),
            seen,
        ),
    )
    key = int(pack_keys(index[None])[0])
    none = TrainingData(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64))

    def step(*local: tuple[int, int]) -> tuple[Evidence, Leaf | None, Leaf | None]:
        keys = corner + np.array(local, dtype=np.int64).reshape(-1, 2)
        ev = gather_evidence(none, grid, config, {key: leaf}.get, keys)
        changed, kept = dict(ev.changed), dict(ev.kept)
        return ev, changed.get(key), kept.get(key)

    # a voxel seen far in the halo never makes one of the leaf's voxels known: left out
    far, changed, kept = step((0, 0))
    assert key not in far.touched
    assert changed is None
    assert kept is None
    # a newly seen voxel that makes voxels known: the leaf is refitted
    near, changed, kept = step((grid.halo_voxels, grid.halo_voxels))
    assert changed is not None
    assert kept is None
    assert near.new_items == 0
    assert changed.evidence.seen.sum() == 9
    assert changed.evidence.n_items == 1
    # a newly seen voxel whose neighbours are known already: stored, not refitted
    inner, changed, kept = step((c, c))
    assert changed is None
    assert kept is not None
    assert kept.evidence.seen.sum() == 9
    assert not inner.changed
    assert len(inner.kept) == 1
    # a voxel seen before: nothing
    again, changed, kept = step((c + 1, c))
    assert not again.changed
    assert not again.kept
    # a voxel far in the halo is not near the leaf; one at the fill's edge is
    flat = np.array([0, (grid.halo_voxels - 1) * (box + 1), box * box - 1])
    np.testing.assert_array_equal(near_leaf(flat, grid, 1), [False, True, False])
    pairs = halo_pairs(corner[None] + grid.halo_voxels, grid)
    assert key in pairs[1].tolist()
    assert changed is None


@pytest.mark.parametrize("dim", [2, 3])
def test_one_by_one_equals_all_at_once_and_a_batch(dim: int) -> None:
    scans = _scans(dim, 5)
    maps = [OnlineMap(_config(dim, "exact", 1)) for _ in range(3)]
    for s in scans:
        maps[0].insert_scan(s)
    maps[1].insert_scans(scans)
    maps[2].insert_batch(scans)
    want = _leaf_bytes(maps[0])
    assert any(np.isnan(leaf.prob).any() for _, leaf in maps[0].leaves())
    for m in maps[1:]:
        assert _leaf_bytes(m) == want


@pytest.mark.parametrize("dim", [2, 3])
def test_the_seen_mask_round_trips_through_the_map_file(tmp_path: Path, dim: int) -> None:
    scans = _scans(dim, 4)
    path = tmp_path / "m.octolgp"
    with OnlineMap(_config(dim, "exact", 1), path=path) as m:
        m.insert_scans(scans[:3])
        want = _leaf_bytes(m)
    with OnlineMap.open(path) as back:
        assert _leaf_bytes(back) == want
        back.insert_scan(scans[3])
        fresh = OnlineMap(_config(dim, "exact", 1))
        fresh.insert_scans(scans)
        assert _leaf_bytes(back) == _leaf_bytes(fresh)


def _strip_to_version_8(path: Path, fill: int) -> None:
    """Make a map file of an exact map without seen masks look as version 8 wrote it:
    the resolved config's ``fill_voxels`` as then (the exact engine ignored it)."""
    con = sqlite3.connect(path)
    stored = json.loads(con.execute("SELECT value FROM meta WHERE key = 'config'").fetchone()[0])
    stored["lattice"]["fill_voxels"] = fill
    con.execute("UPDATE meta SET value = ? WHERE key = 'config'", (json.dumps(stored),))
    con.execute("UPDATE meta SET value = '8' WHERE key = 'version'")
    con.commit()
    con.close()


def test_a_version_8_file_reads_back_unchanged_its_leaves_seen_everywhere(
    tmp_path: Path,
) -> None:
    scans = _scans(2, 5)
    path = tmp_path / "v8.octolgp"
    old = _config(2, "exact", -1)  # the exact engine of version 8: no masks, every voxel filled
    with OnlineMap(old, path=path) as m:
        m.insert_scans(scans[:4])
        want = _leaf_bytes(m)
        probe = np.random.default_rng(0).uniform(0.0, 8.0, (2000, 2))
        occupancy = m.occupancy(probe)
        engine = engine_for(m.config)
        _, leaf = next(iter(m.leaves()))  # an exact leaf record of version 8: no mask
        ev = leaf.evidence
        n = 16 + 8 * (ev.hits.shape[0] * 3 + ev.free_start.shape[0] * 5)
        assert len(engine.record(ev, leaf.index)) == n
    _strip_to_version_8(path, 1)
    with OnlineMap.open(path) as back:
        assert back.config.fill_voxels == 1  # the map keeps masks from now on
        assert _leaf_bytes(back) == want  # read back unchanged
        np.testing.assert_array_equal(back.occupancy(probe), occupancy)
        before = dict(back.leaves())
        back.insert_scan(scans[4])
        for key, leaf in back.leaves():
            if key in before:  # an old leaf counts every voxel as seen
                assert leaf.evidence.seen.size == 0
                assert np.isfinite(leaf.prob).all()
            else:  # a new leaf has its mask
                assert leaf.evidence.seen.size > 0
        rows = sqlite3.connect(path).execute("SELECT value FROM meta WHERE key = 'version'")
        assert rows.fetchone()[0] == str(VERSION)


def test_records_without_a_mask_keep_version_8_bytes() -> None:
    config = OnlineMap(_config(3, "exact", 1)).config
    engine = engine_for(config)
    grid = LeafGrid.from_config(config)
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 1, (5, 3))
    base = ExactEvidence(pts, grid.voxel_keys(pts), pts[:2], pts[1:3], grid.voxel_keys(pts[1:3]))
    record = engine.record(base, np.zeros(3, np.int64))
    assert len(record) == 16 + 8 * (5 * 4 + 2 * 7)
    back = engine.from_record(record, np.zeros(3, np.int64))
    assert back.seen.size == 0
    n_halo = (grid.side + 2 * grid.halo_voxels) ** 3
    masked = dataclasses.replace(base, seen=rng.random(n_halo) < 0.3)
    record = engine.record(masked, np.zeros(3, np.int64))
    assert len(record) == 16 + 8 * (5 * 4 + 2 * 7) + (n_halo + 7) // 8
    back = engine.from_record(record, np.zeros(3, np.int64))
    np.testing.assert_array_equal(back.seen, masked.seen)
    assert zlib.crc32(engine.encode(back)) == zlib.crc32(record)
