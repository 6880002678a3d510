"""Compiled loops of the lattice engine's gather (numba): the halo pairs and the evidence rule.

A step's gather (:func:`octolgp.engines.lattice.gather_observations`) turns each observed
voxel into one copy per leaf whose halo box holds it, then advances each voxel's counts by
the scans' observations (:func:`octolgp.observations.advance`). Their numpy forms make a
dozen passes over arrays the size of every (voxel, leaf) pair, and for a scan that touches
a few hundred leaves the passes' fixed costs dominate. These loops make one pass each,
give the same arrays in the same order (``tests/test_gather_kernel.py``), and serve where
numba is installed (:data:`AVAILABLE`); the numpy forms serve otherwise.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from octolgp.geometry.keys import KEY_BITS
from octolgp.observations import CHORD_CAP, VoxelObservations, VoxelState

AVAILABLE = importlib.util.find_spec("numba") is not None
"""Whether the compiled loops can run (numba is installed; it is imported on first use)."""

IntArray = NDArray[np.int64]


def _pairs(
    cols: IntArray,
    shift: int,
    halo: int,
    n_leaf: int,
    origin: IntArray,
    stride: IntArray,
    cursor: IntArray,
    voxel: IntArray,
    leaf_key: IntArray,
    flat: IntArray,
    cell: IntArray,
    count_only: bool,
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """Count the (voxel, leaf) pairs per offset into ``cursor``, or list them from it.

    ``cursor[o]``: where the pairs of offset ``o`` (``itertools.product((0, 1),
    repeat=dim)`` order) start in the output; counting adds each offset's count to
    ``cursor[o + 1]``. The leaf's edge is ``1 << shift`` voxels (floor division by it is
    an arithmetic shift).
    """
    dim, n = cols.shape
    side = 1 << shift
    box = side + 2 * halo
    n_off = 1 << dim
    lower = np.empty(dim, dtype=np.int64)
    for v in range(n):
        ok_lo = 0
        ok_hi = 0
        for a in range(dim):
            c = cols[a, v]
            q = (c - halo) >> shift  # the lower leaf along the axis
            lower[a] = q
            if q >= 0 and q < n_leaf:
                ok_lo |= 1 << (dim - 1 - a)
            if ((c + halo) >> shift) > q and q + 1 < n_leaf:
                ok_hi |= 1 << (dim - 1 - a)
        for o in range(n_off):  # offset o takes the upper leaf where its bit is set
            if o & ~ok_hi or (o ^ (n_off - 1)) & ~ok_lo:  # a leaf that does not hold it
                continue
            if count_only:
                cursor[o + 1] += 1
                continue
            k = cursor[o]
            cursor[o] += 1
            packed = 0
            at_cell = 0
            at_flat = 0
            scale = 1
            for a in range(dim):
                leaf = lower[a] + ((o >> (dim - 1 - a)) & 1)
                packed |= leaf << (KEY_BITS * a)
                at_cell += (leaf - origin[a]) * stride[a]
                at_flat += (cols[a, v] - (leaf * side - halo)) * scale
                scale *= box
            voxel[k] = v
            leaf_key[k] = packed
            flat[k] = at_flat
            cell[k] = at_cell


def _advance(
    h0: IntArray,
    f0: IntArray,
    at: IntArray,
    obs_hits: IntArray,
    obs_frees: IntArray,
    clear_scans: int,
    restart_hits: IntArray,
    head_frees: IntArray,
    tail_frees: IntArray,
    strong_frees: IntArray,
    first_hit: np.ndarray,
    restart_hit: np.ndarray,
    cap: int,
    h_out: IntArray,
    f_out: IntArray,
    position: np.ndarray,
    replace: NDArray[np.bool_],
    drop: NDArray[np.bool_],
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """The evidence rule of :func:`octolgp.observations.advance`, one voxel copy at a time."""
    k = clear_scans
    dim = first_hit.shape[1]
    for i in range(h0.size):
        j = at[i]
        h_0 = h0[i]
        f_0 = f0[i]
        n_h = obs_hits[j]
        seen = n_h > 0
        take_first = False
        take_restart = False
        if k == 0:  # static: counts add, the first return stays
            h = min(h_0 + n_h, cap)
            f = min(f_0 + obs_frees[j], cap)
            rep = h_0 == 0 and seen
            take_first = rep
            dropped = False
        else:
            restart = restart_hits[j] > 0
            first_on = seen and not restart and (h_0 == 0 or f_0 + head_frees[j] >= k)
            if restart:
                h = restart_hits[j]
            elif first_on:
                h = n_h
            elif seen:
                h = h_0 + n_h
            else:
                h = h_0
            if seen:
                f = tail_frees[j]
            elif h_0 > 0:
                f = f_0 + strong_frees[j]
            else:
                f = f_0 + obs_frees[j]
            cleared = (seen or h_0 > 0) and f >= k
            h = 0 if cleared else min(h, cap)
            f = min(f, k)
            rep = (restart or first_on) and not cleared
            take_restart = restart and rep
            take_first = first_on and rep and not take_restart
            dropped = h_0 > 0 and (h == 0 or rep)
        h_out[i] = h
        f_out[i] = f
        replace[i] = rep
        drop[i] = dropped
        for a in range(dim):
            if take_restart:
                position[i, a] = restart_hit[j, a]
            elif take_first:
                position[i, a] = first_hit[j, a]
            else:
                position[i, a] = np.nan


def _scatter(
    unit: IntArray,
    at_h: IntArray,
    inverse: IntArray,
    n_halo: int,
    hits: IntArray,
    frees: IntArray,
    effective: NDArray[np.bool_],
    stored: NDArray[np.bool_],
    d_h: NDArray[np.bool_],
    d_f: NDArray[np.bool_],
    flat_counts: NDArray[np.uint8],
    refit: NDArray[np.bool_],
    new_counts: NDArray[np.bool_],
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Each pair's unit's new counts into the stacked counts; the leaves that change."""
    gained = 0
    for i in range(unit.size):
        u = unit[i]
        flat_counts[at_h[i]] = hits[u]
        flat_counts[at_h[i] + n_halo] = frees[u]
        if effective[u]:
            refit[inverse[i]] = True
        if stored[u]:
            new_counts[inverse[i]] = True
        gained += d_h[u] + d_f[u]
    return gained


