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

from collections.abc import Iterator

import numpy as np
from scipy import sparse
from scipy.spatial.distance import cdist

from octolgp.gp.quadrature import QuadratureSet
from octolgp.scan import FloatArray

SQRT3 = float(np.sqrt(3.0))
_CHUNK = 1 << 19
"""Node pairs per block (4 MiB of float64). Kernel functions hold at most three such
node blocks at a time (distances, kernel, derivative) besides their item-sized
outputs, so their transient memory is bounded whatever the number of nodes."""


def matern32(
    r: FloatArray, length_scale: float, signal_variance: float, scratch: FloatArray | None = None
) -> FloatArray:
    """Matérn ν=3/2 as a function of distance, ``σf² (1 + a) exp(−a)``, in place on ``r``.

    ``scratch`` (an array of ``r``'s shape, overwritten) holds ``exp(−a)``; by
    default a fresh one. No other temporary is made.
    """
    a = np.multiply(r, SQRT3 / length_scale, out=r)
    e = np.negative(a, out=scratch)
    np.exp(e, out=e)
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


def _aggregate(
    K: FloatArray, A: QuadratureSet, B: QuadratureSet, rows: slice, cols: slice | None = None
) -> FloatArray:
    """Weighted sums of node blocks into item blocks, ``W_A K W_Bᵀ``.

    ``K`` holds the nodes of A's items ``rows`` against those of B's items ``cols``
    (all of B by default). ``W`` is a sparse item-by-node matrix of quadrature
    weights, so each product is one pass over ``K`` (several times faster than
    ``np.add.reduceat`` over node runs). Runs of one-node items (points: as many
    nodes as items) have ``W = I`` and are skipped, so a block of hits is not copied.
    """
    cols = slice(0, B.n_items) if cols is None else cols
    if K.shape[0] != rows.stop - rows.start:
        node_lo = int(A.starts[rows.start])
        W_A = _weight_matrix(A, rows, node_lo, node_lo + K.shape[0])
        K = np.asarray(W_A @ K)
    if K.shape[1] != cols.stop - cols.start:
        col_lo = int(B.starts[cols.start])
        W_B = _weight_matrix(B, cols, col_lo, col_lo + K.shape[1])
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


def _node_blocks(A: QuadratureSet, n_cols: int) -> Iterator[tuple[slice, int, int]]:
    """Each of :func:`_row_blocks`, with the node rows ``lo:hi`` its items own."""
    for rows in _row_blocks(A, n_cols):
        lo = int(A.starts[rows.start])
        hi = int(A.starts[rows.stop]) if rows.stop < A.n_items else A.n_nodes
        yield rows, lo, hi


def item_covariance(
    A: QuadratureSet,
    B: QuadratureSet,
    length_scale: float,
    signal_variance: float,
    work: BlockWorkspace | None = None,
) -> FloatArray:
    """Covariance between items of A and B (points, or segment averages).

    Node pairs are visited in item-aligned row blocks of at most ``_CHUNK`` pairs
    (two of them held at a time besides the output).

    Parameters
    ----------
    A, B : QuadratureSet
        Items with ``I_A`` and ``I_B`` entries.
    length_scale : float
        Metres.
    signal_variance : float
        ``σf²``.
    work : BlockWorkspace, optional
        Node blocks to reuse (see :class:`BlockWorkspace`); by default fresh ones.

    Returns
    -------
    ndarray of shape (I_A, I_B)
    """
    out = np.empty((A.n_items, B.n_items))
    for rows, lo, hi in _node_blocks(A, B.n_nodes):
        if work is None:
            K = matern32(cdist(A.nodes[lo:hi], B.nodes), length_scale, signal_variance)
        else:
            r, e, _ = work.blocks(hi - lo, B.n_nodes)
            cdist(A.nodes[lo:hi], B.nodes, out=r)
            K = matern32(r, length_scale, signal_variance, scratch=e)
        out[rows] = _aggregate(K, A, B, rows)
        del K  # the next block's distances may reuse its memory
    return out


class BlockWorkspace:
    """Three reusable node blocks (distances, kernel, derivative) of ``_CHUNK`` floats.

    :func:`covariance_with_grad` and :func:`item_covariance` fill them block by
    block; the hyperparameter learning, which calls them hundreds of times, passes
    one workspace throughout, so its pages are faulted in once rather than at every
    call (fresh blocks cost twice the page faults and a third more time on 40 FR079
    scans) and glibc's heap does not grow around them. Grows only for a block that
    one item's nodes alone make larger. Drop it to free the memory.
    """

    def __init__(self) -> None:
        self._buffer = np.empty((3, 0))

    def blocks(self, rows: int, cols: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Three C-contiguous ``(rows, cols)`` views into the buffer."""
        size = rows * cols
        if size > self._buffer.shape[1]:
            self._buffer = np.empty((3, max(size, _CHUNK)))
        a, e, g = (self._buffer[i, :size].reshape(rows, cols) for i in range(3))
        return a, e, g


def covariance_with_grad(
    A: QuadratureSet,
    length_scale: float,
    signal_variance: float,
    work: BlockWorkspace | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Item covariance of A with itself and its derivative by ``log length_scale``.

    ``∂k/∂log l = σf² a² e^{−a}`` at every node pair, aggregated like ``k``. Node
    pairs are visited in item-aligned row blocks of at most ``_CHUNK`` pairs, so
    besides the two ``(I, I)`` outputs and the item-by-node partial sums only three
    blocks of 4 MiB are held (the whole ``(N, N)`` node matrices never are). Each
    block covers its items against themselves and the later items only, and the
    rest is mirrored from it (both matrices are symmetric), which halves the work;
    entries agree with :func:`item_covariance` to rounding (``1e-15`` relative).

    Parameters
    ----------
    A : QuadratureSet
        ``I`` items on ``N`` nodes.
    length_scale, signal_variance : float
    work : BlockWorkspace, optional
        The node blocks, to reuse across calls; by default a fresh one.

    Returns
    -------
    K, dK_dlogl : ndarray of shape (I, I)
    """
    work = BlockWorkspace() if work is None else work
    n = A.n_items
    K = np.empty((n, n))
    dK = np.empty((n, n))
    blocks = list(_node_blocks(A, A.n_nodes))
    for rows, lo, hi in blocks:  # the upper triangle: this block's items against later ones
        cols = slice(rows.start, n)
        a, e, g = work.blocks(hi - lo, A.n_nodes - lo)
        cdist(A.nodes[lo:hi], A.nodes[lo:], out=a)
        a *= SQRT3 / length_scale
        np.negative(a, out=e)
        np.exp(e, out=e)
        np.multiply(a, a, out=g)
        g *= e
        g *= signal_variance
        dK[rows, cols] = _aggregate(g, A, A, rows, cols)
        a += 1.0
        e *= a
        e *= signal_variance
        K[rows, cols] = _aggregate(e, A, A, rows, cols)
    for rows, _, _ in blocks:  # the lower triangle mirrors it
        K[rows.stop :, rows] = K[rows, rows.stop :].T
        dK[rows.stop :, rows] = dK[rows, rows.stop :].T
    return K, dK
