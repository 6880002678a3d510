"""The lattice leaf engine: its batched fast path against the DTC written out and the exact GP."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octolgp import Hyperparameters
from octolgp.gp.kernels import matern32
from octolgp.gp.lattice import (
    LatticeGeometry,
    Returns,
    dtc_reference,
    inducing_per_axis,
    inverse_cholesky_factors,
    lattice_posterior,
    lattice_tables,
)

HP = Hyperparameters(length_scale=0.5, signal_variance=1.7, noise_variance=0.05, alpha=3.0)


def _counts(rng: np.random.Generator, n: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    hits = (rng.random((n, H)) < 0.08).astype(np.uint8) * rng.integers(1, 3, (n, H), dtype=np.uint8)
    frees = (rng.random((n, H)) < 0.4).astype(np.uint8) * rng.integers(1, 4, (n, H), dtype=np.uint8)
    return hits, frees


def _as_points(
    g: LatticeGeometry, hits: np.ndarray, frees: np.ndarray, free_weight: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One weighted observation per observed (voxel, class): the counts as point data."""
    X = g.halo_centres()
    h, f = hits > 0, frees > 0
    points = np.concatenate([X[h], X[f]])
    y = np.r_[np.ones(h.sum()), -np.ones(f.sum())]
    w = np.r_[hits[h].astype(float), free_weight * frees[f]]
    return points, y, w


