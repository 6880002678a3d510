"""Box reads and reads at a coarser octree depth, as OctoMap's queries at depth.

A node at depth ``t < tree_depth`` spans ``2**(tree_depth - t)`` voxels per axis;
its key per axis is the voxel key shifted right by ``tree_depth - t`` bits, its
centre OctoMap's ``keyToCoord(key, t)``. Its P(occupied) is the **maximum** over the
voxels inside it that hold a value, as OctoMap's inner nodes after
``updateInnerOccupancy`` (``getMaxChildLogOdds``); a node with no such voxel is
unknown (0.5, left out of voxel reads). A box read takes the voxels (or nodes)
whose keys lie between the keys of the box's corners, both included, as OctoMap's
``begin_leafs_bbx``: every cell that overlaps the box.

Every function here only reads the map.
"""

from __future__ import annotations

import numpy as np

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import pack_keys, unpack_keys
from octolgp.mapping.field import ReadableMap, query_points
from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = [
    "box_voxels",
    "check_bbox",
    "check_depth",
    "depth_occupancy",
    "leaves_in_box",
    "node_keys",
]


def check_depth(depth: object, config: MapConfig) -> int:
    """``depth`` as an int in ``1..tree_depth`` (``None``: ``tree_depth``), else an error."""
    if depth is None:
        return config.tree_depth
    if isinstance(depth, bool) or not isinstance(depth, int | np.integer):
        raise OctolgpError(f"depth must be an integer in 1..{config.tree_depth}, got {depth!r}")
    if not 1 <= int(depth) <= config.tree_depth:
        raise OctolgpError(f"depth must be an integer in 1..{config.tree_depth}, got {depth!r}")
    return int(depth)


def node_keys(X: FloatArray, config: MapConfig, depth: int) -> IntArray:
    """Per-axis keys ``(q, d)`` of the nodes at ``depth`` holding addressable points."""
    edge = config.resolution * (1 << (config.tree_depth - depth))
    origin = -float(1 << (config.tree_depth - 1)) * config.resolution
    keys = np.floor((X - origin) / edge).astype(np.int64)
    return np.clip(keys, 0, (1 << depth) - 1)


def node_centres(keys: IntArray, config: MapConfig, depth: int) -> FloatArray:
    """Centres ``(k, d)`` of nodes at ``depth`` with per-axis keys ``keys``, metres."""
    edge = config.resolution * (1 << (config.tree_depth - depth))
    origin = -float(1 << (config.tree_depth - 1)) * config.resolution
    return np.asarray(origin + (keys + 0.5) * edge, dtype=np.float64)


def _leaf_voxels(m: ReadableMap, keys: list[int]) -> tuple[FloatArray, FloatArray]:
    """Centres and P of the voxels holding a value in the leaves ``keys`` (packed)."""
    cs: list[FloatArray] = [np.zeros((0, m.config.dim))]
    ps: list[FloatArray] = [np.zeros(0)]
    size = m.store.batch
    for lo in range(0, len(keys), size):  # evicted leaves read a batch at a time
        for leaf in m.store.peek_many(keys[lo : lo + size]):  # one iteration per leaf
            if leaf is None or leaf.prob.size == 0:
                continue
            centres = m.grid.voxel_centres(leaf.index)
            prob = np.broadcast_to(leaf.prob, (centres.shape[0],)).astype(np.float64)
            held = ~np.isnan(prob)
            cs.append(centres[held])
            ps.append(prob[held])
    return np.concatenate(cs), np.concatenate(ps)


def _stored_leaves(m: ReadableMap) -> tuple[IntArray, IntArray]:
    """Packed keys (ascending) and per-axis indices ``(k, d)`` of the map's leaves."""
    packed = np.fromiter(iter(m.store), dtype=np.int64, count=len(m.store))
    return packed, unpack_keys(packed, m.config.dim)


def leaves_in_box(m: ReadableMap, lo: FloatArray, hi: FloatArray, depth: int) -> list[int]:
    """Packed keys (ascending) of the map's leaves under the cells that overlap a box.

    The cells are those at ``depth`` overlapping the box ``lo, hi`` (metres,
    addressable).
    """
    config = m.config
    packed, index = _stored_leaves(m)
    node_lo, node_hi = node_keys(np.stack([lo, hi]), config, depth)
    shift = config.tree_depth - depth
    vox_lo, vox_hi = node_lo << shift, ((node_hi + 1) << shift) - 1  # voxel keys
    leaf_shift = m.grid.shift
    inside = ((index >= vox_lo >> leaf_shift) & (index <= vox_hi >> leaf_shift)).all(axis=1)
    return [int(k) for k in packed[inside]]


