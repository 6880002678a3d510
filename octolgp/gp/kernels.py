r"""Matérn ν=3/2 kernel and its integral (line) kernels by Clenshaw-Curtis quadrature.

Point kernel, with :math:`a = \sqrt{3}\,r / l`:

.. math:: k(x, x') = \sigma_f^2 (1 + a)\, e^{-a}.

**Formulation of the integral kernel (one, used everywhere).** A free segment
:math:`S = \{s + u (e - s) : u \in [0, 1]\}` observes the *average* of the latent
function along it, :math:`\bar f(S) = \int_0^1 f(s + u(e - s))\,du`, with target −1.
(The equivalent arc-length form would observe :math:`\int f\,d\ell` with target
−length; we use the average throughout.) Hence

.. math::

    k(S, x) = \int_0^1 k(s + u(e-s), x)\,du, \qquad
    k(S, S') = \int_0^1\!\!\int_0^1 k(s + u(e-s), s' + v(e'-s'))\,du\,dv,

approximated by Clenshaw-Curtis quadrature with nodes :math:`u_j` and positive
weights :math:`w_j` (summing to 1). A hit is an item with one node of weight 1.
Every item is thus a weighted set of nodes, and the item covariance is
:math:`W^\top K_{\text{nodes}} W` with :math:`W \ge 0` — a Gram matrix, so positive
semi-definite for any node placement. A segment of length :math:`L` gets
``ceil(L / spacing) + 1`` nodes (clamped to ``[n_min, n_max]``), so long segments
get more nodes; the caller picks ``spacing`` as a fraction of the length scale.
A clipped piece of a free segment is still a free segment with target −1, which is
why the average form (not the arc-length form) suits clipping.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse
from scipy.spatial.distance import cdist

from octolgp.gp.quadrature import QuadratureSet
from octolgp.scan import FloatArray

SQRT3 = float(np.sqrt(3.0))
_CHUNK = 1 << 22  # node pairs per block (32 MiB of float64)


def matern32(r: FloatArray, length_scale: float, signal_variance: float) -> FloatArray:
    """Matérn ν=3/2 as a function of distance, ``σf² (1 + a) exp(−a)``, in place on ``r``."""
    a = np.multiply(r, SQRT3 / length_scale, out=r)
    e = np.exp(-a)
    a += 1.0
    a *= e
    a *= signal_variance
    return a


def _weight_matrix(Q: QuadratureSet, rows: slice, lo: int, hi: int) -> sparse.csr_matrix:
    """Sparse ``W`` (items ``rows`` x nodes ``lo:hi``) holding the quadrature weights.

    Each item's nodes are one contiguous run, so the CSR arrays are the weights, the
    node numbers and the item starts; built directly (no COO conversion), and cached
    on the set for the common whole-set case.
    """
    if rows.start == 0 and rows.stop >= Q.n_items and lo == 0 and hi == Q.n_nodes:
        return Q.weight_matrix
    indptr = np.append(Q.starts[rows], hi) - lo
    return sparse.csr_matrix(
        (Q.weights[lo:hi], np.arange(hi - lo), indptr), shape=(indptr.size - 1, hi - lo)
    )


def _aggregate(K: FloatArray, A: QuadratureSet, B: QuadratureSet, rows: slice) -> FloatArray:
    """Weighted sums of node blocks into item blocks, ``W_A K W_Bᵀ``, for A's items ``rows``.

    ``W`` is a sparse item-by-node matrix of quadrature weights, so each product is one
    pass over ``K`` (several times faster than ``np.add.reduceat`` over node runs). Sets
    of one-node items (points) have ``W = I`` and are skipped.
    """
    node_lo = int(A.starts[rows.start])
    if A.n_items != A.n_nodes:
        W_A = _weight_matrix(A, rows, node_lo, node_lo + K.shape[0])
        K = np.asarray(W_A @ K)
    if B.n_items != B.n_nodes:
        W_B = _weight_matrix(B, slice(0, B.n_items), 0, B.n_nodes)
        K = np.asarray((W_B @ K.T).T)
    return K


def _row_blocks(A: QuadratureSet, n_cols: int) -> list[slice]:
    """Item-aligned blocks of A so that a block's node rows times ``n_cols`` fits _CHUNK."""
    ends = np.append(A.starts[1:], A.n_nodes)
    budget = max(_CHUNK // max(n_cols, 1), 1)
    blocks, lo = [], 0
    while lo < A.n_items:  # a handful of blocks, not per item
        hi = int(np.searchsorted(ends, A.starts[lo] + budget, side="right"))
        hi = max(hi, lo + 1)
        blocks.append(slice(lo, min(hi, A.n_items)))
        lo = hi
    return blocks


def item_covariance(
    A: QuadratureSet, B: QuadratureSet, length_scale: float, signal_variance: float
) -> FloatArray:
    """Covariance between items of A and B (points, or segment averages).

    Parameters
    ----------
    A, B : QuadratureSet
        Items with ``I_A`` and ``I_B`` entries.
    length_scale : float
        Metres.
    signal_variance : float
        ``σf²``.

    Returns
    -------
    ndarray of shape (I_A, I_B)
    """
    out = np.empty((A.n_items, B.n_items))
    for rows in _row_blocks(A, B.n_nodes):
        lo = int(A.starts[rows.start])
        hi = int(A.starts[rows.stop]) if rows.stop < A.n_items else A.n_nodes
        K = matern32(cdist(A.nodes[lo:hi], B.nodes), length_scale, signal_variance)
        out[rows] = _aggregate(K, A, B, rows)
    return out


def node_distances(A: QuadratureSet) -> FloatArray:
    """Distances between all nodes of A, shape (N, N); reused across likelihood evaluations."""
    return np.asarray(cdist(A.nodes, A.nodes))


def covariance_with_grad(
    A: QuadratureSet, R: FloatArray, length_scale: float, signal_variance: float
) -> tuple[FloatArray, FloatArray]:
    """Item covariance of A with itself and its derivative by ``log length_scale``.

    ``∂k/∂log l = σf² a² e^{−a}`` at every node pair, aggregated like ``k``.

    Parameters
    ----------
    A : QuadratureSet
        ``I`` items on ``N`` nodes.
    R : ndarray of shape (N, N)
        Node distances from :func:`node_distances`.
    length_scale, signal_variance : float

    Returns
    -------
    K, dK_dlogl : ndarray of shape (I, I)
    """
    rows = slice(0, A.n_items)
    a = R * (SQRT3 / length_scale)
    e = np.exp(-a)
    g = a * a * e * signal_variance
    e *= 1.0 + a
    e *= signal_variance
    return _aggregate(e, A, A, rows), _aggregate(g, A, A, rows)
