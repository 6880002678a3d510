"""GP regression on one cluster's items: fit, predict, marginal likelihood and LOO.

The Cholesky steps follow Rasmussen & Williams, *Gaussian Processes for Machine
Learning* (2006), Algorithm 2.1; leave-one-out follows §5.4.2, eq. (5.12).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, solve_triangular
from scipy.special import log_ndtr

from octolgp.config import Hyperparameters
from octolgp.errors import OctolgpError
from octolgp.gp.kernels import (
    QuadratureSet,
    covariance_with_grad,
    item_covariance,
    node_distances,
    points_set,
)
from octolgp.scan import FloatArray

LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class LocalGP:
    """A fitted GP: training items, Cholesky factor and weight vector.

    Attributes
    ----------
    items : QuadratureSet
        Training items (hits and free segments).
    L : ndarray of shape (n, n)
        Lower Cholesky factor of ``K + σn² I``.
    L_inv : ndarray of shape (n, n)
        ``L⁻¹``, so that predictive variances are one matrix product (GEMM runs
        several times faster than a triangular solve with many right-hand sides).
    weights : ndarray of shape (n,)
        ``(K + σn² I)⁻¹ y`` (R&W Alg. 2.1 line 3).
    hp : Hyperparameters
    """

    items: QuadratureSet
    L: FloatArray
    L_inv: FloatArray
    weights: FloatArray
    hp: Hyperparameters


JITTER_STEPS = (1e-10, 1e-8, 1e-6, 1e-4, 1e-2)
"""Relative jitters (times the mean diagonal) tried, in order, on a matrix that is not
numerically positive definite (coincident items, a tiny noise variance)."""

_repairs = 0
_repairs_lock = threading.Lock()


def jitter_repairs() -> int:
    """How many kernel matrices this process has repaired by jitter so far.

    A map reads it before and after a fit to report the repairs of that step
    (:attr:`octolgp.online.ScanUpdate.repaired`).
    """
    return _repairs


def _cholesky(K: FloatArray) -> FloatArray:
    """Lower Cholesky factor (R&W Alg. 2.1 line 2), repaired by jitter when needed.

    A matrix that is not numerically positive definite — coincident training items
    with a tiny noise variance, say — gets the smallest of :data:`JITTER_STEPS` (times
    its mean diagonal) added to its diagonal that makes it factor; each such repair
    is counted (:func:`jitter_repairs`). Only a matrix that no jitter repairs (NaN, a
    negative diagonal) raises.
    """
    try:
        L, _ = cho_factor(K, lower=True, check_finite=False)
        return np.tril(L)
    except LinAlgError:
        pass
    scale = float(np.mean(np.diag(K))) if K.size else 1.0
    if np.isfinite(scale) and scale > 0:
        eye = np.eye(K.shape[0])
        for rel in JITTER_STEPS:  # at most five tries
            try:
                L, _ = cho_factor(K + (rel * scale) * eye, lower=True, check_finite=False)
            except LinAlgError:
                continue
            global _repairs
            with _repairs_lock:
                _repairs += 1
            return np.tril(L)
    raise OctolgpError(
        "kernel matrix is not positive definite even with jitter; raise "
        "Hyperparameters.noise_variance or deduplicate the training data"
    )


def _factor(
    items: QuadratureSet, y: FloatArray, hp: Hyperparameters
) -> tuple[FloatArray, FloatArray]:
    """Cholesky factor of ``K + σn² I`` and the weights ``(K + σn² I)⁻¹ y`` (Alg. 2.1 l. 2-3)."""
    K = item_covariance(items, items, hp.length_scale, hp.signal_variance)
    K[np.diag_indices_from(K)] += hp.noise_variance
    L = _cholesky(K)
    if L.shape[0] == 0:  # no items: the GP is its prior
        return L, np.zeros(0)
    return L, cho_solve((L, True), y, check_finite=False)


def fit_local_gp(items: QuadratureSet, y: FloatArray, hp: Hyperparameters) -> LocalGP:
    """Fit GP regression on items with targets ``y``.

    Parameters
    ----------
    items : QuadratureSet
        ``n`` training items.
    y : ndarray of shape (n,)
        Targets: +1 for hits, −1 for free segments (segment averages).
    hp : Hyperparameters
        Kernel hyperparameters, used as given.

    Returns
    -------
    LocalGP
    """
    L, weights = _factor(items, y, hp)
    L_inv = np.zeros((0, 0))
    if L.shape[0]:
        L_inv = solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
    return LocalGP(items=items, L=L, L_inv=L_inv, weights=weights, hp=hp)


def predict_latent(gp: LocalGP, X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Latent mean and variance at test points.

    Parameters
    ----------
    gp : LocalGP
    X : ndarray of shape (m, d)
        Test points, metres, world frame.

    Returns
    -------
    mean, var : ndarray of shape (m,)
        Posterior of the latent ``f`` (the variance excludes the noise).
    """
    Ks = item_covariance(points_set(X), gp.items, gp.hp.length_scale, gp.hp.signal_variance)
    mean = Ks @ gp.weights  # R&W Alg. 2.1 line 4
    v = Ks @ gp.L_inv.T  # line 5, v = L⁻¹ k* (as rows)
    var = gp.hp.signal_variance - np.einsum("ij,ij->i", v, v)  # line 6, diagonal only
    return mean, np.maximum(var, 0.0)


