"""Deferred fits: inserts store the new evidence, reads fit it; the values are those of fitting at once."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from octolgp import Hyperparameters, MapConfig, OnlineConfig, OnlineMap, Scan, load_scans
from octolgp.engines import engine_for
from octolgp.engines.base import evidence_arrays
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.query import leaves_read
from octolgp.mapping.update import ScanUpdate
from octolgp.persist.mapfile import decode_leaf, encode_leaf
from octolgp.sim.lidar3d import simulate_lidar_room
from octolgp.sinks.base import MapChange

DATA = Path(__file__).parent / "data"
HP2 = Hyperparameters(length_scale=0.6, signal_variance=1.0, noise_variance=0.05, alpha=5.0)
HP3 = Hyperparameters(length_scale=0.8, signal_variance=2.0, noise_variance=0.01, alpha=5.0)


def with_defer(config: MapConfig, defer: bool) -> MapConfig:
    return dataclasses.replace(config, online=dataclasses.replace(config.online, defer_fit=defer))


def leaf_bytes(m: OnlineMap) -> dict[int, tuple[bytes, ...]]:
    """Every leaf's evidence and voxel values, as bytes (a read: it settles the map)."""
    out = {}
    for k, leaf in m.leaves():
        arrays = (*evidence_arrays(leaf.evidence), leaf.mean, leaf.var, leaf.prob)
        out[k] = (*(np.asarray(a).tobytes() for a in arrays), bytes([leaf.pruned]))
    return out


@pytest.fixture(scope="module")
def intel() -> list[Scan]:
    return list(load_scans(DATA / "intel_first20.log"))[:12]


@pytest.fixture(scope="module")
def room() -> list[Scan]:
    sim = simulate_lidar_room(
        5, seed=3, n_azimuth=256, n_elevation=16, max_range=20.0, range_noise=0.01, n_heldout=1
    )
    return [s.downsample(0.2) for s in sim.scans()]


@pytest.mark.parametrize("dim", [2, 3])
def test_a_deferred_map_reads_as_the_map_fitted_at_every_insert(
    dim: int, intel: list[Scan], room: list[Scan]
) -> None:
    scans = intel if dim == 2 else room
    hp = HP2 if dim == 2 else HP3
    base = MapConfig(dim=dim, resolution=0.1 if dim == 2 else 0.2, hyperparameters=hp)
    eager, lazy = OnlineMap(with_defer(base, False)), OnlineMap(with_defer(base, True))
    assert lazy.defers_fit
    assert not eager.defers_fit
    probe = np.concatenate([s.points[::7] for s in scans])
    for i, scan in enumerate(scans):
        a, b = eager.insert_scan(scan), lazy.insert_scan(scan)
        assert (a.touched_leaves, a.refit_leaves, a.new_items) == (
            b.touched_leaves,
            b.refit_leaves,
            b.new_items,
        )
        assert "fit" in a.stages
        assert "fit" not in b.stages
        assert not eager.store.pending
        if i % 3 == 1:  # reads now and then: each sees every scan so far
            assert lazy.store.pending
            np.testing.assert_array_equal(lazy.occupancy(probe), eager.occupancy(probe))
            lazy.settle()
            assert not lazy.store.pending
    # the values are bit for bit those of fitting at every insert: a fit of a leaf's
    # tiles from its evidence is deterministic, whichever scan last changed it
    assert leaf_bytes(lazy) == leaf_bytes(eager)
    np.testing.assert_array_equal(lazy.latent(probe)[1], eager.latent(probe)[1])


def test_settle_fits_the_pending_leaves_once(room: list[Scan]) -> None:
    m = OnlineMap(MapConfig(dim=3, resolution=0.2, hyperparameters=HP3))
    updates = [m.insert_scan(s) for s in room[:3]]
    pending = m.store.pending
    assert pending
    assert all(m.store.get(k).pending for k in pending)
    assert len(pending) <= sum(u.refit_leaves for u in updates)
    assert m.settle() == len(pending)
    assert m.settle() == 0
    assert not m.store.pending
    assert all(not leaf.pending and leaf.refits >= 1 for _, leaf in m.leaves())
    before = leaf_bytes(m)
    assert m.settle() == 0
    assert leaf_bytes(m) == before


