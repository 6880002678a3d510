"""Marginal likelihood and leave-one-out of GP regression, with gradients.

Rasmussen & Williams (2006): the log marginal likelihood of Algorithm 2.1 line 7 and
its gradient (eq. 5.9); closed-form leave-one-out (§5.4.2, eq. 5.12-5.13) and the
PLSC leave-one-out log predictive probability (§6.5) used to fit α and β.

Every function takes an optional per-item ``noise_scale`` ``s``: the noise covariance
is then ``σn² diag(s)`` instead of ``σn² I`` (the lattice engine's voxel observations,
whose noise is ``σn² / w`` for an observation of weight ``w``).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, lapack
from scipy.special import log_ndtr

from octolgp.config import Hyperparameters
from octolgp.gp.kernels import BlockWorkspace, covariance_with_grad
from octolgp.gp.quadrature import QuadratureSet
from octolgp.gp.regression import factor
from octolgp.scan import FloatArray

LOG_2PI = float(np.log(2.0 * np.pi))


def _noise(sn2: float, n: int, noise_scale: FloatArray | None) -> FloatArray | float:
    """The noise variances on the diagonal: ``σn²``, or ``σn² s`` of shape (n,)."""
    return sn2 if noise_scale is None else sn2 * np.broadcast_to(noise_scale, (n,))


def _noisy_factor(
    Kf: FloatArray, sn2: float, noise_scale: FloatArray | None = None
) -> FloatArray | None:
    """Factor of ``Kf + σn² diag(s)`` (``Kf`` untouched), or ``None`` where it is not PD.

    ``s``: ``noise_scale``, ones by default. The optimisers treat a non-PD point as −inf
    rather than an error.
    """
    K = Kf.copy()
    K[np.diag_indices_from(K)] += _noise(sn2, K.shape[0], noise_scale)
    try:
        L, _ = cho_factor(K, lower=True, check_finite=False)
    except LinAlgError:
        return None
    return np.asarray(L)


def _inverse(L: FloatArray) -> FloatArray:
    """``K⁻¹`` from the lower Cholesky factor ``L`` of ``K`` (LAPACK ``potri``, symmetrised).

    A third of the work of solving against the identity.
    """
    n = L.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    inv, info = lapack.dpotri(L, lower=1)
    if info:
        return np.asarray(cho_solve((L, True), np.eye(n), check_finite=False))
    upper = np.triu_indices(n, 1)
    inv[upper] = inv.T[upper]
    return np.asarray(inv)


def log_marginal_likelihood(
    items: QuadratureSet,
    y: FloatArray,
    log_theta: FloatArray,
    work: BlockWorkspace | None = None,
    noise_scale: FloatArray | None = None,
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
    noise_scale : ndarray of shape (n,), optional
        Per-item factors ``s`` of the noise variance (``K = K_f + σn² diag(s)``);
        ones by default.

    Returns
    -------
    value : float
        ``−½ yᵀα − Σ log L_ii − n/2 log 2π`` (R&W Alg. 2.1 line 7).
    grad : ndarray of shape (3,)
        ``½ tr((ααᵀ − K⁻¹) ∂K/∂θ_j)`` (R&W eq. 5.9).
    """
    ell, sf2, sn2 = np.exp(log_theta)
    Kf, dK_dlogl = covariance_with_grad(items, float(ell), float(sf2), work)
    L = _noisy_factor(Kf, float(sn2), noise_scale)
    if L is None:
        return -np.inf, np.zeros(3)
    alpha = cho_solve((L, True), y, check_finite=False)
    n = y.shape[0]
    value = -0.5 * float(y @ alpha) - float(np.log(np.diag(L)).sum()) - 0.5 * n * LOG_2PI
    inner = np.outer(alpha, alpha) - _inverse(L)
    grad = 0.5 * np.array(
        [
            np.einsum("ij,ji->", inner, dK_dlogl),
            np.einsum("ij,ji->", inner, Kf),  # ∂K/∂log σf² = K_f
            np.sum(np.diag(inner) * _noise(float(sn2), n, noise_scale)),  # ∂K/∂log σn²
        ]
    )
    return value, grad


def loo_predictions(
    items: QuadratureSet,
    y: FloatArray,
    hp: Hyperparameters,
    work: BlockWorkspace | None = None,
    noise_scale: FloatArray | None = None,
    latent: bool = False,
) -> tuple[FloatArray, FloatArray]:
    """Closed-form leave-one-out predictive means and variances.

    R&W eq. (5.12): ``μ_i = y_i − [K⁻¹y]_i / [K⁻¹]_ii`` and ``σ_i² = 1 / [K⁻¹]_ii``,
    with ``K`` including the noise, so ``σ_i²`` is the predictive variance of a noisy
    observation of item ``i``; with ``latent`` it is that of the latent function there,
    ``1 / [K⁻¹]_ii − σn² s_i`` (what a map predicts at a point). ``work``: node blocks to
    reuse; ``noise_scale``: the per-item noise factors ``s`` (ones by default).

    Returns
    -------
    mean, var : ndarray of shape (n,)
    """
    L, weights, _ = factor(items, y, hp, work, noise_scale)
    diag = np.diag(_inverse(L))
    var = 1.0 / diag
    if latent:
        var = np.maximum(var - _noise(hp.noise_variance, y.shape[0], noise_scale), 0.0)
    return y - weights / diag, var


def loo_log_predictive(
    items: QuadratureSet,
    y: FloatArray,
    params: FloatArray,
    work: BlockWorkspace | None = None,
    noise_scale: FloatArray | None = None,
    latent: bool = False,
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
    noise_scale : ndarray of shape (n,), optional
        Per-item noise factors ``s``; ones by default.
    latent : bool
        ``σ_i²`` is the latent variance ``1 / [K⁻¹]_ii − σn² s_i`` (as in
        :func:`loo_predictions`).

    Returns
    -------
    value : float
    grad : ndarray of shape (5,)
    """
    ell, sf2, sn2 = np.exp(params[:3])
    alpha, beta = float(params[3]), float(params[4])
    Kf, dK_dlogl = covariance_with_grad(items, float(ell), float(sf2), work)
    L = _noisy_factor(Kf, float(sn2), noise_scale)
    if L is None:
        return -np.inf, np.zeros(5)
    n = y.shape[0]
    noise = np.broadcast_to(_noise(float(sn2), n, noise_scale), (n,))
    Kinv = _inverse(L)
    a = Kinv @ y
    diag = np.diag(Kinv)
    mu = y - a / diag  # R&W eq. 5.12
    var = 1.0 / diag - noise if latent else 1.0 / diag
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
    # ∂K/∂log σn² = diag(noise), so Z = K⁻¹ diag(noise)
    ZKinv_diag = np.einsum("ik,k,ki->i", Kinv, noise, Kinv)
    dmu = (Kinv @ (noise * a)) / diag - a * ZKinv_diag / diag**2
    dvar = ZKinv_diag / diag**2 - noise if latent else ZKinv_diag / diag**2
    grad[2] = dL_dmu @ dmu + dL_dvar @ dvar
    grad[3] = (ratio * y * (mu / s - (alpha * mu + beta) * alpha * var / s**3)).sum()
    grad[4] = (ratio * y / s).sum()
    return float(logp.sum()), grad
