"""The voxels of free segments, walked by a compiled loop (numba): the fast path of observe.

:func:`octolgp.observations.free_codes` finds every voxel a free segment passes through
from the segment's border crossings. Its numpy form computes, for every crossing of
every axis, where the segment is along the other axes (a few passes over arrays the
size of all crossings, and a careful decision near borders). This loop walks each
segment instead, Amanatides & Woo style: the next crossing of each axis is at
``t = (i - gap) / |Δu|`` (``i`` its number along the axis, computed directly, never
accumulated), the segment crosses the nearest one, on ties the last axis first, and
each voxel it enters is marked. The crossings' ``t`` are the numpy form's own, compared
the same way, so both give the same voxels (``tests/test_free_traversal.py``). Without
numba (:data:`AVAILABLE` false) the numpy form serves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether the compiled walk can run (numba is installed; it is imported on first use)."""

IntArray = NDArray[np.int64]


def _walk(
    start: IntArray,
    move: IntArray,
    crossings: IntArray,
    gap: FloatArray,
    size: FloatArray,
    enter_near: FloatArray,
    dense: bool,
    far_map: NDArray[np.bool_],
    near_map: NDArray[np.bool_],
    out: IntArray,
    out_near: NDArray[np.bool_],
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Mark (dense) or list (sparse) each segment's voxels; returns how many were listed."""
    n, dim = crossings.shape
    nxt = np.empty(dim, dtype=np.int64)
    t_next = np.empty(dim)  # each axis's next crossing (inf: none left), computed once
    k = 0
    for s in range(n):  # one segment per iteration
        idx = start[s]
        near_from = enter_near[s]
        t = 0.0
        remaining = 0
        for a in range(dim):
            nxt[a] = 1
            remaining += crossings[s, a]
            t_next[a] = (1 - gap[s, a]) / size[s, a] if crossings[s, a] >= 1 else np.inf
        while True:  # the voxel entered at t, then the next crossing
            near = t >= near_from
            if dense:
                if near:
                    near_map[idx] = True
                else:
                    far_map[idx] = True
            else:
                out[k] = idx
                out_near[k] = near
                k += 1
            if remaining == 0:
                break
            best = -1
            for a in range(dim):  # the nearest crossing; on a tie the last axis
                if nxt[a] <= crossings[s, a] and (best < 0 or t_next[a] <= t):
                    best = a
                    t = t_next[a]
            idx += move[s, best]
            nxt[best] += 1
            remaining -= 1
            if nxt[best] <= crossings[s, best]:
                t_next[best] = (nxt[best] - gap[s, best]) / size[s, best]
    return k


@functools.cache
def _compiled() -> Callable[..., int]:
    """The walk compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    out: Callable[..., int] = njit(cache=True, nogil=True)(_walk)
    return out


def walk_segments(
    start: IntArray,
    move: IntArray,
    crossings: IntArray,
    gap: FloatArray,
    size: FloatArray,
    enter_near: FloatArray,
    far_map: NDArray[np.bool_] | None,
    near_map: NDArray[np.bool_] | None,
) -> tuple[IntArray, NDArray[np.bool_]]:
    """Walk free segments through their voxels, marking or listing each voxel entered.

    Parameters
    ----------
    start : ndarray of int64, shape (b,)
        Each segment's origin voxel as an index (into the maps, or a code).
    move : ndarray of int64, shape (b, d)
        The index change of one step along each axis in the segment's direction.
    crossings : ndarray of int64, shape (b, d)
        Voxel borders crossed along each axis.
    gap, size : ndarray of shape (b, d)
        Per axis: the origin's distance to its first border and ``|Δu|``, in voxels;
        crossing ``i`` of an axis is at ``t = (i - gap) / size``.
    enter_near : ndarray of shape (b,)
        A voxel entered at ``t >= enter_near`` is near the segment's end (``inf``:
        none is).
    far_map, near_map : ndarray of bool, optional
        Dense maps over the indices: set where a voxel is entered far from / near the
        segment's end. ``far_map`` ``None``: list the voxels instead; ``near_map`` may
        be ``None`` when no voxel is near.

    Returns
    -------
    index : ndarray of int64, shape (m,)
        Listed voxels (empty when marking), each segment's in the order entered.
    near : ndarray of bool, shape (m,)
        Whether each was entered near its segment's end.

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled traversal needs numba")
    c = np.ascontiguousarray
    dense = far_map is not None
    total = 0 if dense else int(crossings.sum()) + crossings.shape[0]
    out = np.empty(total, dtype=np.int64)
    out_near = np.empty(total, dtype=bool)
    none = np.zeros(0, dtype=bool)
    written = _compiled()(
        c(start, dtype=np.int64),
        c(move, dtype=np.int64),
        c(crossings, dtype=np.int64),
        c(gap, dtype=np.float64),
        c(size, dtype=np.float64),
        c(enter_near, dtype=np.float64),
        dense,
        none if far_map is None else far_map,
        none if near_map is None else near_map,
        out,
        out_near,
    )
    return out[:written], out_near[:written]
