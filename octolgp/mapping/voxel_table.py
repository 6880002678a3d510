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

from dataclasses import dataclass

import numpy as np

from octolgp.geometry.keys import pack_keys, unpack_keys
from octolgp.mapping.coarse import leaves_in_box
from octolgp.mapping.field import ReadableMap, all_columns
from octolgp.mapping.grid import LeafGrid
from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = ["VoxelTable", "table_pays", "voxel_table"]

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


def voxel_table(m: ReadableMap, lo: FloatArray, hi: FloatArray) -> VoxelTable:
    """The values of every voxel of the leaves overlapping the box ``lo, hi`` (metres)."""
    keys: list[IntArray] = [np.zeros(0, dtype=np.int64)]
    values: dict[str, list[FloatArray]] = {f: [np.zeros(0)] for f in ("mean", "var", "prob")}
    wanted, size = leaves_in_box(m, lo, hi, m.config.tree_depth), m.store.batch
    for start in range(0, len(wanted), size):  # evicted leaves read a batch at a time
        for leaf in m.store.peek_many(wanted[start : start + size]):  # one per leaf
            if leaf is None or leaf.prob.size == 0:
                continue
            centres = m.grid.voxel_centres(leaf.index)
            keys.append(m.grid.voxel_keys(centres))
            for name, parts in values.items():  # mean, var, prob
                v = np.broadcast_to(getattr(leaf, name), (centres.shape[0],))
                parts.append(v.astype(np.float64))
    flat = np.concatenate(keys)
    order = np.argsort(flat, kind="stable")
    flat = flat[order]
    cols = {name: np.concatenate(parts)[order] for name, parts in values.items()}
    dim = m.config.dim
    low = np.zeros(dim, dtype=np.int64)
    slots = None
    if flat.size:
        per_axis = unpack_keys(flat, dim)
        low, high = per_axis.min(axis=0), per_axis.max(axis=0)
        if flat.size >= DENSE_FILL * float(np.prod(high - low + 1)):
            slots = np.full(tuple(high - low + 1), -1, dtype=np.int64)
            slots[tuple((per_axis - low).T)] = np.arange(flat.size)
    return VoxelTable(m.grid, flat, cols["mean"], cols["var"], cols["prob"], low, slots)


def table_pays(m: ReadableMap, lo: FloatArray, hi: FloatArray, lookups: float) -> bool:
    """Whether ``lookups`` point reads in the box ``lo, hi`` are worth a table of it."""
    n_leaves = len(leaves_in_box(m, lo, hi, m.config.tree_depth))
    return lookups >= LOOKUPS_PER_VOXEL * n_leaves * m.grid.voxels_per_leaf
