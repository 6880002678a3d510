"""Probabilistic least-squares classification: range, monotonicity, fit and gradient."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.special import ndtr

from octolgp.gp.plsc import _neg_loo_log_prob, fit_plsc, occupancy_probability

MEAN = st.floats(-50.0, 50.0, allow_nan=False)
VAR = st.floats(0.0, 100.0, allow_nan=False)
ALPHA = st.floats(1e-3, 1e3)
BETA = st.floats(-100.0, 100.0)


@given(
    mean=arrays(np.float64, 20, elements=MEAN),
    var=arrays(np.float64, 20, elements=VAR),
    alpha=st.floats(-1e3, 1e3),
    beta=BETA,
)
def test_occupancy_probability_in_unit_interval(
    mean: np.ndarray, var: np.ndarray, alpha: float, beta: float
) -> None:
    p = occupancy_probability(mean, var, alpha, beta)
    assert p.shape == mean.shape
    assert p.dtype == np.float64
    assert np.all((p >= 0.0) & (p <= 1.0))


@given(
    mean=arrays(np.float64, 20, elements=MEAN, unique=True),
    var=VAR,
    alpha=ALPHA,
    beta=BETA,
)
def test_occupancy_probability_monotone_in_mean(
    mean: np.ndarray, var: float, alpha: float, beta: float
) -> None:
    """For α > 0 and a fixed variance, P(occupied) never decreases as the mean grows."""
    mean = np.sort(mean)
    p = occupancy_probability(mean, np.full(mean.shape, var), alpha, beta)
    assert np.all(np.diff(p) >= 0.0)


@given(mean=MEAN, var=VAR, alpha=ALPHA)
def test_occupancy_probability_symmetric_without_offset(
    mean: float, var: float, alpha: float
) -> None:
    """With β = 0: P(μ) + P(−μ) = 1, and P(0) = ½ whatever the variance."""
    p = occupancy_probability(np.array([mean, -mean, 0.0]), np.full(3, var), alpha, 0.0)
    assert p[0] + p[1] == pytest.approx(1.0, abs=1e-12)
    assert p[2] == 0.5


def test_occupancy_probability_closed_form_and_variance_shrinks_confidence() -> None:
    """Φ((αμ + β) / √(1 + α²σ²)); a larger variance pulls P toward Φ(0) = ½ when β = 0."""
    p = occupancy_probability(np.array([1.0, 1.0]), np.array([0.0, 3.0]), 2.0, 0.0)
    np.testing.assert_allclose(p, ndtr(np.array([2.0, 2.0 / np.sqrt(13.0)])), rtol=1e-15)
    assert 0.5 < p[1] < p[0]


def _plsc_sample(
    n: int, alpha: float, beta: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labels drawn from the PLSC model at random means and variances."""
    rng = np.random.default_rng(seed)
    mu = rng.normal(0.0, 1.0, n)
    var = rng.uniform(0.05, 0.8, n)
    p = ndtr((alpha * mu + beta) / np.sqrt(1.0 + alpha**2 * var))
    y = np.where(rng.uniform(size=n) < p, 1.0, -1.0)
    return mu, var, y


@pytest.mark.parametrize(
    ("alpha", "beta"),
    [
        (0.8, 0.3),
        (1.5, 0.0),
        (2.5, -0.4),
        (6.0, 1.0),
    ],
)
def test_fit_plsc_recovers_parameters(alpha: float, beta: float) -> None:
    """Maximum likelihood on 40 000 labels drawn from the model.

    The fit must beat the true parameters on the sample (it maximises the
    likelihood), and land within 25 % (α) and 0.2 (β) of them. The tolerance is
    loose for large α: there α² σ² ≫ 1, the argument tends to μ / σ, and α is
    weakly identified.
    """
    mu, var, y = _plsc_sample(40_000, alpha, beta, seed=0)
    a, b = fit_plsc(mu, var, y)
    fitted = _neg_loo_log_prob(np.array([a, b]), mu, var, y)[0]
    true = _neg_loo_log_prob(np.array([alpha, beta]), mu, var, y)[0]
    assert fitted <= true + 1e-6 * abs(true)
    assert a == pytest.approx(alpha, rel=0.25)
    assert b == pytest.approx(beta, abs=0.2)


def test_fit_plsc_is_a_stationary_point() -> None:
    mu, var, y = _plsc_sample(5_000, 2.0, -0.3, seed=1)
    a, b = fit_plsc(mu, var, y)
    value, grad = _neg_loo_log_prob(np.array([a, b]), mu, var, y)
    assert np.all(np.abs(grad) < 1e-3 * y.size)
    for da, db in [(0.05, 0.0), (-0.05, 0.0), (0.0, 0.05), (0.0, -0.05)]:
        assert _neg_loo_log_prob(np.array([a + da, b + db]), mu, var, y)[0] > value


