"""OctoMap voxel keys: integer addresses of the cells of a fixed-depth tree.

A key is OctoMap's ``OcTreeKey``: per axis, ``key = floor(x / resolution) +
2**(tree_depth - 1)``, an unsigned integer of ``tree_depth <= 16`` bits. 2D maps use
the first two axes. Keys are packed into one int64 (``x | y << 16 | z << 32``) so
that ``np.unique``, ``np.sort`` and ``np.searchsorted`` work on whole voxels.

Limits
------
A tree of depth ``D`` at resolution ``r`` addresses coordinates in
``[-(2**(D-1)) * r, 2**(D-1) * r)`` on every axis, for example ±3276.8 m at 0.1 m
with the default depth 16.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.scan import as_points

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

KEY_BITS = 16
"""Bits per axis in a packed key; OctoMap's ``key_type`` is ``uint16``."""

_KEY_MASK = (1 << KEY_BITS) - 1


def _check_grid(resolution: float, tree_depth: int) -> None:
    """Raise unless ``resolution > 0`` is finite and ``tree_depth`` is in 1..16."""
    if (
        isinstance(resolution, bool)
        or not isinstance(resolution, int | float | np.floating | np.integer)
        or not math.isfinite(resolution)
        or resolution <= 0
    ):
        raise OctolgpError(f"resolution must be a finite number > 0, got {resolution!r}")
    if (
        isinstance(tree_depth, bool)
        or not isinstance(tree_depth, int | np.integer)
        or not 1 <= tree_depth <= KEY_BITS
    ):
        raise OctolgpError(f"tree_depth must be an integer in 1..{KEY_BITS}, got {tree_depth!r}")


def addressable_range(resolution: float, tree_depth: int = 16) -> tuple[float, float]:
    """Return the coordinates a tree can address, per axis.

    Parameters
    ----------
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Key bits per axis, 1..16 (OctoMap's 16 by default).

    Returns
    -------
    (low, high) : tuple of float
        Coordinates ``x`` with ``low <= x < high`` have a key, metres.

    Raises
    ------
    OctolgpError
        On a non-positive resolution or a depth outside 1..16.
    """
    _check_grid(resolution, tree_depth)
    half = float(2 ** (tree_depth - 1)) * float(resolution)
    return -half, half


def _in_range(points: FloatArray, resolution: float, tree_depth: int) -> NDArray[np.bool_]:
    """Elementwise: ``floor(x / resolution)`` lies in ``[-2**(depth-1), 2**(depth-1))``.

    Checked on the floored float, before the cast, so that huge values cannot wrap.
    """
    cell = np.floor(points / resolution)
    half = float(1 << (tree_depth - 1))
    return (cell >= -half) & (cell < half)


def addressable_mask(
    points: ArrayLike, resolution: float, tree_depth: int = 16
) -> NDArray[np.bool_]:
    """Return which points have a key (all coordinates in the addressable range).

    Parameters
    ----------
    points : array_like of shape (n, d)
        Coordinates in the world frame, metres.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Key bits per axis.

    Returns
    -------
    ndarray of bool, shape (n,)
        True where :func:`coord_to_key` accepts the row.

    Raises
    ------
    OctolgpError
        On a bad shape or a non-finite coordinate in ``points``.
    """
    _check_grid(resolution, tree_depth)
    inside: NDArray[np.bool_] = np.all(
        _in_range(as_points(points, "points"), resolution, tree_depth), axis=1
    )
    return inside


