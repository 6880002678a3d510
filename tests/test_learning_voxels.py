"""Learning on voxel observations: the lattice engine's point model.

Oracles: scikit-learn's ``GaussianProcessRegressor`` (Matérn 3/2 times a constant, the
per-item noise as its ``alpha``) for the log marginal likelihood and its kernel
gradients, central finite differences for every gradient, and leave-one-out refits
written out (the GP of the other items, predicted at the left-out one) for the
closed-form LOO means and variances.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.linalg import cho_solve
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern
from test_learning import _room_scans
from threadpoolctl import threadpool_limits

import octolgp.gp.learning as learning_module
from octolgp import MapConfig, OctolgpError
from octolgp.config import Hyperparameters, LearningConfig, OnlineConfig
from octolgp.geometry.keys import (
    RETURN_STEPS,
    coord_to_key,
    key_to_coord,
    return_steps,
    step_points,
)
from octolgp.gp.kernels import item_covariance
from octolgp.gp.learning import (
    learn_from_voxels,
    learn_hyperparameters,
    learning_model,
    voxel_learning_sets,
    voxel_observations,
)
from octolgp.gp.likelihood import log_marginal_likelihood, loo_log_predictive, loo_predictions
from octolgp.gp.quadrature import points_set
from octolgp.observations import observe
from octolgp.scan import Scan


def _points(seed: int, n: int, dim: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random points, ±1 targets and noise scales in [1, 20] (free voxels weigh little)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2.0, 2.0, (n, dim))
    y = np.where(rng.random(n) < 0.4, 1.0, -1.0)
    scale = np.where(y > 0, 1.0, rng.uniform(1.0, 20.0, n))
    return X, y, scale


@pytest.mark.parametrize("seed", range(4))
def test_log_marginal_likelihood_with_noise_scale_equals_scikit_learn(seed: int) -> None:
    """Value to 1e-10 relative, kernel gradients to 1e-8: ``K = K_f + σn² diag(s)``."""
    X, y, scale = _points(seed, 40, dim=2 + seed % 2)
    ell, sf2, sn2 = 0.7 + 0.2 * seed, 1.5, 0.03
    value, grad = log_marginal_likelihood(points_set(X), y, np.log([ell, sf2, sn2]), None, scale)
    kernel = ConstantKernel(sf2, "fixed") * Matern(ell, "fixed", nu=1.5)
    gpr = GaussianProcessRegressor(kernel, alpha=sn2 * scale, optimizer=None).fit(X, y)
    free = ConstantKernel(sf2) * Matern(ell, nu=1.5)
    gpr_free = GaussianProcessRegressor(free, alpha=sn2 * scale, optimizer=None).fit(X, y)
    ref, ref_grad = gpr_free.log_marginal_likelihood(np.log([sf2, ell]), eval_gradient=True)
    assert value == pytest.approx(gpr.log_marginal_likelihood_value_, rel=1e-10)
    assert value == pytest.approx(ref, rel=1e-10)
    np.testing.assert_allclose(grad[[1, 0]], ref_grad, rtol=1e-8, atol=1e-10)


def _central_difference(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    out = np.zeros_like(x)
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        out[j] = (f(x + e) - f(x - e)) / (2 * h)
    return out


@pytest.mark.parametrize("seed", range(3))
def test_log_marginal_likelihood_gradient_equals_finite_differences(seed: int) -> None:
    """All three log-parameters, the noise one included, to 1e-6 relative."""
    X, y, scale = _points(seed, 30)
    items = points_set(X)
    x = np.log([0.6, 1.2, 0.05]) + np.random.default_rng(seed).normal(0, 0.2, 3)
    _, grad = log_marginal_likelihood(items, y, x, None, scale)
    fd = _central_difference(lambda t: log_marginal_likelihood(items, y, t, None, scale)[0], x)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("latent", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_loo_log_predictive_gradient_equals_finite_differences(seed: int, latent: bool) -> None:
    """All five parameters, per-item noise, noisy or latent LOO variances: to 1e-5 relative."""
    X, y, scale = _points(seed, 25)
    items = points_set(X)
    params = np.array([np.log(0.6), np.log(1.3), np.log(0.04), 2.5, -0.4])

    def value(p: np.ndarray) -> float:
        return loo_log_predictive(items, y, p, None, scale, latent)[0]

    _, grad = loo_log_predictive(items, y, params, None, scale, latent)
    np.testing.assert_allclose(grad, _central_difference(value, params), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("latent", [False, True])
def test_loo_predictions_equal_refits_without_each_item(latent: bool) -> None:
    """μ_i, σ_i² of the GP of the other items at item i (plus its noise unless latent), 1e-9."""
    X, y, scale = _points(5, 20)
    hp = Hyperparameters(length_scale=0.8, signal_variance=1.4, noise_variance=0.05)
    mean, var = loo_predictions(points_set(X), y, hp, None, scale, latent)
    K = item_covariance(points_set(X), points_set(X), hp.length_scale, hp.signal_variance)
    for i in range(y.size):
        rest = np.delete(np.arange(y.size), i)
        A = K[np.ix_(rest, rest)] + np.diag(hp.noise_variance * scale[rest])
        L = np.linalg.cholesky(A)
        k = K[rest, i]
        mu = k @ cho_solve((L, True), y[rest])
        v = K[i, i] - k @ cho_solve((L, True), k)
        if not latent:
            v += hp.noise_variance * scale[i]
        assert mean[i] == pytest.approx(mu, rel=1e-9, abs=1e-12)
        assert var[i] == pytest.approx(v, rel=1e-9, abs=1e-12)


def test_loo_predictions_without_noise_scale_are_those_of_unit_scale() -> None:
    X, y, _ = _points(1, 15)
    hp = Hyperparameters(length_scale=0.5, noise_variance=0.02)
    plain = loo_predictions(points_set(X), y, hp)
    ones = loo_predictions(points_set(X), y, hp, None, np.ones(y.size))
    for a, b in zip(plain, ones, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12)


def test_voxel_observations_are_the_lattice_engines_counts() -> None:
    """Occupied voxels at their first return, free ones at their centres, weights as the engine."""
    config = MapConfig(dim=2, resolution=0.1)
    scans = _room_scans(3, 60)
    points, y, weights = voxel_observations(scans, config)
    obs = observe(scans, config)
    res, depth = config.resolution, config.tree_depth
    returns = np.concatenate([s.points for s in scans])
    hit_keys = {tuple(k) for k in coord_to_key(returns, res, depth)}
    occupied = y > 0
    assert {tuple(k) for k in coord_to_key(points[occupied], res, depth)} == hit_keys
    assert int(occupied.sum()) == len(hit_keys)
    np.testing.assert_array_equal(weights[occupied], 1.0)  # one return counts (evidence_cap 1)
    free_keys = coord_to_key(points[~occupied], res, depth)
    np.testing.assert_allclose(points[~occupied], key_to_coord(free_keys, res, depth))
    assert not {tuple(k) for k in free_keys} & hit_keys
    seen_free = obs.frees[obs.hits == 0]
    assert int((~occupied).sum()) == int(np.count_nonzero(seen_free))
    # a free voxel weighs free_weight per scan that saw it free, up to clear_scans
    k = config.clear_scans
    expected = np.sort(config.lattice.free_weight * np.minimum(seen_free[seen_free > 0], k))
    np.testing.assert_allclose(np.sort(weights[~occupied]), expected)
    # each occupied voxel sits at a return in it, at the cell of its voxel the map keeps
    return_keys = coord_to_key(returns, res, depth)
    kept = step_points(return_steps(returns, return_keys, res, depth), return_keys, res, depth)
    assert np.abs(kept - returns).max() <= 0.5 * res / RETURN_STEPS * (1 + 1e-9)
    tree_points = {tuple(np.round(p, 12)) for p in kept}
    assert all(tuple(np.round(p, 12)) in tree_points for p in points[occupied])


def test_voxel_learning_sets_hold_the_nearest_returns_and_the_free_voxels_around() -> None:
    config = dataclasses.replace(
        MapConfig(dim=2, resolution=0.1),
        learning=LearningConfig(max_clusters=5, max_items_per_cluster=60),
    )
    points, y, weights = voxel_observations(_room_scans(4, 90), config)
    sets = voxel_learning_sets(points, y, weights, config)
    assert len(sets) == 5
    hit_points = points[y > 0]
    for part in sets:
        X = part.items.nodes
        assert part.y.size <= 60
        assert int((part.y > 0).sum()) == 30
        assert part.noise_scale is not None
        hits, frees = X[part.y > 0], X[part.y < 0]
        seed = hits[0]
        radius = np.max(np.linalg.norm(hits - seed, axis=1))
        others = np.linalg.norm(hit_points - seed, axis=1)
        assert np.sum(others < radius) < 30  # no nearer return left out
        assert np.all(np.linalg.norm(frees - seed, axis=1) <= radius + 1e-12)
        # noise scales are 1 / weight of the observations picked
        lookup = {tuple(p): w for p, w in zip(points, weights, strict=True)}
        np.testing.assert_allclose(part.noise_scale, [1.0 / lookup[tuple(p)] for p in X])


def test_voxel_learning_recovers_the_length_scale_of_a_gp_sample() -> None:
    """Targets drawn from a GP with l = 0.5 m on voxel-like points: learnt l within 25 %."""
    rng = np.random.default_rng(0)
    hp = Hyperparameters(length_scale=0.5, signal_variance=1.0, noise_variance=0.01)
    sets = []
    for _ in range(6):
        X = rng.uniform(0, 3, (250, 2))
        scale = rng.choice([1.0, 5.0], 250)
        K = item_covariance(points_set(X), points_set(X), hp.length_scale, hp.signal_variance)
        K[np.diag_indices_from(K)] += hp.noise_variance * scale + 1e-10
        y = np.linalg.cholesky(K) @ rng.standard_normal(250)
        sets.append(learning_module.LearningSet(points_set(X), y, scale))
    ell, sf2, sn2 = learning_module.fit_kernel(
        sets, Hyperparameters(length_scale=1.0), 1e-4, shifts=(0.0,)
    )
    assert ell == pytest.approx(0.5, rel=0.25)
    assert sf2 == pytest.approx(1.0, rel=0.5)
    assert sn2 == pytest.approx(0.01, rel=0.5)


def test_the_model_follows_the_engine_unless_chosen() -> None:
    lattice = MapConfig(dim=2, resolution=0.1)
    exact = dataclasses.replace(lattice, online=OnlineConfig(engine="exact"))
    assert learning_model(lattice) == "voxels"
    assert learning_model(exact) == "segments"
    for model in ("voxels", "segments"):
        chosen = dataclasses.replace(exact, learning=LearningConfig(model=model))
        assert learning_model(chosen) == model
    with pytest.raises(OctolgpError, match=r"LearningConfig\.model"):
        LearningConfig(model="points")


def test_learn_hyperparameters_dispatches_on_the_model() -> None:
    scans = _room_scans(4, 90)
    lattice = MapConfig(dim=2, resolution=0.1)
    segments = dataclasses.replace(lattice, learning=LearningConfig(model="segments"))
    exact = dataclasses.replace(lattice, online=OnlineConfig(engine="exact"))
    voxels = learn_hyperparameters(scans, lattice)
    with threadpool_limits(limits=1):  # as learn_hyperparameters: the same BLAS rounding
        assert voxels == learn_from_voxels(scans, lattice)
    assert learn_hyperparameters(scans, exact) == learn_hyperparameters(scans, segments)
    assert voxels.length_scale != pytest.approx(
        learn_hyperparameters(scans, segments).length_scale, rel=1e-3
    )


def test_voxel_learning_refuses_scans_without_data_or_returns() -> None:
    config = MapConfig(dim=2, resolution=0.1)
    origin = np.zeros(2)
    with pytest.raises(OctolgpError, match="no training data"):
        learn_hyperparameters([Scan(origin, np.zeros((3, 2)))], config)
    blind = Scan(origin, np.array([[5.0, 0.0], [0.0, 5.0]]), max_range=5.0)
    with pytest.raises(OctolgpError, match="no return"):
        learn_hyperparameters([blind], config)


def test_voxel_learning_with_lml_loo_refinement_runs_and_stays_in_bounds() -> None:
    config = dataclasses.replace(
        MapConfig(dim=2, resolution=0.1), learning=LearningConfig(objective="lml+loo")
    )
    hp = learn_hyperparameters(_room_scans(4, 90), config)
    assert 1e-2 <= hp.length_scale <= 1e2
    assert hp.alpha > 0


def test_learning_thins_large_scans_to_every_kth_beam() -> None:
    rng = np.random.default_rng(5)
    scans = [Scan(origin=np.zeros(2), points=rng.uniform(-4, 4, (n, 2))) for n in (100, 250, 37)]
    assert learning_module.thinned(scans, None) is scans
    assert learning_module.thinned(scans, 387) is scans  # every beam fits
    for cap in (386, 200, 100, 1):
        out = learning_module.thinned(scans, cap)
        k = -(-387 // cap)  # the smallest stride that fits
        assert sum(len(s) for s in out) <= cap or k > max(len(s) for s in scans)
        for a, b in zip(scans, out, strict=True):
            np.testing.assert_array_equal(b.points, a.points[::k])
            np.testing.assert_array_equal(b.origin, a.origin)
            assert b.max_range == a.max_range


def test_learning_on_thinned_scans_is_learning_on_those_beams() -> None:
    scans = _room_scans(3, 180)
    total = sum(len(s) for s in scans)
    config = MapConfig(dim=2, resolution=0.1, learning=LearningConfig(max_beams=total // 2))
    whole = MapConfig(dim=2, resolution=0.1, learning=LearningConfig(max_beams=None))
    k = -(-total // (total // 2))
    thin = [dataclasses.replace(s, points=s.points[::k]) for s in scans]
    assert learn_hyperparameters(scans, config) == learn_hyperparameters(thin, whole)
    assert LearningConfig().max_beams == 25_000


@pytest.mark.parametrize("value", [0, -3, 2.5, True])
def test_bad_max_beams_is_refused(value: object) -> None:
    with pytest.raises(OctolgpError, match=r"LearningConfig\.max_beams"):
        LearningConfig(max_beams=value)  # type: ignore[arg-type]