class Recorder:
    """A sink that keeps the values it is shown."""

    def __init__(self) -> None:
        self.values: list[np.ndarray] = []

    def on_scan(self, scan: Scan, index: int) -> None:
        pass

    def on_update(self, update: ScanUpdate, change: MapChange) -> None:
        self.values.extend(v.prob for v in change.leaves)


def test_maps_that_show_every_step_fit_at_once(room: list[Scan]) -> None:
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP3)
    sink = Recorder()
    maps = [
        OnlineMap(config, sink=sink),  # a sink
        OnlineMap(with_defer(config, False)),
        OnlineMap(
            dataclasses.replace(config, online=OnlineConfig(engine="exact"))
        ),  # the exact reference
    ]
    for m in maps:
        assert not m.defers_fit
        u = m.insert_scan(room[0])
        assert "fit" in u.stages
        assert not m.store.pending
        m.close()
    assert sink.values
    # finite values, NaN where a voxel is too far from every observation to hold one
    assert all(v.size and np.isfinite(v).any() and not np.isinf(v).any() for v in sink.values)


def test_maps_with_a_file_defer_and_read_as_fitted_at_once(
    tmp_path: Path, room: list[Scan]
) -> None:
    """A map file keeps lattice evidence only, so file and spill maps defer as well: their
    reads, the file read by another reader and the file reopened equal an eager map."""
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP3)
    eager = OnlineMap(with_defer(config, False))
    path = tmp_path / "a.octolgp"
    filed = OnlineMap(config, path)
    spilled = OnlineMap(dataclasses.replace(config, memory_budget_mb=0.5))
    for scan in room[:4]:
        eager.insert_scan(scan)
        for m in (filed, spilled):
            u = m.insert_scan(scan)
            assert m.defers_fit
            assert "fit" not in u.stages
    assert filed.store.pending
    with OnlineMap.open(path, read_only=True) as reader:  # beside the writer, unsettled
        assert leaf_bytes(reader) == leaf_bytes(eager)
    assert spilled.store.evictions > 0
    for m in (filed, spilled):
        assert leaf_bytes(m) == leaf_bytes(eager)
        assert not m.store.pending
        m.close()
    with OnlineMap.open(path) as back:
        assert leaf_bytes(back) == leaf_bytes(eager)
        back.insert_scan(room[4])
        eager.insert_scan(room[4])
        assert leaf_bytes(back) == leaf_bytes(eager)


def test_a_pending_leaf_is_written_as_its_evidence_and_reads_back_pending(room: list[Scan]) -> None:
    """Lattice records keep no values, so a pending leaf's record is complete; an engine
    whose records keep the values refuses one (they would not be its evidence's)."""
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP3)
    m = OnlineMap(config)
    m.insert_scan(room[0])
    key = m.store.pending[0]
    leaf = m.store.get(key)
    assert leaf is not None
    assert leaf.pending
    engine, grid = engine_for(m.config), LeafGrid.from_config(m.config)
    back = decode_leaf(encode_leaf(leaf, engine), engine, grid)
    assert back.pending
    assert back.prob.size == 0
    assert all(
        np.array_equal(a, b)
        for a, b in zip(evidence_arrays(back.evidence), evidence_arrays(leaf.evidence), strict=True)
    )
    exact = dataclasses.replace(config, online=dataclasses.replace(config.online, engine="exact"))
    e = OnlineMap(exact)
    e.insert_scan(room[0])
    _, fitted = next(iter(e.leaves()))
    with pytest.raises(ValueError, match="pending"):
        encode_leaf(fitted.evolve(pending=True), engine_for(e.config))


