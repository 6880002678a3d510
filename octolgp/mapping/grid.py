"""The octree leaf grid: leaf boxes, overlap halos, and which leaves points and segments reach.

The map is cut into *leaves*: the nodes of the OctoMap key tree at depth
``leaf_depth``. A leaf spans ``2**(tree_depth - leaf_depth)`` voxels per axis (16 × 16
in 2D, 16³ in 3D with the lattice engine and 8³ with the exact one, by default); its
index per axis is the voxel key shifted right by ``tree_depth - leaf_depth`` bits, so leaf indices are OctoMap keys of a
coarser tree and pack the same way (:func:`octolgp.geometry.keys.pack_keys`).

A leaf's *halo box* is its box grown by ``halo`` times its edge on every side. A leaf
trains on every hit inside its halo box and on every free segment clipped to it, so
neighbouring leaves share the data near their common border and their local GPs
agree there (the overlap of Kim & Kim §III-B).

Everything here is a pure function of the training data and the grid.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.config import MapConfig
from octolgp.geometry.boxes import clip_to_box
from octolgp.geometry.keys import pack_keys
from octolgp.geometry.raycast import traverse_voxels
from octolgp.scan import FloatArray
from octolgp.training import IntArray


@dataclass(frozen=True, slots=True)
class LeafGrid:
    """Geometry of the leaf grid of a map.

    Attributes
    ----------
    dim : int
        2 or 3.
    resolution : float
        Voxel edge, metres.
    tree_depth : int
        OctoMap key depth (16).
    leaf_depth : int
        Tree depth of the leaves; a leaf spans ``2**shift`` voxels per axis,
        ``shift = tree_depth - leaf_depth``.
    halo : float
        Halo margin as a fraction of the leaf edge.
    """

    dim: int
    resolution: float
    tree_depth: int
    leaf_depth: int
    halo: float

    @classmethod
    def from_config(cls, config: MapConfig) -> LeafGrid:
        """The grid of a map config (``config.online``).

        A lattice leaf fitted in tiles smaller than itself keeps the tiles' halo: the
        ``online.halo`` of a tile's edge, in whole voxels (``LatticeConfig.tile_voxels``).
        """
        halo = config.halo
        side = 1 << (config.tree_depth - config.leaf_depth)
        if config.online.engine == "lattice" and config.tile_voxels < side:
            halo = config.tile_halo_voxels / side
        return cls(config.dim, float(config.resolution), config.tree_depth, config.leaf_depth, halo)

    @property
    def shift(self) -> int:
        """Voxel key bits below a leaf."""
        return self.tree_depth - self.leaf_depth

    @property
    def side(self) -> int:
        """Voxels along a leaf's edge."""
        return 1 << self.shift

    @property
    def edge(self) -> float:
        """Leaf edge, metres."""
        return self.side * self.resolution

    @property
    def halo_voxels(self) -> int:
        """Whole voxels the halo adds on every side of a leaf (the halo rounded up)."""
        return int(np.ceil(self.halo * self.side - 1e-9))

    @property
    def voxels_per_leaf(self) -> int:
        """Voxels in a leaf, ``side**dim``."""
        return int(self.side**self.dim)

    @property
    def _origin(self) -> float:
        """Coordinate of voxel key 0, metres."""
        return -float(1 << (self.tree_depth - 1)) * self.resolution

    def leaf_of(self, points: FloatArray) -> IntArray:
        """Leaf index (per axis) of each point, shape (n, d); points must be addressable."""
        return np.floor((points - self._origin) / self.edge).astype(np.int64)

    def voxel_keys(self, points: FloatArray, scale: int = 1) -> IntArray:
        """Packed keys of the voxels (of edge ``scale`` resolutions) holding points, shape (n,)."""
        keys = np.floor((points - self._origin) / (self.resolution * scale)).astype(np.int64)
        return pack_keys(np.clip(keys, 0, (1 << self.tree_depth) - 1))

    def voxel_index_keys(self, points: FloatArray) -> IntArray:
        """Per-axis voxel keys ``(n, d)`` of addressable points (OctoMap's ``coordToKey``)."""
        return np.floor((points - self._origin) / self.resolution).astype(np.int64)

    def key_centres(self, keys: IntArray) -> FloatArray:
        """Centres ``(n, d)`` of the voxels with per-axis keys ``(n, d)``, metres."""
        return np.asarray(self._origin + (keys + 0.5) * self.resolution)

    def box(self, index: IntArray) -> tuple[FloatArray, FloatArray]:
        """Core boxes ``lo, hi`` of leaves with indices (k, d), metres."""
        lo = self._origin + np.asarray(index, dtype=np.float64) * self.edge
        return lo, lo + self.edge

    def halo_box(self, index: IntArray) -> tuple[FloatArray, FloatArray]:
        """Halo boxes ``lo, hi`` of leaves with indices (k, d), metres."""
        lo, hi = self.box(index)
        margin = self.halo * self.edge
        return lo - margin, hi + margin

    def voxel_centres(self, index: IntArray) -> FloatArray:
        """Centres of one leaf's voxels, shape (side**d, d), in flat order (x fastest)."""
        lo, _ = self.box(np.asarray(index).reshape(1, -1))
        return np.asarray(lo[0] + _centre_offsets(self.dim, self.side, self.resolution))

    def voxel_index(self, points: FloatArray, index: IntArray) -> IntArray:
        """Flat index of each point's voxel within the leaf ``index`` (points inside it)."""
        lo, _ = self.box(np.asarray(index).reshape(1, -1))
        local = np.floor((points - lo[0]) / self.resolution).astype(np.int64)
        local = np.clip(local, 0, self.side - 1)
        weights = self.side ** np.arange(self.dim, dtype=np.int64)
        flat: IntArray = local @ weights
        return flat

    def pack(self, index: IntArray) -> IntArray:
        """Packed leaf keys of leaf indices (k, d)."""
        return pack_keys(index)


