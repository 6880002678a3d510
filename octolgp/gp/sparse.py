r"""A local GP in information form on fixed inducing points (DTC), for the issue #14 engine.

Groundwork for a leaf engine whose cost per scan does not grow with the evidence a leaf
holds (``docs/design-realtime-3d.md``); not yet used by the maps. With ``m`` inducing
points ``U`` and training items ``f`` (points or segment averages, as everywhere in
octolgp), the Deterministic Training Conditional approximation (Quiñonero-Candela &
Rasmussen 2005, §5; R&W §8.3.3) keeps only the sufficient statistics

.. math::

    A = \sigma_n^{-2} K_{uf} K_{fu}, \qquad b = \sigma_n^{-2} K_{uf}\, y,

which are sums over items: absorbing evidence adds to them, removing evidence (a moved
object, a corrected pose) subtracts the same terms, and their size ``m² + m`` is fixed.
With :math:`\Sigma = (K_{uu} + A)^{-1}` the posterior at test points is

.. math::

    \mu_* = K_{*u} \Sigma b, \qquad
    \sigma_*^2 = k_{**} - K_{*u} K_{uu}^{-1} K_{u*} + K_{*u} \Sigma K_{u*}.

When the inducing points are the training points themselves this is the exact GP
(tested); with fewer, it approximates it, the closer the denser ``U``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from octolgp.config import Hyperparameters
from octolgp.gp.kernels import item_covariance
from octolgp.gp.quadrature import QuadratureSet, points_set
from octolgp.gp.regression import cholesky
from octolgp.scan import FloatArray


@dataclass(frozen=True, slots=True)
class InducingStats:
    """Sufficient statistics of a DTC local GP on ``m`` fixed inducing points.

    Attributes
    ----------
    A : ndarray of shape (m, m)
        ``σn⁻² K_uf K_fu``, summed over the absorbed items.
    b : ndarray of shape (m,)
        ``σn⁻² K_uf y``.
    n_items : int
        Items absorbed minus items removed.
    """

    A: FloatArray
    b: FloatArray
    n_items: int

    @classmethod
    def empty(cls, m: int) -> InducingStats:
        """No evidence yet: the posterior is the prior."""
        return cls(np.zeros((m, m)), np.zeros(m), 0)


def absorb(
    stats: InducingStats,
    inducing: FloatArray,
    items: QuadratureSet,
    y: FloatArray,
    hp: Hyperparameters,
    sign: float = 1.0,
) -> InducingStats:
    """Add (``sign=1``) or remove (``sign=-1``) items' evidence to the statistics.

    Parameters
    ----------
    stats : InducingStats
    inducing : ndarray of shape (m, d)
        The inducing points, metres, world frame.
    items : QuadratureSet
        ``n`` training items (hits, segment averages).
    y : ndarray of shape (n,)
        Their targets.
    hp : Hyperparameters
    sign : float
        ``1`` adds the items, ``-1`` removes items added before.

    Returns
    -------
    InducingStats
        New statistics (``stats`` is not modified).
    """
    Kuf = item_covariance(points_set(inducing), items, hp.length_scale, hp.signal_variance)
    scale = sign / hp.noise_variance
    return InducingStats(
        stats.A + scale * (Kuf @ Kuf.T),
        stats.b + scale * (Kuf @ y),
        stats.n_items + int(sign) * items.n_items,
    )


def inducing_posterior(
    stats: InducingStats,
    Kuu: FloatArray,
    Ksu: FloatArray,
    hp: Hyperparameters,
) -> tuple[FloatArray, FloatArray, bool]:
    """Latent mean and variance at test points from the statistics (DTC).

    Parameters
    ----------
    stats : InducingStats
    Kuu : ndarray of shape (m, m)
        Covariance of the inducing points (noise-free).
    Ksu : ndarray of shape (q, m)
        Covariance of the test points with the inducing points. In a leaf grid both
        ``Kuu`` and ``Ksu`` are the same for every leaf (the voxel centres and the
        inducing lattice sit at the same offsets), so a map computes them once.
    hp : Hyperparameters

    Returns
    -------
    mean, var : ndarray of shape (q,)
        Latent posterior (the variance excludes the noise).
    repaired : bool
        Whether a factor needed a jitter (:func:`octolgp.gp.regression.cholesky`).
    """
    L_uu, rep_uu = cholesky(Kuu)
    L_s, rep_s = cholesky(Kuu + stats.A)
    mean = Ksu @ cho_solve((L_s, True), stats.b, check_finite=False)
    V_uu = solve_triangular(L_uu, Ksu.T, lower=True, check_finite=False)  # (m, q)
    V_s = solve_triangular(L_s, Ksu.T, lower=True, check_finite=False)
    var = hp.signal_variance - np.einsum("ij,ij->j", V_uu, V_uu) + np.einsum("ij,ij->j", V_s, V_s)
    return mean, np.maximum(var, 0.0), rep_uu or rep_s
