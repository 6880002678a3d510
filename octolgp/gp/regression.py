"""GP regression on one cluster's items: fit and predict (R&W Algorithm 2.1).

The Cholesky steps follow Rasmussen & Williams, *Gaussian Processes for Machine
Learning* (2006), Algorithm 2.1. The marginal likelihood and leave-one-out live in
:mod:`octolgp.gp.likelihood`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve, solve_triangular

from octolgp.config import Hyperparameters
from octolgp.errors import OctolgpError
from octolgp.gp.kernels import BlockWorkspace, item_covariance
from octolgp.gp.quadrature import QuadratureSet, points_set
from octolgp.scan import FloatArray

logger = logging.getLogger(__name__)


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
    repaired : bool
        Whether ``K + σn² I`` needed a jitter to factor (:func:`cholesky`).
    """

    items: QuadratureSet
    L: FloatArray
    L_inv: FloatArray
    weights: FloatArray
    hp: Hyperparameters
    repaired: bool = False


JITTER_STEPS = (1e-10, 1e-8, 1e-6, 1e-4, 1e-2)
"""Relative jitters (times the mean diagonal) tried, in order, on a matrix that is not
numerically positive definite (coincident items, a tiny noise variance)."""


def cholesky(K: FloatArray) -> tuple[FloatArray, bool]:
    """Lower Cholesky factor (R&W Alg. 2.1 line 2), repaired by jitter when needed.

    A matrix that is not numerically positive definite — coincident training items
    with a tiny noise variance, say — gets the smallest of :data:`JITTER_STEPS` (times
    its mean diagonal) added to its diagonal that makes it factor. Only a matrix that
    no jitter repairs (NaN, a negative diagonal) raises.

    Returns
    -------
    L : ndarray of shape (n, n)
        Lower factor.
    repaired : bool
        Whether a jitter was needed. Callers report it with their result (there is no
        process-wide count), so two maps in one process never see each other's repairs.
    """
    try:
        L, _ = cho_factor(K, lower=True, check_finite=False)
        return np.tril(L), False
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
            logger.debug("kernel matrix of %d items repaired by jitter %g", K.shape[0], rel)
            return np.tril(L), True
    raise OctolgpError(
        "kernel matrix is not positive definite even with jitter; raise "
        "Hyperparameters.noise_variance or deduplicate the training data"
    )


def factor(
    items: QuadratureSet,
    y: FloatArray,
    hp: Hyperparameters,
    work: BlockWorkspace | None = None,
    noise_scale: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, bool]:
    """Cholesky factor of ``K + σn² I`` and the weights ``(K + σn² I)⁻¹ y`` (Alg. 2.1 l. 2-3).

    The third value tells whether the factor needed a jitter (:func:`cholesky`).
    ``work``: node blocks for :func:`~octolgp.gp.kernels.item_covariance`, to reuse;
    ``noise_scale``: per-item factors ``s`` of shape (n,), the noise then ``σn² diag(s)``.
    """
    K = item_covariance(items, items, hp.length_scale, hp.signal_variance, work)
    noise = hp.noise_variance if noise_scale is None else hp.noise_variance * noise_scale
    K[np.diag_indices_from(K)] += noise
    L, repaired = cholesky(K)
    if L.shape[0] == 0:  # no items: the GP is its prior
        return L, np.zeros(0), repaired
    return L, cho_solve((L, True), y, check_finite=False), repaired


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
    L, weights, repaired = factor(items, y, hp)
    L_inv = np.zeros((0, 0))
    if L.shape[0]:
        L_inv = solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
    return LocalGP(items=items, L=L, L_inv=L_inv, weights=weights, hp=hp, repaired=repaired)


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
) -> tuple[FloatArray, FloatArray, bool]:
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
    repaired : bool
        Whether the factor needed a jitter (:func:`cholesky`).
    """
    if K is None:
        L, weights, repaired = factor(items, y, hp)
    else:
        Kn = K.copy()
        Kn[np.diag_indices_from(Kn)] += hp.noise_variance
        L, repaired = cholesky(Kn)
        weights = cho_solve((L, True), y, check_finite=False)
    if Ks is None:
        Ks = item_covariance(points_set(X), items, hp.length_scale, hp.signal_variance)
    mean = Ks @ weights
    V = solve_triangular(L, Ks.T, lower=True, check_finite=False)  # (n, m)
    var = hp.signal_variance - np.einsum("ij,ij->j", V, V)
    return mean, np.maximum(var, 0.0), repaired
