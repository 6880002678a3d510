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
cells a word of eight at a time, since most of a box's cells are never entered. For one
scan, :func:`read_marks` adds the returns' bit and reads every marked cell as a voxel (its
key, counts, chord shares and first return) in one pass over the list. Without numba
(:data:`AVAILABLE` false) the numpy form serves.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.scan import FloatArray

FAR = 1
"""Bit of a dense state map: a segment entered the voxel far from its end."""

NEAR = 2
"""Bit of a dense state map: a segment entered the voxel near its end."""

HIT = 4
"""Bit of a dense state map that :func:`read_marks` sets: a return in the voxel."""

CHORD_UNITS = 1024
"""Units of a chord share: a voxel's share of a segment's chord through a box is kept as
a whole number of 1/1024 (rounded to nearest, at least 1), exact when summed."""

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether the compiled walk can run (numba is installed; it is imported on first use)."""

IntArray = NDArray[np.int64]

_Reading = tuple[IntArray, IntArray, IntArray, IntArray, IntArray, IntArray, IntArray, FloatArray]
"""The fields of :class:`MarkedVoxels`, in order, as the compiled reading returns them."""


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


def _byte_tables() -> tuple[IntArray, IntArray]:
    """For each 8-bit mask: the positions of its set bits, ascending (then zeros), and how many.

    int64, as the loop adds them to int64 cells (a narrower table costs a conversion each).
    """
    positions = np.zeros((256, 8), dtype=np.int64)
    counts = np.zeros(256, dtype=np.int64)
    for mask in range(256):  # 256 masks, once at import
        bits = [j for j in range(8) if mask >> j & 1]
        positions[mask, : len(bits)] = bits
        counts[mask] = len(bits)
    return positions, counts


_BYTE_CELLS, _BYTE_COUNT = _byte_tables()


def _nonzero(
    words: NDArray[np.uint64],
    out: IntArray,
    most: int,
    byte_cells: IntArray,
    byte_count: IntArray,
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """List the cells of the nonzero bytes of ``words`` ascending; -1 past ``most`` of them.

    A nonzero word's nonzero bytes become an 8-bit mask (a high bit per byte, gathered by
    one multiplication), whose cells the tables give: its 8 slots are written and as many
    as it has are kept, with no branch per cell. ``out`` has room for ``most + 8``.
    """
    low7 = np.uint64(0x7F7F7F7F7F7F7F7F)
    gather = np.uint64(0x0102040810204080)  # bit 8 j + 7 → bit 56 + j
    k = 0
    for w in range(words.size):  # most words of a sparse map are zero: skipped whole
        x = words[w]
        if x != 0:
            if k > most:
                return -1
            high = (((x & low7) + low7) | x) & ~low7  # each nonzero byte's high bit
            mask = np.int64(((high >> np.uint64(7)) * gather) >> np.uint64(56))
            for j in range(8):
                out[k + j] = 8 * w + byte_cells[mask, j]
            k += byte_count[mask]
    return k if k <= most else -1


def _read(
    cell: IntArray,
    state: NDArray[np.uint8],
    weights: NDArray[np.int32],
    low: IntArray,
    extent: IntArray,
    hit_cell: IntArray,
    hit_point: FloatArray,
) -> _Reading:  # pragma: no cover - compiled; tested through the compiled form
    """:func:`read_marks`' loops over the marked cells ``cell`` (ascending, up to 3 axes).

    Returns the fields of :class:`MarkedVoxels` in order, the shares empty where
    ``weights`` is. The first loop reads each cell's byte and decodes its key; the next
    ones each fill arrays from arrays of the listed cells, a store per element, which is
    what bounds them.
    """
    n, dim = cell.size, low.size
    keys = np.empty((n, dim), dtype=np.int64)
    mark = np.empty(n, dtype=np.uint8)
    e0 = extent[0]
    e1 = extent[1] if dim > 1 else 1
    x0 = x1 = x2 = 0  # the current cell's key in the box: cell 0's at first
    before = 0
    for i in range(n):  # cells ascend: a step shorter than a row carries at most once
        c = cell[i]
        mark[i] = state[c]
        step = c - before
        before = c
        if step < e0:
            x0 += step
            if x0 >= e0:
                x0 -= e0
                x1 += 1
                if x1 >= e1:
                    x1 -= e1
                    x2 += 1
        else:
            x1 = c // e0
            x0 = c - x1 * e0
            x2 = x1 // e1
            x1 -= x2 * e1
        keys[i, 0] = x0 + low[0]
        if dim > 1:
            keys[i, 1] = x1 + low[1]
        if dim > 2:
            keys[i, 2] = x2 + low[2]
    hits = np.empty(n, dtype=np.int64)
    frees = np.empty(n, dtype=np.int64)
    weak = np.empty(n, dtype=np.int64)
    strong = np.empty(n, dtype=np.int64)
    for i in range(n):  # weak: NEAR alone
        hit = np.int64((mark[i] & HIT) != 0)
        only_near = np.int64(mark[i] == NEAR)
        hits[i] = hit
        frees[i] = 1 - hit
        weak[i] = only_near
        strong[i] = 1 - hit - only_near
    m = n if weights.size else 0
    shares = np.empty(m, dtype=np.int64)
    strong_shares = np.empty(m, dtype=np.int64)
    for i in range(m):
        shares[i] = weights[cell[i]] * frees[i]
    for i in range(m):
        strong_shares[i] = shares[i] * strong[i]
    first_hit = np.empty((n, dim))
    flat = first_hit.ravel()
    for i in range(flat.size):
        flat[i] = np.nan
    for r in range(hit_cell.size - 1, -1, -1):  # the last written is the first given
        lo, hi = 0, n
        while lo < hi:  # the return's cell among the marked ones (it is marked)
            mid = (lo + hi) >> 1
            if cell[mid] < hit_cell[r]:
                lo = mid + 1
            else:
                hi = mid
        for a in range(dim):
            first_hit[lo, a] = hit_point[r, a]
    return keys, hits, frees, weak, strong, shares, strong_shares, first_hit


@functools.cache
def _compiled() -> tuple[Callable[..., int], Callable[..., int], Callable[..., _Reading]]:
    """The loops compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    walk: Callable[..., int] = njit(cache=True, nogil=True)(_walk)
    nonzero: Callable[..., int] = njit(cache=True, nogil=True)(_nonzero)
    read: Callable[..., _Reading] = njit(cache=True, nogil=True)(_read)
    return walk, nonzero, read


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
    ValueError
        If more than ``most`` cells are marked.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled traversal needs numba")
    out = np.empty(most + 8, dtype=np.int64)
    written = _compiled()[1](state.view(np.uint64), out, int(most), _BYTE_CELLS, _BYTE_COUNT)
    if written < 0:
        raise ValueError(f"the map holds more than {most} marked cells")
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


