"""The map store: one mutable table of leaves keyed by packed OctoMap keys.

A :class:`Leaf` holds its training evidence (hits and clipped free pieces, each
tagged with the packed key of its voxel) and its predicted voxels (latent mean,
variance and P(occupied), float32). The evidence is bounded by construction: a
leaf keeps the *first* hit per voxel and the *first* free piece per voxel of the
piece's end, so its training set can never exceed two items per voxel of its halo
box, however often the robot comes back (see :mod:`octolgp.mapping.online`).

:class:`LeafStore` is the one mutable structure of an online map; everything
around it is a pure function.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray
from octolgp.training import IntArray

Float32Array = NDArray[np.float32]


def _new_first(existing: IntArray, keys: IntArray) -> IntArray:
    """Indices of ``keys`` whose value is not in ``existing`` nor earlier in ``keys``."""
    _, first = np.unique(keys, return_index=True)
    first = np.sort(first)
    if existing.size:
        first = first[~np.isin(keys[first], existing)]
    return first.astype(np.int64)


@dataclass
class Leaf:
    """One leaf of the map: its evidence and its predicted voxels.

    Attributes
    ----------
    index : ndarray of shape (d,)
        Leaf index per axis (a voxel key shifted right by the leaf's level).
    hits : ndarray of shape (h, d)
        Hit points in the halo box, metres, world frame.
    hit_keys : ndarray of shape (h,)
        Packed voxel key of each hit.
    free_start, free_end : ndarray of shape (s, d)
        Free pieces clipped to the halo box, metres, world frame.
    free_keys : ndarray of shape (s,)
        Packed voxel key of each piece's end.
    mean, var, prob : ndarray of float32, shape (V,) or (1,)
        Latent mean, latent variance and P(occupied) per voxel, in flat voxel
        order (x fastest), or one value for a pruned leaf. Empty before the first fit.
    pruned : bool
        Whether the voxels were collapsed to one value.
    refits : int
        How many times the leaf's GP was fitted.
    touched : int
        Number of the last scan that touched the leaf (for least-recently-used order).
    """

    index: IntArray
    hits: FloatArray
    hit_keys: IntArray
    free_start: FloatArray
    free_end: FloatArray
    free_keys: IntArray
    mean: Float32Array = field(default_factory=lambda: np.zeros(0, np.float32))
    var: Float32Array = field(default_factory=lambda: np.zeros(0, np.float32))
    prob: Float32Array = field(default_factory=lambda: np.zeros(0, np.float32))
    pruned: bool = False
    refits: int = 0
    touched: int = 0

    @classmethod
    def empty(cls, index: IntArray) -> Leaf:
        """A leaf with no evidence yet."""
        d = int(np.asarray(index).size)
        return cls(
            index=np.asarray(index, dtype=np.int64).copy(),
            hits=np.zeros((0, d)),
            hit_keys=np.zeros(0, dtype=np.int64),
            free_start=np.zeros((0, d)),
            free_end=np.zeros((0, d)),
            free_keys=np.zeros(0, dtype=np.int64),
        )

    @property
    def n_items(self) -> int:
        """Training items: hits plus free pieces."""
        return int(self.hits.shape[0] + self.free_start.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the leaf's arrays."""
        arrays = (
            self.index,
            self.hits,
            self.hit_keys,
            self.free_start,
            self.free_end,
            self.free_keys,
            self.mean,
            self.var,
            self.prob,
        )
        return sum(a.nbytes for a in arrays)

    def add_evidence(
        self,
        hits: FloatArray,
        hit_keys: IntArray,
        free_start: FloatArray,
        free_end: FloatArray,
        free_keys: IntArray,
    ) -> int:
        """Append the hits and pieces whose voxel the leaf has no item of that class in.

        Returns
        -------
        int
            Number of items added (0 means the leaf's GP would not change).
        """
        new_h = _new_first(self.hit_keys, hit_keys)
        new_f = _new_first(self.free_keys, free_keys)
        if new_h.size:
            self.hits = np.concatenate([self.hits, hits[new_h]])
            self.hit_keys = np.concatenate([self.hit_keys, hit_keys[new_h]])
        if new_f.size:
            self.free_start = np.concatenate([self.free_start, free_start[new_f]])
            self.free_end = np.concatenate([self.free_end, free_end[new_f]])
            self.free_keys = np.concatenate([self.free_keys, free_keys[new_f]])
        return int(new_h.size + new_f.size)


class LeafBacking(Protocol):
    """Where evicted leaves live: the map file (:class:`octolgp.mapfile.MapFile`)."""

    def read_leaf(self, key: int) -> Leaf:
        """The persisted leaf ``key``."""
        ...


class LeafStore:
    """Leaves by packed leaf key; the map's only mutable state besides counters.

    Without a budget every leaf stays in RAM. With ``budget_bytes`` and a
    ``backing`` (the map file, which holds every leaf after each scan),
    :meth:`trim` drops the least recently used leaves from RAM until the RAM
    held is within the budget; :meth:`get` loads an evicted leaf back
    transparently. Eviction never loses data: a leaf is only dropped once it is
    in the file (``persisted``).
    """

    def __init__(self, budget_bytes: int | None = None) -> None:
        self._leaves: OrderedDict[int, Leaf] = OrderedDict()  # in RAM, LRU first
        self._keys: set[int] = set()  # every key, in RAM or in the file
        self._dirty: set[int] = set()  # in RAM and not yet in the file
        self._nbytes = 0
        self.budget_bytes = budget_bytes
        self.backing: LeafBacking | None = None
        self.loads = 0
        self.evictions = 0

    def attach(self, backing: LeafBacking, keys: Iterable[int]) -> None:
        """Use ``backing`` for the persisted leaves ``keys`` (not loaded now)."""
        self.backing = backing
        self._keys.update(int(k) for k in keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._keys

    def __iter__(self) -> Iterator[int]:
        return iter(sorted(self._keys))

    def get(self, key: int) -> Leaf | None:
        """The leaf with this packed key (loaded from the file if evicted), or ``None``."""
        key = int(key)
        leaf = self._leaves.get(key)
        if leaf is not None:
            self._leaves.move_to_end(key)
            return leaf
        if key not in self._keys or self.backing is None:
            return None
        leaf = self.backing.read_leaf(key)
        self._leaves[key] = leaf
        self._nbytes += leaf.nbytes
        self.loads += 1
        return leaf

    def peek(self, key: int) -> Leaf | None:
        """The leaf without making it resident (a read for iteration)."""
        key = int(key)
        leaf = self._leaves.get(key)
        if leaf is not None or key not in self._keys or self.backing is None:
            return leaf
        return self.backing.read_leaf(key)

    def put(self, key: int, leaf: Leaf) -> None:
        """Insert or replace a leaf (dirty until :meth:`persisted`)."""
        key = int(key)
        old = self._leaves.get(key)
        self._nbytes += leaf.nbytes - (old.nbytes if old is not None else 0)
        self._leaves[key] = leaf
        self._leaves.move_to_end(key)
        self._keys.add(key)
        self._dirty.add(key)

    def persisted(self, keys: Iterable[int]) -> None:
        """Mark leaves as written to the backing file."""
        self._dirty.difference_update(int(k) for k in keys)

    @property
    def dirty(self) -> list[int]:
        """Keys of leaves changed in RAM and not yet in the file."""
        return sorted(self._dirty)

    def trim(self) -> int:
        """Evict least recently used, persisted leaves until RAM is within budget.

        Returns the number of leaves evicted.
        """
        if self.budget_bytes is None or self.backing is None:
            return 0
        evicted = 0
        for key in list(self._leaves):  # LRU first; stops once within budget
            if self._nbytes <= self.budget_bytes:
                break
            if key in self._dirty:
                continue
            leaf = self._leaves.pop(key)
            self._nbytes -= leaf.nbytes
            evicted += 1
        self.evictions += evicted
        return evicted

    def items(self) -> Iterator[tuple[int, Leaf]]:
        """``(key, leaf)`` in ascending key order; evicted leaves are read, not kept."""
        for key in sorted(self._keys):
            leaf = self.peek(key)
            if leaf is not None:
                yield key, leaf

    @property
    def resident(self) -> int:
        """Leaves held in RAM."""
        return len(self._leaves)

    @property
    def nbytes(self) -> int:
        """Bytes held in RAM by the resident leaves' arrays (a running total)."""
        return self._nbytes