def fit_predict(
    items: QuadratureSet,
    y: FloatArray,
    hp: Hyperparameters,
    X: FloatArray,
    K: FloatArray | None = None,
    Ks: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Fit on items and predict at one set of test points, without forming ``L⁻¹``.

    The same posterior as :func:`fit_local_gp` then :func:`predict_latent`, for a
    GP that predicts once (an online leaf): one triangular solve with the test
    covariances replaces the inverse factor.

    Parameters
    ----------
    items : QuadratureSet
        ``n`` training items.
    y : ndarray of shape (n,)
        Targets.
    hp : Hyperparameters
    X : ndarray of shape (m, d)
        Test points, metres, world frame.
    K : ndarray of shape (n, n), optional
        The noise-free item covariance of ``items``, if the caller has it (an online
        leaf reuses the blocks of the items it already had); not modified.
    Ks : ndarray of shape (m, n), optional
        The covariance between ``X`` and ``items``, likewise.

    Returns
    -------
    mean, var : ndarray of shape (m,)
        Latent posterior (variance excludes the noise).
    """
    if K is None:
        L, weights = _factor(items, y, hp)
    else:
        Kn = K.copy()
        Kn[np.diag_indices_from(Kn)] += hp.noise_variance
        L = _cholesky(Kn)
        weights = cho_solve((L, True), y, check_finite=False)
    if Ks is None:
        Ks = item_covariance(points_set(X), items, hp.length_scale, hp.signal_variance)
    mean = Ks @ weights
    V = solve_triangular(L, Ks.T, lower=True, check_finite=False)  # (n, m)
    var = hp.signal_variance - np.einsum("ij,ij->j", V, V)
    return mean, np.maximum(var, 0.0)


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
    items: QuadratureSet, y: FloatArray, log_theta: FloatArray, R: FloatArray | None = None
) -> tuple[float, FloatArray]:
    """Log marginal likelihood and its gradient in log-parameters.

    Parameters
    ----------
    items : QuadratureSet
    y : ndarray of shape (n,)
    log_theta : ndarray of shape (3,)
        ``log`` of (length_scale, signal_variance, noise_variance).
    R : ndarray of shape (N, N), optional
        Node distances (:func:`octolgp.kernels.node_distances`), to reuse.

    Returns
    -------
    value : float
        ``−½ yᵀα − Σ log L_ii − n/2 log 2π`` (R&W Alg. 2.1 line 7).
    grad : ndarray of shape (3,)
        ``½ tr((ααᵀ − K⁻¹) ∂K/∂θ_j)`` (R&W eq. 5.9).
    """
    ell, sf2, sn2 = np.exp(log_theta)
    R = node_distances(items) if R is None else R
    Kf, dK_dlogl = covariance_with_grad(items, R, float(ell), float(sf2))
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
    items: QuadratureSet, y: FloatArray, hp: Hyperparameters
) -> tuple[FloatArray, FloatArray]:
    """Closed-form leave-one-out predictive means and variances.

    R&W eq. (5.12): ``μ_i = y_i − [K⁻¹y]_i / [K⁻¹]_ii`` and ``σ_i² = 1 / [K⁻¹]_ii``,
    with ``K`` including the noise, so ``σ_i²`` is the predictive variance of a noisy
    observation of item ``i``.

    Returns
    -------
    mean, var : ndarray of shape (n,)
    """
    L, weights = _factor(items, y, hp)
    diag = np.diag(cho_solve((L, True), np.eye(y.shape[0]), check_finite=False))
    return y - weights / diag, 1.0 / diag


def loo_log_predictive(
    items: QuadratureSet, y: FloatArray, params: FloatArray, R: FloatArray | None = None
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
    R : ndarray of shape (N, N), optional
        Node distances, to reuse.

    Returns
    -------
    value : float
    grad : ndarray of shape (5,)
    """
    ell, sf2, sn2 = np.exp(params[:3])
    alpha, beta = float(params[3]), float(params[4])
    R = node_distances(items) if R is None else R
    Kf, dK_dlogl = covariance_with_grad(items, R, float(ell), float(sf2))
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
