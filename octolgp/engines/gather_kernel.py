"""Compiled loops of the lattice engine's gather (numba): the halo pairs and the evidence rule.

A step's gather (:func:`octolgp.engines.lattice.gather_observations`) turns each observed
voxel into one copy per leaf whose halo box holds it, then advances each voxel's counts by
the scans' observations (:func:`octolgp.observations.advance`). Their numpy forms make a
dozen passes over arrays the size of every (voxel, leaf) pair, and for a scan that touches
a few hundred leaves the passes' fixed costs dominate. These loops make one pass each,
give the same arrays in the same order (``tests/test_gather_kernel.py``), and serve where
numba is installed (:data:`AVAILABLE`); the numpy forms serve otherwise. The stored
counts themselves are read and written in the leaves' own buffers
(:mod:`octolgp.engines.leaf_buffers`).
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


def _pair_masks(
    cols: IntArray, shift: int, halo: int, n_leaf: int, mask: NDArray[np.uint8], cursor: IntArray
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """Each voxel's offsets whose leaf holds it, as bits of ``mask``; counts into ``cursor``.

    Offset ``o`` (``itertools.product((0, 1), repeat=dim)`` order) takes the upper leaf
    along the axes whose bit is set; ``cursor[o + 1]`` gains one per voxel it holds. The
    leaf's edge is ``1 << shift`` voxels (floor division by it is an arithmetic shift).
    """
    dim, n = cols.shape
    n_off = 1 << dim
    for v in range(n):
        ok_lo = 0
        ok_hi = 0
        for a in range(dim):
            c = cols[a, v]
            q = (c - halo) >> shift  # the lower leaf along the axis
            bit = 1 << (dim - 1 - a)
            if q >= 0 and q < n_leaf:
                ok_lo |= bit
            if ((c + halo) >> shift) > q and q + 1 < n_leaf:
                ok_hi |= bit
        m = 0
        for o in range(n_off):
            if not (o & ~ok_hi or (o ^ (n_off - 1)) & ~ok_lo):  # the offset's leaf holds it
                m |= 1 << o
                cursor[o + 1] += 1
        mask[v] = m


def _pair_list(
    cols: IntArray,
    shift: int,
    halo: int,
    mask: NDArray[np.uint8],
    origin: IntArray,
    stride: IntArray,
    cursor: IntArray,
    voxel: IntArray,
    leaf_key: IntArray,
    flat: IntArray,
    cell: IntArray,
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """List the pairs of :func:`_pair_masks`' offsets, each at ``cursor[o]`` (advanced).

    Per voxel the lower leaf's key, cell and flat index are worked out once per axis;
    the upper leaf along an axis is one key step and one cell stride on, and ``side``
    voxels lower in its halo box.
    """
    dim, n = cols.shape
    side = 1 << shift
    box = side + 2 * halo
    n_off = 1 << dim
    for v in range(n):
        m = mask[v]
        if m == 0:
            continue
        packed0 = 0
        cell0 = 0
        flat0 = 0
        scale = 1
        for a in range(dim):  # the lower leaf along every axis
            c = cols[a, v]
            q = (c - halo) >> shift
            packed0 += q << (KEY_BITS * a)  # a sum: q may be -1 where only the upper holds it
            cell0 += (q - origin[a]) * stride[a]
            flat0 += (c - (q * side - halo)) * scale
            scale *= box
        for o in range(n_off):
            if not (m >> o) & 1:
                continue
            k = cursor[o]
            cursor[o] += 1
            packed = packed0
            at_cell = cell0
            at_flat = flat0
            scale = 1
            for a in range(dim):
                if (o >> (dim - 1 - a)) & 1:  # the upper leaf along the axis
                    packed += 1 << (KEY_BITS * a)
                    at_cell += stride[a]
                    at_flat -= side * scale
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


def _leaf_flags(
    unit: IntArray,
    inverse: IntArray,
    effective: NDArray[np.bool_],
    stored: NDArray[np.bool_],
    d_h: NDArray[np.bool_],
    d_f: NDArray[np.bool_],
    chord_flag: NDArray[np.uint8],
    refit: NDArray[np.bool_],
    new_counts: NDArray[np.bool_],
    moved: NDArray[np.bool_],
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """The leaves whose GP input or stored evidence moves, from their pairs' units."""
    gained = 0
    for i in range(unit.size):
        u = unit[i]
        j = inverse[i]
        if effective[u]:
            refit[j] = True
        if stored[u]:
            new_counts[j] = True
        if chord_flag[u] & 1:
            refit[j] = True
            new_counts[j] = True
            moved[i] = True
        elif chord_flag[u] & 2:
            new_counts[j] = True
        gained += d_h[u] + d_f[u]
    return gained


