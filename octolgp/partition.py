"""Partitioning (Kim & Kim §III-B): coarse boxes, iterative k-means, overlap.

1. Hits are split into coarse boxes of edge ``box_size``.
2. Within a box, k-means (scikit-learn) clusters the hits, and is repeated on any
   cluster whose own items (each hit plus the free segment ending at it) exceed
   ``max_cluster_size``.
3. A test point is predicted by the cluster with the nearest centre, so a cluster
   answers for its Voronoi cell. Its *region* is the bounding box of its hits and of
   its Voronoi cell within the data's bounding box (found on a lattice), grown by
   ``overlap`` times its extent on every side; the Voronoi part reaches at most
   ``box_size / 2`` beyond the hits (farther away a local GP has nothing to say).
   Its training set is every hit in the region and every free segment that crosses
   it, clipped to it (a piece of a free segment is free, target −1, in the average
   formulation of the integral kernel). Neighbouring regions overlap, so
   neighbouring local GPs share data at their borders; clipping keeps segments
   short, so few quadrature nodes suffice.
4. Bounded size: hits shared from neighbours are thinned at random (seeded) so a
   cluster holds at most ``max_cluster_size`` hits, and free pieces likewise, so a
   local GP never has more than ``2 * max_cluster_size`` items.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from octolgp.config import MapConfig, PartitionConfig
from octolgp.geometry.boxes import clip_to_box
from octolgp.scan import FloatArray
from octolgp.training import IntArray, TrainingData


@dataclass(frozen=True)
class Cluster:
    """One local GP's training set.

    Attributes
    ----------
    centre : ndarray of shape (d,)
        Mean of the cluster's own hits, metres.
    lo, hi : ndarray of shape (d,)
        Extended box, metres.
    hits : ndarray of shape (h,)
        Indices into ``TrainingData.hits`` of the hits in the region.
    seg_start, seg_end : ndarray of shape (s, d)
        Free segments clipped to the region, metres.
    n_own : int
        Own items (own hits plus their segments), at most the cap unless one hit
        alone exceeds it.
    """

    centre: FloatArray
    lo: FloatArray
    hi: FloatArray
    hits: IntArray
    seg_start: FloatArray
    seg_end: FloatArray
    n_own: int

    @property
    def n_items(self) -> int:
        """Training items: hits and free pieces."""
        return int(self.hits.size + self.seg_start.shape[0])


def _kmeans(points: FloatArray, k: int, seed: int) -> IntArray:
    """Labels of k-means with ``k`` clusters (one Lloyd run, seeded k-means++)."""
    if k <= 1 or points.shape[0] <= k:
        return np.minimum(np.arange(points.shape[0]), max(k - 1, 0)).astype(np.int64)
    if np.unique(points, axis=0).shape[0] < k:  # fewer distinct points than clusters
        return np.zeros(points.shape[0], dtype=np.int64)
    from sklearn.cluster import KMeans  # imported on first use: it is slow to import

    km = KMeans(n_clusters=k, n_init=1, random_state=seed, max_iter=100, tol=1e-4)
    return np.asarray(km.fit_predict(points), dtype=np.int64)


def _split_by_weight(idx: IntArray, weight: IntArray, cap: int) -> list[IntArray]:
    """Cut an index run into consecutive pieces of summed weight at most ``cap``.

    A piece starts a new block of ``cap - max(w) + 1`` weight, so a block's last hit
    can add at most ``max(w)``; a hit heavier than ``cap`` stays alone.
    """
    w = weight[idx]
    block = max(cap - int(w.max()) + 1, 1)
    piece = (np.cumsum(w) - w) // block
    cuts = np.flatnonzero(np.diff(piece)) + 1
    return np.split(idx, cuts)


def split_under_cap(points: FloatArray, weight: IntArray, cap: int, seed: int) -> list[IntArray]:
    """Iterative k-means: split until every group's summed weight is within ``cap``.

    Parameters
    ----------
    points : ndarray of shape (n, d)
        Hit positions.
    weight : ndarray of shape (n,)
        Items each hit brings (itself plus its segments).
    cap : int
        Maximum items per group.
    seed : int

    Returns
    -------
    list of ndarray
        Index arrays into ``points``, a partition of ``range(n)``.
    """
    done: list[IntArray] = []
    todo = [np.arange(points.shape[0], dtype=np.int64)]
    while todo:  # one pass per level of splitting, over groups, not points
        idx = todo.pop()
        total = int(weight[idx].sum())
        if total <= cap or idx.size <= 1:
            done.append(idx)
            continue
        k = max(2, math.ceil(total / cap))
        labels = _kmeans(points[idx], k, seed)
        groups = [idx[labels == g] for g in range(k)]
        groups = [g for g in groups if g.size]
        if len(groups) == 1:  # k-means could not separate (coincident hits)
            done.extend(_split_by_weight(idx, weight, cap))
            continue
        todo.extend(groups)
    return done


def voronoi_boxes(
    centres: FloatArray, lo: FloatArray, hi: FloatArray, cells: int
) -> tuple[FloatArray, FloatArray]:
    """Bounding boxes of the nearest-centre cells within ``[lo, hi]``, on a lattice.

    Parameters
    ----------
    centres : ndarray of shape (c, d)
    lo, hi : ndarray of shape (d,)
        The domain, metres.
    cells : int
        Lattice points along the longest axis.

    Returns
    -------
    box_lo, box_hi : ndarray of shape (c, d)
        Per centre; a centre that owns no lattice point gets its own position.
    """
    from scipy.spatial import cKDTree

    step = float(np.max(hi - lo)) / max(cells - 1, 1) or 1.0
    axes = [np.arange(a, b + step, step) for a, b in zip(lo, hi, strict=True)]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, lo.size)
    _, owner = cKDTree(centres).query(lattice)
    box_lo = centres.copy()
    box_hi = centres.copy()
    np.minimum.at(box_lo, owner, lattice)
    np.maximum.at(box_hi, owner, lattice)
    # a lattice point stands for a cell of edge ``step``
    return box_lo - step / 2.0, box_hi + step / 2.0


def partition(
    data: TrainingData, config: MapConfig, overlap: float | None = None, cells: int | None = None
) -> list[Cluster]:
    """Partition training data into overlapping clusters.

    Parameters
    ----------
    data : TrainingData
    config : MapConfig
        Uses ``partition.box_size``, ``max_cluster_size``, ``overlap``, ``seed``
        and ``resolution``.
    overlap : float, optional
        Overrides ``config.partition.overlap`` (0 gives regions that only touch).
    cells : int, optional
        Lattice points along the longest axis for the Voronoi cells (default 256
        in 2D, 48 in 3D; the online map uses one per voxel of a leaf).

    Returns
    -------
    list of Cluster
    """
    pc = config.partition
    frac = pc.overlap if overlap is None else overlap
    hits = data.hits
    if hits.shape[0] == 0:
        return []
    own_seg = data.seg_hit >= 0
    weight = 1 + np.bincount(data.seg_hit[own_seg], minlength=hits.shape[0]).astype(np.int64)
    groups = _groups_under_cap(hits, weight, pc)

    # 3. regions: hit boxes and Voronoi cells in the data's bounding box, grown by overlap
    centres = np.array([hits[g].mean(axis=0) for g in groups])
    everything = np.concatenate([hits, data.seg_start, data.seg_end])
    dom_lo, dom_hi = everything.min(axis=0), everything.max(axis=0)
    if cells is None:
        cells = 256 if data.dim == 2 else 48
    vor_lo, vor_hi = voronoi_boxes(centres, dom_lo, dom_hi, cells)
    min_extent = 2.0 * config.resolution
    min_piece = 0.5 * config.resolution
    reach = 0.5 * pc.box_size
    rng = np.random.default_rng(pc.seed)
    clusters = []
    for k, g in enumerate(groups):  # one iteration per cluster
        lo, hi = _region(hits[g], vor_lo[k], vor_hi[k], reach, frac, min_extent)
        inside = _region_hits(hits, g, lo, hi, pc.max_cluster_size, rng)
        s, e = _region_pieces(data, lo, hi, min_piece, pc.max_cluster_size, rng)
        clusters.append(
            Cluster(
                centre=centres[k],
                lo=lo,
                hi=hi,
                hits=inside.astype(np.int64),
                seg_start=s,
                seg_end=e,
                n_own=int(weight[g].sum()),
            )
        )
    return clusters


def _groups_under_cap(hits: FloatArray, weight: IntArray, pc: PartitionConfig) -> list[IntArray]:
    """Steps 1 and 2: the hits' coarse boxes, each split by iterative k-means under the cap.

    Returns
    -------
    list of ndarray
        Index arrays into ``hits``, one per cluster, boxes in lexicographic order.
    """
    # 1. coarse boxes
    box = np.floor(hits / pc.box_size).astype(np.int64)
    _, box_of = np.unique(box, axis=0, return_inverse=True)
    box_of = box_of.ravel()
    order = np.argsort(box_of, kind="stable")
    bounds = np.flatnonzero(np.diff(box_of[order])) + 1
    groups: list[IntArray] = []
    # 2. iterative k-means within each box
    for members in np.split(order, bounds):
        for g in split_under_cap(hits[members], weight[members], pc.max_cluster_size, pc.seed):
            groups.append(members[g])
    return groups


def _region(
    own: FloatArray,
    vor_lo: FloatArray,
    vor_hi: FloatArray,
    reach: float,
    frac: float,
    min_extent: float,
) -> tuple[FloatArray, FloatArray]:
    """A cluster's region: its hits' box and Voronoi cell box, grown by ``frac`` per side.

    The Voronoi part reaches at most ``reach`` beyond the hits ``own``, and the margin is
    ``frac`` times the region's extent, but at least ``frac * min_extent``.
    """
    # the Voronoi cell, but no further than half a coarse box beyond the hits
    hit_lo, hit_hi = own.min(axis=0), own.max(axis=0)
    lo = np.minimum(hit_lo, np.maximum(vor_lo, hit_lo - reach))
    hi = np.maximum(hit_hi, np.minimum(vor_hi, hit_hi + reach))
    margin = frac * np.maximum(hi - lo, min_extent)
    return lo - margin, hi + margin


def _region_hits(
    hits: FloatArray,
    g: IntArray,
    lo: FloatArray,
    hi: FloatArray,
    cap: int,
    rng: np.random.Generator,
) -> IntArray:
    """The cluster's own hits ``g`` and the other hits in ``[lo, hi]``, sorted.

    Shared hits are thinned at random so that the cluster holds at most ``cap`` hits
    (its own hits are always kept).
    """
    inside = np.flatnonzero(((hits >= lo) & (hits <= hi)).all(axis=1))
    shared = np.setdiff1d(inside, g, assume_unique=True)
    room = max(cap - g.size, 0)
    if shared.size > room:
        shared = rng.choice(shared, room, replace=False)
    return np.union1d(g, shared)


def _region_pieces(
    data: TrainingData,
    lo: FloatArray,
    hi: FloatArray,
    min_piece: float,
    cap: int,
    rng: np.random.Generator,
) -> tuple[FloatArray, FloatArray]:
    """The free segments clipped to ``[lo, hi]``: starts and ends of the pieces kept.

    Pieces no longer than ``min_piece`` are dropped, and the rest thinned at random
    to at most ``cap``, in segment order.
    """
    s, e, keep = clip_to_box(data.seg_start, data.seg_end, lo, hi)
    keep &= np.linalg.norm(e - s, axis=1) > min_piece
    pieces = np.flatnonzero(keep)
    if pieces.size > cap:
        pieces = np.sort(rng.choice(pieces, cap, replace=False))
    return s[pieces], e[pieces]
