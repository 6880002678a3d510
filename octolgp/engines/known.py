"""Honest unknown, shared by the leaf engines: which voxels a leaf may give a value.

A map never claims space it never saw. A voxel is *seen* when a scan observed it,
occupied or free (:func:`octolgp.observations.observe`), or swept it between two beams
(:func:`octolgp.sweep.swept_keys`); a voxel of a leaf is *known* when a seen voxel lies
within ``MapConfig.fill_voxels`` of it along every axis, and only a known voxel takes
the GP's value (elsewhere it holds NaN and reads unknown). Each engine keeps, per leaf,
which voxels of its halo box are seen (the lattice engine in its counts and swept
bitmap, the exact engine in a seen mask); :func:`halo_pairs` scatters a step's seen
voxels into the leaves whose halo boxes hold them (:func:`near_leaf`: those that can make
a voxel of the leaf known), :func:`grow_seen` merges them into the leaves' masks, and
:func:`seen_near` gives the known voxels of leaves from their masks. ``fill_voxels`` is at most the leaf's halo in voxels, so a leaf's halo box holds
every seen voxel that counts for its voxels.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from octolgp.engines import gather_kernel
from octolgp.geometry.keys import KEY_BITS
from octolgp.mapping.grid import LeafGrid
from octolgp.training import IntArray

HaloPairs = tuple[IntArray, IntArray, IntArray, IntArray, tuple[int, ...], tuple[int, ...]]
"""``voxel, leaf_key, flat, cell, origin, extent`` (:func:`halo_pairs_numpy`)."""


def halo_pairs(voxel_keys: IntArray, grid: LeafGrid) -> HaloPairs:
    """:func:`halo_pairs_numpy`, by the compiled loop where numba is installed."""
    if gather_kernel.AVAILABLE:
        n_leaf = 1 << grid.leaf_depth
        return gather_kernel.halo_pairs(voxel_keys, grid.side, grid.halo_voxels, n_leaf)
    return halo_pairs_numpy(voxel_keys, grid)


def halo_pairs_numpy(voxel_keys: IntArray, grid: LeafGrid) -> HaloPairs:
    """Every (voxel, leaf whose halo box holds it) pair of the voxels ``voxel_keys``.

    A pair's cell is its leaf's place in the box of the pairs' leaves.

    Parameters
    ----------
    voxel_keys : ndarray of int64, shape (n, d)
        OctoMap keys of voxels.
    grid : LeafGrid

    Returns
    -------
    voxel, leaf_key, flat : ndarray of int64, shape (p,)
        Per pair: the voxel (row of ``voxel_keys``), the leaf's packed key and the
        voxel's flat index in that leaf's halo box (x fastest); pairs are grouped by the
        neighbour offset.
    cell : ndarray of int64, shape (p,)
        The leaf's flat index (x fastest) in the box of leaf indices that holds every
        pair's leaf; cells ascend as packed keys do.
    origin, extent : tuple of int, length d
        That box's lowest leaf index and its size, per axis.
    """
    side, halo, d = grid.side, grid.halo_voxels, grid.dim
    box = side + 2 * halo
    n_leaf = 1 << grid.leaf_depth
    cols = [np.ascontiguousarray(voxel_keys[:, a]) for a in range(d)]
    lo = [(c - halo) // side for c in cols]  # the lower leaf per axis
    # per axis: whether the lower and the upper leaf (lo + 1) hold the voxel in their halo
    has = [
        ((q >= 0) & (q < n_leaf), ((c + halo) // side > q) & (q + 1 < n_leaf))
        for c, q in zip(cols, lo, strict=True)
    ]
    origin = tuple(int(q.min()) if q.size else 0 for q in lo)
    extent = tuple(int(q.max()) - o + 2 if q.size else 1 for q, o in zip(lo, origin, strict=True))
    stride = np.cumprod((1, *extent[:-1])).tolist()
    vox_parts, leaf_parts, flat_parts, cell_parts = [], [], [], []
    for offset in itertools.product((0, 1), repeat=d):  # 4 or 8 neighbours
        ok = has[0][offset[0]]
        for a in range(1, d):
            ok = ok & has[a][offset[a]]
        v = np.flatnonzero(ok)
        packed = np.zeros(v.size, dtype=np.int64)
        flat = np.zeros(v.size, dtype=np.int64)
        cell = np.zeros(v.size, dtype=np.int64)
        for a in range(d):  # per axis: the leaf index, packed, its cell and the offset in it
            leaf = lo[a][v] + offset[a]
            packed |= leaf << (KEY_BITS * a)
            cell += (leaf - origin[a]) * stride[a]
            flat += (cols[a][v] - (leaf * side - halo)) * box**a
        vox_parts.append(v)
        leaf_parts.append(packed)
        flat_parts.append(flat)
        cell_parts.append(cell)
    parts = (vox_parts, leaf_parts, flat_parts, cell_parts)
    voxel, leaf_key, flat, cell = (np.concatenate(p) for p in parts)
    return voxel, leaf_key, flat, cell, origin, extent


def near_leaf(flat: IntArray, grid: LeafGrid, fill: int) -> NDArray[np.bool_]:
    """Whether halo-box voxels lie within ``fill`` voxels of their leaf along every axis.

    Only such a seen voxel makes a voxel of the leaf known (:func:`seen_near`).

    Parameters
    ----------
    flat : ndarray of int64, shape (p,)
        Flat indices into a leaf's halo box (x fastest).
    grid : LeafGrid
    fill : int
        At least 0.

    Returns
    -------
    ndarray of bool, shape (p,)
    """
    side, halo = grid.side, grid.halo_voxels
    box = side + 2 * halo
    lo, hi = halo - fill, halo + side + fill
    out = np.ones(flat.shape, dtype=bool)
    for a in range(grid.dim):  # per axis
        c = (flat // box**a) % box
        out &= (c >= lo) & (c < hi)
    return out


def grow_seen(
    before: NDArray[np.bool_], owner: IntArray, flat: IntArray
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Leaves' seen masks with a step's seen voxels added.

    Parameters
    ----------
    before : ndarray of bool, shape (n, H)
        The leaves' seen masks over their halo boxes (x fastest); only read.
    owner, flat : ndarray of int64, shape (p,)
        Per (seen voxel, leaf) pair: the leaf (row of ``before``) and the voxel's flat
        index in its halo box.

    Returns
    -------
    after : ndarray of bool, shape (n, H)
        The masks with the pairs' voxels seen (a new array).
    grown : ndarray of bool, shape (n,)
        Whether a leaf's mask gained a voxel.
    """
    after = before.copy()
    after[owner, flat] = True
    grown: NDArray[np.bool_] = np.any(after != before, axis=1)
    return after, grown