SEGMENT_BLOCK = 16_384
"""Segments assigned to leaves per block (bounds the transient arrays to ~100 MB)."""


@functools.lru_cache(maxsize=8)
def _centre_offsets(dim: int, side: int, resolution: float) -> FloatArray:
    """Voxel centres of a leaf relative to its lower corner, (side**dim, dim), x fastest."""
    steps = (np.arange(side) + 0.5) * resolution
    grids = np.meshgrid(*([steps] * dim), indexing="ij")
    # flat index = x + side * y (+ side² z): x varies fastest
    offsets = np.stack([g.ravel(order="F") for g in grids], axis=1)
    offsets.setflags(write=False)
    return offsets


def _valid_leaves(grid: LeafGrid, index: IntArray) -> NDArray[np.bool_]:
    """Leaves inside the key range of the leaf depth."""
    inside = (index >= 0) & (index < (1 << grid.leaf_depth))
    return np.asarray(inside.all(axis=1), dtype=bool)


def assign_points(grid: LeafGrid, points: FloatArray) -> tuple[IntArray, IntArray]:
    """Every (point, leaf) pair where the point lies in the leaf's halo box.

    A halo narrower than half a leaf puts a point in at most two leaves per axis.

    Parameters
    ----------
    grid : LeafGrid
    points : ndarray of shape (n, d)
        World frame, metres.

    Returns
    -------
    point : ndarray of shape (k,)
        Index into ``points``.
    leaf : ndarray of shape (k, d)
        Leaf index of each pair.
    """
    margin = grid.halo * grid.edge
    lo = grid.leaf_of(points - margin)
    hi = grid.leaf_of(points + margin)
    pts, leaves = [], []
    for offset in itertools.product((0, 1), repeat=grid.dim):  # 4 or 8 combinations
        cand = lo + np.asarray(offset, dtype=np.int64)
        ok = (cand <= hi).all(axis=1) & _valid_leaves(grid, cand)
        pts.append(np.flatnonzero(ok))
        leaves.append(cand[ok])
    point = np.concatenate(pts)
    order = np.argsort(point, kind="stable")
    return point[order], np.concatenate(leaves)[order]


