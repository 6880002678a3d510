"""The voxels of free segments, walked by a compiled loop (numba): the fast path of observe.

:func:`octolgp.observations.free_codes` finds every voxel a free segment passes through
from the segment's border crossings. Its numpy form computes, for every crossing of
every axis, where the segment is along the other axes (a few passes over arrays the
size of all crossings, and a careful decision near borders). This loop walks each
segment instead, Amanatides & Woo style: the next crossing of each axis is at
``t = (i - gap) / |Δu|`` (``i`` its number along the axis, computed directly, never
accumulated), the segment crosses the nearest one, on ties the last axis first, and
each voxel it enters is marked. The crossings' ``t`` are the numpy form's own, compared
the same way, so both give the same voxels (``tests/test_free_traversal.py``). Marks go
into a byte per cell of a dense box of keys (a state map: bits for entered far from and
near a segment's end, and any the caller adds), and :func:`marked_cells` lists the marked
cells a word of eight at a time, since most of a box's cells are never entered. Without
numba (:data:`AVAILABLE` false) the numpy form serves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray

FAR = 1
"""Bit of a dense state map: a segment entered the voxel far from its end."""

NEAR = 2
"""Bit of a dense state map: a segment entered the voxel near its end."""

CHORD_UNITS = 1024
"""Units of a chord share: a voxel's share of a segment's chord through a box is kept as
a whole number of 1/1024 (rounded to nearest, at least 1), exact when summed."""

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
    state: NDArray[np.uint8],
    out: IntArray,
    out_near: NDArray[np.bool_],
    key0: IntArray,
    sign: IntArray,
    box: int,
    weights: NDArray[np.int32],
    out_weight: IntArray,
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Mark (dense) or list (sparse) each segment's voxels; returns how many were listed.

    With ``box > 0`` each voxel entered also gets its share of the segment's chord
    through the box of ``box`` keys per axis holding it (:func:`walk_segments`): added
    to ``weights`` at its index (dense) or listed in ``out_weight`` (sparse).
    """
    n, dim = crossings.shape
    nxt = np.empty(dim, dtype=np.int64)
    t_next = np.empty(dim)  # each axis's next crossing (inf: none left), computed once
    coord = np.empty(dim, dtype=np.int64)
    weigh = box > 0
    shift = 0  # box is a power of two: floor division by it is a shift
    while (1 << shift) < box:
        shift += 1
    held = np.empty(3 * max(box, 1) + 1, dtype=np.int64)  # the current box's voxels
    t_held = np.empty(3 * max(box, 1) + 1)  # ... and where the segment entered each
    k = 0
    for s in range(n):  # one segment per iteration
        idx = start[s]
        near_from = enter_near[s]
        t = 0.0
        remaining = 0
        n_held = 0
        for a in range(dim):
            nxt[a] = 1
            if weigh:  # key0 is empty without shares
                coord[a] = key0[s, a]
            remaining += crossings[s, a]
            t_next[a] = (1 - gap[s, a]) / size[s, a] if crossings[s, a] >= 1 else np.inf
        while True:  # the voxel entered at t, then the next crossing
            near = t >= near_from
            if dense:
                state[idx] |= NEAR if near else FAR
            else:
                out[k] = idx
                out_near[k] = near
                k += 1
            if weigh:
                held[n_held] = idx if dense else k - 1
                t_held[n_held] = t
                n_held += 1
            t_out = 1.0  # where the segment leaves the current box
            best = -1
            if remaining:
                for a in range(dim):  # the nearest crossing; on a tie the last axis
                    if nxt[a] <= crossings[s, a] and (best < 0 or t_next[a] <= t):
                        best = a
                        t = t_next[a]
                if weigh:
                    c = coord[best] + sign[s, best]
                    t_out = t if c >> shift != coord[best] >> shift else -1.0
                    coord[best] = c
            if weigh and t_out >= 0.0:  # the box's voxels' shares of the chord through it
                total = t_out - t_held[0]
                for i in range(n_held):
                    t_end = t_held[i + 1] if i + 1 < n_held else t_out
                    share = (t_end - t_held[i]) / total if total > 0.0 else 1.0 / n_held
                    q = max(1, int(share * CHORD_UNITS + 0.5))  # floor: it is positive
                    if dense:
                        weights[held[i]] += q
                    else:
                        out_weight[held[i]] = q
                n_held = 0
            if remaining == 0:
                break
            idx += move[s, best]
            nxt[best] += 1
            remaining -= 1
            if nxt[best] <= crossings[s, best]:
                t_next[best] = (nxt[best] - gap[s, best]) / size[s, best]
    return k


