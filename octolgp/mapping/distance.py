"""Distance to the nearest occupied voxel: exact, over the voxel cubes, with a KD-tree.

The occupied set is the union of the cubes (squares in 2D) of edge ``resolution`` of
the voxels whose stored P(occupied) is at least a threshold. The distance from a
point to that set is exact, not the distance to voxel centres: a KD-tree
(:class:`scipy.spatial.cKDTree`) over the occupied centres gives each point's ``k``
nearest centres, the distance to each one's cube is
``|| max(|p - c| - r/2, 0) ||``, and the minimum over them is the answer once the
``k``-th centre lies beyond that minimum plus the half-diagonal ``r sqrt(d) / 2``
(no farther cube can then be nearer); the few points where it does not get more
neighbours, rounds of ``4 k``, until it does. With a finite ``max_distance`` the
tree is asked only for centres within it plus the half-diagonal (no cube farther
can be within it), so points far from every obstacle settle at once.

Where numba is installed (:data:`COMPILED`), points near the occupied voxels are
answered first by a compiled search of the shells of voxels around each point over a
dense grid of the occupied ones (:mod:`octolgp.mapping.distance_kernel`), exact as
well; the points it leaves (farther than :data:`SHELLS` voxels from any, and within
``max_distance``) go to the KD-tree, built only then. A ``max_distance`` of at most
:data:`BOUNDED_SHELLS` voxels is searched by shells alone.

Against the true geometry the occupied cubes cover each observed surface point
with a cube at most one voxel across, so the distance is within a voxel diagonal
below the true distance to observed surfaces (measured in BENCHMARKS.md), and 0
inside an occupied voxel.

The occupied centres are kept between reads, leaf by leaf (:class:`OccupiedIndex`):
a leaf's entry holds a weak reference to the P(occupied) array it was computed from
and is recomputed only when the leaf holds another one (a fit gives a leaf new
arrays, never writes into old ones), so a read after an insert recomputes the
leaves the insert changed, not the map. A read with a finite ``max_distance`` takes
only the leaves overlapping the queries' bounding box grown by it; the tree of the
last read (and the grid) is kept and used again while its leaves and their entries are
the same (repeated queries between two inserts build neither again).

Every function here only reads the map: the index is a cache of its values.
"""

from __future__ import annotations

import importlib.util
import math
import weakref
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from scipy.spatial import cKDTree

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range
from octolgp.mapping.coarse import leaves_in_box
from octolgp.mapping.field import QUERY_CHUNK, ReadableMap
from octolgp.mapping.store import Leaf
from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = [
    "Occupied",
    "OccupiedIndex",
    "check_max_distance",
    "cube_distance",
    "nearest_cube",
    "occupied_distance",
]

FIRST_NEIGHBOURS = 8
"""Centres a point's first KD-tree query asks for."""

COMPILED = importlib.util.find_spec("numba") is not None
"""Whether near points are answered by the compiled search of voxel shells."""

SHELLS = MappingProxyType({1: 32, 2: 10, 3: 3})
"""Most shells of voxels searched around a point, by dimension, before the KD-tree."""

BOUNDED_SHELLS = MappingProxyType({1: 256, 2: 32, 3: 3})
"""Most shells, by dimension, searched to cover a whole ``max_distance`` (no KD-tree)."""

GRID_CELLS = 1 << 26
"""Most cells of the dense grid of occupied voxels (bytes); a larger box: the KD-tree only."""

THRESHOLDS_KEPT = 4
"""Thresholds whose occupied centres :class:`OccupiedIndex` keeps (the latest used)."""


def cube_distance(X: FloatArray, centres: FloatArray, half: float) -> FloatArray:
    """Distance from points ``(q, d)`` to axis-aligned cubes ``(q, k, d)`` of half-edge ``half``.

    Returns an array of shape ``(q, k)``, metres; 0 inside a cube.
    """
    gap = np.maximum(np.abs(X[:, None, :] - centres) - half, 0.0)
    return np.asarray(np.sqrt((gap * gap).sum(axis=2)))


