"""Partitioning (Kim & Kim §III-B): coarse boxes, iterative k-means, overlap.

1. Hits are split into coarse boxes of edge ``box_size``.
2. Within a box, k-means (scikit-learn) clusters the hits into
   ``ceil(items / max_cluster_size)`` groups, and is repeated on any cluster whose
   own items (hits plus the free segments that end at them) exceed the cap.
3. Each cluster is *extended*: its hit bounding box grows by ``overlap`` times its
   extent on every side, and every hit inside (with its free segment) joins its
   training set, so neighbouring local GPs share data at their borders.
   No-return segments join each cluster whose extended box they cross, clipped
   to it. Free segments of hits stay whole: they carry the free space between the
   sensor and the cluster.
4. A test point is predicted by the cluster with the nearest centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sklearn.cluster import KMeans

from octolgp.config import MapConfig
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
        Indices into ``TrainingData.hits`` (own and shared).
    segments : ndarray of shape (s,)
        Indices into the segments that end at those hits.
    nr_start, nr_end : ndarray of shape (r, d)
        No-return segments clipped to the extended box.
    n_own : int
        Own items before extension (at most the cap, unless one hit's items do).
    """

    centre: FloatArray
    lo: FloatArray
    hi: FloatArray
    hits: IntArray
    segments: IntArray
    nr_start: FloatArray
    nr_end: FloatArray
    n_own: int

    @property
    def n_items(self) -> int:
        """Training items: hits, their segments and clipped no-returns."""
        return int(self.hits.size + self.segments.size + self.nr_start.shape[0])


def _kmeans(points: FloatArray, k: int, seed: int) -> IntArray:
    """Labels of k-means with ``k`` clusters (one Lloyd run, seeded k-means++)."""
    if k <= 1 or points.shape[0] <= k:
        return np.minimum(np.arange(points.shape[0]), max(k - 1, 0)).astype(np.int64)
    km = KMeans(n_clusters=k, n_init=1, random_state=seed, max_iter=100, tol=1e-4)
    return km.fit_predict(points).astype(np.int64)


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
            done.extend(np.array_split(idx, k))
            continue
        todo.extend(groups)
    return done


def _clip_to_box(
    a: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Liang-Barsky clipping of segments ``a → b`` to the box ``[lo, hi]``."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - a) / d
        t1 = (hi - a) / d
    tmin = np.where(d != 0, np.minimum(t0, t1), np.where((a >= lo) & (a <= hi), -np.inf, np.inf))
    tmax = np.where(d != 0, np.maximum(t0, t1), np.where((a >= lo) & (a <= hi), np.inf, -np.inf))
    t_in = np.clip(tmin.max(axis=1), 0.0, 1.0)
    t_out = np.clip(tmax.min(axis=1), 0.0, 1.0)
    keep = t_out > t_in
    return a + t_in[:, None] * d, a + t_out[:, None] * d, keep


def partition(data: TrainingData, config: MapConfig, overlap: float | None = None) -> list[Cluster]:
    """Partition training data into overlapping clusters.

    Parameters
    ----------
    data : TrainingData
    config : MapConfig
        Uses ``partition.box_size``, ``max_cluster_size``, ``overlap``, ``seed``
        and ``resolution``.
    overlap : float, optional
        Overrides ``config.partition.overlap`` (0 gives disjoint clusters).

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

    # segments sorted by their hit, for gathering by hit index
    seg_idx = np.flatnonzero(own_seg)
    seg_idx = seg_idx[np.argsort(data.seg_hit[seg_idx], kind="stable")]
    seg_ptr = np.searchsorted(data.seg_hit[seg_idx], np.arange(hits.shape[0] + 1))
    nr = np.flatnonzero(~own_seg)
    min_extent = 2.0 * config.resolution

    clusters = []
    for g in groups:  # one iteration per cluster
        lo, hi = hits[g].min(axis=0), hits[g].max(axis=0)
        margin = frac * np.maximum(hi - lo, min_extent)
        lo, hi = lo - margin, hi + margin
        # 3. extension: every hit inside the extended box, with its segments
        inside = np.flatnonzero(((hits >= lo) & (hits <= hi)).all(axis=1)) if frac > 0 else g
        inside = np.union1d(inside, g)
        counts = seg_ptr[inside + 1] - seg_ptr[inside]
        rep = np.repeat(seg_ptr[inside], counts)
        offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        segs = seg_idx[rep + offs]
        if nr.size:
            s, e, keep = _clip_to_box(data.seg_start[nr], data.seg_end[nr], lo, hi)
            s, e = s[keep], e[keep]
        else:
            s = e = np.zeros((0, hits.shape[1]))
        clusters.append(
            Cluster(
                centre=hits[g].mean(axis=0),
                lo=lo,
                hi=hi,
                hits=inside.astype(np.int64),
                segments=segs.astype(np.int64),
                nr_start=s,
                nr_end=e,
                n_own=int(weight[g].sum()),
            )
        )
    return clusters