def _chord_rule(
    w0: IntArray,
    chord: IntArray,
    strong_chord: IntArray,
    tail_chord: IntArray,
    obs_hits: IntArray,
    clear_scans: int,
    hits0: IntArray,
    frees0: IntArray,
    free0: IntArray,
    free1: IntArray,
    w1: IntArray,
    flag: NDArray[np.uint8],
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """The rule of :func:`octolgp.observations.advance_chord` per voxel, then what moved.

    ``flag``: bit 0 where the GP input moved (the sum of a voxel with a positive
    effective free count), bit 1 where the stored sum did.
    """
    looks = chord.shape[1]
    for v in range(w0.size):
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


@functools.cache
def _compiled() -> tuple[
    tuple[Callable[..., None], Callable[..., None]],
    Callable[..., None],
    Callable[..., int],
    Callable[..., None],
]:
    """The loops compiled by numba (cached on disk beside the module after the first run)."""
    from numba import njit

    masks: Callable[..., None] = njit(cache=True, nogil=True)(_pair_masks)
    listing: Callable[..., None] = njit(cache=True, nogil=True)(_pair_list)
    rule: Callable[..., None] = njit(cache=True, nogil=True)(_advance)
    flags: Callable[..., int] = njit(cache=True, nogil=True)(_leaf_flags)
    chord: Callable[..., None] = njit(cache=True, nogil=True)(_chord_rule)
    return (masks, listing), rule, flags, chord


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
    masks, listing = _compiled()[0]
    shift = side.bit_length() - 1
    cursor = np.zeros((1 << d) + 1, dtype=np.int64)
    mask = np.empty(keys.shape[0], dtype=np.uint8)
    masks(cols, shift, halo, n_leaf, mask, cursor)
    cursor = np.cumsum(cursor)
    n = int(cursor[-1])
    out = [np.empty(n, dtype=np.int64) for _ in range(4)]
    listing(cols, shift, halo, mask, at, stride, cursor, *out)
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


def leaf_flags(
    unit: IntArray,
    inverse: IntArray,
    state: tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]],
    chord_flag: NDArray[np.uint8] | None,
    n_touched: int,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], int, NDArray[np.bool_] | None]:
    """Which leaves change, from what changes per unit, in one pass over the pairs.

    Parameters
    ----------
    unit, inverse : ndarray of int64, shape (p,)
        Per (voxel, leaf) pair: its unit (the voxel whose state it shares) and its leaf
        among the touched ones.
    state : tuple of ndarray of bool, shape (units,) each
        Per unit: what its leaf GP sees moved (``effective``); its stored counts moved
        (``stored``); its effective return / free count moved (``d_h``, ``d_f``).
    chord_flag : ndarray of uint8, shape (units,), or None
        :func:`chord_rule`'s flags (``None``: no sums kept).
    n_touched : int

    Returns
    -------
    refit, new_counts : ndarray of bool, shape (n_touched,)
        The leaves holding a pair whose GP input / stored evidence moved.
    gained : int
        Pairs whose effective return count moved plus those whose free count did.
    moved : ndarray of bool, shape (p,), or None
        The pairs whose summed chord shares, as the GP sees them, moved (``None``
        without ``chord_flag``).

    Raises
    ------
    RuntimeError
        If numba is not available.
    """
    if not AVAILABLE:
        raise RuntimeError("the compiled gather needs numba")
    effective, stored, d_h, d_f = state
    refit = np.zeros(n_touched, dtype=bool)
    new_counts = np.zeros(n_touched, dtype=bool)
    moved = np.zeros(unit.size, dtype=bool)
    flag = np.zeros(effective.size, dtype=np.uint8) if chord_flag is None else chord_flag
    flags = _compiled()[2]
    gained = flags(unit, inverse, effective, stored, d_h, d_f, flag, refit, new_counts, moved)
    return refit, new_counts, int(gained), None if chord_flag is None else moved


def chord_rule(
    obs: VoxelObservations,
    w0: IntArray,
    counts0: tuple[NDArray[np.integer], NDArray[np.integer]],
    free01: tuple[NDArray[np.integer], NDArray[np.integer]],
) -> tuple[IntArray, NDArray[np.uint8]]:
    """Advance each voxel's summed chord shares once (:func:`~octolgp.observations.advance_chord`).

    Parameters
    ----------
    obs : VoxelObservations
        The step's observations, with chord shares.
    w0 : ndarray of int64, shape (n,)
        Each voxel's stored sum before the step (``n = obs.n_voxels``).
    counts0 : tuple of ndarray of int, shape (n,) each
        Each voxel's stored return and free counts before the step (which looks its
        free count still counts).
    free01 : tuple of ndarray of int, shape (n,) each
        Each voxel's effective free count before and after the step: a sum is the GP's
        input where the count is positive.

    Returns
    -------
    w1 : ndarray of int64, shape (n,)
        The new sums.
    flag : ndarray of uint8, shape (n,)
        Bit 0 where the sum as the GP sees it moved, bit 1 where the stored sum did.

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
    w1 = np.zeros(n, dtype=np.int64)
    flag = np.zeros(n, dtype=np.uint8)
    _compiled()[3](
        c(w0, dtype=np.int64),
        np.asarray(obs.chord, dtype=np.int64),  # one scan's: columns of stride 0
        np.asarray(obs.strong_chord, dtype=np.int64),
        c(obs.tail_chord, dtype=np.int64),
        c(obs.hits, dtype=np.int64),
        int(obs.clear_scans),
        c(counts0[0], dtype=np.int64),
        c(counts0[1], dtype=np.int64),
        c(free01[0], dtype=np.int64),
        c(free01[1], dtype=np.int64),
        w1,
        flag,
    )
    return w1, flag