def coord_to_key(
    points: ArrayLike, resolution: float, tree_depth: int = 16, *, name: str = "points"
) -> IntArray:
    """Map coordinates to OctoMap keys (OctoMap's ``coordToKeyChecked``).

    Parameters
    ----------
    points : array_like of shape (n, d)
        Coordinates in the world frame, metres; ``d`` is 1, 2 or 3.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Key bits per axis, 1..16.
    name : str, optional
        Name of ``points`` in error messages.

    Returns
    -------
    ndarray of int64, shape (n, d)
        ``floor(x / resolution) + 2**(tree_depth - 1)`` per axis, in
        ``[0, 2**tree_depth)``.

    Raises
    ------
    OctolgpError
        On a bad shape or a non-finite value in ``points``, or when a coordinate
        lies outside the addressable range (see :func:`addressable_range`).
    """
    _check_grid(resolution, tree_depth)
    pts = as_points(points, name)
    bad = ~_in_range(pts, resolution, tree_depth)
    if bad.any():
        low, high = addressable_range(resolution, tree_depth)
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        raise OctolgpError(
            f"{name} row {row} ({pts[row].tolist()}) is outside the addressable range "
            f"[{low:g}, {high:g}) m of a depth-{tree_depth} tree at resolution {resolution:g} m"
        )
    return np.floor(pts / resolution).astype(np.int64) + (1 << (tree_depth - 1))


def key_to_coord(keys: ArrayLike, resolution: float, tree_depth: int = 16) -> FloatArray:
    """Return the voxel centres of keys (OctoMap's ``keyToCoord``).

    Parameters
    ----------
    keys : array_like of int, shape (n, d)
        OctoMap keys.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        Key bits per axis.

    Returns
    -------
    ndarray of float64, shape (n, d)
        ``(key - 2**(tree_depth - 1) + 0.5) * resolution``, metres, world frame.

    Raises
    ------
    OctolgpError
        On a non-integer array or a key outside ``[0, 2**tree_depth)``.
    """
    _check_grid(resolution, tree_depth)
    k = _as_keys(keys, "keys", 1 << tree_depth)
    return (k - (1 << (tree_depth - 1)) + 0.5).astype(np.float64) * float(resolution)


RETURN_STEPS = 1 << 16
"""Steps per voxel edge at which a kept return's position is stored: a return sits at
the centre of one of ``RETURN_STEPS**d`` cells of its voxel (0.003 mm at 0.2 m)."""


def return_steps(
    points: FloatArray, keys: IntArray, resolution: float, tree_depth: int
) -> NDArray[np.uint16]:
    """Each point's cell of :data:`RETURN_STEPS` per axis inside its voxel, (n, d) uint16.

    ``keys`` are the points' voxel keys; a point on a voxel's far face (rounding) goes
    to the last cell.
    """
    u = points / resolution - (keys - (1 << (tree_depth - 1)))
    steps = np.clip(np.floor(u * RETURN_STEPS), 0, RETURN_STEPS - 1)
    return steps.astype(np.uint16)


def step_points(steps: ArrayLike, keys: IntArray, resolution: float, tree_depth: int) -> FloatArray:
    """Positions of :func:`return_steps` cells: each cell's centre, metres, (n, d).

    ``step_points(return_steps(p, k, ...), k, ...)`` moves each point by at most half a
    step per axis and is its own fixed point, so a kept return stored as its cell reads
    back bit for bit.
    """
    cell = (np.asarray(steps, dtype=np.float64) + 0.5) / RETURN_STEPS
    out: FloatArray = ((keys - (1 << (tree_depth - 1))) + cell) * float(resolution)
    return out


def _as_keys(keys: ArrayLike, name: str, limit: int = 1 << KEY_BITS) -> IntArray:
    """Validate an ``(n, d)`` integer key array with entries in ``[0, limit)``."""
    k = np.asarray(keys)
    if k.dtype.kind not in "iu":
        raise OctolgpError(f"{name} must be an integer array, got dtype {k.dtype}")
    if k.ndim != 2 or k.shape[1] not in (1, 2, 3):
        raise OctolgpError(f"{name} must have shape (n, d) with d in 1..3, got {k.shape}")
    k = k.astype(np.int64, copy=False)
    if k.size and (k.min() < 0 or k.max() >= limit):
        raise OctolgpError(f"{name} must lie in [0, {limit}), got [{k.min()}, {k.max()}]")
    return k