@pytest.mark.parametrize(
    ("dim", "side", "halo", "k"),
    [(2, 16, 4, 6), (2, 16, 4, 12), (2, 8, 2, 5), (3, 8, 2, 3), (3, 4, 1, 4)],
)  # (2, 16, 4, 12): the 2D default's 144-point lattice, inverted through Cholesky
@pytest.mark.parametrize("free_weight", [1.0, 0.1])
@pytest.mark.parametrize("compiled", [False, True])
def test_the_batched_posterior_is_the_dtc_written_out(
    dim: int, side: int, halo: int, k: int, free_weight: float, compiled: bool
) -> None:
    g = LatticeGeometry(dim, side, halo, k, 0.1)
    tables = lattice_tables(g, HP)
    rng = np.random.default_rng(dim * 100 + k)
    hits, frees = _counts(rng, 5, g.n_halo)
    hits[0] = frees[0] = 0  # a leaf with nothing observed
    mean, var = lattice_posterior(tables, hits, frees, free_weight, compiled=compiled)
    for j in range(hits.shape[0]):
        pts, y, w = _as_points(g, hits[j], frees[j], free_weight)
        ref_mean, ref_var = dtc_reference(g.inducing_points(), pts, y, w, g.leaf_centres(), HP)
        # stated tolerance: 1e-9 (both are float64 solves of the same well-posed system)
        np.testing.assert_allclose(mean[j], ref_mean, atol=1e-9)
        np.testing.assert_allclose(var[j], ref_var, atol=1e-9)
    # an unobserved leaf is the prior
    np.testing.assert_allclose(mean[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(var[0], HP.signal_variance, rtol=1e-9)


@pytest.mark.parametrize("m", [5, 27, 127, 128, 150])
def test_the_inverse_cholesky_factor_whitens_the_matrix(m: int) -> None:
    X = np.random.default_rng(m).standard_normal((3, m, m + 7))
    A = X @ X.transpose(0, 2, 1) + np.eye(m)
    R = inverse_cholesky_factors(A.copy())
    # stated tolerance: 1e-12 relative (two float64 factorizations of a matrix >= I)
    inverse = np.linalg.inv(A)
    np.testing.assert_allclose(
        R.transpose(0, 2, 1) @ R, inverse, rtol=0, atol=1e-12 * np.abs(inverse).max()
    )
    np.testing.assert_array_equal(np.triu(R, 1), 0.0)  # lower triangular
    np.testing.assert_allclose(
        R, np.linalg.inv(np.linalg.cholesky(A)), rtol=0, atol=1e-12 * np.abs(R).max()
    )


@pytest.mark.parametrize("m", [5, 130])
def test_the_inverse_cholesky_factor_refuses_an_indefinite_matrix(m: int) -> None:
    A = np.tile(np.eye(m), (2, 1, 1))
    A[1, 0, 0] = -1.0
    with pytest.raises(np.linalg.LinAlgError):
        inverse_cholesky_factors(A)


def test_flat_returns_are_the_per_leaf_list() -> None:
    g = LatticeGeometry(3, 4, 1, 3, 0.2)
    tables = lattice_tables(g, HP)
    rng = np.random.default_rng(4)
    hits, frees = _counts(rng, 5, g.n_halo)
    X = g.halo_centres()
    points = []
    for j in range(5):  # leaf 2 holds no return
        occupied = np.flatnonzero(hits[j]) if j != 2 else np.zeros(0, dtype=np.int64)
        jitter = rng.uniform(-0.1, 0.1, (occupied.size, 3))
        points.append((X[occupied] + jitter, hits[j, occupied].astype(float)))
    flat = Returns.from_list(points, 3)
    np.testing.assert_array_equal(flat.counts, [p.shape[0] for p, _ in points])
    np.testing.assert_array_equal(flat.leaves(2, 4).points, np.concatenate([points[3][0]]))
    a = lattice_posterior(tables, hits, frees, 0.3, points)
    b = lattice_posterior(tables, hits, frees, 0.3, flat)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_small_chunks_give_the_same_posterior(monkeypatch: pytest.MonkeyPatch) -> None:
    from octolgp.gp import lattice

    g = LatticeGeometry(2, 8, 2, 4, 0.1)
    tables = lattice_tables(g, HP)
    hits, frees = _counts(np.random.default_rng(1), 40, g.n_halo)
    whole = lattice_posterior(tables, hits, frees)
    monkeypatch.setattr(lattice, "CHUNK_BYTES", 1)  # one leaf per chunk
    chunked = lattice_posterior(tables, hits, frees)
    # BLAS may sum a product's rows in another order when a chunk holds other leaves:
    # a leaf's posterior depends on its batch only at rounding level
    np.testing.assert_allclose(whole[0], chunked[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(whole[1], chunked[1], rtol=0, atol=1e-12)


def _exact_gp(
    points: np.ndarray, y: np.ndarray, w: np.ndarray, test: np.ndarray, hp: Hyperparameters
) -> tuple[np.ndarray, np.ndarray]:
    """The exact GP with noise σn²/w per point, by dense linear algebra."""

    def k(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        r = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
        return matern32(r, hp.length_scale, hp.signal_variance)

    K = k(points, points) + np.diag(hp.noise_variance / w)
    Ks = k(test, points)
    mean = Ks @ np.linalg.solve(K, y)
    var = hp.signal_variance - np.einsum("ij,ji->i", Ks, np.linalg.solve(K, Ks.T))
    return mean, var


def test_the_lattice_converges_to_the_exact_gp_on_the_observations() -> None:
    """Inducing points at every halo voxel centre make the DTC exact; coarser ones approach it."""
    g0 = LatticeGeometry(2, 8, 2, 12, 0.1)  # box 12: a 12 x 12 lattice at the voxel centres
    rng = np.random.default_rng(3)
    hits, frees = _counts(rng, 1, g0.n_halo)
    pts, y, w = _as_points(g0, hits[0], frees[0], 0.3)
    exact_mean, exact_var = _exact_gp(pts, y, w, g0.leaf_centres(), HP)
    errors = []
    for k in (3, 6, 12):
        g = LatticeGeometry(2, 8, 2, k, 0.1)
        mean, var = lattice_posterior(lattice_tables(g, HP), hits, frees, 0.3)
        errors.append(max(np.abs(mean[0] - exact_mean).max(), np.abs(var[0] - exact_var).max()))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-5  # lattice on the voxel centres: exact up to the 1e-8 jitter


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    ls=st.floats(0.05, 3.0),
    sf2=st.floats(0.1, 10.0),
    sn2=st.floats(1e-6, 1.0),
)
def test_the_posterior_variance_lies_between_zero_and_the_prior(
    seed: int, ls: float, sf2: float, sn2: float
) -> None:
    hp = Hyperparameters(length_scale=ls, signal_variance=sf2, noise_variance=sn2)
    g = LatticeGeometry(2, 4, 1, 4, 0.1)
    hits, frees = _counts(np.random.default_rng(seed), 3, g.n_halo)
    mean, var = lattice_posterior(lattice_tables(g, hp), hits, frees)
    assert np.isfinite(mean).all()
    assert (var >= -1e-9 * sf2).all()
    assert (var <= sf2 * (1 + 1e-9)).all()


@pytest.mark.parametrize("compiled", [False, True])
def test_a_vanishing_noise_variance_stays_finite(compiled: bool) -> None:
    hp = Hyperparameters(0.5, 1.0, 1e-300, 1.0, 0.0)
    g = LatticeGeometry(2, 8, 2, 4, 0.1)
    hits, frees = _counts(np.random.default_rng(5), 2, g.n_halo)
    mean, var = lattice_posterior(lattice_tables(g, hp), hits, frees, compiled=compiled)
    assert np.isfinite(mean).all()
    assert np.isfinite(var).all()


def test_the_lattice_density_follows_the_length_scale() -> None:
    assert inducing_per_axis(2.4, 0.6, 0.5, 2, 16) == 8  # 0.3 m apart
    assert inducing_per_axis(2.4, 0.6, 0.5, 2, 6) == 6  # capped
    assert inducing_per_axis(2.4, 50.0, 0.5, 2, 8) == 2  # at least two
    assert inducing_per_axis(2.4, 50.0, 0.5, 8, 16) == 8  # at least k_min


def test_the_geometry_lays_the_halo_box_out_x_fastest() -> None:
    g = LatticeGeometry(3, 4, 1, 2, 0.5)
    X = g.halo_centres()
    assert X.shape == (216, 3)
    np.testing.assert_allclose(X[0], [-0.25, -0.25, -0.25])
    np.testing.assert_allclose(X[1], [0.25, -0.25, -0.25])  # x varies fastest
    np.testing.assert_allclose(X[6], [-0.25, 0.25, -0.25])
    np.testing.assert_allclose(g.leaf_centres()[0], [0.25, 0.25, 0.25])
    U = g.inducing_points()
    np.testing.assert_allclose(U.min(0), -0.5 + 1.5 / 2)


@pytest.mark.parametrize("compiled", [False, True])
def test_returns_at_their_positions_are_the_dtc_written_out(compiled: bool) -> None:
    g = LatticeGeometry(2, 8, 2, 5, 0.1)
    tables = lattice_tables(g, HP)
    rng = np.random.default_rng(11)
    hits, frees = _counts(rng, 3, g.n_halo)
    points = []
    for j in range(3):  # each occupied voxel's return somewhere inside the voxel
        occupied = np.flatnonzero(hits[j])
        jitter = rng.uniform(-0.05, 0.05, (occupied.size, 2))
        points.append((g.halo_centres()[occupied] + jitter, hits[j, occupied].astype(float)))
    mean, var = lattice_posterior(tables, hits, frees, 0.3, points, compiled=compiled)
    X = g.halo_centres()
    for j in range(3):
        f = frees[j] > 0
        pts = np.concatenate([points[j][0], X[f]])
        y = np.r_[np.ones(points[j][0].shape[0]), -np.ones(f.sum())]
        w = np.r_[points[j][1], 0.3 * frees[j][f]]
        ref_mean, ref_var = dtc_reference(g.inducing_points(), pts, y, w, g.leaf_centres(), HP)
        np.testing.assert_allclose(mean[j], ref_mean, atol=1e-9)
        np.testing.assert_allclose(var[j], ref_var, atol=1e-9)
    # returns at their voxel centres are the table's returns
    centred = [(X[np.flatnonzero(hits[j])], p[1]) for j, p in enumerate(points)]
    a = lattice_posterior(tables, hits, frees, 0.3, centred, compiled=compiled)
    b = lattice_posterior(tables, hits, frees, 0.3, compiled=compiled)
    np.testing.assert_allclose(a[0], b[0], atol=1e-9)
    np.testing.assert_allclose(a[1], b[1], atol=1e-9)


@pytest.mark.parametrize("prune", [True, False])
def test_fitted_leaves_are_with_values_row_by_row(prune: bool) -> None:
    from octolgp.engines.base import fitted_leaves, with_values
    from octolgp.engines.lattice import LatticeEvidence
    from octolgp.mapping.store import Leaf

    rng = np.random.default_rng(2)
    n, v = 6, 64
    prob = rng.uniform(0.2, 0.8, (n, v))
    prob[1] = rng.uniform(0.0, 0.1, v)  # confidently free: pruned
    prob[2] = rng.uniform(0.98, 1.0, v)  # confidently occupied: pruned
    prob[3, 0] = 0.5  # one doubtful voxel: kept
    prob[3, 1:] = 0.01
    mean, var = rng.standard_normal((n, v)), rng.uniform(0.1, 2.0, (n, v))
    leaves = [Leaf(np.array([j, 0, 0]), LatticeEvidence.empty(3), refits=j) for j in range(n)]
    fast = fitted_leaves(leaves, mean, var, prob, prune)
    for j, leaf in enumerate(leaves):
        ref = with_values(leaf, mean[j], var[j], prob[j], prune)
        assert fast[j].pruned == ref.pruned
        assert fast[j].refits == ref.refits
        for name in ("mean", "var", "prob"):
            a, b = getattr(fast[j], name), getattr(ref, name)
            assert a.dtype == b.dtype == np.float32
            np.testing.assert_array_equal(a, b)
            assert a.base is None  # owns its values
    assert [f.pruned for f in fast] == (
        [False, True, True, False, False, False] if prune else [False] * n
    )


def _room_observations() -> tuple[object, object]:
    from octolgp import MapConfig, Scan
    from octolgp.observations import observe

    rng = np.random.default_rng(8)
    config = MapConfig(dim=3, resolution=0.2)
    scans = []
    for _ in range(3):
        ends = rng.uniform(-3.0, 3.0, (400, 3))
        scans.append(Scan(origin=rng.uniform(-0.5, 0.5, 3), points=ends, max_range=10.0))
    return observe(scans, config), config


def test_advancing_each_voxel_once_is_advancing_every_copy() -> None:
    from octolgp.engines.lattice import advance_copies, halo_copies
    from octolgp.mapping.grid import LeafGrid
    from octolgp.observations import advance

    obs, config = _room_observations()
    voxel, _, _ = halo_copies(obs, LeafGrid.from_config(config))
    rng = np.random.default_rng(3)
    per_voxel = rng.integers(0, 3, (2, obs.n_voxels))
    for hits, frees in (
        (per_voxel[0][voxel], per_voxel[1][voxel]),  # copies agree: once per voxel
        (rng.integers(0, 3, voxel.size), rng.integers(0, 3, voxel.size)),  # they differ
    ):
        a = advance_copies(hits, frees, obs, voxel, 1)
        b = advance(hits, frees, obs, voxel, 1)
        for name in ("hits", "frees", "position", "replace", "drop"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_halo_copies_are_every_leaf_whose_halo_box_holds_the_voxel() -> None:
    from octolgp.engines.lattice import halo_copies
    from octolgp.geometry.keys import unpack_keys
    from octolgp.mapping.grid import LeafGrid

    obs, config = _room_observations()
    grid = LeafGrid.from_config(config)
    voxel, leaf_key, flat = halo_copies(obs, grid)
    side, halo, box = grid.side, grid.halo_voxels, grid.side + 2 * grid.halo_voxels
    leaf = unpack_keys(leaf_key, 3)
    local = obs.keys[voxel] - (leaf * side - halo)
    assert ((local >= 0) & (local < box)).all()
    np.testing.assert_array_equal(flat, local @ (box ** np.arange(3)))
    # brute force: per voxel, every leaf within one leaf of its own whose halo box holds it
    expected = set()
    for v, key in enumerate(obs.keys):
        own = key // side
        for off in np.ndindex(3, 3, 3):
            cand = own + np.array(off) - 1
            lo = cand * side - halo
            if ((key >= lo) & (key < lo + box)).all():
                expected.add((v, tuple(cand)))
    assert {(int(v), tuple(map(int, q))) for v, q in zip(voxel, leaf, strict=True)} == expected
