"""The online mapper: leaf geometry, bounded evidence, incremental updates, queries, files."""

from __future__ import annotations

import dataclasses
import itertools
import sqlite3

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score

from octolgp import (
    ExactConfig,
    Hyperparameters,
    LatticeConfig,
    MapConfig,
    OctolgpError,
    OnlineConfig,
    OnlineMap,
    Scan,
    build_map,
)
from octolgp.engines.base import evidence_arrays
from octolgp.engines.exact import ExactEvidence
from octolgp.errors import MapFileNotFound
from octolgp.geometry.boxes import clip_to_box
from octolgp.geometry.keys import key_to_coord
from octolgp.gp.plsc import occupancy_probability
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments
from octolgp.mapping.store import Leaf
from octolgp.observations import observe
from octolgp.sim.scenes import simulate_paper2d

ENGINES = ["lattice", "exact"]
HP = Hyperparameters(length_scale=0.8, signal_variance=1.0, noise_variance=0.05, alpha=5.0)


def room_scan(origin: tuple[float, float], n: int = 90, size: float = 4.0) -> Scan:
    """A 2D scan from ``origin`` inside the square room [-size, size]²."""
    ang = np.linspace(-np.pi, np.pi, n, endpoint=False)
    d = np.c_[np.cos(ang), np.sin(ang)]
    o = np.asarray(origin, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.min(np.where(d != 0, (np.sign(d) * size - o) / d, np.inf), axis=1)
    return Scan(origin=o, points=o + t[:, None] * d)


def config2d(exact: ExactConfig | None = None, **online: object) -> MapConfig:
    return MapConfig(
        dim=2,
        resolution=0.1,
        hyperparameters=HP,
        online=OnlineConfig(**online),  # type: ignore[arg-type]
        exact=exact or ExactConfig(),
    )


LATTICE_TOLERANCE = 1e-6
"""The lattice engine fits many leaves per BLAS call; a leaf fitted in another batch may
round differently, so two lattice maps of the same scans agree to a few float32 ulps in
their voxel values (and bit for bit in their evidence). The exact engine: bit for bit."""


def assert_same_map(a: OnlineMap, b: OnlineMap) -> None:
    """The same leaves, evidence bit for bit, values bit for bit (exact) or to the tolerance."""
    la, lb = dict(a.leaves()), dict(b.leaves())
    assert list(la) == list(lb)
    exact = a.config.online.engine == "exact"
    for k, x in la.items():
        y = lb[k]
        assert evidence_bytes(x) == evidence_bytes(y), k
        assert x.pruned == y.pruned
        for name in ("mean", "var", "prob"):
            if exact:
                assert getattr(x, name).tobytes() == getattr(y, name).tobytes(), (k, name)
            else:
                np.testing.assert_allclose(
                    getattr(x, name), getattr(y, name), rtol=0, atol=LATTICE_TOLERANCE
                )


def snapshot(m: OnlineMap) -> dict[int, tuple[bytes, ...]]:
    """Every stored array of every leaf, as bytes."""
    fields = ("mean", "var", "prob")
    return {
        k: (*evidence_bytes(leaf), *(getattr(leaf, f).tobytes() for f in fields))
        for k, leaf in m.leaves()
    }


# ---------------------------------------------------------------- leaf geometry
@pytest.mark.parametrize("dim", [2, 3])
def test_assign_points_matches_brute_force(dim: int) -> None:
    grid = LeafGrid(dim, 0.1, 16, 16 - (4 if dim == 2 else 3), 0.2)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, size=(300, dim))
    idx, leaf = assign_points(grid, pts)
    got = {(int(i), *map(int, k)) for i, k in zip(idx, leaf, strict=True)}
    centre = grid.leaf_of(pts)
    want = set()
    for offset in itertools.product((-1, 0, 1), repeat=dim):
        cand = centre + np.array(offset)
        lo, hi = grid.halo_box(cand)
        inside = ((pts >= lo) & (pts <= hi)).all(axis=1)
        want |= {(int(i), *map(int, cand[i])) for i in np.flatnonzero(inside)}
    assert got == want
    # the leaf that owns a point (its core box) is always among its leaves
    assert {(i, *map(int, centre[i])) for i in range(pts.shape[0])} <= got