def test_learning_inserts_defer_too_and_reads_answer_in_between(intel: list[Scan]) -> None:
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=4))
    lazy, eager = OnlineMap(config), OnlineMap(with_defer(config, False))
    probe = np.concatenate([s.points[::5] for s in intel[:6]])
    for scan in intel[:6]:
        lazy.insert_scan(scan)
        eager.insert_scan(scan)
        np.testing.assert_array_equal(lazy.occupancy(probe), eager.occupancy(probe))
    assert lazy.hyperparameters == eager.hyperparameters
    assert leaf_bytes(lazy) == leaf_bytes(eager)


@pytest.mark.parametrize("finish", ["flush", "insert_batch", "set_hyperparameters"])
def test_ending_the_learning_any_way_gives_the_map_fitted_at_once(
    finish: str, intel: list[Scan]
) -> None:
    """The buffered scans' evidence is stored as they come (it needs no hyperparameters);
    flush, a batch or given hyperparameters then end the learning without storing it twice."""
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=8))
    lazy, eager = OnlineMap(config), OnlineMap(with_defer(config, False))
    for m in (lazy, eager):
        m.insert_scans(intel[:5])  # buffered, fewer than learn_scans
        if finish == "flush":
            update = m.flush()
            assert update is not None
            assert "learning" in update.stages
        elif finish == "insert_batch":
            m.insert_batch(intel[5:9])
        else:
            m.set_hyperparameters(HP2)
        assert m.hyperparameters is not None
        assert not m.provisional
    assert lazy.hyperparameters == eager.hyperparameters
    assert leaf_bytes(lazy) == leaf_bytes(eager)
    assert lazy.n_scans == eager.n_scans


def test_a_learning_insert_stores_one_scan_and_learns(intel: list[Scan]) -> None:
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=4))
    m = OnlineMap(config)
    updates = m.insert_scans(intel[:4])
    assert [u.buffered for u in updates] == [True, True, True, False]
    assert all(u.touched_leaves > 0 for u in updates)  # each insert stored its own scan
    assert "learning" in updates[3].stages
    assert m.buffered_scans == 0
    assert m.store.pending  # fitted at the first read, with the learnt hyperparameters
    assert m.settle() == len(m.store)


@pytest.mark.parametrize("interpolate", [True, False])
def test_a_small_query_fits_only_the_leaves_it_reads(interpolate: bool, room: list[Scan]) -> None:
    config = MapConfig(dim=3, resolution=0.2, hyperparameters=HP3)
    lazy, eager = OnlineMap(config), OnlineMap(with_defer(config, False))
    rng = np.random.default_rng(7)
    for scan in room[:3]:
        lazy.insert_scan(scan)
        eager.insert_scan(scan)
        before = len(lazy.store.pending)
        # a planner's window: points around one return, on voxel centres, borders and corners
        centre = scan.points[rng.integers(len(scan))]
        window = centre + rng.uniform(-0.5, 0.5, (200, 3))
        window[:8] = np.round(window[:8] / 0.2) * 0.2  # voxel borders
        for read in ("occupancy", "latent"):
            a = getattr(lazy, read)(window, interpolate=interpolate)
            b = getattr(eager, read)(window, interpolate=interpolate)
            np.testing.assert_array_equal(a, b)
        assert 0 < len(lazy.store.pending) < before  # the far leaves still wait
    assert leaf_bytes(lazy) == leaf_bytes(eager)  # a whole read fits the rest


def test_leaves_read_cover_the_interpolation_corners() -> None:
    grid = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=HP2)).grid
    rng = np.random.default_rng(3)
    X = rng.uniform(-3, 3, (500, 2))
    keys = leaves_read(grid, X)
    res = grid.resolution
    for dx in (-res, 0.0, res):  # every voxel within one voxel of a point
        for dy in (-res, 0.0, res):
            near = grid.pack(grid.leaf_of(X + np.array([dx, dy])))
            assert set(np.unique(near).tolist()) <= keys