def _coarsen(
    centres: FloatArray, prob: FloatArray, config: MapConfig, depth: int
) -> tuple[IntArray, FloatArray]:
    """Packed node keys (ascending) at ``depth`` and the max P of the voxels in each."""
    packed = pack_keys(node_keys(centres, config, depth))
    order = np.argsort(packed, kind="stable")
    s = packed[order]
    if s.size == 0:
        return s, np.zeros(0)
    starts = np.flatnonzero(np.r_[True, s[1:] != s[:-1]])
    return s[starts], np.maximum.reduceat(prob[order], starts)


def box_voxels(
    m: ReadableMap, lo: FloatArray | None, hi: FloatArray | None, depth: int
) -> tuple[FloatArray, FloatArray]:
    """Centres and P(occupied) of the known cells at ``depth`` overlapping a box.

    Parameters
    ----------
    m : ReadableMap
    lo, hi : ndarray of shape (d,) or None
        Box corners, metres, world frame (addressable; ``lo <= hi``); ``None``: the
        whole map.
    depth : int
        ``tree_depth`` reads voxels; less, nodes with the max of their voxels.

    Returns
    -------
    centres : ndarray of shape (k, d)
        Cell centres (OctoMap's ``keyToCoord`` at ``depth``), in packed key order at
        ``depth`` (voxels: leaf by leaf).
    prob : ndarray of shape (k,)
    """
    config = m.config
    if lo is not None and hi is not None:
        node_lo, node_hi = node_keys(np.stack([lo, hi]), config, depth)
        centres, prob = _leaf_voxels(m, leaves_in_box(m, lo, hi, depth))
        keys = node_keys(centres, config, depth)
        keep = ((keys >= node_lo) & (keys <= node_hi)).all(axis=1)
        centres, prob = centres[keep], prob[keep]
    else:
        centres, prob = _leaf_voxels(m, list(m.store))
    if depth == config.tree_depth:
        return centres, prob
    nodes, pmax = _coarsen(centres, prob, config, depth)
    return node_centres(unpack_keys(nodes, config.dim), config, depth), pmax


def depth_occupancy(m: ReadableMap, X: FloatArray, depth: int) -> FloatArray:
    """P(occupied) of the node at ``depth`` holding each point: the max of its voxels.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.
    depth : int
        In ``1..tree_depth``.

    Returns
    -------
    ndarray of shape (q,)
        0.5 where no voxel inside the node holds a value.
    """
    config = m.config
    dim = config.dim
    nodes = node_keys(X, config, depth)
    wanted = np.unique(pack_keys(nodes))
    leaf_depth = config.tree_depth - m.grid.shift
    stored, index = _stored_leaves(m)
    if depth >= leaf_depth:  # each node lies inside one leaf
        candidates = np.unique(pack_keys(unpack_keys(wanted, dim) >> (depth - leaf_depth)))
        read = candidates[np.isin(candidates, stored)]
    else:  # a node covers many leaves: those whose node at this depth is wanted
        read = stored[np.isin(pack_keys(index >> (leaf_depth - depth)), wanted)]
    centres, prob = _leaf_voxels(m, read.tolist())
    have, pmax = _coarsen(centres, prob, config, depth)
    if have.size == 0:
        return np.full(X.shape[0], 0.5)
    packed = pack_keys(nodes)
    at = np.minimum(np.searchsorted(have, packed), have.size - 1)
    return np.where(have[at] == packed, pmax[at], 0.5)


def check_bbox(
    bbox: tuple[object, object] | None, config: MapConfig
) -> tuple[FloatArray | None, FloatArray | None]:
    """Validated box corners ``lo, hi`` of shape (d,), or ``(None, None)`` for ``None``.

    Raises
    ------
    OctolgpError
        Naming ``bbox``: not a pair of points of shape (d,), non-finite, outside the
        addressable range, or ``lo > hi`` on an axis.
    """
    if bbox is None:
        return None, None
    if not isinstance(bbox, tuple | list) or len(bbox) != 2:
        raise OctolgpError("bbox must be a pair (lo, hi) of points of shape (d,)")
    try:
        corners = np.asarray(bbox, dtype=np.float64)
    except (TypeError, ValueError):
        raise OctolgpError("bbox must be a pair (lo, hi) of points of shape (d,)") from None
    if corners.shape != (2, config.dim):
        raise OctolgpError(
            f"bbox must be a pair (lo, hi) of points of shape ({config.dim},), "
            f"got shape {corners.shape}"
        )
    lo, hi = query_points(corners, config, "bbox")
    if (lo > hi).any():
        raise OctolgpError(f"bbox lo {lo.tolist()} must be <= hi {hi.tolist()} on every axis")
    return lo, hi