@pytest.mark.parametrize("dim", [2, 3])
def test_assign_segments_matches_brute_force(dim: int) -> None:
    grid = LeafGrid(dim, 0.1, 16, 16 - (4 if dim == 2 else 3), 0.2)
    rng = np.random.default_rng(1)
    a = rng.uniform(-4, 4, size=(60, dim))
    b = a + rng.normal(scale=2.0, size=(60, dim))
    seg, leaf, pa, pb = assign_segments(grid, a, b, 0.05)
    got = {(int(s), *map(int, k)) for s, k in zip(seg, leaf, strict=True)}
    # brute force: every leaf in the bounding region, clipped
    lo_idx = grid.leaf_of(np.minimum(a, b).min(axis=0)[None] - grid.edge)[0]
    hi_idx = grid.leaf_of(np.maximum(a, b).max(axis=0)[None] + grid.edge)[0]
    cells = np.array(
        list(itertools.product(*[range(lo, hi + 1) for lo, hi in zip(lo_idx, hi_idx, strict=True)]))
    )
    want = set()
    for s in range(a.shape[0]):
        lo, hi = grid.halo_box(cells)
        ca, cb, keep = clip_to_box(
            np.repeat(a[s : s + 1], len(cells), 0), np.repeat(b[s : s + 1], len(cells), 0), lo, hi
        )
        keep &= np.linalg.norm(cb - ca, axis=1) > 0.05
        want |= {(s, *map(int, c)) for c in cells[keep]}
    assert got == want
    # pieces lie on their segment and inside their leaf's halo box
    lo, hi = grid.halo_box(leaf)
    tol = 1e-9
    assert ((pa >= lo - tol) & (pa <= hi + tol) & (pb >= lo - tol) & (pb <= hi + tol)).all()
    for p in (pa, pb):
        u = p - a[seg]
        d = b[seg] - a[seg]
        cross = np.abs(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0])
        assert cross.max() < 1e-9 * np.abs(d).max() * 10 + 1e-9


def test_voxel_index_inverts_voxel_centres() -> None:
    grid = LeafGrid(3, 0.2, 16, 13, 0.2)
    index = np.array([4000, 4100, 4090])
    centres = grid.voxel_centres(index)
    assert centres.shape == (512, 3)
    assert np.array_equal(grid.voxel_index(centres, index), np.arange(512))
    lo, hi = grid.box(index[None])
    assert (centres > lo).all()
    assert (centres < hi).all()


def test_leaf_keeps_first_item_per_voxel() -> None:
    ev = ExactEvidence.empty(2)
    pts = np.array([[0.01, 0.01], [0.02, 0.02], [0.5, 0.5]])
    keys = np.array([7, 7, 9])
    ev, added = ev.extended(pts, keys, pts[:0], pts[:0], keys[:0])
    assert added == 2
    assert np.array_equal(ev.hits, pts[[0, 2]])
    new, added = ev.extended(pts, keys, pts, pts + 1, keys)
    assert added == 2  # only the free ones are new
    assert ev.free_start.shape[0] == 0  # new evidence: the old one is unchanged
    assert new.extended(pts, keys, pts, pts + 1, keys) == (new, 0)


# ---------------------------------------------------------------- updates
@pytest.mark.parametrize("engine", ENGINES)
def test_untouched_leaves_are_bit_for_bit_unchanged(engine: str) -> None:
    m = OnlineMap(config2d(engine=engine))
    m.insert_scan(room_scan((-2.5, -2.5), size=4.0))
    before = snapshot(m)
    second = Scan(origin=[-2.5, -2.5], points=[[-1.0, -2.5], [-2.5, -1.2]])
    update = m.insert_scan(second)
    after = snapshot(m)
    assert 0 < update.refit_leaves <= update.touched_leaves < len(before)
    changed = {k for k in before if before[k] != after[k]}
    refit = {k for k in before if before[k][4:] != after[k][4:]}  # mean, var, prob
    # a leaf's values move only when it is refitted; its evidence only when touched
    # (a free count on its way to clear_scans changes no value)
    assert 0 < len(refit) <= update.refit_leaves
    assert len(changed) <= update.touched_leaves
    for key in set(before) - changed:
        assert before[key] == after[key]
    # a far-away leaf did not move at all
    assert m.store.get(max(before)).refits == 1  # type: ignore[union-attr]


@pytest.mark.parametrize("engine", ENGINES)
def test_one_by_one_equals_all_at_once(engine: str) -> None:
    scans = [room_scan((x, y)) for x, y in [(-2, -2), (0, 0), (2, 1), (-1, 2)]]
    a = OnlineMap(config2d(engine=engine))
    for s in scans:
        a.insert_scan(s)
    b = OnlineMap(config2d(engine=engine))
    b.insert_batch(scans)
    assert_same_map(a, b)
    assert a.n_scans == b.n_scans == len(scans)


