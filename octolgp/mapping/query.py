"""Queries: read voxel values from the store, at voxels or interpolated between them.

Every function here only reads the store (a query never changes a map). A map
with a memory budget loads evicted leaves for reading without making them
resident, so a query does not change which leaves stay in RAM either.
"""

from __future__ import annotations

import numpy as np

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_mask, addressable_range
from octolgp.mapping.evidence import group_keys
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import LeafStore
from octolgp.scan import FloatArray, as_points


def query_points(points: object, config: MapConfig) -> FloatArray:
    """Validate query points: shape ``(q, d)``, finite, inside the addressable range.

    Raises
    ------
    OctolgpError
        Naming the first offending row.
    """
    X = as_points(points, "points", dim=config.dim)
    inside = addressable_mask(X, config.resolution, config.tree_depth)
    if not inside.all():
        low, high = addressable_range(config.resolution, config.tree_depth)
        row = int(np.flatnonzero(~inside)[0])
        raise OctolgpError(
            f"points row {row} ({X[row].tolist()}) is outside the addressable range "
            f"[{low:g}, {high:g}) m"
        )
    return X


def lookup(
    store: LeafStore, grid: LeafGrid, X: FloatArray, fields: tuple[str, ...]
) -> list[FloatArray]:
    """Stored voxel values (``fields`` of :class:`~octolgp.mapping.store.Leaf`) at points.

    Parameters
    ----------
    store : LeafStore
    grid : LeafGrid
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.
    fields : tuple of str
        Among ``"mean"``, ``"var"``, ``"prob"``.

    Returns
    -------
    list of ndarray of shape (q,)
        One per field; NaN where no leaf holds a value for the point.
    """
    out = [np.full(X.shape[0], np.nan) for _ in fields]
    if X.shape[0] == 0 or len(store) == 0:
        return out
    order, keys, bounds = group_keys(grid.pack(grid.leaf_of(X)))
    for j, key in enumerate(keys.tolist()):  # one iteration per leaf queried
        leaf = store.peek(key)
        if leaf is None or leaf.prob.size == 0:
            continue
        sel = order[bounds[j] : bounds[j + 1]]
        flat = np.zeros(sel.size, dtype=np.int64)
        if not leaf.pruned:
            flat = grid.voxel_index(X[sel], leaf.index)
        for arr, name in zip(out, fields, strict=True):
            arr[sel] = getattr(leaf, name)[flat]
    return out


def interpolate(
    store: LeafStore, grid: LeafGrid, config: MapConfig, prior: float, X: FloatArray
) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Multilinear interpolation of the voxel latent mean and variance at points.

    The ``2**d`` voxel centres around each point are weighted by the usual
    bilinear/trilinear weights; a corner no leaf holds (or outside the addressable
    range) contributes the GP prior ``(0, prior)``.

    Returns
    -------
    mean, var : ndarray of shape (q,)
    known : ndarray of bool, shape (q,)
        Points whose own voxel holds a value.
    """
    d = config.dim
    res = config.resolution
    (own,) = lookup(store, grid, X, ("mean",))
    u = X / res - 0.5
    base = np.floor(u)
    frac = u - base
    corners = np.array(list(np.ndindex(*(2,) * d)), dtype=np.float64)  # (2^d, d)
    weights = np.prod(np.where(corners[:, None, :] == 1, frac, 1.0 - frac), axis=2)
    centres = ((base[None, :, :] + corners[:, None, :] + 0.5) * res).reshape(-1, d)
    inside = addressable_mask(centres, res, config.tree_depth)
    mean = np.full(centres.shape[0], np.nan)
    var = np.full(centres.shape[0], np.nan)
    mean[inside], var[inside] = lookup(store, grid, centres[inside], ("mean", "var"))
    known = ~np.isnan(mean)
    mean = np.where(known, mean, 0.0).reshape(weights.shape)
    var = np.where(known, var, prior).reshape(weights.shape)
    return (weights * mean).sum(axis=0), (weights * var).sum(axis=0), ~np.isnan(own)