def pack_keys(keys: ArrayLike) -> IntArray:
    """Pack per-axis keys into one int64 per voxel: ``x | y << 16 | z << 32``.

    Sorting packed keys sorts voxels by ``(z, y, x)``; equal voxels give equal
    integers, so ``np.unique`` and ``np.searchsorted`` work on voxels.

    Parameters
    ----------
    keys : array_like of int, shape (n, d)
        OctoMap keys, each in ``[0, 2**16)``.

    Returns
    -------
    ndarray of int64, shape (n,)
        Packed keys, non-negative and below ``2**(16 d)``.

    Raises
    ------
    OctolgpError
        On a non-integer array, a bad shape or a key outside 16 bits.
    """
    k = _as_keys(keys, "keys")
    packed = np.zeros(k.shape[0], dtype=np.int64)
    for axis in range(k.shape[1]):  # at most 3 axes, never per point
        packed |= k[:, axis] << (KEY_BITS * axis)
    return packed


def unpack_keys(packed: ArrayLike, dim: int) -> IntArray:
    """Invert :func:`pack_keys`.

    Parameters
    ----------
    packed : array_like of int, shape (n,)
        Packed keys.
    dim : int
        Number of axes, 1..3.

    Returns
    -------
    ndarray of int64, shape (n, dim)
        Per-axis OctoMap keys.

    Raises
    ------
    OctolgpError
        On a bad shape, a negative key, or bits above ``16 dim``.
    """
    if isinstance(dim, bool) or dim not in (1, 2, 3):
        raise OctolgpError(f"dim must be 1, 2 or 3, got {dim!r}")
    p = np.asarray(packed)
    if p.dtype.kind not in "iu" or p.ndim != 1:
        raise OctolgpError(f"packed must be a 1D integer array, got {p.dtype} {p.shape}")
    p = p.astype(np.int64, copy=False)
    if p.size and (p.min() < 0 or p.max() >= (1 << (KEY_BITS * dim))):
        raise OctolgpError(f"packed holds values outside [0, 2**{KEY_BITS * dim})")
    shifts = KEY_BITS * np.arange(dim, dtype=np.int64)
    return (p[:, None] >> shifts[None, :]) & _KEY_MASK


def child_index(keys: ArrayLike, level: int) -> NDArray[np.uint8]:
    """Return which child of its parent each key falls in (OctoMap's ``computeChildIdx``).

    OctoMap orders the eight children of a node by ``x + 2 y + 4 z``, where each
    term is 1 when the key's bit ``level`` on that axis is set (the upper half of
    the parent) and 0 otherwise: bit 0 is x, bit 1 is y, bit 2 is z. ``level``
    counts from the bottom, as OctoMap's ``depth`` argument: the root's children
    use bit ``tree_depth - 1`` and a leaf's place in its parent uses bit 0. So a
    node at depth ``t`` chooses its child with ``level = tree_depth - 1 - t``.
    2D keys have no z bit and give indices 0..3.

    Parameters
    ----------
    keys : array_like of int, shape (n, d)
        OctoMap keys, ``d`` in 1..3.
    level : int
        Bit index, 0..15.

    Returns
    -------
    ndarray of uint8, shape (n,)
        Child index in 0..7.

    Raises
    ------
    OctolgpError
        On bad keys or a level outside 0..15.
    """
    if isinstance(level, bool) or not isinstance(level, int | np.integer) or not 0 <= level < 16:
        raise OctolgpError(f"level must be an integer in 0..15, got {level!r}")
    k = _as_keys(keys, "keys")
    bits = (k >> int(level)) & 1
    weights = (1 << np.arange(k.shape[1], dtype=np.int64))[None, :]
    index: NDArray[np.uint8] = (bits * weights).sum(axis=1).astype(np.uint8)
    return index