@pytest.mark.parametrize("engine", ENGINES)
def test_revisiting_adds_nothing_and_memory_saturates(engine: str) -> None:
    """A static world (``clear_scans=0``, the exact engine's rule): a revisit is free."""
    scans = [room_scan((x, 0.5 * x)) for x in np.linspace(-2, 2, 5)]
    m = OnlineMap(config2d(engine=engine, clear_scans=0))
    m.insert_scans(scans)
    first = snapshot(m)
    mem = m.memory_bytes()
    updates = m.insert_scans(scans)
    assert all(u.refit_leaves == 0 and u.new_items == 0 for u in updates)
    assert all(u.touched_leaves > 0 for u in updates)
    assert m.memory_bytes() == mem
    assert snapshot(m) == first


def test_a_static_revisit_settles_when_newer_evidence_wins() -> None:
    """The default rule on a static scene: once its voxels have been seen free
    ``clear_scans`` times, a revisit refits nothing and memory stays put.

    No voxel of this room is seen free ``clear_scans`` times between two of its returns,
    so no return is forgotten; a wall voxel that a grazing beam sees free keeps reading
    occupied (its frees only count towards forgetting). A free voxel's evidence grows
    with its first ``clear_scans`` looks (the first revisits refit), then saturates.
    """
    scans = [room_scan((x, 0.5 * x)) for x in np.linspace(-2, 2, 5)]
    m = OnlineMap(config2d())
    k = m.config.clear_scans
    assert k > 0
    m.insert_scans(scans)
    refits = [sum(u.refit_leaves for u in m.insert_scans(scans)) for _ in range(k - 1)]
    assert refits[0] > 0  # free evidence still growing
    first = snapshot(m)
    mem = m.memory_bytes()
    for _ in range(2):
        updates = m.insert_scans(scans)
        assert all(u.refit_leaves == 0 and u.new_items == 0 for u in updates)
        assert all(u.touched_leaves > 0 for u in updates)
    again = snapshot(m)
    assert again.keys() == first.keys()
    assert all(again[k][4:] == first[k][4:] for k in again)  # mean, var, prob
    assert all(again[k][:3] == first[k][:3] for k in again)  # kept returns
    assert m.memory_bytes() == mem


def test_evidence_per_leaf_is_bounded_by_its_voxels() -> None:
    rng = np.random.default_rng(3)
    # exact engine: the bound is on its hits and free pieces (lattice leaves keep counts)
    m = OnlineMap(config2d(ExactConfig(max_leaf_items=10_000), engine="exact"))
    for _ in range(30):
        m.insert_scan(room_scan(tuple(rng.uniform(-3, 3, 2)), n=180, size=4.0))
    halo_voxels = int(np.ceil(m.grid.side * (1 + 2 * m.grid.halo)) + 1) ** 2
    for _, leaf in m.leaves():
        ev = leaf.evidence
        assert isinstance(ev, ExactEvidence)
        assert np.unique(ev.hit_keys).size == ev.hit_keys.size <= halo_voxels
        assert np.unique(ev.free_keys).size == ev.free_keys.size <= 4 * halo_voxels


@pytest.mark.parametrize("engine", ENGINES)
def test_threads_give_identical_maps(engine: str) -> None:
    scans = [room_scan((x, -x)) for x in (-2.0, 0.0, 2.0)]
    a = OnlineMap(config2d(engine=engine, n_jobs=1))
    b = OnlineMap(config2d(engine=engine, n_jobs=2))
    a.insert_scans(scans)
    b.insert_scans(scans)
    assert_same_map(a, b)
    b.close()


def test_leaf_over_the_cap_is_split_by_kmeans() -> None:
    # exact engine: max_leaf_items and the k-means split are its own (lattice leaves never split)
    scans = [room_scan((x, 0.0), n=360) for x in (-3.0, -2.8)]
    small = OnlineMap(config2d(ExactConfig(max_leaf_items=40), engine="exact"))
    small.insert_scans(scans)
    big = OnlineMap(config2d(engine="exact"))
    big.insert_scans(scans)
    corner = np.array([[-3.95, -3.95], [-3.95, 3.95], [-3.0, -3.9]])
    assert (small.occupancy(corner) > 0.5).all()
    assert np.abs(small.occupancy(corner) - big.occupancy(corner)).max() < 0.2
    assert any(leaf.n_items > 40 for _, leaf in small.leaves())


