"""Training items as weighted quadrature nodes: hits are one node, free segments many.

A free segment observes the *average* of the latent function along it (target −1;
see :mod:`octolgp.gp.kernels` for the formulation); its average is approximated by
Clenshaw-Curtis quadrature with ``ceil(L / spacing) + 1`` nodes, clamped to
``[n_min, n_max]``, with ``spacing`` a fraction of the length scale.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import sparse

from octolgp.config import MapConfig
from octolgp.partition import Cluster
from octolgp.scan import FloatArray
from octolgp.training import IntArray, TrainingData


@lru_cache(maxsize=64)
def clenshaw_curtis(n: int) -> tuple[FloatArray, FloatArray]:
    """Clenshaw-Curtis nodes and weights on [0, 1].

    Parameters
    ----------
    n : int
        Number of nodes, ``n >= 1`` (``n == 1`` is the midpoint rule).

    Returns
    -------
    nodes : ndarray of shape (n,)
        ``(1 - cos(pi j / (n-1))) / 2``, increasing from 0 to 1.
    weights : ndarray of shape (n,)
        Positive, summing to 1; exact for polynomials of degree ``n - 1``.
    """
    if n == 1:
        return np.array([0.5]), np.array([1.0])
    N = n - 1
    j = np.arange(n)
    theta = np.pi * j / N
    nodes = (1.0 - np.cos(theta)) / 2.0
    k = np.arange(1, N // 2 + 1)
    b = np.where(2 * k == N, 1.0, 2.0)
    c = np.where((j == 0) | (j == N), 1.0, 2.0)
    s = (
        b[None, :] / (4.0 * k[None, :] ** 2 - 1.0) * np.cos(2.0 * k[None, :] * theta[:, None])
    ).sum(1)
    weights = c / N * (1.0 - s) / 2.0
    return nodes, weights


@lru_cache(maxsize=8)
def _cc_table(n_max: int) -> tuple[FloatArray, FloatArray]:
    """Tables ``U[n, j]``, ``W[n, j]`` of CC nodes/weights for every order up to ``n_max``."""
    U = np.zeros((n_max + 1, n_max))
    W = np.zeros((n_max + 1, n_max))
    for n in range(1, n_max + 1):  # a table of at most n_max rows, built once
        U[n, :n], W[n, :n] = clenshaw_curtis(n)
    U[1, 0] = 0.0  # a one-node item is a point: node at its start
    return U, W


@dataclass(frozen=True)
class QuadratureSet:
    """Training or test items as weighted quadrature nodes.

    Attributes
    ----------
    nodes : ndarray of shape (N, d)
        Node positions, metres, world frame; item ``i`` owns
        ``nodes[starts[i]:starts[i+1]]``.
    weights : ndarray of shape (N,)
        Quadrature weights (sum to 1 per item).
    starts : ndarray of shape (I,)
        First node of each item (``np.add.reduceat`` offsets).
    """

    nodes: FloatArray
    weights: FloatArray
    starts: IntArray

    @property
    def n_items(self) -> int:
        """Number of items ``I``."""
        return int(self.starts.shape[0])

    @property
    def n_nodes(self) -> int:
        """Number of nodes ``N``."""
        return int(self.nodes.shape[0])

    def subset(self, idx: IntArray) -> QuadratureSet:
        """The items ``idx`` (in that order) as a new set, their nodes copied."""
        ends = np.append(self.starts[1:], self.n_nodes)
        counts = (ends - self.starts)[idx]
        first = self.starts[idx]
        offsets = np.cumsum(counts) - counts
        node_idx = np.repeat(first, counts) + (
            np.arange(int(counts.sum())) - np.repeat(offsets, counts)
        )
        return QuadratureSet(self.nodes[node_idx], self.weights[node_idx], offsets.astype(np.int64))

    @functools.cached_property
    def weight_matrix(self) -> sparse.csr_matrix:
        """Sparse ``(I, N)`` matrix of the quadrature weights.

        ``W[i, j] = w_j`` for item ``i``'s nodes ``j``, so item covariances are
        ``W K_nodes Wᵀ``.
        """
        indptr = np.append(self.starts, self.n_nodes)
        return sparse.csr_matrix(
            (self.weights, np.arange(self.n_nodes), indptr), shape=(self.n_items, self.n_nodes)
        )


def node_counts(lengths: FloatArray, spacing: float, n_min: int, n_max: int) -> IntArray:
    """Nodes per segment: ``ceil(L / spacing) + 1`` clamped to ``[n_min, n_max]``."""
    n = np.ceil(lengths / spacing).astype(np.int64) + 1
    return np.clip(n, n_min, n_max)


def quadrature_set(
    points: FloatArray,
    seg_start: FloatArray,
    seg_end: FloatArray,
    spacing: float,
    n_min: int = 3,
    n_max: int = 33,
) -> QuadratureSet:
    """Lay quadrature nodes on points (one node each) then segments (CC nodes).

    Parameters
    ----------
    points : ndarray of shape (p, d)
        Point items, metres.
    seg_start, seg_end : ndarray of shape (s, d)
        Segment items, metres.
    spacing : float
        Target node spacing along segments, metres.
    n_min, n_max : int
        Bounds on nodes per segment.

    Returns
    -------
    QuadratureSet
        Items in the order: points, then segments.
    """
    d = points.shape[1] if points.size else seg_start.shape[1]
    a = np.concatenate([points.reshape(-1, d), seg_start.reshape(-1, d)])
    b = np.concatenate([points.reshape(-1, d), seg_end.reshape(-1, d)])
    lengths = np.linalg.norm(seg_end - seg_start, axis=1) if seg_start.size else np.zeros(0)
    counts = np.concatenate(
        [np.ones(len(points), dtype=np.int64), node_counts(lengths, spacing, n_min, n_max)]
    )
    starts = (np.cumsum(counts) - counts).astype(np.int64)
    item = np.repeat(np.arange(counts.size), counts)
    j = np.arange(item.size) - starts[item]
    U, W = _cc_table(int(max(n_max, 1)))
    u = U[counts[item], j]
    nodes = a[item] + u[:, None] * (b[item] - a[item])
    return QuadratureSet(nodes=nodes, weights=W[counts[item], j], starts=starts)


def points_set(points: FloatArray) -> QuadratureSet:
    """A :class:`QuadratureSet` of point items (test points)."""
    n = points.shape[0]
    return QuadratureSet(
        nodes=np.ascontiguousarray(points, dtype=np.float64),
        weights=np.ones(n),
        starts=np.arange(n, dtype=np.int64),
    )


def quadrature_spacing(config: MapConfig, length_scale: float) -> float:
    """Node spacing along segments, metres: a fraction of the length scale."""
    return config.training.quadrature_spacing * length_scale


def items_and_targets(
    hits: FloatArray, seg_start: FloatArray, seg_end: FloatArray, config: MapConfig, spacing: float
) -> tuple[QuadratureSet, FloatArray]:
    """Hits and free segments as quadrature nodes, and their targets (+1 hits, −1 free).

    Parameters
    ----------
    hits : ndarray of shape (h, d)
        Hit points, metres.
    seg_start, seg_end : ndarray of shape (s, d)
        Free segments, metres.
    config : MapConfig
        Uses the quadrature node bounds of ``config.training``.
    spacing : float
        Node spacing along segments, metres.

    Returns
    -------
    items : QuadratureSet
        Hits, then free segments.
    y : ndarray of shape (h + s,)
    """
    tc = config.training
    items = quadrature_set(
        hits, seg_start, seg_end, spacing, tc.min_quadrature_nodes, tc.max_quadrature_nodes
    )
    y = np.concatenate([np.ones(hits.shape[0]), -np.ones(seg_start.shape[0])])
    return items, y


def cluster_items(
    data: TrainingData, cluster: Cluster, config: MapConfig, spacing: float
) -> tuple[QuadratureSet, FloatArray]:
    """A cluster's items and targets (:func:`items_and_targets` of its hits and pieces)."""
    return items_and_targets(
        data.hits[cluster.hits], cluster.seg_start, cluster.seg_end, config, spacing
    )
