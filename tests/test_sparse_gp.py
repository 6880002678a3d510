"""The DTC local GP on inducing points (octolgp.gp.sparse) against the exact local GP."""

from __future__ import annotations

import numpy as np
import pytest

from octolgp import Hyperparameters
from octolgp.gp.kernels import item_covariance
from octolgp.gp.quadrature import points_set, quadrature_set
from octolgp.gp.regression import fit_predict
from octolgp.gp.sparse import InducingStats, absorb, inducing_posterior

HP = Hyperparameters(length_scale=0.8, signal_variance=1.5, noise_variance=0.05, alpha=5.0)


def _posterior(stats: InducingStats, U: np.ndarray, Xs: np.ndarray) -> tuple:
    Kuu = item_covariance(points_set(U), points_set(U), HP.length_scale, HP.signal_variance)
    Ksu = item_covariance(points_set(Xs), points_set(U), HP.length_scale, HP.signal_variance)
    return inducing_posterior(stats, Kuu, Ksu, HP)


@pytest.mark.parametrize("d", [2, 3])
def test_inducing_points_at_the_training_points_give_the_exact_gp(d: int) -> None:
    rng = np.random.default_rng(d)
    X = rng.uniform(-2, 2, (40, d))
    y = np.where(rng.uniform(size=40) < 0.5, 1.0, -1.0)
    Xs = rng.uniform(-2.5, 2.5, (60, d))
    stats = absorb(InducingStats.empty(40), X, points_set(X), y, HP)
    mean, var, _ = _posterior(stats, X, Xs)
    exact_mean, exact_var, _ = fit_predict(points_set(X), y, HP, Xs)
    np.testing.assert_allclose(mean, exact_mean, rtol=0, atol=1e-7)
    np.testing.assert_allclose(var, exact_var, rtol=0, atol=1e-7)


def test_removing_evidence_restores_the_statistics() -> None:
    rng = np.random.default_rng(0)
    U = rng.uniform(-1, 1, (27, 3))
    a = rng.uniform(-1, 1, (30, 3))
    items = quadrature_set(a[:10], a[10:20], a[20:30], 0.2)
    y = np.r_[np.ones(10), -np.ones(10)]
    base = absorb(InducingStats.empty(27), U, points_set(a[:5]), np.ones(5), HP)
    added = absorb(base, U, items, y, HP)
    removed = absorb(added, U, items, y, HP, sign=-1.0)
    assert removed.n_items == base.n_items == 5
    np.testing.assert_allclose(removed.A, base.A, rtol=0, atol=1e-9 * np.abs(added.A).max())
    np.testing.assert_allclose(removed.b, base.b, rtol=0, atol=1e-9 * np.abs(added.b).max())


def test_denser_inducing_lattices_approach_the_exact_gp_with_segments() -> None:
    """Hits and free segments in a 2D leaf: the DTC error falls as the lattice grows."""
    rng = np.random.default_rng(1)
    hits = np.c_[np.full(12, 1.2), np.linspace(0.1, 1.5, 12)]
    origin = np.array([0.1, 0.8])
    ends = hits - 0.1 * (hits - origin) / np.linalg.norm(hits - origin, axis=1)[:, None]
    items = quadrature_set(hits, np.repeat(origin[None], 12, 0), ends, 0.2)
    y = np.r_[np.ones(12), -np.ones(12)]
    Xs = rng.uniform(0.0, 1.6, (200, 2))
    exact_mean, exact_var, _ = fit_predict(items, y, HP, Xs)
    errors = []
    for k in (4, 8, 16):
        g = (np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1) + 0.5) / k
        U = (g.reshape(-1, 2) * 1.6).astype(np.float64)
        stats = absorb(InducingStats.empty(U.shape[0]), U, items, y, HP)
        mean, var, _ = _posterior(stats, U, Xs)
        errors.append(max(np.abs(mean - exact_mean).max(), np.abs(var - exact_var).max()))
    # measured: 0.116, 0.0073, 0.0014 (mean and variance, the larger)
    assert errors[0] > errors[1] > errors[2]
    assert errors[1] < 0.01  # an 8 x 8 lattice (0.2 m, the voxel size) within 0.01
    assert errors[2] < 0.002  # a 16 x 16 lattice (0.1 m) within 0.002