# ---------------------------------------------------------------- against batch
@pytest.mark.parametrize("engine", ENGINES)
def test_online_matches_batch_on_the_paper_simulation(engine: str) -> None:
    data = simulate_paper2d(seed=0)
    config = MapConfig(
        dim=2,
        resolution=0.2,
        hyperparameters=Hyperparameters(1.2, 1.0, 0.1, 6.0, -0.2),
        online=OnlineConfig(engine=engine),
    )
    batch = build_map(data.scans, config, method="lgp")
    online = OnlineMap(config)
    online.insert_scans(data.scans)
    auc_b = roc_auc_score(data.truth_labels, batch.occupancy(data.truth_points))
    auc_o = roc_auc_score(data.truth_labels, online.occupancy(data.truth_points))
    assert auc_o > 0.97
    assert abs(auc_o - auc_b) < 0.01


EXACT_AUC_SLACK = 0.005
"""How far below the exact engine's AUC the lattice engine may read on the paper scene."""


def test_the_lattice_engine_matches_the_exact_reference() -> None:
    """The default engine against the paper's exact local GPs, same scans, same
    hyperparameters: AUC against the scene's true labels within EXACT_AUC_SLACK, and the
    same class (P > 0.5) at 95 % of the observed voxels."""
    data = simulate_paper2d(seed=0)
    maps = {}
    for engine in ENGINES:
        config = MapConfig(
            dim=2,
            resolution=0.2,
            hyperparameters=Hyperparameters(1.2, 1.0, 0.1, 6.0, -0.2),
            online=OnlineConfig(engine=engine, clear_scans=0),
        )
        maps[engine] = OnlineMap(config)
        maps[engine].insert_batch(data.scans)
    auc = {
        e: roc_auc_score(data.truth_labels, m.occupancy(data.truth_points)) for e, m in maps.items()
    }
    assert auc["exact"] > 0.97
    assert auc["lattice"] >= auc["exact"] - EXACT_AUC_SLACK, auc
    # the voxels a beam passed through or ended in (the maps differ in how far beyond
    # them their halos reach, where the exact engine extrapolates)
    observed = observe(data.scans, maps["exact"].config).keys
    centres = key_to_coord(observed, 0.2)
    agree = (maps["lattice"].occupancy(centres) > 0.5) == (maps["exact"].occupancy(centres) > 0.5)
    assert agree.mean() >= 0.95, agree.mean()


# ---------------------------------------------------------------- queries
def test_unknown_space_is_exactly_half_and_prior() -> None:
    m = OnlineMap(config2d())
    assert m.occupancy([[0.0, 0.0]])[0] == 0.5
    m.insert_scan(room_scan((0.0, 0.0), size=2.0))
    far = np.array([[100.0, 100.0], [-50.0, 3.0]])
    assert np.array_equal(m.occupancy(far), [0.5, 0.5])
    mean, var = m.latent(far)
    assert np.array_equal(mean, [0.0, 0.0])
    assert np.array_equal(var, [1.0, 1.0])
    wall, free = m.occupancy([[2.0, 0.0], [0.5, 0.0]])
    assert wall > 0.7
    assert free < 0.3


def replace_fill(config: MapConfig, fill: int) -> LatticeConfig:
    """``config``'s lattice settings with ``fill_voxels = fill``."""
    return dataclasses.replace(config.lattice, fill_voxels=fill)


def test_nearest_queries_read_the_voxel_values() -> None:
    m = OnlineMap(config2d(prune=False))
    m.insert_scan(room_scan((0.0, 0.0), size=2.0))
    _key, leaf = next(iter(m.leaves()))
    centres = m.grid.voxel_centres(leaf.index)
    jitter = np.random.default_rng(0).uniform(-0.049, 0.049, centres.shape)
    probs = m.occupancy(centres + jitter, interpolate=False)
    known = ~np.isnan(leaf.prob)  # voxels far from every observation hold no value
    assert known.any()
    assert not known.all()
    assert np.array_equal(probs, np.where(known, leaf.prob.astype(float), 0.5))
    mean, var = m.latent(centres + jitter, interpolate=False)
    prior = m.hyperparameters.signal_variance
    assert np.array_equal(mean, np.where(known, leaf.mean.astype(float), 0.0))
    assert np.array_equal(var, np.where(known, leaf.var.astype(float), prior))
    pts, prob = m.occupied_voxels(0.5)
    assert (prob > 0.5).all()
    assert pts.shape == (prob.size, 2)
    assert np.array_equal(m.occupancy(pts, interpolate=False), prob)