def _unit_counts(
    voxel: IntArray,
    at_h: IntArray,
    n_halo: int,
    flat_counts: NDArray[np.uint8],
    h0: IntArray,
    f0: IntArray,
    seen: NDArray[np.bool_],
) -> bool:  # pragma: no cover - compiled; tested through the compiled form
    """Each voxel's counts from its pairs into ``h0``, ``f0``; False where copies differ."""
    for i in range(voxel.size):
        v = voxel[i]
        h = flat_counts[at_h[i]]
        f = flat_counts[at_h[i] + n_halo]
        if seen[v]:
            if h0[v] != h or f0[v] != f:
                return False
        else:
            seen[v] = True
            h0[v] = h
            f0[v] = f
    return True


def _chord_units(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    row: int,
    offset: int,
    flat_chord: NDArray[np.uint16],
    chord: IntArray,
    strong_chord: IntArray,
    tail_chord: IntArray,
    obs_hits: IntArray,
    clear_scans: int,
    hits0: IntArray,
    frees0: IntArray,
    free0: IntArray,
    free1: IntArray,
    w0: IntArray,
    seen: NDArray[np.bool_],
    refit: NDArray[np.bool_],
    new_counts: NDArray[np.bool_],
    moved: NDArray[np.bool_],
) -> bool:  # pragma: no cover - compiled; tested through the compiled form
    """Advance each voxel's summed chord shares once and write them to its pairs.

    False, and nothing written, where two copies of a voxel hold different sums.
    """
    for i in range(voxel.size):  # each voxel's sum, read once from its copies
        v = voxel[i]
        w = flat_chord[inverse[i] * row + offset + flat[i]]
        if seen[v]:
            if w0[v] != w:
                return False
        else:
            seen[v] = True
            w0[v] = w
    n = w0.size
    looks = chord.shape[1]
    w1 = np.empty(n, dtype=np.int64)
    flag = np.zeros(n, dtype=np.uint8)  # bit 0: the GP input moved, bit 1: the sum
    for v in range(n):  # the rule of advance_chord, then what moved
        if not seen[v]:
            continue
        before = w0[v]
        left = min(looks - frees0[v], looks)  # looks the free count still counts
        if clear_scans and obs_hits[v] > 0:
            w = tail_chord[v]
        elif left <= 0:
            w = before
        elif clear_scans and hits0[v] > 0:
            w = before + strong_chord[v, left - 1]
        else:
            w = before + chord[v, left - 1]
        w = min(w, CHORD_CAP)
        w1[v] = w
        if (w if free1[v] > 0 else 0) != (before if free0[v] > 0 else 0):
            flag[v] = 3
        elif w != before:
            flag[v] = 2
    for i in range(voxel.size):  # each pair's new sum; the leaves that change
        v = voxel[i]
        flat_chord[inverse[i] * row + offset + flat[i]] = w1[v]
        if flag[v] & 1:
            refit[inverse[i]] = True
            moved[i] = True
        if flag[v] & 2:
            new_counts[inverse[i]] = True
    return True


