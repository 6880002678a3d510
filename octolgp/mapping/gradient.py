r"""Analytic gradients of the continuous map: of the latent mean and variance, and of P(occupied).

The interpolated read (:func:`~octolgp.mapping.field.interpolate`) is multilinear in
each cell of ``2**d`` voxel centres, so the latent mean and variance have exact
gradients there: with ``f`` the position in the cell (``u = x / r - 1/2``, voxel
edge ``r``),

.. math:: \frac{\partial \mu}{\partial x_j} = \frac{1}{r} \sum_c \mu_c
   \frac{\partial w_c}{\partial f_j}, \qquad
   \frac{\partial w_c}{\partial f_j} = \pm \prod_{i \ne j} w_{c,i}(f_i)

(``+`` where corner ``c`` is the upper one on axis ``j``). P(occupied) is PLSC of
them (:func:`~octolgp.gp.plsc.latent_occupancy`),
``P = Φ(z)``, ``z = (α μ + β κ) / s``, ``s = sqrt(1 + α² (σ² + σn²))``,
``κ = clip(1 - σ² / σf², 0, 1)``, so by the chain rule

.. math:: \nabla P = φ(z) \left( \frac{α \nabla μ + β \nabla κ}{s}
   - \frac{(α μ + β κ) α^2 \nabla σ^2}{2 s^3} \right),
   \qquad \nabla κ = -\nabla σ^2 / σ_f^2 \ (0 < σ^2 < σ_f^2, \text{ else } 0).

This is the derivative of what :meth:`~octolgp.mapping.query.MapReads.occupancy`
reads, so it matches its finite differences inside a cell. On a cell face the
derivative is one-sided (the field is continuous there, its derivative not); where
the point's own voxel is unknown the read is the constant 0.5 and the gradient 0.
"""

from __future__ import annotations

import numpy as np

from octolgp.mapping.field import (
    ReadableMap,
    StoreReader,
    corner_latent,
    corner_weights,
    prior_variance,
)
from octolgp.scan import FloatArray

__all__ = ["latent_gradient", "occupancy_gradient"]


def latent_gradient(
    m: ReadableMap, X: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, np.ndarray]:
    """Interpolated latent mean and variance at points and their gradients.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.

    Returns
    -------
    mean, var : ndarray of shape (q,)
        As :func:`~octolgp.mapping.field.interpolate_latent`.
    grad_mean, grad_var : ndarray of shape (q, d)
        Per metre, world axes.
    known : ndarray of bool, shape (q,)
        Points whose own voxel holds a value.
    """
    res = m.config.resolution
    read = StoreReader(m.store, m.grid)
    frac, corners, mc, vc, known = corner_latent(read, m.config, prior_variance(m), X)
    w = corner_weights(frac, corners)
    upper = corners[:, None, :] == 1  # (2^d, 1, d)
    factors = np.where(upper, frac, 1.0 - frac)  # (2^d, q, d): each axis's weight
    d = X.shape[1]
    grad_mean = np.empty_like(X)
    grad_var = np.empty_like(X)
    for j in range(d):  # one axis at a time (2 or 3)
        others = np.prod(np.delete(factors, j, axis=2), axis=2)  # (2^d, q)
        dw = np.where(upper[:, :, j], others, -others) / res
        grad_mean[:, j] = (dw * mc).sum(axis=0)
        grad_var[:, j] = (dw * vc).sum(axis=0)
    return (w * mc).sum(axis=0), (w * vc).sum(axis=0), grad_mean, grad_var, known


def occupancy_gradient(m: ReadableMap, X: FloatArray) -> FloatArray:
    """Gradient of the interpolated P(occupied) at points, per metre.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.

    Returns
    -------
    ndarray of shape (q, d)
        ``∂P/∂x`` along the world axes; 0 where the point's own voxel is unknown and
        before hyperparameters exist (the read is then piecewise constant).
    """
    hp = m.hyperparameters
    if hp is None:
        return np.zeros_like(X)
    mean, var, g_mean, g_var, known = latent_gradient(m, X)
    s = np.sqrt(1.0 + hp.alpha**2 * (var + hp.noise_variance))
    kappa = np.clip(1.0 - var / hp.signal_variance, 0.0, 1.0)
    inner = (var > 0.0) & (var < hp.signal_variance)
    g_kappa = np.where(inner[:, None], -g_var / hp.signal_variance, 0.0)
    num = hp.alpha * mean + hp.beta * kappa
    z = num / s
    pdf = np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)
    g_z = (hp.alpha * g_mean + hp.beta * g_kappa) / s[:, None] - (num * hp.alpha**2 / (2.0 * s**3))[
        :, None
    ] * g_var
    return np.where(known[:, None], pdf[:, None] * g_z, 0.0)