def seen_near(seen: NDArray[np.bool_], grid: LeafGrid, fill: int) -> NDArray[np.bool_]:
    """Whether each leaf voxel has a seen voxel within ``fill`` voxels (it is known).

    Within ``fill`` voxels along every axis: a cube of edge ``2 fill + 1``.

    Parameters
    ----------
    seen : ndarray of bool, shape (n, H)
        The leaves' seen voxels over their halo boxes (x fastest).
    grid : LeafGrid
    fill : int
        At least 0 and at most the leaf's halo in voxels, so that the halo box holds
        every voxel that counts.

    Returns
    -------
    ndarray of bool, shape (n, V)
        Per leaf, in its voxel order (x fastest).
    """
    n, d, side, halo = seen.shape[0], grid.dim, grid.side, grid.halo_voxels
    if not 0 <= fill <= halo:
        raise ValueError(f"fill must be in 0..{halo} (the leaf's halo in voxels), got {fill}")
    box = side + 2 * halo
    cube = seen.astype(np.uint8).reshape((n,) + (box,) * d)
    if fill > 0:
        cube = ndimage.maximum_filter(
            cube, size=(1,) + (2 * fill + 1,) * d, mode="constant", cval=0
        )
    inner = cube[(slice(None),) + (slice(halo, halo + side),) * d]
    out: NDArray[np.bool_] = inner.reshape(n, -1) > 0
    return out