def nearest_cube(
    tree: cKDTree, cubes: FloatArray, X: FloatArray, half: float, bound: float = math.inf
) -> FloatArray:
    """Exact distance from each point to the nearest cube of the tree's centres.

    Parameters
    ----------
    tree : cKDTree
        Over ``cubes``.
    cubes : ndarray of shape (n, d)
        Cube centres, metres (at least one).
    X : ndarray of shape (q, d)
        Points, metres.
    half : float
        Half the cubes' edge, metres.
    bound : float, optional
        Metres: answers above it may be ``inf`` (and are found faster); every
        answer up to it is exact. Default: no bound.

    Returns
    -------
    ndarray of shape (q,)
    """
    n = cubes.shape[0]
    slack = half * math.sqrt(X.shape[1])
    reach = (bound + slack) * (1 + 1e-9) + 1e-9 * half  # the tree's bound is strict
    padded = np.vstack([cubes, np.full((1, X.shape[1]), np.inf)])  # row n: no neighbour
    out = np.full(X.shape[0], np.inf)
    todo = np.arange(X.shape[0])
    k = min(FIRST_NEIGHBOURS, n)
    while todo.size:  # rounds of more neighbours for the few points not settled
        dist, idx = tree.query(X[todo], k=k, distance_upper_bound=reach)
        dist, idx = dist.reshape(todo.size, k), idx.reshape(todo.size, k)
        with np.errstate(invalid="ignore"):  # inf - inf where there is no neighbour
            best = cube_distance(X[todo], padded[idx], half).min(axis=1)
        out[todo] = best
        # settled: every centre asked for, fewer than k within reach, or the k-th too far
        settled = (k == n) | np.isinf(dist[:, -1]) | (dist[:, -1] > best + slack)
        todo = todo[~settled]
        k = min(4 * k, n)
    return out


@dataclass(slots=True)
class _LeafEntry:
    """The occupied voxel centres of one leaf, and the values they come from."""

    source: weakref.ref[np.ndarray]
    centres: FloatArray


@dataclass(slots=True)
class Occupied:
    """The occupied voxels of some leaves, and the search structures over them.

    Each structure is built when a read first needs it, and kept with the voxels
    while their leaves stay the same.

    Attributes
    ----------
    cubes : ndarray of shape (n, d)
        Occupied voxel centres, metres.
    resolution : float
    origin : float
        Coordinate of voxel key 0, metres.
    """

    cubes: FloatArray
    resolution: float
    origin: float
    _tree: cKDTree | None = None
    _grid: tuple[np.ndarray, IntArray] | None = None
    _grid_too_large: bool = False

    @property
    def tree(self) -> cKDTree:
        """A KD-tree over :attr:`cubes` (at least one)."""
        if self._tree is None:
            self._tree = cKDTree(self.cubes)
        return self._tree

    @property
    def grid(self) -> tuple[np.ndarray, IntArray] | None:
        """The occupied voxels as a dense bool grid over their bounding box, and its first key.

        ``None`` when that box holds more than :data:`GRID_CELLS` cells.
        """
        if self._grid is None and not self._grid_too_large:
            keys = np.floor((self.cubes - self.origin) / self.resolution).astype(np.int64)
            low = keys.min(axis=0)
            shape = keys.max(axis=0) - low + 1
            if float(np.prod(shape.astype(np.float64))) > GRID_CELLS:
                self._grid_too_large = True
            else:
                occupied = np.zeros(tuple(shape), dtype=bool)
                occupied[tuple((keys - low).T)] = True
                self._grid = (occupied, low)
        return self._grid


@dataclass(slots=True)
class _Tree:
    """The occupied voxels of some leaves' entries, kept while they stay the same."""

    keys: list[int]
    entries: list[_LeafEntry]
    occupied: Occupied | None


@dataclass
class OccupiedIndex:
    """The occupied voxel centres of a map's leaves at a few thresholds, kept between reads.

    A cache of the map's values, never a part of them: an entry whose leaf now holds
    other values (or whose values are gone) is recomputed when it is next read.
    """

    _entries: dict[float, dict[int, _LeafEntry]] = field(default_factory=dict)
    _trees: dict[float, _Tree] = field(default_factory=dict)

    def _at(self, threshold: float) -> dict[int, _LeafEntry]:
        """The entries at ``threshold``; the oldest threshold is dropped past a few."""
        entries = self._entries.pop(threshold, None)
        if entries is None:
            entries = {}
            while len(self._entries) >= THRESHOLDS_KEPT:
                oldest = next(iter(self._entries))
                del self._entries[oldest]
                self._trees.pop(oldest, None)
        self._entries[threshold] = entries  # the latest used last
        return entries

    def occupied(self, m: ReadableMap, keys: list[int], threshold: float) -> Occupied | None:
        """The occupied voxels of the leaves ``keys`` (packed); ``None`` where there are none."""
        entries = self._at(threshold)
        if len(entries) > len(m.store):  # leaves a correction removed: their entries go
            for key in [k for k in entries if k not in m.store]:  # one per removed leaf
                del entries[key]
        current: list[_LeafEntry] = []
        size = m.store.batch
        for lo in range(0, len(keys), size):  # evicted leaves read a batch at a time
            part = keys[lo : lo + size]
            for key, leaf in zip(part, m.store.peek_many(part), strict=True):  # one per leaf
                if leaf is None or leaf.prob.size == 0:
                    continue
                entry = entries.get(key)
                if entry is None or entry.source() is not leaf.prob:
                    entry = entries[key] = _occupied(m, leaf, threshold)
                current.append(entry)
        kept = self._trees.get(threshold)
        if kept is not None and kept.keys == keys and _same(kept.entries, current):
            return kept.occupied
        parts = [e.centres for e in current if e.centres.shape[0]]
        found = None
        if parts:
            res = m.config.resolution
            origin = -float(1 << (m.config.tree_depth - 1)) * res  # of voxel key 0
            found = Occupied(np.concatenate(parts), res, origin)
        self._trees[threshold] = _Tree(keys, current, found)
        return found


