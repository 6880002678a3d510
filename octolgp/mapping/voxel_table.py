"""A table of the voxel values of part of a map, read at many points without a per-leaf loop.

:func:`~octolgp.mapping.field.lookup` groups the points of a read by leaf and reads
leaf by leaf, a few microseconds of Python per leaf touched; a ray cast of many long
rays touches the same leaves again and again. :class:`VoxelTable` reads the leaves of
a box once into one sorted array of packed voxel keys, and each read is then a
``searchsorted``: the same values, as a :data:`~octolgp.mapping.field.Reader`.

Building the table reads every voxel of the box; :func:`table_pays` says when the
reads it saves are worth that.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from octolgp.geometry.keys import pack_keys
from octolgp.mapping.coarse import leaves_in_box
from octolgp.mapping.field import ReadableMap, all_columns
from octolgp.mapping.grid import LeafGrid
from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = ["VoxelTable", "dense_box", "table_pays", "voxel_table"]

LOOKUPS_PER_VOXEL = 4
"""Point reads that justify reading one voxel into a table (measured on the lidar room)."""


DENSE_FILL = 0.25
"""Least share of its bounding box the table's voxels fill for a dense index of the box."""


@dataclass(frozen=True, slots=True)
class VoxelTable:
    """Voxel values of a set of leaves, by voxel key.

    Attributes
    ----------
    grid : LeafGrid
    keys : ndarray of int64, shape (v,)
        Packed voxel keys, ascending.
    mean, var, prob : ndarray of shape (v,)
        The stored values (NaN where a leaf holds none).
    low : ndarray of int64, shape (d,)
        Per-axis voxel key of the dense index's first cell.
    slots : ndarray of int64 or None
        Dense index over the voxels' bounding box (``slots[k - low]``: the row of key
        ``k``, -1 for none), when they fill at least :data:`DENSE_FILL` of it; else
        ``None`` and reads search ``keys``.
    """

    grid: LeafGrid
    keys: IntArray
    mean: FloatArray
    var: FloatArray
    prob: FloatArray
    low: IntArray
    slots: IntArray | None

    def rows(self, keys: IntArray) -> IntArray:
        """Row of the voxel with each per-axis key ``(q, d)``; -1 where the table has none."""
        if self.keys.size == 0:
            return np.full(keys.shape[0], -1, dtype=np.int64)
        if self.slots is not None:
            local = keys - self.low
            shape = np.array(self.slots.shape)
            inside = all_columns(local.view(np.uint64) < shape.astype(np.uint64))  # 0 <= local
            flat = local[:, 0].copy()
            for j in range(1, local.shape[1]):  # C order: the last axis varies fastest
                flat *= shape[j]
                flat += local[:, j]
            flat[~inside] = 0
            return np.where(inside, self.slots.reshape(-1)[flat], -1)
        packed = pack_keys(keys)
        at = np.minimum(np.searchsorted(self.keys, packed), self.keys.size - 1)
        return np.where(self.keys[at] == packed, at, -1)

    def at_keys(self, keys: IntArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """Stored values of the voxels with per-axis keys ``(q, d)`` (NaN where none)."""
        rows = self.rows(keys)
        found = rows >= 0
        out = [np.full(keys.shape[0], np.nan) for _ in fields]
        for arr, name in zip(out, fields, strict=True):
            arr[found] = getattr(self, name)[rows[found]]
        return out

    def at_points(self, X: FloatArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """Stored values at addressable points ``(q, d)``, as :func:`~octolgp.mapping.field.lookup`.

        NaN where the table holds no voxel for a point: the table must cover the
        leaves of every point read.
        """
        return self.at_keys(self.grid.voxel_index_keys(X), fields)


def _read_box(
    m: ReadableMap, lo: FloatArray, hi: FloatArray, fields: tuple[str, ...]
) -> tuple[IntArray, IntArray, list[np.ndarray]]:
    """The leaves overlapping a box: their indices ``(L, d)``, voxel keys, and values.

    Returns the leaf indices, the per-axis keys ``(L V, d)`` of their voxels (leaf by
    leaf, each in flat order) and, per field, the voxels' values in that order (the
    leaves' dtype; one value broadcast for a pruned leaf).
    """
    dim, grid = m.config.dim, m.grid
    index: list[IntArray] = [np.zeros((0, dim), dtype=np.int64)]
    values: list[list[np.ndarray]] = [[np.zeros(0, dtype=np.float32)] for _ in fields]
    wanted, size = leaves_in_box(m, lo, hi, m.config.tree_depth), m.store.batch
    per_leaf = grid.voxels_per_leaf
    for start in range(0, len(wanted), size):  # evicted leaves read a batch at a time
        for leaf in m.store.peek_many(wanted[start : start + size]):  # one per leaf
            if leaf is None or leaf.prob.size == 0:
                continue
            index.append(leaf.index.reshape(1, dim))
            for name, parts in zip(fields, values, strict=True):  # one value: pruned
                parts.append(np.broadcast_to(getattr(leaf, name), (per_leaf,)))
    leaves = np.concatenate(index).astype(np.int64)
    # per-axis voxel keys: the leaf's first key plus the voxel's place in it (x fastest)
    per_axis = (leaves[:, None, :] * grid.side + _local_keys(dim, grid.side)).reshape(-1, dim)
    return leaves, per_axis, [np.concatenate(parts) for parts in values]


def dense_box(
    m: ReadableMap, lo: FloatArray, hi: FloatArray, fields: tuple[str, ...]
) -> tuple[IntArray, IntArray, np.ndarray] | None:
    """The values of the voxels of the leaves overlapping a box, in a dense array of their box.

    Returns ``(low, shape, values)``: the box's first per-axis key and its shape, and
    ``values`` of shape ``(prod(shape), len(fields))``, a row per cell in C order
    (NaN where no leaf holds the cell), in the leaves' dtype. ``None`` when the
    voxels fill less than :data:`DENSE_FILL` of their box (or there are none).
    """
    leaves, per_axis, columns = _read_box(m, lo, hi, fields)
    if leaves.shape[0] == 0:
        return None
    side = m.grid.side
    low, high = leaves.min(axis=0) * side, (leaves.max(axis=0) + 1) * side - 1
    shape = high - low + 1
    cells = int(np.prod(shape))
    if per_axis.shape[0] < DENSE_FILL * cells:
        return None
    flat = np.ravel_multi_index(tuple((per_axis - low).T), tuple(shape))
    dtype = np.result_type(*columns)
    values = np.full((cells, len(fields)), np.nan, dtype=dtype)
    for j, column in enumerate(columns):  # one field at a time
        values[flat, j] = column
    return low, shape, values


def voxel_table(m: ReadableMap, lo: FloatArray, hi: FloatArray) -> VoxelTable:
    """The values of every voxel of the leaves overlapping the box ``lo, hi`` (metres)."""
    leaves, per_axis, columns = _read_box(m, lo, hi, ("mean", "var", "prob"))
    grid = m.grid
    if leaves.shape[0] == 0:
        empty = np.zeros(0)
        low = np.zeros(m.config.dim, dtype=np.int64)
        return VoxelTable(grid, np.zeros(0, dtype=np.int64), empty, empty, empty, low, None)
    low, high = leaves.min(axis=0) * grid.side, (leaves.max(axis=0) + 1) * grid.side - 1
    slots = None
    if per_axis.shape[0] >= DENSE_FILL * float(np.prod(high - low + 1)):
        # a dense index: its cells in reversed axis order are the packed keys ascending
        slots = np.full(tuple(high - low + 1), -1, dtype=np.int64)
        slots[tuple((per_axis - low).T)] = np.arange(per_axis.shape[0])
        ascending = slots.transpose().ravel()
        order = ascending[ascending >= 0]
        slots[tuple((per_axis[order] - low).T)] = np.arange(order.size)
    else:
        order = np.argsort(pack_keys(per_axis))  # voxel keys are unique
    flat = pack_keys(per_axis[order])
    mean, var, prob = (column.astype(np.float64)[order] for column in columns)
    return VoxelTable(grid, flat, mean, var, prob, low, slots)


@functools.lru_cache(maxsize=8)
def _local_keys(dim: int, side: int) -> IntArray:
    """Per-axis key offsets ``(side**dim, dim)`` of a leaf's voxels, in flat order (x fastest)."""
    steps = np.arange(side, dtype=np.int64)
    grids = np.meshgrid(*([steps] * dim), indexing="ij")
    offsets = np.stack([g.ravel(order="F") for g in grids], axis=1)
    offsets.setflags(write=False)
    return offsets


def table_pays(m: ReadableMap, lo: FloatArray, hi: FloatArray, lookups: float) -> bool:
    """Whether ``lookups`` point reads in the box ``lo, hi`` are worth a table of it."""
    n_leaves = len(leaves_in_box(m, lo, hi, m.config.tree_depth))
    return lookups >= LOOKUPS_PER_VOXEL * n_leaves * m.grid.voxels_per_leaf