@dataclass(frozen=True, slots=True)
class KeyRegion:
    """A set of voxels held as blocks of ``2**shift`` voxels on an edge.

    Reads that need the observations of a few places only (the learning sets) ask for
    them in a region, so that the voxels elsewhere are dropped as soon as they are
    walked instead of being sorted and counted.

    Attributes
    ----------
    shift : int
        A block is ``2**shift`` voxels on an edge; block index = key >> shift.
    low : ndarray of int64, shape (d,)
        The lowest block index per axis of ``blocks``.
    blocks : ndarray of bool, shape (n_x, n_y[, n_z])
        Which blocks, indexed by block index minus ``low``, belong to the region.
    """

    shift: int
    low: IntArray
    blocks: NDArray[np.bool_]

    @classmethod
    def around(
        cls,
        centres: FloatArray,
        radii: FloatArray,
        resolution: float,
        tree_depth: int,
        shift: int = 3,
    ) -> KeyRegion:
        """The blocks that meet the balls ``|x - centre| <= radius`` (a superset of them).

        Parameters
        ----------
        centres : ndarray of shape (k, d)
            Ball centres, metres (addressable).
        radii : ndarray of shape (k,)
            Ball radii, metres, non-negative.
        resolution : float
            Voxel edge, metres.
        tree_depth : int
        shift : int
            Blocks of ``2**shift`` voxels on an edge.
        """
        c = np.asarray(centres, dtype=np.float64)
        r = np.asarray(radii, dtype=np.float64)
        dim = c.shape[1]
        edge = resolution * (1 << shift)  # a block's edge, metres
        offset = (1 << (tree_depth - 1)) >> shift  # the block index of coordinate 0
        lo = np.floor((c - r[:, None]) / edge).astype(np.int64) + offset
        hi = np.floor((c + r[:, None]) / edge).astype(np.int64) + offset
        low = lo.min(axis=0) if c.size else np.zeros(dim, np.int64)
        extent = (hi.max(axis=0) - low + 1) if c.size else np.zeros(dim, np.int64)
        blocks = np.zeros(tuple(int(e) for e in extent), dtype=bool)
        grids = np.indices(blocks.shape).reshape(dim, -1).T + low  # (cells, d) block indices
        corner = (grids - offset) * edge  # each block's lower corner, metres
        for centre, radius in zip(c, r, strict=True):  # one pass per ball, a few
            nearest = np.clip(centre, corner, corner + edge)  # the block's point nearest it
            inside = np.sum((nearest - centre) ** 2, axis=1) <= radius**2
            blocks.reshape(-1)[inside] = True
        return cls(shift, low, blocks)

    @classmethod
    def holding(cls, packed: IntArray, dim: int, shift: int = 3) -> KeyRegion:
        """The blocks that hold the voxels of packed keys ``(n,)`` of ``dim`` axes."""
        keys = (packed[:, None] >> (KEY_BITS * np.arange(dim))) & _KEY_MASK
        block = keys >> shift
        low = block.min(axis=0) if packed.size else np.zeros(dim, np.int64)
        extent = block.max(axis=0) - low + 1 if packed.size else np.zeros(dim, np.int64)
        blocks = np.zeros(tuple(int(e) for e in extent), dtype=bool)
        blocks[tuple((block - low).T)] = True
        return cls(shift, low, blocks)

    def contains(self, packed: IntArray) -> NDArray[np.bool_]:
        """Whether each packed key's voxel lies in the region.

        Parameters
        ----------
        packed : ndarray of int64, shape (n,)
            Packed keys (:func:`pack_keys`) of ``d`` axes; higher bits are ignored.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        flat = np.zeros(packed.shape, dtype=np.int64)
        inside = np.ones(packed.shape, dtype=bool)
        for axis, size in enumerate(self.blocks.shape):  # at most 3 axes, C order
            block = ((packed >> (KEY_BITS * axis)) & _KEY_MASK) >> self.shift
            block -= self.low[axis]
            inside &= (block >= 0) & (block < size)
            flat *= size
            flat += block
        where = np.flatnonzero(inside)
        inside[where] = self.blocks.reshape(-1)[flat[where]]
        return inside