def _same(a: list[_LeafEntry], b: list[_LeafEntry]) -> bool:
    """Whether two lists hold the same entry objects, in order."""
    return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))


def _occupied(m: ReadableMap, leaf: Leaf, threshold: float) -> _LeafEntry:
    """The entry of one leaf: the centres of its voxels with P >= ``threshold``."""
    prob = leaf.prob
    if leaf.pruned:
        occupied = bool(prob[0] >= threshold)
        centres = m.grid.voxel_centres(leaf.index) if occupied else np.zeros((0, m.config.dim))
    else:
        centres = m.grid.voxel_centres(leaf.index)[prob >= threshold]
    return _LeafEntry(weakref.ref(prob), centres)


def occupied_distance(
    m: ReadableMap,
    X: FloatArray,
    threshold: float,
    max_distance: float,
    index: OccupiedIndex | None = None,
) -> FloatArray:
    """Distance from each point to the nearest voxel with P(occupied) >= ``threshold``.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.
    threshold : float
        In (0, 1).
    max_distance : float
        Metres, > 0 or ``inf``; farther answers are ``inf``, and a finite value
        limits the leaves read to those overlapping the queries' box grown by it.
    index : OccupiedIndex, optional
        The occupied centres kept from earlier reads of ``m`` (a fresh one: none).

    Returns
    -------
    ndarray of shape (q,)
        Metres; 0 inside an occupied voxel, ``inf`` where no occupied voxel lies
        within ``max_distance``.
    """
    res = m.config.resolution
    out = np.full(X.shape[0], np.inf)
    if X.shape[0] == 0:
        return out
    if math.isfinite(max_distance):
        low, high = addressable_range(res, m.config.tree_depth)
        grow = max_distance + res
        lo = np.maximum(X.min(axis=0) - grow, low)
        hi = np.minimum(X.max(axis=0) + grow, high - 1e-9 * res)
        keys = leaves_in_box(m, lo, hi, m.config.tree_depth)
    else:
        keys = list(m.store)
    found = (OccupiedIndex() if index is None else index).occupied(m, keys, threshold)
    if found is None:
        return out
    todo = np.arange(X.shape[0])
    grid = found.grid if COMPILED else None
    if grid is not None:  # near points by shells of voxels, the rest by the tree
        from octolgp.mapping.distance_kernel import ring_search  # imports numba

        shells = SHELLS[m.config.dim]
        if math.isfinite(max_distance):  # the whole reach by shells, when few enough
            reach = math.ceil(max_distance / res) + 1
            shells = reach if reach <= BOUNDED_SHELLS[m.config.dim] else shells
        out, settled = ring_search(X, grid[0], grid[1], res, found.origin, max_distance, shells)
        todo = np.flatnonzero(~settled)
    for first in range(0, todo.size, QUERY_CHUNK):  # bounded temporaries, chunk by chunk
        at = todo[first : first + QUERY_CHUNK]
        out[at] = nearest_cube(found.tree, found.cubes, X[at], 0.5 * res, max_distance)
    return np.where(out <= max_distance, out, np.inf)


def check_max_distance(max_distance: object) -> float:
    """``max_distance`` as a float > 0 (``None``: ``inf``), else :class:`OctolgpError`."""
    if max_distance is None:
        return math.inf
    ok = isinstance(max_distance, int | float | np.floating) and not isinstance(max_distance, bool)
    if not ok or not float(max_distance) > 0:  # type: ignore[arg-type]
        raise OctolgpError(f"max_distance must be a number > 0, got {max_distance!r}")
    return float(max_distance)  # type: ignore[arg-type]