def _nonzero(
    words: NDArray[np.uint64], state: NDArray[np.uint8], out: IntArray
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """List the nonzero cells of ``state`` (``words`` its view, 8 cells a word) ascending."""
    k = 0
    for w in range(words.size):  # most words of a sparse map are zero: skipped whole
        if words[w] != 0:
            for c in range(8 * w, 8 * w + 8):
                if state[c] != 0:
                    out[k] = c
                    k += 1
    return k


@functools.cache
def _compiled() -> tuple[Callable[..., int], Callable[..., int]]:
    """The loops compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    walk: Callable[..., int] = njit(cache=True, nogil=True)(_walk)
    nonzero: Callable[..., int] = njit(cache=True, nogil=True)(_nonzero)
    return walk, nonzero


def state_map(cells: int) -> NDArray[np.uint8]:
    """A zeroed dense state map of ``cells`` cells (padded to whole words of 8)."""
    return np.zeros(-(-cells // 8) * 8, dtype=np.uint8)


def marked_cells(state: NDArray[np.uint8], most: int) -> IntArray:
    """The cells of a state map (:func:`state_map`) with any bit set, ascending.

    ``np.flatnonzero(state)``, reading the map a word at a time; ``most`` bounds how
    many there are (the cells the walk visited).

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled traversal needs numba")
    out = np.empty(most, dtype=np.int64)
    written = _compiled()[1](state.view(np.uint64), state, out)
    return out[:written]


def walk_segments(
    start: IntArray,
    move: IntArray,
    crossings: IntArray,
    gap: FloatArray,
    size: FloatArray,
    enter_near: FloatArray,
    state: NDArray[np.uint8] | None,
    chord: tuple[IntArray, int, NDArray[np.int32] | None] | None = None,
) -> tuple[IntArray, NDArray[np.bool_], IntArray]:
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
    state : ndarray of uint8, optional
        A dense map over the indices: each voxel entered gets the bit :data:`FAR` or
        :data:`NEAR` (entered far from / near its segment's end) or-ed in, the other
        bits kept. ``None``: list the voxels instead.
    chord : tuple, optional
        ``(key0, box, weights)``: each segment's origin voxel key, shape (b, d), the edge
        of the boxes (keys ``box`` apart per axis, aligned to key 0; a power of two) and,
        with ``state``, a dense map of int32 over the indices. Each voxel entered gets its
        share of the segment's chord through the box holding it: the part of the chord
        inside the voxel over the chord's length (equal shares where the chord has none),
        in whole :data:`CHORD_UNITS` rounded to nearest and at least 1; added into
        ``weights`` (dense) or listed. ``None``: no shares.

    Returns
    -------
    index : ndarray of int64, shape (m,)
        Listed voxels (empty when marking), each segment's in the order entered.
    near : ndarray of bool, shape (m,)
        Whether each was entered near its segment's end.
    share : ndarray of int64, shape (m,)
        The listed voxels' chord shares in :data:`CHORD_UNITS` (empty without ``chord``
        or when marking).

    Raises
    ------
    RuntimeError
        If numba is not available.
    ValueError
        If ``box`` is not a power of two.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled traversal needs numba")
    c = np.ascontiguousarray
    dense = state is not None
    total = 0 if dense else int(crossings.sum()) + crossings.shape[0]
    out = np.empty(total, dtype=np.int64)
    out_near = np.empty(total, dtype=bool)
    none = np.zeros(0, dtype=np.uint8)
    key0 = sign = np.zeros((0, crossings.shape[1]), dtype=np.int64)
    box = 0
    weights = np.zeros(0, dtype=np.int32)
    out_weight = np.zeros(0, dtype=np.int64)
    if chord is not None:
        key0, box, dense_weights = chord
        if box < 1 or box & (box - 1):
            raise ValueError(f"the boxes' edge must be a power of two, got {box}")
        sign = np.sign(move)
        if dense_weights is not None:
            weights = dense_weights
        if not dense:
            out_weight = np.empty(total, dtype=np.int64)
    written = _compiled()[0](
        c(start, dtype=np.int64),
        c(move, dtype=np.int64),
        c(crossings, dtype=np.int64),
        c(gap, dtype=np.float64),
        c(size, dtype=np.float64),
        c(enter_near, dtype=np.float64),
        dense,
        none if state is None else state,
        out,
        out_near,
        c(key0, dtype=np.int64),
        c(sign, dtype=np.int64),
        int(box),
        weights,
        out_weight,
    )
    return out[:written], out_near[:written], out_weight[: written if chord else 0]
