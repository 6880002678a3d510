"""OctoMap's 16-level tree on Morton codes: key checks, Morton codes and the pruned tree.

Shared by the ``.bt``/``.ot`` writers (:mod:`octolgp.export.octomap`) and the ``.bt``
reader (:mod:`octolgp.export.octomap_read`). Children are ordered ``x + 2 y + 4 z``
(see :func:`octolgp.geometry.keys.child_index`).

The tree is built bottom up, one vectorised pass per level, on Morton codes of
the keys; the depth-first order is a sort of ``(code << 3 (16 - depth), depth)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import KEY_BITS

IntArray = NDArray[np.int64]

DEPTH = KEY_BITS  # OctoMap's OcTree always has 16 levels below the root
CENTER = 1 << (DEPTH - 1)  # OctoMap's tree_max_val: the key of coordinate 0
FREE, OCCUPIED, INNER = 1, 2, 3  # 2-bit child states of the .bt format


def to_keys16(keys: ArrayLike, tree_depth: int) -> IntArray:
    """Validate ``(k, 3)`` or 2D ``(k, 2)`` keys of a depth-``tree_depth`` tree; return 16-bit keys.

    2D keys get the z key of ``z in [0, resolution)``. Keys of a shallower tree are
    shifted so that they address the same coordinates in OctoMap's depth-16 tree.
    """
    k = np.asarray(keys)
    if k.dtype.kind not in "iu":
        raise OctolgpError(f"keys must be an integer array, got dtype {k.dtype}")
    if k.ndim != 2 or k.shape[1] not in (2, 3):
        raise OctolgpError(f"keys must have shape (k, 3) or (k, 2), got {k.shape}")
    limit = 1 << tree_depth
    if k.size and (k.min() < 0 or k.max() >= limit):
        raise OctolgpError(f"keys must lie in [0, {limit}), got [{k.min()}, {k.max()}]")
    shift = CENTER - (1 << (tree_depth - 1))
    k16 = k.astype(np.int64) + shift
    if k16.shape[1] == 2:
        k16 = np.column_stack([k16, np.full(k16.shape[0], CENTER, dtype=np.int64)])
    return k16


# --- Morton codes ----------------------------------------------------------------


def spread3(v: IntArray) -> IntArray:
    """Spread the 16 low bits of ``v`` to every third bit (bit ``i`` to bit ``3 i``)."""
    v = v & 0xFFFF
    v = (v | (v << 16)) & 0x0000_FF00_00FF
    v = (v | (v << 8)) & 0x00F0_0F00_F00F
    v = (v | (v << 4)) & 0x0C30_C30C_30C3
    v = (v | (v << 2)) & 0x2492_4924_9249
    return v


def compact3(v: IntArray) -> IntArray:
    """Invert :func:`spread3`: gather every third bit into the 16 low bits."""
    v = v & 0x2492_4924_9249
    v = (v | (v >> 2)) & 0x0C30_C30C_30C3
    v = (v | (v >> 4)) & 0x00F0_0F00_F00F
    v = (v | (v >> 8)) & 0x0000_FF00_00FF
    v = (v | (v >> 16)) & 0xFFFF
    return v


def morton(keys16: IntArray) -> IntArray:
    """Interleave key bits so that bits ``3 l .. 3 l + 2`` are the child index at level ``l``."""
    code: IntArray = (
        spread3(keys16[:, 0]) | (spread3(keys16[:, 1]) << 1) | (spread3(keys16[:, 2]) << 2)
    )
    return code


def unmorton(code: IntArray) -> IntArray:
    """Invert :func:`morton`: return the ``(k, 3)`` keys of Morton codes."""
    return np.column_stack([compact3(code), compact3(code >> 1), compact3(code >> 2)])


# --- the pruned tree, bottom up ------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Level:
    """The nodes at one depth, sorted by Morton prefix."""

    code: IntArray  # Morton prefix, 3 bits per level above
    value: NDArray[np.float32]  # leaf value, or the maximum of the children
    inner: NDArray[np.bool_]
    children: NDArray[np.uint8]  # .ot child bitmask, 0 for leaves
    states: NDArray[np.uint16]  # .bt 2-bit child states, 0 for leaves


def build_tree(keys16: IntArray, values: NDArray[np.float32], top: int = 0) -> list[Level]:
    """Build the pruned tree over leaf voxels; ``levels[d - top]`` holds the nodes at depth ``d``.

    A leaf's .bt state is occupied when its value is positive. With ``top > 0`` the
    tree stops at depth ``top``: the subtrees below are exact, but whether a node at
    depth ``top`` is pruned into its parent is left to :func:`grow_tree` on the
    nodes of every such subtree. Raises on duplicate keys.
    """
    code = morton(keys16)
    order = np.argsort(code)
    code, values = code[order], values[order]
    if code.size > 1 and (code[1:] == code[:-1]).any():
        raise OctolgpError("keys must be unique, got duplicate voxels")
    n = code.size
    leaves = Level(code, values, np.zeros(n, bool), np.zeros(n, np.uint8), np.zeros(n, np.uint16))
    return grow_tree(leaves, DEPTH, top)


def grow_tree(nodes: Level, depth: int, top: int) -> list[Level]:
    """The pruned tree above the nodes at ``depth``, up to ``top``; ``levels[d - top]`` at depth ``d``.

    ``nodes`` are sorted by code and unique. Groups of eight leaf siblings of equal
    value are pruned into their parent level by level (OctoMap's ``prune()``, never
    into the root), so ``levels[-1]`` may hold fewer nodes than ``nodes``.
    """
    levels = [nodes]
    for d in range(depth, top, -1):
        nodes = levels[-1]
        # Group the nodes of this depth by parent (codes are sorted, so groups are runs).
        slot = (nodes.code & 7).astype(np.int64)
        parent = nodes.code >> 3
        first = np.ones(parent.size, bool)
        first[1:] = parent[1:] != parent[:-1]
        starts = np.flatnonzero(first)
        n_children = np.diff(np.append(starts, parent.size))
        state = np.where(nodes.inner, INNER, np.where(nodes.value > 0, OCCUPIED, FREE))
        children = np.bitwise_or.reduceat((1 << slot).astype(np.uint8), starts)
        states = np.bitwise_or.reduceat((state << (2 * slot)).astype(np.uint16), starts)
        high = np.maximum.reduceat(nodes.value, starts)
        low = np.minimum.reduceat(nodes.value, starts)
        any_inner = np.logical_or.reduceat(nodes.inner, starts)
        # OcTreeBaseImpl::isNodeCollapsible: eight leaf children of equal value (never the root).
        collapse = (n_children == 8) & ~any_inner & (high == low) & (d > 1)
        if collapse.any():
            keep = ~np.repeat(collapse, n_children)
            levels[-1] = Level(
                nodes.code[keep],
                nodes.value[keep],
                nodes.inner[keep],
                nodes.children[keep],
                nodes.states[keep],
            )
        levels.append(
            Level(
                parent[starts],
                high,
                ~collapse,
                np.where(collapse, 0, children).astype(np.uint8),
                np.where(collapse, 0, states).astype(np.uint16),
            )
        )
    levels.reverse()
    return levels


def depth_first(levels: list[Level], inner_only: bool, top: int = 0) -> NDArray[np.int64]:
    """Return the permutation putting the levels' nodes (concatenated) in depth-first order.

    ``levels[i]`` holds the nodes at depth ``top + i``. A node's first descendant leaf
    has the node's code padded to depth 16; sorting on ``(padded code, depth)`` puts
    every node right before its subtree (pre-order).
    """
    sort_keys = []
    for depth, level in enumerate(levels, start=top):
        code = level.code[level.inner] if inner_only else level.code
        sort_keys.append((code << (3 * (DEPTH - depth))) << 5 | depth)
    order: NDArray[np.int64] = np.argsort(np.concatenate(sort_keys))
    return order