@dataclass(frozen=True)
class MarkedVoxels:
    """The marked cells of a state map over a box of keys, read as one scan's voxels.

    A cell is seen occupied where :data:`HIT` is set, else seen free; weakly free where
    only :data:`NEAR` is set (every segment through it entered it near its end).

    Attributes
    ----------
    keys : ndarray of int64, shape (n, d)
        The marked cells' keys, ascending by cell (the first axis fastest).
    hits : ndarray of int64, shape (n,)
        1 where the cell holds a return, else 0.
    frees : ndarray of int64, shape (n,)
        ``1 - hits``.
    weak : ndarray of int64, shape (n,)
        1 where the cell is seen free only near segments' ends, else 0.
    strong : ndarray of int64, shape (n,)
        ``frees - weak``.
    shares : ndarray of int64, shape (n,) or (0,)
        The cell's summed chord shares where it is seen free, else 0; empty without
        ``weights``.
    strong_shares : ndarray of int64, shape (n,) or (0,)
        ``shares`` where ``strong`` is 1, else 0; empty without ``weights``.
    first_hit : ndarray of shape (n, d)
        The first of the given returns in the cell; NaN where none is.
    """

    keys: IntArray
    hits: IntArray
    frees: IntArray
    weak: IntArray
    strong: IntArray
    shares: IntArray
    strong_shares: IntArray
    first_hit: FloatArray


def read_marks(
    state: NDArray[np.uint8],
    low: IntArray,
    extent: IntArray,
    hit_cell: IntArray,
    hit_point: FloatArray,
    most: int,
    weights: NDArray[np.int32] | None = None,
) -> MarkedVoxels:
    """Mark a scan's returns in its state map and read every marked cell as a voxel.

    The numpy form lists ``np.flatnonzero(state)``, then decodes, classifies and
    gathers with a pass over the listed cells per array and operation; these loops list
    the cells a word at a time (:func:`marked_cells`), decode each cell's key from the
    previous one's (no division but where a step skips a row), and fill each array in
    one pass.

    Parameters
    ----------
    state : ndarray of uint8
        A state map (:func:`state_map`) over the box of keys ``low`` to
        ``low + extent - 1``, the first axis fastest (cell ``(key - low) @ stride`` with
        strides ``1, extent[0], extent[0] * extent[1]``); :data:`HIT` is or-ed into the
        returns' cells.
    low, extent : ndarray of int64, shape (d,)
        The box's least key and its keys per axis, ``d`` at most 3.
    hit_cell : ndarray of int64, shape (h,)
        The returns' cells.
    hit_point : ndarray of shape (h, d)
        The returns, in the order whose first per cell ``first_hit`` keeps.
    most : int
        At least the marked cells once the returns are (a bound for the listing).
    weights : ndarray of int32, optional
        Summed chord shares per cell (:func:`walk_segments`' dense map); ``None``: none.

    Returns
    -------
    MarkedVoxels

    Raises
    ------
    RuntimeError
        If numba is not available.
    ValueError
        If more than ``most`` cells are marked.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled traversal needs numba")
    state[hit_cell] |= HIT
    cell = marked_cells(state, most)
    c = np.ascontiguousarray
    fields = _compiled()[2](
        cell,
        state,
        np.zeros(0, dtype=np.int32) if weights is None else weights,
        c(low, dtype=np.int64),
        c(extent, dtype=np.int64),
        c(hit_cell, dtype=np.int64),
        c(hit_point, dtype=np.float64),
    )
    return MarkedVoxels(*fields)
