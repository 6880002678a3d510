"""Marginal likelihood and leave-one-out of GP regression, with gradients.

Rasmussen & Williams (2006): the log marginal likelihood of Algorithm 2.1 line 7 and
its gradient (eq. 5.9); closed-form leave-one-out (§5.4.2, eq. 5.12-5.13) and the
PLSC leave-one-out log predictive probability (§6.5) used to fit α and β.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.special import log_ndtr

from octolgp.config import Hyperparameters
from octolgp.gp.kernels import BlockWorkspace, covariance_with_grad
from octolgp.gp.quadrature import QuadratureSet
from octolgp.gp.regression import factor
from octolgp.scan import FloatArray

LOG_2PI = float(np.log(2.0 * np.pi))


def _noisy_factor(Kf: FloatArray, sn2: float) -> FloatArray | None:
    """Factor of ``Kf + σn² I`` (``Kf`` untouched), or ``None`` where it is not PD.

    The optimisers treat a non-PD point as −inf rather than an error.
    """
    K = Kf.copy()
    K[np.diag_indices_from(K)] += sn2
    try:
        L, _ = cho_factor(K, lower=True, check_finite=False)
    except LinAlgError:
        return None
    return np.asarray(L)


def log_marginal_likelihood(
    items: QuadratureSet, y: FloatArray, log_theta: FloatArray, work: BlockWorkspace | None = None
) -> tuple[float, FloatArray]:
    """Log marginal likelihood and its gradient in log-parameters.

    Parameters
    ----------
    items : QuadratureSet
    y : ndarray of shape (n,)
    log_theta : ndarray of shape (3,)
        ``log`` of (length_scale, signal_variance, noise_variance).
    work : BlockWorkspace, optional
        Node blocks for :func:`octolgp.gp.kernels.covariance_with_grad`, to reuse
        across calls.

    Returns
    -------
    value : float
        ``−½ yᵀα − Σ log L_ii − n/2 log 2π`` (R&W Alg. 2.1 line 7).
    grad : ndarray of shape (3,)
        ``½ tr((ααᵀ − K⁻¹) ∂K/∂θ_j)`` (R&W eq. 5.9).
    """
    ell, sf2, sn2 = np.exp(log_theta)
    Kf, dK_dlogl = covariance_with_grad(items, float(ell), float(sf2), work)
    L = _noisy_factor(Kf, float(sn2))
    if L is None:
        return -np.inf, np.zeros(3)
    alpha = cho_solve((L, True), y, check_finite=False)
    n = y.shape[0]
    value = -0.5 * float(y @ alpha) - float(np.log(np.diag(L)).sum()) - 0.5 * n * LOG_2PI
    inner = np.outer(alpha, alpha) - cho_solve((L, True), np.eye(n), check_finite=False)
    grad = 0.5 * np.array(
        [
            np.einsum("ij,ji->", inner, dK_dlogl),
            np.einsum("ij,ji->", inner, Kf),  # ∂K/∂log σf² = K_f
            sn2 * np.trace(inner),  # ∂K/∂log σn² = σn² I
        ]
    )
    return value, grad


def loo_predictions(
    items: QuadratureSet, y: FloatArray, hp: Hyperparameters, work: BlockWorkspace | None = None
) -> tuple[FloatArray, FloatArray]:
    """Closed-form leave-one-out predictive means and variances.

    R&W eq. (5.12): ``μ_i = y_i − [K⁻¹y]_i / [K⁻¹]_ii`` and ``σ_i² = 1 / [K⁻¹]_ii``,
    with ``K`` including the noise, so ``σ_i²`` is the predictive variance of a noisy
    observation of item ``i``. ``work``: node blocks to reuse.

    Returns
    -------
    mean, var : ndarray of shape (n,)
    """
    L, weights, _ = factor(items, y, hp, work)
    diag = np.diag(cho_solve((L, True), np.eye(y.shape[0]), check_finite=False))
    return y - weights / diag, 1.0 / diag


def loo_log_predictive(
    items: QuadratureSet, y: FloatArray, params: FloatArray, work: BlockWorkspace | None = None
) -> tuple[float, FloatArray]:
    """Summed LOO log predictive probability of PLSC and its gradient (R&W §6.5).

    ``Σ_i log Φ(y_i (α μ_i + β) / sqrt(1 + α² σ_i²))`` with the closed-form LOO
    ``μ_i, σ_i²`` of eq. (5.12); derivatives of ``μ_i, σ_i²`` by the kernel
    parameters follow eq. (5.13) with ``Z_j = K⁻¹ ∂K/∂θ_j``.

    Parameters
    ----------
    items : QuadratureSet
    y : ndarray of shape (n,)
        Labels in {−1, +1}.
    params : ndarray of shape (5,)
        ``log`` length_scale, ``log`` signal_variance, ``log`` noise_variance,
        ``alpha``, ``beta``.
    work : BlockWorkspace, optional
        Node blocks, to reuse across calls.

    Returns
    -------
    value : float
    grad : ndarray of shape (5,)
    """
    ell, sf2, sn2 = np.exp(params[:3])
    alpha, beta = float(params[3]), float(params[4])
    Kf, dK_dlogl = covariance_with_grad(items, float(ell), float(sf2), work)
    L = _noisy_factor(Kf, float(sn2))
    if L is None:
        return -np.inf, np.zeros(5)
    Kinv = cho_solve((L, True), np.eye(y.shape[0]), check_finite=False)
    a = Kinv @ y
    diag = np.diag(Kinv)
    mu = y - a / diag  # R&W eq. 5.12
    var = 1.0 / diag
    s = np.sqrt(1.0 + alpha * alpha * var)
    z = y * (alpha * mu + beta) / s
    logp = log_ndtr(z)
    ratio = np.exp(-0.5 * z * z - 0.5 * LOG_2PI - logp)  # φ(z) / Φ(z)
    dL_dmu = ratio * y * alpha / s
    dL_dvar = -0.5 * ratio * y * (alpha * mu + beta) * alpha * alpha / s**3
    grad = np.zeros(5)
    for j, dK in enumerate((dK_dlogl, Kf)):
        Z = Kinv @ dK
        ZKinv_diag = np.einsum("ik,ki->i", Z, Kinv)
        dmu = (Z @ a) / diag - a * ZKinv_diag / diag**2  # R&W eq. 5.13
        dvar = ZKinv_diag / diag**2
        grad[j] = dL_dmu @ dmu + dL_dvar @ dvar
    # ∂K/∂log σn² = σn² I, so Z = σn² K⁻¹
    ZKinv_diag = sn2 * np.einsum("ik,ki->i", Kinv, Kinv)
    dmu = sn2 * (Kinv @ a) / diag - a * ZKinv_diag / diag**2
    grad[2] = dL_dmu @ dmu + dL_dvar @ (ZKinv_diag / diag**2)
    grad[3] = (ratio * y * (mu / s - (alpha * mu + beta) * alpha * var / s**3)).sum()
    grad[4] = (ratio * y / s).sum()
    return float(logp.sum()), grad
