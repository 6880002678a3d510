r"""Probabilistic least-squares classification (R&W §6.5; Kim & Kim eq. 9).

.. math:: p(y \mid \mu, \sigma^2) = \Phi\!\left(\frac{y(\alpha\mu + \beta)}{\sqrt{1 + \alpha^2\sigma^2}}\right)

``α`` and ``β`` maximise the sum of leave-one-out log predictive probabilities, with
the closed-form LOO means and variances of :func:`octolgp.gp.likelihood.loo_predictions`
(R&W eq. 6.42). The variance ``σ²`` is that of a noisy observation both in fitting
(LOO) and in prediction (latent variance plus ``σn²``), so the two agree:
:func:`latent_occupancy` is the one place a map turns its latent posterior into P.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize
from scipy.special import log_ndtr, ndtr

from octolgp.config import Hyperparameters
from octolgp.scan import FloatArray


def occupancy_probability(
    mean: FloatArray, var: FloatArray, alpha: float, beta: float | FloatArray
) -> FloatArray:
    """P(occupied) = Φ((α μ + β) / sqrt(1 + α² σ²)), in [0, 1].

    Parameters
    ----------
    mean, var : ndarray of shape (m,)
        Predictive mean and variance (noisy observation).
    alpha, beta : float
        PLSC parameters.
    """
    z = (alpha * mean + beta) / np.sqrt(1.0 + alpha * alpha * var)
    return np.asarray(ndtr(z), dtype=np.float64)


def latent_occupancy(mean: FloatArray, var: FloatArray, hp: Hyperparameters) -> FloatArray:
    """P(occupied) from the latent posterior: add the noise variance, then PLSC.

    Parameters
    ----------
    mean, var : ndarray of shape (m,)
        Latent mean and variance (the variance without the noise).
    hp : Hyperparameters
        Uses ``noise_variance``, ``alpha`` and ``beta``.

    Returns
    -------
    ndarray of shape (m,)
        In [0, 1].
    """
    informed = np.clip(1.0 - var / hp.signal_variance, 0.0, 1.0)
    return occupancy_probability(mean, var + hp.noise_variance, hp.alpha, hp.beta * informed)


def _neg_loo_log_prob(
    params: FloatArray, mu: FloatArray, var: FloatArray, y: FloatArray, w: FloatArray | None = None
) -> tuple[float, FloatArray]:
    """−Σ w_i log Φ(y_i z_i) and its gradient in (α, β) (``w`` of ones by default)."""
    alpha, beta = params
    s = np.sqrt(1.0 + alpha * alpha * var)
    z = y * (alpha * mu + beta) / s
    logp = log_ndtr(z)
    ratio = np.exp(-0.5 * z * z - 0.5 * np.log(2.0 * np.pi) - logp)  # φ(z) / Φ(z)
    if w is not None:
        logp = w * logp
        ratio = w * ratio
    dz_dalpha = y * (mu / s - (alpha * mu + beta) * alpha * var / s**3)
    dz_dbeta = y / s
    grad = -np.array([(ratio * dz_dalpha).sum(), (ratio * dz_dbeta).sum()])
    return -float(logp.sum()), grad


def fit_plsc(
    mu: FloatArray, var: FloatArray, y: FloatArray, balanced: bool = False
) -> tuple[float, float]:
    """Fit α, β by maximising the LOO predictive log probability.

    Parameters
    ----------
    mu, var : ndarray of shape (n,)
        Leave-one-out predictive means and variances.
    y : ndarray of shape (n,)
        Labels in {−1, +1}.
    balanced : bool
        Weight each class's items by ``n / (2 n_class)`` so that occupied and free
        count equally however many items each has (free segments usually outnumber
        hits several times; unweighted, the rarer hits pull β towards "occupied").

    Returns
    -------
    alpha, beta : float
    """
    n = max(y.shape[0], 1)
    w = None
    if balanced:
        n_pos = max(int(np.count_nonzero(y > 0)), 1)
        n_neg = max(int(np.count_nonzero(y < 0)), 1)
        w = np.where(y > 0, n / (2.0 * n_pos), n / (2.0 * n_neg))

    def mean_objective(params: FloatArray) -> tuple[float, FloatArray]:
        # the per-item mean keeps L-BFGS-B's first step sane for any n
        value, grad = _neg_loo_log_prob(params, mu, var, y, w)
        return value / n, grad / n

    res = minimize(
        mean_objective,
        x0=np.array([1.0, 0.0]),
        jac=True,
        method="L-BFGS-B",
        bounds=[(1e-3, 1e3), (-1e2, 1e2)],
    )
    return float(res.x[0]), float(res.x[1])