def assign_segments(
    grid: LeafGrid, start: FloatArray, end: FloatArray, min_piece: float
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """Every (segment, leaf) pair where the segment crosses the leaf's halo box, clipped.

    The segments are traversed on the leaf grid (Amanatides & Woo); a halo box can
    only be crossed by a segment that enters the leaf or one of its neighbours, so
    those candidates are clipped to the halo boxes (Liang-Barsky) and pieces
    shorter than ``min_piece`` are dropped.

    Parameters
    ----------
    grid : LeafGrid
    start, end : ndarray of shape (s, d)
        Free segments, world frame, metres.
    min_piece : float
        Shortest piece kept, metres.

    Returns
    -------
    segment : ndarray of shape (k,)
        Index into the segments, ascending.
    leaf : ndarray of shape (k, d)
    piece_start, piece_end : ndarray of shape (k, d)
        The segment clipped to the leaf's halo box.
    """
    d = grid.dim
    empty = np.zeros((0, d))
    if start.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, d), dtype=np.int64), empty, empty
    if start.shape[0] > SEGMENT_BLOCK:
        # blocks of segments bound the transient (segment, leaf) candidate arrays
        parts = [
            assign_segments(
                grid, start[lo : lo + SEGMENT_BLOCK], end[lo : lo + SEGMENT_BLOCK], min_piece
            )
            for lo in range(0, start.shape[0], SEGMENT_BLOCK)
        ]
        offsets = np.arange(0, start.shape[0], SEGMENT_BLOCK)
        return (
            np.concatenate([p[0] + off for p, off in zip(parts, offsets, strict=True)]),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]),
            np.concatenate([p[3] for p in parts]),
        )
    # keys of a depth-``leaf_depth`` tree with voxels of one leaf edge are leaf indices
    seg, keys = traverse_voxels(start, end, grid.edge, grid.leaf_depth)
    # traverse_voxels stops before the end's leaf: add it
    seg = np.concatenate([seg, np.arange(start.shape[0], dtype=np.int64)])
    cells = np.concatenate([keys, grid.leaf_of(end)])
    # Which neighbours of a crossed leaf can the segment reach? Only those whose halo the
    # segment's piece inside the crossed leaf comes within ``halo * edge`` of: per axis,
    # the lower neighbour when the piece gets that close to the lower face, the upper
    # one likewise. This keeps ~1-3 of the 3^d candidates per crossed leaf.
    lo, hi = grid.box(cells)
    a, b, inside = clip_to_box(start[seg], end[seg], lo, hi)
    margin = grid.halo * grid.edge * (1.0 + 1e-9) + 1e-12
    near_lo = (np.minimum(a, b) - lo <= margin) | ~inside[:, None]
    near_hi = (hi - np.maximum(a, b) <= margin) | ~inside[:, None]
    neighbours = np.array(list(itertools.product((-1, 0, 1), repeat=d)), dtype=np.int64)
    reach = np.ones((seg.size, neighbours.shape[0]), dtype=bool)
    for axis in range(d):  # one iteration per axis
        off = neighbours[:, axis]
        reach &= np.where(off < 0, near_lo[:, axis : axis + 1], True)
        reach &= np.where(off > 0, near_hi[:, axis : axis + 1], True)
    pair, which = np.nonzero(reach)
    seg = seg[pair]
    cells = cells[pair] + neighbours[which]
    ok = _valid_leaves(grid, cells)
    seg, cells = seg[ok], cells[ok]
    # unique (segment, leaf) pairs
    packed = pack_keys(cells)
    order = np.lexsort((packed, seg))
    seg, cells, packed = seg[order], cells[order], packed[order]
    first = np.r_[True, (seg[1:] != seg[:-1]) | (packed[1:] != packed[:-1])]
    seg, cells = seg[first], cells[first]
    lo, hi = grid.halo_box(cells)
    a, b, keep = clip_to_box(start[seg], end[seg], lo, hi)
    keep &= np.linalg.norm(b - a, axis=1) > min_piece
    return seg[keep], cells[keep], a[keep], b[keep]


def group_keys(packed: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Sort order, unique values and run bounds of packed keys.

    Returns
    -------
    order : ndarray of shape (n,)
        Stable sort order of ``packed``.
    keys : ndarray of shape (u,)
        The distinct keys, ascending.
    bounds : ndarray of shape (u + 1,)
        Key ``keys[j]`` holds ``order[bounds[j]:bounds[j + 1]]``.
    """
    order = np.argsort(packed, kind="stable")
    s = packed[order]
    starts = np.flatnonzero(np.r_[True, s[1:] != s[:-1]]) if s.size else np.zeros(0, np.int64)
    return order, s[starts], np.append(starts, s.size).astype(np.int64)