def test_interpolated_queries_are_multilinear_between_voxel_centres() -> None:
    config = config2d(prune=False)  # every voxel filled: the blend of four known centres
    m = OnlineMap(dataclasses.replace(config, lattice=replace_fill(config, -1)))
    m.insert_scan(room_scan((0.0, 0.0), size=2.0))
    hp = m.hyperparameters
    assert hp is not None
    _key, leaf = next(iter(m.leaves()))
    centres = m.grid.voxel_centres(leaf.index)
    # At a voxel centre the continuous map is the voxel's own latent value.
    mean, var = m.latent(centres)
    np.testing.assert_allclose(mean, leaf.mean, rtol=0, atol=1e-6)
    np.testing.assert_allclose(var, leaf.var, rtol=0, atol=1e-6)
    np.testing.assert_allclose(m.occupancy(centres), leaf.prob, rtol=0, atol=1e-5)
    # Inside a square of four known centres: the bilinear blend of their latents.
    rng = np.random.default_rng(1)
    c0 = centres[0]
    q = c0 + rng.uniform(0.0, 0.1, (50, 2))
    corners = c0 + 0.1 * np.array([[0, 0], [0, 1], [1, 0], [1, 1]])
    cm, cv = m.latent(corners, interpolate=False)
    fx, fy = ((q - c0) / 0.1).T
    w = np.stack([(1 - fx) * (1 - fy), (1 - fx) * fy, fx * (1 - fy), fx * fy], axis=1)
    mean, var = m.latent(q)
    np.testing.assert_allclose(mean, w @ cm, atol=1e-9)
    np.testing.assert_allclose(var, w @ cv, atol=1e-9)
    expected = occupancy_probability(w @ cm, w @ cv + hp.noise_variance, hp.alpha, hp.beta)
    np.testing.assert_allclose(m.occupancy(q), expected, atol=1e-12)
    # Unknown stays exactly unknown, however close to known voxels.
    far = np.array([[50.0, 50.0]])
    assert m.occupancy(far)[0] == 0.5
    assert m.latent(far)[1][0] == hp.signal_variance


def test_pruned_leaves_hold_one_conservative_value() -> None:
    scans = [room_scan((x, y), n=360, size=6.0) for x in (-3, 0, 3) for y in (-3, 0, 3)]
    pruned = OnlineMap(config2d())
    full = OnlineMap(config2d(prune=False))
    pruned.insert_scans(scans)
    full.insert_scans(scans)
    n_pruned = 0
    others = dict(full.leaves())  # a read: the deferred fits are done first
    for key, leaf in pruned.leaves():
        other = others.get(key)
        assert other is not None
        if leaf.pruned:
            n_pruned += 1
            assert leaf.prob.size == 1
            if leaf.prob[0] < 0.5:
                assert leaf.prob[0] == other.prob.max() < 0.1192
            else:
                assert leaf.prob[0] == other.prob.min() > 0.971
        else:
            assert np.array_equal(leaf.prob, other.prob, equal_nan=True)  # NaN: no value
    assert n_pruned > 0
    assert pruned.memory_bytes() < full.memory_bytes()


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("bad", "field"),
    [
        ("not a scan", "scan must be a Scan"),
        (Scan(origin=[0.0, 0.0, 0.0], points=[[1.0, 0.0, 0.0]]), "MapConfig.dim"),
        (Scan(origin=[0.0, 0.0], points=[[1e6, 0.0]]), "scan.points"),
        (Scan(origin=[-1e6, 0.0], points=[[1.0, 0.0]]), "scan.origin"),
    ],
)
def test_rejected_scans_leave_the_map_unchanged(bad: object, field: str) -> None:
    m = OnlineMap(config2d())
    m.insert_scan(room_scan((0.0, 0.0), size=2.0))
    before, n = snapshot(m), m.n_scans
    with pytest.raises(OctolgpError, match=field):
        m.insert_scan(bad)  # type: ignore[arg-type]
    assert snapshot(m) == before
    assert m.n_scans == n


