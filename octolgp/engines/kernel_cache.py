"""The exact engine's kernel cache: a leaf's item covariance blocks, reused as it gains items.

A leaf's items are append-only (hits, then free pieces), so when a scan adds items
only the new rows and columns of ``K`` and ``Ks`` need the kernel; the rest is
copied from the leaf's last fit. The cache is bounded in bytes (least recently
used first out) and never changes a result: the assembled blocks equal fresh ones
bit for bit.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from octolgp.config import Hyperparameters
from octolgp.gp.kernels import item_covariance
from octolgp.gp.quadrature import QuadratureSet, points_set
from octolgp.scan import FloatArray


@dataclass(frozen=True, slots=True)
class LeafBlocks:
    """A leaf's item covariance blocks for its first ``n_hits`` hits and ``n_free`` pieces."""

    n_hits: int
    n_free: int
    K: FloatArray  # (n, n) noise-free item covariance, items = hits then pieces
    Ks: FloatArray  # (V, n) voxel centres x items
    key: tuple[float, ...]  # what the blocks depend on besides the items


class KernelCache:
    """Least-recently-used item covariance blocks of leaves, bounded in bytes.

    Thread-safe (the map refits leaves on several threads); each leaf's entry is
    touched by one thread at a time.

    Parameters
    ----------
    max_bytes : int
        Entries are dropped, oldest first, while the total exceeds this.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self._entries: OrderedDict[int, LeafBlocks] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: int) -> LeafBlocks | None:
        """The entry of leaf ``key``, or ``None``."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
            return entry

    def discard(self, keys: list[int]) -> None:
        """Forget the entries of leaves whose items were rebuilt (not appended to)."""
        with self._lock:
            for key in keys:  # one iteration per rebuilt leaf
                old = self._entries.pop(key, None)
                if old is not None:
                    self.bytes -= old.K.nbytes + old.Ks.nbytes

    def put(self, key: int, entry: LeafBlocks) -> None:
        """Store (or replace) the entry of leaf ``key`` and evict down to the budget."""
        size = entry.K.nbytes + entry.Ks.nbytes
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self.bytes -= old.K.nbytes + old.Ks.nbytes
            if size > self.max_bytes:
                return
            self._entries[key] = entry
            self.bytes += size
            while self.bytes > self.max_bytes:  # oldest first
                _, gone = self._entries.popitem(last=False)
                self.bytes -= gone.K.nbytes + gone.Ks.nbytes


def leaf_blocks(
    packed: int,
    n_hits: int,
    n_free: int,
    items: QuadratureSet,
    centres: FloatArray,
    hp: Hyperparameters,
    key: tuple[float, ...],
    cache: KernelCache,
) -> tuple[FloatArray, FloatArray]:
    """The leaf's ``K`` and ``Ks``, reusing its cached blocks for the items it already had.

    Items are the hits then the free pieces, both append-only, so the old items sit at
    known rows. Every entry of an item covariance depends only on its two items (node
    distances, the kernel and the weighted sums over each item's nodes, in a fixed
    order), so the assembled blocks equal freshly computed ones bit for bit.
    """
    h, f = n_hits, n_free
    old = cache.get(packed)
    ls, sf2 = hp.length_scale, hp.signal_variance
    if old is None or old.key != key or old.n_hits > h or old.n_free > f:
        cache.misses += 1
        K = item_covariance(items, items, ls, sf2)
        Ks = item_covariance(points_set(centres), items, ls, sf2)
    else:
        cache.hits += 1
        h0, f0 = old.n_hits, old.n_free
        old_idx = np.concatenate([np.arange(h0), h + np.arange(f0)])
        new_idx = np.concatenate([np.arange(h0, h), h + np.arange(f0, f)])
        new = items.subset(new_idx)
        K = np.empty((h + f, h + f))
        K[np.ix_(old_idx, old_idx)] = old.K
        K[new_idx, :] = item_covariance(new, items, ls, sf2)
        K[:, new_idx] = item_covariance(items, new, ls, sf2)
        Ks = np.empty((centres.shape[0], h + f))
        Ks[:, old_idx] = old.Ks
        Ks[:, new_idx] = item_covariance(points_set(centres), new, ls, sf2)
    cache.put(packed, LeafBlocks(h, f, K, Ks, key))
    return K, Ks
