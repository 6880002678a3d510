"""The map's continuous field: voxel values looked up and interpolated between voxel centres.

The reads of :class:`~octolgp.mapping.query.MapReads` and the planning queries built
on them (:mod:`octolgp.mapping.planning`, :mod:`octolgp.mapping.gradient`,
:mod:`octolgp.mapping.distance`, :mod:`octolgp.mapping.coarse`,
:mod:`octolgp.mapping.surface`) come from here: the stored voxel values
(:func:`lookup`) and their multilinear interpolation (:func:`interpolate`). Every
function only reads the store.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_mask, addressable_range
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping.grid import LeafGrid, group_keys
from octolgp.mapping.store import Leaf, LeafStore
from octolgp.scan import FloatArray, as_points
from octolgp.training import IntArray


def query_points(points: object, config: MapConfig, name: str = "points") -> FloatArray:
    """Validate query points: shape ``(q, d)``, finite, inside the addressable range.

    Raises
    ------
    OctolgpError
        Naming the argument (``name``) and the first offending row.
    """
    X = as_points(points, name, dim=config.dim)
    inside = addressable_mask(X, config.resolution, config.tree_depth)
    if not inside.all():
        low, high = addressable_range(config.resolution, config.tree_depth)
        row = int(np.flatnonzero(~inside)[0])
        raise OctolgpError(
            f"{name} row {row} ({X[row].tolist()}) is outside the addressable range "
            f"[{low:g}, {high:g}) m"
        )
    return X


QUERY_CHUNK = 1 << 16
"""Points a query (:class:`MapReads`) handles at once: its temporaries (the ``2**d``
corners of each point, their values, the probabilities) stay a few tens of megabytes
whatever the query's size."""


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
    key_list, size = keys.tolist(), store.batch
    batch: list[Leaf | None] = []
    for j in range(len(key_list)):  # one iteration per leaf queried
        if j % size == 0:  # evicted leaves read and fitted a batch at a time
            batch = store.peek_many(key_list[j : j + size])
        leaf = batch[j % size]
        if leaf is None or leaf.prob.size == 0:
            continue
        sel = order[bounds[j] : bounds[j + 1]]
        flat = np.zeros(sel.size, dtype=np.int64)
        if not leaf.pruned:
            flat = grid.voxel_index(X[sel], leaf.index)
        for arr, name in zip(out, fields, strict=True):
            arr[sel] = getattr(leaf, name)[flat]
    return out