@pytest.mark.parametrize(
    ("points", "field"),
    [
        ([[np.nan, 0.0]], "NaN"),
        ([[0.0, 0.0, 0.0]], r"shape \(n, 2\)"),
        ([[1e7, 0.0]], "addressable"),
        ("abc", "numeric"),
    ],
)
def test_bad_queries_raise(points: object, field: str) -> None:
    m = OnlineMap(config2d())
    with pytest.raises(OctolgpError, match=field):
        m.occupancy(points)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"halo": 0.5}, "halo"),
        ({"halo": -0.1}, "halo"),
        ({"leaf_depth": 0}, "leaf_depth"),
        ({"n_jobs": 0}, "n_jobs"),
        ({"prune": 1}, "prune"),
        ({"engine": "fast"}, "engine"),
        ({"clear_scans": -1}, "clear_scans"),
        ({"clear_scans": 256}, "clear_scans"),
        ({"clear_scans": 2.0}, "clear_scans"),
        ({"clear_scans": 3, "engine": "exact"}, "clear_scans"),
        ({"defer_fit": 1}, "defer_fit"),
    ],
)
def test_bad_online_config(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        OnlineConfig(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("section", "kwargs", "field"),
    [
        (ExactConfig, {"max_leaf_items": 1}, "ExactConfig.max_leaf_items"),
        (ExactConfig, {"free_voxels": 0}, "ExactConfig.free_voxels"),
        (LatticeConfig, {"evidence_cap": 0}, "LatticeConfig.evidence_cap"),
        (LatticeConfig, {"evidence_cap": 256}, "LatticeConfig.evidence_cap"),
        (LatticeConfig, {"free_weight": 0.0}, "LatticeConfig.free_weight"),
        (LatticeConfig, {"free_weight": float("nan")}, "LatticeConfig.free_weight"),
        (LatticeConfig, {"inducing_spacing": -1.0}, "LatticeConfig.inducing_spacing"),
        (LatticeConfig, {"max_inducing_per_axis": 1}, "LatticeConfig.max_inducing_per_axis"),
        (LatticeConfig, {"max_inducing_per_axis": 17}, "LatticeConfig.max_inducing_per_axis"),
        (LatticeConfig, {"clear_margin": -0.1}, "LatticeConfig.clear_margin"),
        (LatticeConfig, {"clear_margin": float("inf")}, "LatticeConfig.clear_margin"),
        (LatticeConfig, {"free_evidence": "rays"}, "LatticeConfig.free_evidence"),
        (LatticeConfig, {"chord_weight": 0.0}, "LatticeConfig.chord_weight"),
        (LatticeConfig, {"chord_weight": float("nan")}, "LatticeConfig.chord_weight"),
    ],
)
def test_bad_engine_config(section: type, kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(OctolgpError, match=field):
        section(**kwargs)


def test_clear_scans_defaults_by_engine() -> None:
    assert MapConfig().clear_scans == 5
    assert MapConfig(online=OnlineConfig(engine="exact")).clear_scans == 0
    assert MapConfig(online=OnlineConfig(clear_scans=0)).clear_scans == 0
    assert MapConfig(resolution=0.2).clear_margin == pytest.approx(1.0)
    assert MapConfig(lattice=LatticeConfig(clear_margin=0.0)).clear_margin == 0.0


def test_leaf_depth_beyond_tree_depth_is_refused() -> None:
    with pytest.raises(OctolgpError, match="leaf_depth"):
        MapConfig(tree_depth=10, online=OnlineConfig(leaf_depth=12))


# ---------------------------------------------------------------- hyperparameters
@pytest.mark.parametrize("defer", [True, False])
def test_hyperparameters_learnt_from_first_scans_then_fixed(defer: bool) -> None:
    scans = [room_scan((x, 0.3 * x), n=120) for x in np.linspace(-2, 2, 5)]
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=3, defer_fit=defer))
    m = OnlineMap(config)
    u1, u2 = m.insert_scan(scans[0]), m.insert_scan(scans[1])
    assert u1.buffered
    assert u2.buffered
    if defer:  # the buffered scans' evidence is stored, its fit waits for the hyperparameters
        assert len(m.store) == len(m.store.pending) > 0
        assert m.settle() == 0
    else:
        assert len(m.store) == 0
    u3 = m.insert_scan(scans[2])
    assert not u3.buffered
    assert "learning" in u3.stages
    assert u3.refit_leaves > 0
    hp = m.hyperparameters
    assert hp is not None
    m.insert_scans(scans[3:])
    assert m.hyperparameters is hp
    # the same as a map given those hyperparameters from the start
    fixed = OnlineMap(dataclasses.replace(config, hyperparameters=hp))
    fixed.insert_scans(scans)
    assert_same_map(fixed, m)


