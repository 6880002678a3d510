"""Local GP regression against scikit-learn, finite differences and brute-force LOO."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern

from octolgp.config import Hyperparameters
from octolgp.errors import OctolgpError
from octolgp.gp.kernels import item_covariance
from octolgp.gp.likelihood import log_marginal_likelihood, loo_log_predictive, loo_predictions
from octolgp.gp.plsc import _neg_loo_log_prob
from octolgp.gp.quadrature import QuadratureSet, points_set, quadrature_set
from octolgp.gp.regression import fit_local_gp, fit_predict, predict_latent

HP = Hyperparameters(length_scale=0.7, signal_variance=1.3, noise_variance=0.05)


def _sklearn_gp(hp: Hyperparameters, fixed: bool = True) -> GaussianProcessRegressor:
    bounds = "fixed" if fixed else (1e-5, 1e5)
    kernel = ConstantKernel(hp.signal_variance, bounds) * Matern(hp.length_scale, bounds, nu=1.5)
    return GaussianProcessRegressor(kernel=kernel, alpha=hp.noise_variance, optimizer=None)


def _point_data(d: int, n: int = 30, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (n, d))
    y = np.sin(2 * X).sum(axis=1) + 0.1 * rng.normal(size=n)
    return X, y


def _mixed_items(seed: int = 0, d: int = 2) -> tuple[QuadratureSet, np.ndarray]:
    """Hits (+1) on a wall and free segments (−1) from a sensor at the origin to them."""
    rng = np.random.default_rng(seed)
    hits = np.column_stack([np.full(8, 2.0), rng.uniform(-1.5, 1.5, 8)])
    if d == 3:
        hits = np.column_stack([hits, rng.uniform(-1, 1, 8)])
    ends = 0.9 * hits[:6]
    items = quadrature_set(hits, np.zeros((6, d)), ends, spacing=0.3)
    y = np.concatenate([np.ones(8), -np.ones(6)])
    return items, y


def _subset(items: QuadratureSet, keep: np.ndarray) -> QuadratureSet:
    """The items ``keep`` of a set, nodes and weights carried along."""
    ends = np.append(items.starts[1:], items.n_nodes)
    node_idx = np.concatenate([np.arange(items.starts[i], ends[i]) for i in keep])
    counts = ends[keep] - items.starts[keep]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    return QuadratureSet(items.nodes[node_idx], items.weights[node_idx], starts)


# --------------------------------------------------------------------------- prediction


@pytest.mark.parametrize("d", [1, 2, 3])
def test_prediction_matches_sklearn(d: int) -> None:
    X, y = _point_data(d)
    Xs = np.random.default_rng(1).uniform(-2.5, 2.5, (50, d))
    gp = fit_local_gp(points_set(X), y, HP)
    mean, var = predict_latent(gp, Xs)
    ref_mean, ref_std = _sklearn_gp(HP).fit(X, y).predict(Xs, return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(var, ref_std**2, rtol=0, atol=1e-8)
    assert np.all(var <= HP.signal_variance)


@pytest.mark.parametrize("d", [2, 3])
def test_fit_predict_matches_sklearn_and_the_two_step_path(d: int) -> None:
    X, y = _point_data(d)
    Xs = np.random.default_rng(3).uniform(-2.5, 2.5, (40, d))
    mean, var, repaired = fit_predict(points_set(X), y, HP, Xs)
    assert not repaired
    ref_mean, ref_std = _sklearn_gp(HP).fit(X, y).predict(Xs, return_std=True)
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(var, ref_std**2, rtol=0, atol=1e-8)
    # with segments too: the same posterior as fit_local_gp + predict_latent
    a = X[:5]
    items = quadrature_set(X, a, a + 0.7, 0.3)
    y2 = np.concatenate([y, -np.ones(5)])
    two_step = predict_latent(fit_local_gp(items, y2, HP), Xs)
    np.testing.assert_allclose(fit_predict(items, y2, HP, Xs)[:2], two_step, rtol=0, atol=1e-10)


def test_prediction_via_quadrature_set_of_points_matches_points_set() -> None:
    X, y = _point_data(3)
    Xs = np.random.default_rng(2).uniform(-2, 2, (20, 3))
    a = predict_latent(fit_local_gp(points_set(X), y, HP), Xs)
    b = predict_latent(
        fit_local_gp(quadrature_set(X, np.zeros((0, 3)), np.zeros((0, 3)), 0.35), y, HP), Xs
    )
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_prediction_far_from_data_reverts_to_prior() -> None:
    X, y = _point_data(2)
    mean, var = predict_latent(fit_local_gp(points_set(X), y, HP), np.array([[100.0, 100.0]]))
    assert abs(mean[0]) < 1e-12
    assert var[0] == pytest.approx(HP.signal_variance, rel=1e-12)


# --------------------------------------------------------------------------- marginal likelihood


@pytest.mark.parametrize("d", [1, 2, 3])
def test_log_marginal_likelihood_matches_sklearn(d: int) -> None:
    X, y = _point_data(d, seed=3)
    log_theta = np.log([HP.length_scale, HP.signal_variance, HP.noise_variance])
    value, grad = log_marginal_likelihood(points_set(X), y, log_theta)
    ref = _sklearn_gp(HP, fixed=False).fit(X, y)
    # sklearn's theta is (log σf², log l); the noise ``alpha`` is not a hyperparameter
    ref_value, ref_grad = ref.log_marginal_likelihood(ref.kernel_.theta, eval_gradient=True)
    assert value == pytest.approx(ref_value, rel=1e-10)
    np.testing.assert_allclose(grad[[1, 0]], ref_grad, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize(
    "log_theta", [np.log([0.7, 1.3, 0.05]), np.log([2.0, 0.5, 0.3]), np.log([0.3, 4.0, 0.01])]
)
@pytest.mark.parametrize("d", [2, 3])
def test_log_marginal_likelihood_gradient_matches_finite_differences(
    log_theta: np.ndarray, d: int
) -> None:
    """Hits and free segments together; central differences in the log-parameters."""
    items, y = _mixed_items(seed=4, d=d)
    _, grad = log_marginal_likelihood(items, y, log_theta)
    h = 1e-6
    fd = np.zeros(3)
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        fd[j] = (
            log_marginal_likelihood(items, y, log_theta + step)[0]
            - log_marginal_likelihood(items, y, log_theta - step)[0]
        ) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_log_marginal_likelihood_value_by_dense_formula() -> None:
    """−½ yᵀ(K+σn²I)⁻¹y − ½ log det(K+σn²I) − n/2 log 2π with segment items."""
    items, y = _mixed_items(seed=5)
    log_theta = np.log([0.8, 1.1, 0.07])
    value, _ = log_marginal_likelihood(items, y, log_theta)
    C = item_covariance(items, items, 0.8, 1.1) + 0.07 * np.eye(y.size)
    expected = (
        -0.5 * y @ np.linalg.solve(C, y)
        - 0.5 * np.linalg.slogdet(C)[1]
        - 0.5 * y.size * np.log(2 * np.pi)
    )
    assert value == pytest.approx(expected, rel=1e-10)


# --------------------------------------------------------------------------- leave-one-out


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("d", [2, 3])
def test_loo_matches_brute_force_refits(seed: int, d: int) -> None:
    """Closed form (R&W eq. 5.12) against refitting without each item in turn.

    Items include free segments. The LOO variance is that of a noisy observation of
    the left-out item: latent variance of the item plus the noise variance.
    """
    items, y = _mixed_items(seed=seed, d=d)
    hp = Hyperparameters(length_scale=0.9, signal_variance=1.2, noise_variance=0.08)
    mean, var = loo_predictions(items, y, hp)
    n = y.size
    bf_mean, bf_var = np.zeros(n), np.zeros(n)
    for i in range(n):
        rest = np.delete(np.arange(n), i)
        gp = fit_local_gp(_subset(items, rest), y[rest], hp)
        item = _subset(items, np.array([i]))
        k = item_covariance(item, gp.items, hp.length_scale, hp.signal_variance)[0]
        kii = item_covariance(item, item, hp.length_scale, hp.signal_variance)[0, 0]
        v = np.linalg.solve(gp.L, k)
        bf_mean[i] = k @ gp.weights
        bf_var[i] = kii - v @ v + hp.noise_variance
    np.testing.assert_allclose(mean, bf_mean, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(var, bf_var, rtol=1e-9, atol=1e-12)
    assert np.all(var > hp.noise_variance)


def test_loo_matches_sklearn_refits_for_points() -> None:
    X, y = _point_data(2, n=15, seed=6)
    mean, var = loo_predictions(points_set(X), y, HP)
    for i in range(y.size):
        rest = np.delete(np.arange(y.size), i)
        m, s = _sklearn_gp(HP).fit(X[rest], y[rest]).predict(X[i : i + 1], return_std=True)
        assert mean[i] == pytest.approx(m[0], abs=1e-9)
        assert var[i] == pytest.approx(s[0] ** 2 + HP.noise_variance, abs=1e-9)


PARAMS = [
    np.array([np.log(0.7), np.log(1.3), np.log(0.05), 2.0, 0.3]),
    np.array([np.log(2.0), np.log(0.5), np.log(0.3), 0.5, -0.2]),
    np.array([np.log(0.3), np.log(4.0), np.log(0.01), 8.0, 1.0]),
]


@pytest.mark.parametrize("params", PARAMS)
@pytest.mark.parametrize("d", [2, 3])
def test_loo_log_predictive_value_and_gradient(params: np.ndarray, d: int) -> None:
    """Σ log Φ(y (α μ_i + β) / √(1 + α² σ_i²)) on the LOO moments; gradient vs differences."""
    items, y = _mixed_items(seed=4, d=d)
    value, grad = loo_log_predictive(items, y, params)
    hp = Hyperparameters(*np.exp(params[:3]))
    mu, var = loo_predictions(items, y, hp)
    assert value == pytest.approx(-_neg_loo_log_prob(params[3:], mu, var, y)[0], rel=1e-12)
    h = 1e-6
    fd = np.zeros(5)
    for j in range(5):
        step = np.zeros(5)
        step[j] = h
        fd[j] = (
            loo_log_predictive(items, y, params + step)[0]
            - loo_log_predictive(items, y, params - step)[0]
        ) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


# --------------------------------------------------------------------------- failure


def test_not_positive_definite_is_repaired_in_fits_and_minus_inf_in_the_likelihood() -> None:
    """Coincident hits with a negligible noise give a singular ``K + σn² I``."""
    from octolgp.gp.regression import cholesky

    X = np.zeros((2, 2))
    y = np.ones(2)
    hp = Hyperparameters(length_scale=1.0, signal_variance=1.0, noise_variance=1e-300)
    gp = fit_local_gp(points_set(X), y, hp)  # repaired by jitter (see the test below)
    assert np.isfinite(gp.weights).all()
    # a matrix no jitter can repair raises, with the hint
    with pytest.raises(OctolgpError, match=r"not positive definite.*noise_variance"):
        cholesky(-np.eye(3))
    mu, _var = loo_predictions(points_set(X), y, hp)  # repaired there too
    assert np.isfinite(mu).all()
    value, grad = log_marginal_likelihood(points_set(X), y, np.log([1.0, 1.0, 1e-300]))
    assert value == -np.inf
    np.testing.assert_array_equal(grad, 0.0)
    value, grad = loo_log_predictive(points_set(X), y, np.array([0.0, 0.0, np.log(1e-300), 1, 0]))
    assert value == -np.inf
    np.testing.assert_array_equal(grad, 0.0)


def test_same_coincident_hits_fit_with_ordinary_noise() -> None:
    """The failure above is the noise, not the data: σn² = 0.1 fits the same hits."""
    X = np.zeros((2, 2))
    gp = fit_local_gp(points_set(X), np.ones(2), Hyperparameters(noise_variance=0.1))
    mean, _ = predict_latent(gp, np.zeros((1, 2)))
    # two observations of +1 at one place: mean 2σf² / (2σf² + σn²)
    assert mean[0] == pytest.approx(2.0 / 2.1, rel=1e-12)


def test_non_positive_definite_kernel_is_repaired_by_jitter_and_counted() -> None:
    from octolgp.gp.quadrature import quadrature_set
    from octolgp.gp.regression import cholesky, fit_local_gp

    # coincident hits and no noise: K is singular (rank 1) before jitter
    pts = np.tile([[1.0, 2.0]], (6, 1))
    items = quadrature_set(pts, np.zeros((0, 2)), np.zeros((0, 2)), 0.1)
    hp = Hyperparameters(0.5, 1.0, 1e-300, 1.0, 0.0)
    gp = fit_local_gp(items, np.ones(6), hp)
    assert gp.repaired  # reported with the result, no process-wide count
    assert not fit_local_gp(items, np.ones(6), Hyperparameters(noise_variance=0.1)).repaired
    _, repaired = cholesky(np.eye(3))
    assert not repaired
    assert np.isfinite(gp.weights).all()
    # the factor is of K plus a small jitter only
    K = np.ones((6, 6))
    np.testing.assert_allclose(gp.L @ gp.L.T, K, atol=1e-3)


def test_online_map_reports_repaired_leaves() -> None:
    from octolgp import MapConfig, OnlineConfig, OnlineMap, Scan

    # two hits 2e-12 m apart on either side of a voxel border: both kept (one per
    # voxel), nearly coincident, so with no noise the leaf's kernel matrix is singular
    # (the exact engine's: lattice leaves never need a jitter repair)
    exact = OnlineConfig(engine="exact", scan_precision=None)
    hp = Hyperparameters(0.5, 1.0, 1e-300, 1.0, 0.0)
    m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=hp, online=exact))
    pts = np.array([[1.0 - 1e-12, 0.05], [1.0 + 1e-12, 0.05], [1.0, 0.35]])
    update = m.insert_scan(Scan(np.zeros(2), pts))
    assert update.repaired >= 1
    assert np.isfinite(m.voxels()[1]).all()
    # a second map in the same process does not see the first map's repairs
    other = OnlineMap(
        MapConfig(dim=2, resolution=0.1, hyperparameters=Hyperparameters(), online=exact)
    )
    assert other.insert_scan(Scan(np.zeros(2), pts)).repaired == 0
    assert other.repaired == 0
    assert m.repaired == update.repaired


def test_concurrent_maps_count_only_their_own_repairs() -> None:
    """Two maps fitting at the same time on two threads: each sees its own repairs only."""
    import threading

    from octolgp import MapConfig, OnlineConfig, OnlineMap, Scan

    bad = Hyperparameters(0.5, 1.0, 1e-300, 1.0, 0.0)  # no noise: near-coincident hits repair
    pts = np.array([[1.0 - 1e-12, 0.05], [1.0 + 1e-12, 0.05], [1.0, 0.35]])
    healthy = np.c_[np.full(20, 2.0), np.linspace(-1, 1, 20)]
    # jitter repairs are the exact engine's; the points as given, not rounded
    exact = OnlineConfig(engine="exact", scan_precision=None)
    a = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=bad, online=exact))
    b = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=Hyperparameters(), online=exact))
    counts: dict[str, list[int]] = {"a": [], "b": []}

    def feed(m: OnlineMap, name: str, points: np.ndarray) -> None:
        for k in range(30):  # each scan from a new place: every insert refits
            shift = np.array([0.0, 3.0 * k])
            counts[name].append(m.insert_scan(Scan(shift, points + shift)).repaired)

    threads = [
        threading.Thread(target=feed, args=(a, "a", pts)),
        threading.Thread(target=feed, args=(b, "b", healthy)),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(c >= 1 for c in counts["a"])
    assert counts["b"] == [0] * 30
    assert a.repaired == sum(counts["a"])
    assert b.repaired == 0