class Reader(Protocol):
    """Where stored voxel values come from: NaN where no leaf holds one (as :func:`lookup`)."""

    def at_points(self, X: FloatArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """Values of the voxels holding addressable points ``(q, d)``, one array per field."""
        ...

    def at_keys(self, keys: IntArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """Values of the voxels with per-axis keys ``(q, d)`` (in range), one array per field."""
        ...


@dataclass(frozen=True, slots=True)
class StoreReader:
    """:func:`lookup` on a map's store, as a :class:`Reader`."""

    store: LeafStore
    grid: LeafGrid

    def at_points(self, X: FloatArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """:func:`lookup` at points."""
        return lookup(self.store, self.grid, X, fields)

    def at_keys(self, keys: IntArray, fields: tuple[str, ...]) -> list[FloatArray]:
        """:func:`lookup` at the centres of the voxels with these keys."""
        return lookup(self.store, self.grid, self.grid.key_centres(keys), fields)


def corner_latent(
    read: Reader, config: MapConfig, prior: float, X: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, np.ndarray]:
    """The ``2**d`` voxel centres around each point and their latent values (from ``read``).

    Returns
    -------
    frac : ndarray of shape (q, d)
        Each point's position in the cell of voxel centres around it, in ``[0, 1)``
        per axis (``0``: on the lower centre).
    corners : ndarray of shape (2**d, d)
        The cell's corners as 0/1 offsets (the first axis varies slowest).
    mean, var : ndarray of shape (2**d, q)
        Latent mean and variance at each corner; ``(0, prior)`` where no leaf holds
        the corner (or it lies outside the addressable range).
    known : ndarray of bool, shape (q,)
        Points whose own voxel holds a value.
    """
    d = config.dim
    res = config.resolution
    (own,) = read.at_points(X, ("mean",))
    u = X / res - 0.5
    base = np.floor(u)
    frac = u - base
    corners = np.array(list(np.ndindex(*(2,) * d)), dtype=np.float64)  # (2^d, d)
    # per-axis voxel keys of the corners: key = floor(x / res) + 2**(tree_depth - 1)
    half = 1 << (config.tree_depth - 1)
    lower = base.astype(np.int64) + half
    keys = (lower[None, :, :] + corners.astype(np.int64)[:, None, :]).reshape(-1, d)
    inside = all_columns(keys.view(np.uint64) < (1 << config.tree_depth))  # 0 <= key < 2**depth
    mean = np.full(keys.shape[0], np.nan)
    var = np.full(keys.shape[0], np.nan)
    mean[inside], var[inside] = read.at_keys(keys[inside], ("mean", "var"))
    held = ~np.isnan(mean)
    shape = (corners.shape[0], X.shape[0])
    corner_mean: FloatArray = np.where(held, mean, 0.0).reshape(shape)
    corner_var: FloatArray = np.where(held, var, prior).reshape(shape)
    return frac, corners, corner_mean, corner_var, ~np.isnan(own)


def all_columns(flags: np.ndarray) -> np.ndarray:
    """``flags.all(axis=1)`` for a few columns, faster than numpy's reduce over a short axis."""
    out = flags[:, 0].copy()
    for j in range(1, flags.shape[1]):  # 2 or 3 axes
        out &= flags[:, j]
    return out


def corner_weights(frac: FloatArray, corners: FloatArray) -> FloatArray:
    """Multilinear weights ``(2**d, q)`` of the corners (:func:`corner_latent`)."""
    factors = np.where(corners[:, None, :] == 1, frac, 1.0 - frac)  # (2^d, q, d)
    weights = factors[:, :, 0].copy()
    for j in range(1, frac.shape[1]):  # the product over axes, in axis order (2 or 3)
        weights *= factors[:, :, j]
    return weights


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
    frac, corners, mean, var, known = corner_latent(StoreReader(store, grid), config, prior, X)
    weights = corner_weights(frac, corners)
    return (weights * mean).sum(axis=0), (weights * var).sum(axis=0), known


class ReadableMap(Protocol):
    """What a read needs of a map: its config, leaf grid, store and hyperparameters."""

    config: MapConfig
    grid: LeafGrid
    store: LeafStore
    hyperparameters: Hyperparameters | None


def leaves_read(grid: LeafGrid, X: FloatArray) -> set[int]:
    """Packed keys of every leaf a query at ``X`` may read (interpolated or not).

    The ``2**d`` voxel centres around a point lie within one voxel of it, so their
    leaves are those of the points moved by up to a voxel along each axis.
    """
    res = grid.resolution
    low, high = grid.leaf_of(X - res), grid.leaf_of(X + res)
    keys: set[int] = set()
    for corner in itertools.product((0, 1), repeat=X.shape[1]):  # 4 or 8 corners
        index = np.where(np.array(corner, dtype=bool), high, low)
        keys.update(np.unique(grid.pack(index)).tolist())
    return keys


def prior_variance(m: ReadableMap) -> float:
    """The latent variance of unknown space: ``σf²``, or 1 before hyperparameters exist."""
    return 1.0 if m.hyperparameters is None else m.hyperparameters.signal_variance


def interpolate_latent(m: ReadableMap, X: FloatArray) -> tuple[FloatArray, FloatArray, np.ndarray]:
    """Multilinear latent mean and variance of map ``m`` at points (see :func:`interpolate`)."""
    return interpolate(m.store, m.grid, m.config, prior_variance(m), X)


def occupancy_field(
    m: ReadableMap, X: FloatArray, read: Reader | None = None
) -> tuple[FloatArray, np.ndarray]:
    """P(occupied) as :meth:`~octolgp.mapping.query.MapReads.occupancy` reads it, anywhere.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Finite points, metres, world frame; points outside the addressable range
        read as unknown.
    read : Reader, optional
        Where the voxel values come from: the map's store (default), or a table of
        them (:class:`~octolgp.mapping.voxel_table.VoxelTable`), the same values.

    Returns
    -------
    prob : ndarray of shape (q,)
        The interpolated P(occupied) (the stored voxel value before hyperparameters
        exist); 0.5 where unknown.
    known : ndarray of bool, shape (q,)
        Points whose own voxel holds a value.
    """
    res, depth = m.config.resolution, m.config.tree_depth
    prob = np.full(X.shape[0], 0.5)
    known = np.zeros(X.shape[0], dtype=bool)
    inside = np.flatnonzero(addressable_mask(X, res, depth))
    hp = m.hyperparameters
    reader = StoreReader(m.store, m.grid) if read is None else read
    for lo in range(0, inside.size, QUERY_CHUNK):  # bounded temporaries, chunk by chunk
        at = inside[lo : lo + QUERY_CHUNK]
        if hp is None:
            (p,) = reader.at_points(X[at], ("prob",))
            held = ~np.isnan(p)
        else:
            frac, corners, mc, vc, held = corner_latent(reader, m.config, hp.signal_variance, X[at])
            w = corner_weights(frac, corners)
            p = latent_occupancy((w * mc).sum(axis=0), (w * vc).sum(axis=0), hp)
        prob[at] = np.where(held, p, 0.5)
        known[at] = held
    return prob, known


def held_at(m: ReadableMap, X: FloatArray, read: Reader | None = None) -> np.ndarray:
    """Whether the voxel holding each point ``(q, d)`` holds a value (bool, (q,)).

    ``False`` outside the addressable range; ``read`` as in :func:`occupancy_field`.
    """
    reader = StoreReader(m.store, m.grid) if read is None else read
    held = np.zeros(X.shape[0], dtype=bool)
    inside = np.flatnonzero(addressable_mask(X, m.config.resolution, m.config.tree_depth))
    for lo in range(0, inside.size, QUERY_CHUNK):  # bounded temporaries, chunk by chunk
        at = inside[lo : lo + QUERY_CHUNK]
        held[at] = ~np.isnan(reader.at_points(X[at], ("mean",))[0])
    return held