def test_queries_answer_provisionally_and_never_learn() -> None:
    config = MapConfig(dim=2, resolution=0.1, online=OnlineConfig(learn_scans=50))
    m = OnlineMap(config)
    m.insert_scans([room_scan((0.0, 0.0), n=120), room_scan((1.0, 0.0), n=120)])
    assert m.hyperparameters is None
    assert m.provisional
    assert m.occupancy([[4.0, 0.0]])[0] > 0.5  # a provisional fit of the buffered scans
    assert m.hyperparameters is None  # ... thrown away: nothing learnt, nothing fitted
    assert len(m.store) == len(m.store.pending)  # evidence only, waiting to be fitted
    assert m.buffered_scans == 2
    # what flush() would make, which is the one explicit way to learn early
    flushed = OnlineMap(config)
    flushed.insert_scans([room_scan((0.0, 0.0), n=120), room_scan((1.0, 0.0), n=120)])
    flushed.flush()
    assert not flushed.provisional
    probe = np.array([[4.0, 0.0], [1.0, 1.0], [0.5, -3.9]])
    np.testing.assert_array_equal(m.occupancy(probe), flushed.occupancy(probe))


@pytest.mark.parametrize("engine", ENGINES)
def test_set_hyperparameters_refits_every_leaf(engine: str) -> None:
    scans = [room_scan((x, 0.0)) for x in (-1.0, 1.0)]
    other = dataclasses.replace(HP, length_scale=0.5)
    m = OnlineMap(config2d(engine=engine))
    m.insert_scans(scans)
    m.set_hyperparameters(other)
    fresh = OnlineMap(dataclasses.replace(config2d(engine=engine), hyperparameters=other))
    fresh.insert_scans(scans)
    assert {k: v[3:] for k, v in snapshot(m).items()} == {
        k: v[3:] for k, v in snapshot(fresh).items()
    }


# ---------------------------------------------------------------- files
@pytest.mark.parametrize("engine", ENGINES)
def test_map_file_round_trip(tmp_path, engine: str) -> None:  # type: ignore[no-untyped-def]
    scans = [room_scan((x, 0.0)) for x in (-1.0, 1.0)]
    path = tmp_path / "m.octolgp"
    with OnlineMap(config2d(engine=engine), path=path) as m:
        m.insert_scans(scans)
        want = snapshot(m)
        probe = np.random.default_rng(0).uniform(-4, 4, (500, 2))
        prob = m.occupancy(probe)
    with OnlineMap.open(path) as back:
        assert back.n_scans == 2
        assert back.hyperparameters == HP
        assert back.config == config2d(engine=engine).resolve()
        assert snapshot(back) == want
        assert np.array_equal(back.occupancy(probe), prob)
        back.insert_scan(room_scan((0.0, 1.0)))  # keeps writing through
    saved = tmp_path / "copy.octolgp"
    with OnlineMap.open(path) as again:
        assert again.n_scans == 3
        again.save(saved)
        with OnlineMap.open(saved) as copy:
            assert snapshot(copy) == snapshot(again)
            assert copy.n_scans == 3
            assert [s.points.tolist() for s in copy._file.scans()] == [
                s.points.tolist() for s in again._file.scans()
            ]