@pytest.mark.parametrize(
    "params", [np.array([1.0, 0.0]), np.array([3.0, -0.7]), np.array([0.05, 2.0])]
)
def test_neg_loo_log_prob_gradient_matches_finite_differences(params: np.ndarray) -> None:
    """Includes labels far on the wrong side (|z| up to ~30), where log Φ needs care."""
    mu, var, y = _plsc_sample(200, 2.0, 0.1, seed=2)
    mu[:5] = [-10.0, 10.0, 8.0, -9.0, 0.0]
    y[:5] = [1.0, -1.0, -1.0, 1.0, 1.0]
    value, grad = _neg_loo_log_prob(params, mu, var, y)
    assert np.isfinite(value)
    h = 1e-6
    fd = np.array(
        [
            (
                _neg_loo_log_prob(params + step, mu, var, y)[0]
                - _neg_loo_log_prob(params - step, mu, var, y)[0]
            )
            / (2 * h)
            for step in (np.array([h, 0.0]), np.array([0.0, h]))
        ]
    )
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6)


def test_neg_loo_log_prob_value() -> None:
    mu, var, y = np.array([0.5, -1.0]), np.array([0.2, 0.4]), np.array([1.0, 1.0])
    value, _ = _neg_loo_log_prob(np.array([2.0, 0.5]), mu, var, y)
    z = (2.0 * mu + 0.5) / np.sqrt(1.0 + 4.0 * var)
    assert value == pytest.approx(-np.log(ndtr(z)).sum(), rel=1e-14)


# ------------------------------------------------- a point the sensor never informed


def test_latent_occupancy_reads_half_at_the_prior_and_is_unchanged_where_informed() -> None:
    """β acts in proportion to the informed share ``1 - var/σf²``: at the prior P = 0.5."""
    from octolgp.config import Hyperparameters
    from octolgp.gp.plsc import latent_occupancy

    hp = Hyperparameters(0.5, 2.0, 0.05, alpha=3.0, beta=1.5)
    prior = latent_occupancy(np.zeros(3), np.full(3, 2.0), hp)
    np.testing.assert_array_equal(prior, 0.5)
    # far from the data the variance can round above σf²: still the prior
    assert latent_occupancy(np.zeros(1), np.array([2.0 + 1e-12]), hp)[0] == 0.5
    mean, var = np.array([0.8, -0.7]), np.array([0.1, 0.5])
    share = 1.0 - var / 2.0
    expected = ndtr((3.0 * mean + 1.5 * share) / np.sqrt(1.0 + 9.0 * (var + 0.05)))
    np.testing.assert_allclose(latent_occupancy(mean, var, hp), expected, rtol=1e-14)
    # exactly informed (zero variance): plain PLSC
    np.testing.assert_allclose(
        latent_occupancy(mean, np.zeros(2), hp), occupancy_probability(mean, 0.05, 3.0, 1.5)
    )


def test_online_map_far_from_evidence_reads_near_half() -> None:
    """Voxels of the map's leaves at least 3 length scales from every beam read 0.5 ± 0.05.

    The PLSC offset β is large (P would read Φ(β / sqrt(1 + α² σf²)) ≈ 0.64 at the prior
    under plain PLSC), so the test fails without the informed-share rule.
    """
    from octolgp import Hyperparameters, LatticeConfig, MapConfig, OnlineMap, Scan

    hp = Hyperparameters(0.5, 1.0, 0.05, alpha=2.0, beta=0.8)
    every = LatticeConfig(fill_voxels=-1)  # every voxel of a leaf filled: the GP's own values
    angles = np.linspace(-0.3, 0.3, 7)
    ends = np.c_[np.cos(angles), np.sin(angles)] * 4.0
    scan = Scan(np.zeros(2), ends)
    with OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=hp, lattice=every)) as m:
        m.insert_scan(scan)
        centres, prob = m.voxels()
    # distance from each voxel centre to the nearest beam segment (origin to hit)
    u = ends / np.linalg.norm(ends, axis=1, keepdims=True)
    t = np.clip(centres @ u.T, 0.0, 4.0)  # (v, beams)
    closest = t[:, :, None] * u[None, :, :]
    dist = np.linalg.norm(centres[:, None, :] - closest, axis=2).min(axis=1)
    far = dist >= 3 * hp.length_scale
    assert far.sum() >= 20, far.sum()
    assert np.all(np.abs(prob[far] - 0.5) <= 0.05), np.abs(prob[far] - 0.5).max()
    near_hit = np.linalg.norm(centres[:, None, :] - ends[None], axis=2).min(axis=1) < 0.05
    assert prob[near_hit].min() > 0.6  # the returns still read occupied