@functools.cache
def _compiled() -> tuple[
    Callable[..., None],
    Callable[..., None],
    Callable[..., int],
    Callable[..., bool],
    Callable[..., bool],
]:
    """The loops compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    pairs: Callable[..., None] = njit(cache=True, nogil=True)(_pairs)
    rule: Callable[..., None] = njit(cache=True, nogil=True)(_advance)
    scatter: Callable[..., int] = njit(cache=True, nogil=True)(_scatter)
    units: Callable[..., bool] = njit(cache=True, nogil=True)(_unit_counts)
    chord: Callable[..., bool] = njit(cache=True, nogil=True)(_chord_units)
    return pairs, rule, scatter, units, chord


def halo_pairs(
    keys: IntArray, side: int, halo: int, n_leaf: int
) -> tuple[IntArray, IntArray, IntArray, IntArray, tuple[int, ...], tuple[int, ...]]:
    """Every (voxel, leaf whose halo box holds it) pair, as the numpy form lists them.

    Parameters
    ----------
    keys : ndarray of int64, shape (n, d)
        Voxel keys.
    side, halo : int
        A leaf's edge (a power of two) and its halo, in voxels (``halo <= side``).
    n_leaf : int
        Leaves per axis of the tree.

    Returns
    -------
    voxel, leaf_key, flat, cell : ndarray of int64, shape (p,)
        Per pair: the voxel (row of ``keys``), the leaf's packed key, the voxel's flat
        index in the leaf's halo box (x fastest) and the leaf's cell in the box of
        leaf indices ``origin .. origin + extent``; grouped by the neighbour offset
        (``itertools.product((0, 1), repeat=d)`` order), voxels ascending in each.
    origin, extent : tuple of int, length d

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    if side & (side - 1) or side < 1:
        raise ValueError(f"a leaf's edge must be a power of two, got {side}")
    d = keys.shape[1]
    cols = np.ascontiguousarray(keys.T, dtype=np.int64)
    if keys.shape[0]:
        low, high = cols.min(axis=1), cols.max(axis=1)
        origin = tuple(int(c) for c in (low - halo) // side)
        extent = tuple(int(c) - o + 2 for c, o in zip((high - halo) // side, origin, strict=True))
    else:
        origin, extent = (0,) * d, (1,) * d
    stride = np.cumprod((1, *extent[:-1])).astype(np.int64)
    at = np.asarray(origin, dtype=np.int64)
    pairs = _compiled()[0]
    shift = side.bit_length() - 1
    cursor = np.zeros((1 << d) + 1, dtype=np.int64)
    none = np.zeros(0, dtype=np.int64)
    pairs(cols, shift, halo, n_leaf, at, stride, cursor, none, none, none, none, True)
    cursor = np.cumsum(cursor)
    n = int(cursor[-1])
    out = [np.empty(n, dtype=np.int64) for _ in range(4)]
    pairs(cols, shift, halo, n_leaf, at, stride, cursor, *out, False)
    return out[0], out[1], out[2], out[3], origin, extent


def advance(
    hits: IntArray, frees: IntArray, obs: VoxelObservations, at: IntArray, evidence_cap: int
) -> VoxelState:
    """:func:`octolgp.observations.advance`, compiled: the same state, array for array.

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    c = np.ascontiguousarray
    p, dim = hits.size, obs.first_hit.shape[1]
    h, f = np.empty(p, dtype=np.int64), np.empty(p, dtype=np.int64)
    position = np.empty((p, dim))
    replace, drop = np.empty(p, dtype=bool), np.empty(p, dtype=bool)
    rule = _compiled()[1]
    rule(
        c(hits, dtype=np.int64),
        c(frees, dtype=np.int64),
        c(at, dtype=np.int64),
        c(obs.hits, dtype=np.int64),
        c(obs.frees, dtype=np.int64),
        int(obs.clear_scans),
        c(obs.restart_hits, dtype=np.int64),
        c(obs.head_frees, dtype=np.int64),
        c(obs.tail_frees, dtype=np.int64),
        c(obs.strong_frees, dtype=np.int64),
        c(obs.first_hit, dtype=np.float64),
        c(obs.restart_hit, dtype=np.float64),
        int(evidence_cap),
        h,
        f,
        position,
        replace,
        drop,
    )
    return VoxelState(h, f, position, replace, drop)


def scatter_units(
    unit: IntArray,
    at_h: IntArray,
    inverse: IntArray,
    n_halo: int,
    state: VoxelState,
    effective: NDArray[np.bool_],
    stored: NDArray[np.bool_],
    d_h: NDArray[np.bool_],
    d_f: NDArray[np.bool_],
    flat_counts: NDArray[np.uint8],
    n_touched: int,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], int]:
    """Write each (voxel, leaf) pair's new counts; which leaves change, and the inputs gained.

    Parameters
    ----------
    unit, at_h, inverse : ndarray of int64, shape (p,)
        Per pair: its unit (the voxel whose state it shares), its return count's index
        in ``flat_counts`` (the free count's is ``n_halo`` further) and its leaf among
        the ``n_touched`` touched ones.
    n_halo : int
    state : VoxelState
        Per unit, the new counts.
    effective, stored, d_h, d_f : ndarray of bool, shape (units,)
        Per unit: what its leaf GP sees moved; its stored counts moved; its effective
        return / free count moved.
    flat_counts : ndarray of uint8
        The touched leaves' stacked counts, flat; written in place.
    n_touched : int

    Returns
    -------
    refit, new_counts : ndarray of bool, shape (n_touched,)
        The leaves holding a pair whose unit is ``effective`` / ``stored``.
    gained : int
        Pairs whose effective return count moved plus those whose free count did.

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    refit = np.zeros(n_touched, dtype=bool)
    new_counts = np.zeros(n_touched, dtype=bool)
    scatter = _compiled()[2]
    gained = scatter(
        unit,
        at_h,
        inverse,
        n_halo,
        state.hits,
        state.frees,
        effective,
        stored,
        d_h,
        d_f,
        flat_counts,
        refit,
        new_counts,
    )
    return refit, new_counts, int(gained)


def unit_counts(
    voxel: IntArray, at_h: IntArray, n_halo: int, flat_counts: NDArray[np.uint8], n: int
) -> tuple[IntArray, IntArray] | None:
    """Each observed voxel's stored counts, read once from its (voxel, leaf) copies.

    Parameters
    ----------
    voxel, at_h : ndarray of int64, shape (p,)
        Per pair: its voxel, in ``[0, n)``, and its return count's index in
        ``flat_counts`` (the free count's is ``n_halo`` further).
    n_halo : int
    flat_counts : ndarray of uint8
        The touched leaves' stacked counts, flat.
    n : int
        Observed voxels.

    Returns
    -------
    tuple of ndarray of int64, shape (n,), or None
        The return and free counts of each voxel (0 for a voxel without copies);
        ``None`` when two copies of a voxel differ (each copy is then a unit of its own).

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    h0 = np.zeros(n, dtype=np.int64)
    f0 = np.zeros(n, dtype=np.int64)
    seen = np.zeros(n, dtype=bool)
    agree = _compiled()[3](voxel, at_h, n_halo, flat_counts, h0, f0, seen)
    return (h0, f0) if agree else None


def chord_units(
    voxel: IntArray,
    inverse: IntArray,
    flat: IntArray,
    row: int,
    offset: int,
    flat_chord: NDArray[np.uint16],
    obs: VoxelObservations,
    counts0: tuple[NDArray[np.integer], NDArray[np.integer]],
    free01: tuple[NDArray[np.integer], NDArray[np.integer]],
    refit: NDArray[np.bool_],
    new_counts: NDArray[np.bool_],
) -> NDArray[np.bool_] | None:
    """Advance the summed chord shares once per voxel and write them to its copies.

    The chord part of :func:`octolgp.engines.lattice.gather_observations` where the
    copies of each voxel agree: each voxel's sum read once from its (voxel, leaf) pairs,
    advanced by :func:`octolgp.observations.advance_chord`, and written back to each
    pair.

    Parameters
    ----------
    voxel, inverse, flat : ndarray of int64, shape (p,)
        Per pair: its voxel, in ``[0, n)`` (``n = obs.n_voxels``), its leaf among the
        touched ones and its flat index in the leaf's halo box.
    row, offset : int
        The touched leaves' rows in ``flat_chord``, and where in a row the sums start:
        a pair's sum is at ``inverse * row + offset + flat``.
    flat_chord : ndarray of uint16
        The touched leaves' stacked rows, flat; written in place (only where the
        copies agree).
    obs : VoxelObservations
        The step's observations, with chord shares.
    counts0 : tuple of ndarray of int, shape (n,) each
        Each voxel's stored return and free counts before the step (which looks its
        free count still counts).
    free01 : tuple of ndarray of int, shape (n,) each
        Each voxel's effective free count before and after the step: a sum is the GP's
        input where the count is positive.
    refit, new_counts : ndarray of bool, shape (touched,)
        Set in place for the leaves holding a pair whose GP input / stored sum moved.

    Returns
    -------
    ndarray of bool, shape (p,), or None
        The pairs whose GP input moved; ``None`` (nothing written or set) when two
        copies of a voxel hold different sums.

    Raises
    ------
    RuntimeError
        If numba is not available.
    ValueError
        If ``obs`` holds no chord shares.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    if obs.chord is None or obs.strong_chord is None or obs.tail_chord is None:
        raise ValueError("the observations hold no chord shares")
    n = obs.n_voxels
    c = np.ascontiguousarray
    moved = np.zeros(voxel.size, dtype=bool)
    agree = _compiled()[4](
        voxel,
        inverse,
        flat,
        int(row),
        int(offset),
        flat_chord,
        np.asarray(obs.chord, dtype=np.int64),  # one scan's: columns of stride 0
        np.asarray(obs.strong_chord, dtype=np.int64),
        c(obs.tail_chord, dtype=np.int64),
        c(obs.hits, dtype=np.int64),
        int(obs.clear_scans),
        c(counts0[0], dtype=np.int64),
        c(counts0[1], dtype=np.int64),
        c(free01[0], dtype=np.int64),
        c(free01[1], dtype=np.int64),
        np.zeros(n, dtype=np.int64),
        np.zeros(n, dtype=bool),
        refit,
        new_counts,
        moved,
    )
    return moved if agree else None