def test_map_file_refuses_to_overwrite_and_rejects_foreign_files(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "m.octolgp"
    path.write_bytes(b"hello")
    with pytest.raises(OctolgpError, match="already exists"):
        OnlineMap(config2d(), path=path)
    assert path.read_bytes() == b"hello"
    with pytest.raises(OctolgpError, match="not an octolgp map"):
        OnlineMap.open(path)
    with pytest.raises(MapFileNotFound):
        OnlineMap.open(tmp_path / "missing.octolgp")
    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE t(x)")
    con.commit()
    con.close()
    with pytest.raises(OctolgpError, match=r"corrupt|not an octolgp"):
        OnlineMap.open(other)


def test_downsample_keeps_one_real_beam_per_voxel() -> None:
    rng = np.random.default_rng(5)
    pts = rng.uniform(-2, 2, (2000, 3))
    far = np.array([[30.0, 0.0, 0.0], [30.0, 0.01, 0.0]])  # two no-returns, one voxel
    scan = Scan(origin=[0.0, 0.0, 0.0], points=np.vstack([pts, far]), max_range=25.0)
    small = scan.downsample(0.5)
    keys = np.floor(small.points / 0.5).astype(int)
    ret = np.linalg.norm(small.points, axis=1) < 25.0
    assert np.unique(keys[ret], axis=0).shape[0] == int(ret.sum())  # one return per voxel
    assert int((~ret).sum()) == 1  # the no-returns keep their own voxel entry
    assert np.unique(np.floor(pts / 0.5), axis=0).shape[0] == int(ret.sum())
    # every kept point is an original beam endpoint, in the original order
    idx = [int(np.flatnonzero((scan.points == p).all(axis=1))[0]) for p in small.points]
    assert idx == sorted(idx)
    assert small.max_range == 25.0
    with pytest.raises(OctolgpError, match="voxel"):
        scan.downsample(0.0)


def test_coarser_free_voxels_keep_fewer_pieces() -> None:
    # exact engine: free_voxels thins its free pieces (lattice leaves keep counts)
    scans = [room_scan((x, 0.2 * x), n=180) for x in (-2.0, 0.0, 2.0)]
    fine = OnlineMap(config2d(engine="exact"))
    coarse = OnlineMap(config2d(ExactConfig(free_voxels=3), engine="exact"))
    fine.insert_scans(scans)
    coarse.insert_scans(scans)
    n_fine = sum(leaf.evidence.free_start.shape[0] for _, leaf in fine.leaves())  # type: ignore[attr-defined]
    n_coarse = sum(leaf.evidence.free_start.shape[0] for _, leaf in coarse.leaves())  # type: ignore[attr-defined]
    assert n_coarse < 0.6 * n_fine
    for key, leaf in coarse.leaves():  # hits are untouched by the free-piece rule
        assert np.array_equal(leaf.evidence.hit_keys, fine.store.get(key).evidence.hit_keys)  # type: ignore[attr-defined, union-attr]


def test_free_weight_default_and_round_trip() -> None:
    assert LatticeConfig().free_weight == 0.05
    given = MapConfig(dim=2, lattice=LatticeConfig(free_weight=0.5))
    for config in (MapConfig(dim=2), MapConfig(dim=3), given):
        assert MapConfig.from_dict(config.to_dict()) == config


def test_free_weight_changes_the_lattice_map() -> None:
    """The resolved weight reaches the fit: free space reads more confidently free at 1.0."""
    hp = Hyperparameters(0.5, 1.0, 0.05, alpha=3.0, beta=0.0)
    angles = np.linspace(-0.5, 0.5, 41)
    ends = np.c_[np.cos(angles), np.sin(angles)] * 3.0
    scan = Scan(np.zeros(2), ends)
    probe = np.array([[1.5, 0.0]])
    probs = []
    for weight in (0.06, 0.3, 1.0):
        cfg = MapConfig(dim=2, hyperparameters=hp, lattice=LatticeConfig(free_weight=weight))
        with OnlineMap(cfg) as m:
            m.insert_scan(scan)
            probs.append(float(m.occupancy(probe)[0]))
    assert probs[2] < probs[1] < probs[0] < 0.5


def test_free_looks_count_up_to_clear_scans() -> None:
    """With newer evidence winning, each scan that sees a voxel free adds to its free
    evidence until clear_scans scans have: P falls with every look up to K, then stays."""
    hp = Hyperparameters(0.5, 1.0, 0.05, alpha=3.0, beta=0.0)
    angles = np.linspace(-0.5, 0.5, 41)
    scan = Scan(np.zeros(2), np.c_[np.cos(angles), np.sin(angles)] * 3.0)
    probe = np.array([[1.5, 0.0]])
    k = 4
    cfg = MapConfig(dim=2, hyperparameters=hp, online=OnlineConfig(clear_scans=k))
    probs = []
    with OnlineMap(cfg) as m:
        for _ in range(k + 2):
            m.insert_scan(scan)
            probs.append(float(m.occupancy(probe)[0]))
    assert all(b < a for a, b in itertools.pairwise(probs[:k]))
    assert probs[k - 1] == probs[k] == probs[k + 1]
    static = MapConfig(dim=2, hyperparameters=hp, online=OnlineConfig(clear_scans=0))
    with OnlineMap(static) as m:  # static: one free count per voxel (evidence_cap 1)
        m.insert_scan(scan)
        once = float(m.occupancy(probe)[0])
        m.insert_scan(scan)
        assert float(m.occupancy(probe)[0]) == once


def evidence_bytes(leaf: Leaf) -> tuple[bytes, ...]:
    """Every array of a leaf's engine evidence, as bytes."""
    return tuple(a.tobytes() for a in evidence_arrays(leaf.evidence))
