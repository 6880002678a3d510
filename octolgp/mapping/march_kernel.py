"""Ray casts on the continuous field compiled ray by ray (numba): the fast path of raycast.

:func:`octolgp.mapping.planning.raycast` marches all rays of a block at once in numpy:
every step reads the ``2**d`` voxel centres around each sample from a table of the
voxels (:class:`~octolgp.mapping.voxel_table.VoxelTable`), one array operation per
stage, most of the time spent building index arrays and reading them back. This
kernel marches one ray at a time from the same table and with the same rules:

1. the origin: a ray starting where it stops (at or above the threshold, or in
   unknown space unless unknown space is free) ends at 0 (NaN where unknown and
   ``unknown="stop"``);
2. samples at ``k * step`` (the last exactly at ``max_range``), each a read of the
   interpolated field as :func:`~octolgp.mapping.field.occupancy_field` reads it
   (multilinear latent mean and variance, PLSC; the stored value before
   hyperparameters exist); where unknown space stops a ray, the voxels between two
   samples are walked too (Amanatides & Woo: the next face crossing of each axis at
   ``t = (i * resolution - o) / u``, computed directly, never accumulated), one read
   of each voxel entered at the middle of the ray's piece in it;
3. the first event (a sample at or above the threshold, or the middle of a piece in
   unknown space) and the sample before it bracket the answer, narrowed by the same
   number of halvings as the numpy path.

Samples lie where the numpy path's lie (its blocks of steps add the same multiples of
``step``, up to rounding); the voxels walked are sampled at the middles of pieces cut
at steps rather than at block ends, inside the same voxels. The two agree within the
bisection's width (``tests/test_planning_queries.py``).

This module imports numba: import it only where :data:`AVAILABLE` (it is imported on
the first ray cast, not with the package).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from types import MappingProxyType
from typing import Any

import numpy as np
from numba import njit

from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = ["MODES", "cast", "keyed_table"]

MODES = MappingProxyType({"stop": 0, "free": 1, "occupied": 2})
"""The kernel's code of each unknown mode (:data:`octolgp.mapping.planning.UNKNOWN_MODES`)."""

_jit: Callable[[Any], Any] = njit(cache=True, nogil=True)
_inline: Callable[[Any], Any] = njit(cache=True, nogil=True, inline="always")


@_inline
def _row(
    keys: IntArray,
    dense: bool,
    shape: IntArray,
    low: IntArray,
    packed: IntArray,
    limit: int,
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Row of the voxel with per-axis keys ``keys`` in the values (-1: out of range, or none).

    Dense: the cell of the box (whose values may be NaN); else the row of the sorted
    packed keys holding it.
    """
    d = keys.shape[0]
    for a in range(d):
        if keys[a] < 0 or keys[a] >= limit:
            return -1
    if dense:
        flat = 0
        for a in range(d):  # C order: the last axis varies fastest
            local = keys[a] - low[a]
            if local < 0 or local >= shape[a]:
                return -1
            flat = flat * shape[a] + local
        return flat
    want = 0
    for a in range(d):
        want |= keys[a] << (16 * a)
    lo, hi = 0, packed.shape[0]
    while lo < hi:  # binary search of the sorted packed keys
        mid = (lo + hi) >> 1
        if packed[mid] < want:
            lo = mid + 1
        else:
            hi = mid
    if lo < packed.shape[0] and packed[lo] == want:
        return lo
    return -1


@_inline
def _own_row(
    x: FloatArray,
    res: float,
    half: float,
    origin: float,
    keys: IntArray,
    dense: bool,
    shape: IntArray,
    low: IntArray,
    packed: IntArray,
    limit: int,
) -> int:  # pragma: no cover - compiled; tested through the compiled form
    """Row of the voxel holding ``x`` (-1: none, or ``x`` not addressable)."""
    for a in range(x.shape[0]):
        cell = math.floor(x[a] / res)
        if cell < -half or cell >= half:
            return -1
        keys[a] = math.floor((x[a] - origin) / res)
    row: int = _row(keys, dense, shape, low, packed, limit)
    return row


@_inline
def _known(
    x: FloatArray,
    table: tuple[bool, IntArray, IntArray, IntArray, FloatArray],
    field: tuple[bool, float, float, float, float, float],
    grid: tuple[float, float, float, int, int],
    keys: IntArray,
) -> bool:  # pragma: no cover - compiled; tested through the compiled form
    """Whether the voxel holding ``x`` holds a value."""
    dense, shape, low, packed, values = table
    res, half, origin, limit, _ = grid
    row = _own_row(x, res, half, origin, keys, dense, shape, low, packed, limit)
    return row >= 0 and not math.isnan(values[row, 0])


@_inline
def _event(
    x: FloatArray,
    table: tuple[bool, IntArray, IntArray, IntArray, FloatArray],
    field: tuple[bool, float, float, float, float, float],
    grid: tuple[float, float, float, int, int],
    stop_unknown: bool,
    keys: IntArray,
    frac: FloatArray,
    lower: IntArray,
    offsets: IntArray,
    cell: IntArray,
    corner_mean: FloatArray,
    corner_var: FloatArray,
) -> tuple[bool, bool]:  # pragma: no cover - compiled; tested through the compiled form
    """``(event, known)`` at ``x``: whether a ray stops there, whether its voxel holds a value.

    ``field``'s last item is the threshold (its probit where the field interpolates:
    P >= threshold where the PLSC argument reaches it); ``offsets``: the dense index's
    offsets of a cell's corners from its lower corner.
    """
    dense, shape, low, packed, values = table
    interp, prior, noise, alpha, beta, z_threshold = field
    res, half, origin, limit, key_half = grid
    row = _own_row(x, res, half, origin, keys, dense, shape, low, packed, limit)
    if row < 0 or math.isnan(values[row, 0]):
        return stop_unknown, False
    if not interp:
        return values[row, 0] >= z_threshold, True
    d = x.shape[0]
    same = True
    for a in range(d):  # the cell's lower corner and the point's place in the cell
        v = x[a] / res - 0.5
        base = math.floor(v)
        frac[a] = v - base
        lower[a] = int(base) + key_half
        same = same and lower[a] == cell[a]
    if not same:  # another cell: read its corners
        inside = dense
        flat = 0
        for a in range(d):
            cell[a] = lower[a]
            local = lower[a] - low[a]
            if local < 0 or local + 1 >= shape[a]:
                inside = False
            flat = flat * shape[a] + local
        for c in range(1 << d):  # the first axis slowest
            if inside:
                r = flat + offsets[c]
            else:
                for a in range(d):
                    keys[a] = lower[a] + ((c >> (d - 1 - a)) & 1)
                r = _row(keys, dense, shape, low, packed, limit)
            corner_mean[c], corner_var[c] = 0.0, prior
            if r >= 0 and not math.isnan(values[r, 0]):
                corner_mean[c], corner_var[c] = values[r, 0], values[r, 1]
    m_sum = 0.0
    v_sum = 0.0
    for c in range(1 << d):  # the corners' weights, in the same order
        w = 1.0
        for a in range(d):
            w *= frac[a] if (c >> (d - 1 - a)) & 1 == 1 else 1.0 - frac[a]
        m_sum += w * corner_mean[c]
        v_sum += w * corner_var[c]
    informed = min(max(1.0 - v_sum / prior, 0.0), 1.0)
    z = (alpha * m_sum + beta * informed) / math.sqrt(1.0 + alpha * alpha * (v_sum + noise))
    return z >= z_threshold, True


@_jit
def _cast(
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    table: tuple[bool, IntArray, IntArray, IntArray, FloatArray],
    field: tuple[bool, float, float, float, float, float],
    grid: tuple[float, float, float, int, int],
    mode: int,
    step: float,
    halvings: int,
    out: FloatArray,
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """Fill ``out`` (n,) with each ray's distance (see the module docstring)."""
    n, d = origins.shape
    stop_unknown = mode != 1
    dense, shape, low, packed, values = table
    res, half, _, limit, key_half = grid
    keys = np.empty(d, dtype=np.int64)
    frac = np.empty(d)
    lower = np.empty(d, dtype=np.int64)
    offsets = np.zeros(1 << d, dtype=np.int64)
    if dense:  # the dense index's offsets of a cell's corners from its lower corner
        for c in range(1 << d):
            stride = 1
            for a in range(d - 1, -1, -1):  # C order: the last axis varies fastest
                offsets[c] += ((c >> (d - 1 - a)) & 1) * stride
                stride *= shape[a]
    cell = np.full(d, -1, dtype=np.int64)  # no cell read yet
    corner_mean = np.empty(1 << d)
    corner_var = np.empty(1 << d)
    x = np.empty(d)
    plane = np.empty(d)
    t_next = np.empty(d)
    for r in range(n):  # one ray per iteration
        o, u, reach = origins[r], directions[r], max_range[r]
        ev, known = _event(
            o,
            table,
            field,
            grid,
            stop_unknown,
            keys,
            frac,
            lower,
            offsets,
            cell,
            corner_mean,
            corner_var,
        )
        if ev:
            out[r] = 0.0 if known or mode == 2 else np.nan
            continue
        out[r] = np.inf
        if reach <= 0.0:
            continue
        for a in range(d):  # the first face ahead along each axis
            if u[a] > 0:
                plane[a] = math.floor(o[a] / res) + 1.0
            elif u[a] < 0:
                plane[a] = math.ceil(o[a] / res) - 1.0
            else:  # never crossed: the origin's voxel along this axis
                plane[a] = math.floor(o[a] / res)
            t_next[a] = (plane[a] * res - o[a]) / u[a] if u[a] != 0 else np.inf
        k = 1
        before = 0.0
        first = np.inf
        while True:  # one step per iteration
            s = min(k * step, reach)
            if stop_unknown:  # the voxels between the samples, each read once
                cur = before
                while True:  # one piece of the ray in one voxel per iteration
                    tn = np.inf
                    for a in range(d):
                        tn = min(tn, t_next[a])
                    end = min(tn, s)
                    if end > cur:  # the piece's voxel: from the faces, no division
                        inside = True
                        for a in range(d):
                            vox = int(plane[a]) - (1 if u[a] > 0 else 0)
                            inside = inside and -half <= vox < half
                            keys[a] = vox + key_half
                        row = _row(keys, dense, shape, low, packed, limit) if inside else -1
                        if row < 0 or math.isnan(values[row, 0]):
                            first = 0.5 * (cur + end)
                            break
                    if tn >= s:
                        break
                    cur = tn
                    for a in range(d):  # every axis crossed here (a corner: several)
                        if t_next[a] == tn:
                            plane[a] += 1.0 if u[a] > 0 else -1.0
                            t_next[a] = (plane[a] * res - o[a]) / u[a]
            if first == np.inf:
                for a in range(d):
                    x[a] = o[a] + s * u[a]
                if _event(
                    x,
                    table,
                    field,
                    grid,
                    stop_unknown,
                    keys,
                    frac,
                    lower,
                    offsets,
                    cell,
                    corner_mean,
                    corner_var,
                )[0]:
                    first = s
            if first < np.inf or s >= reach:
                break
            before = s
            k += 1
        if first == np.inf:
            continue
        lo, hi = before, first
        for _ in range(halvings):  # bisection of the bracket
            mid = 0.5 * (lo + hi)
            for a in range(d):
                x[a] = o[a] + mid * u[a]
            if _event(
                x,
                table,
                field,
                grid,
                stop_unknown,
                keys,
                frac,
                lower,
                offsets,
                cell,
                corner_mean,
                corner_var,
            )[0]:
                hi = mid
            else:
                lo = mid
        for a in range(d):
            x[a] = o[a] + hi * u[a]
        known = _known(x, table, field, grid, keys)
        out[r] = hi if known or mode != 0 else np.nan


def keyed_table(
    low: IntArray, keys: IntArray, first: FloatArray, second: FloatArray
) -> tuple[bool, IntArray, IntArray, IntArray, np.ndarray]:
    """The kernel's table by key: each voxel's two values side by side, a row per key.

    Parameters
    ----------
    low : ndarray of int64, shape (d,)
    keys : ndarray of int64, shape (v,)
        Packed voxel keys, ascending (a :class:`~octolgp.mapping.voxel_table.VoxelTable`'s).
    first, second : ndarray of shape (v,)
        The values read: the latent mean (NaN where none) and variance, or the
        stored P twice.

    Returns
    -------
    tuple
        ``(False, shape, low, keys, values)`` (``shape`` unused), ``values`` float32
        where the values are exactly (a leaf's are), else float64.
    """
    pairs: np.ndarray = np.stack([first, second], axis=1)
    narrow = pairs.astype(np.float32)
    if np.array_equal(narrow, pairs, equal_nan=True):  # a leaf's float32 values, exactly
        pairs = narrow
    shape = np.zeros(low.shape[0], dtype=np.int64)
    return False, shape, np.ascontiguousarray(low), np.ascontiguousarray(keys), pairs


def cast(
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    table: tuple[bool, IntArray, IntArray, IntArray, FloatArray],
    field: tuple[bool, float, float, float, float, float],
    grid: tuple[float, float, float, int, int],
    mode: str,
    step: float,
    halvings: int,
) -> FloatArray:
    """Each ray's distance to its first event, compiled (see the module docstring).

    Parameters
    ----------
    origins, directions : ndarray of shape (n, d)
        Ray origins (metres, addressable) and unit directions.
    max_range : ndarray of shape (n,)
        Metres (>= 0).
    table : tuple
        ``(dense, shape, low, keys, values)`` covering every voxel the rays may
        read: dense, ``values`` holds a row per cell of the box of first key ``low``
        and ``shape`` (:func:`~octolgp.mapping.voxel_table.dense_box`: C order, NaN
        where no voxel); else a row per packed key of ``keys``
        (:func:`keyed_table`).
    field : tuple
        ``(interpolate, prior variance, noise variance, alpha, beta, threshold)``;
        ``interpolate`` false reads the stored P of each point's voxel; true
        interpolates the latent mean and variance, and the threshold is given as its
        probit (``scipy.special.ndtri``).
    grid : tuple
        ``(resolution, 2**(depth - 1) as float, origin of key 0, 2**depth,
        2**(depth - 1))``.
    mode : str
        One of :data:`MODES`.
    step : float
        Metres between samples.
    halvings : int
        Bisection steps on each ray's first bracket.

    Returns
    -------
    ndarray of shape (n,)
        As :func:`octolgp.mapping.planning.raycast`.
    """
    out = np.empty(origins.shape[0])
    c = np.ascontiguousarray
    _cast(
        c(origins, dtype=np.float64),
        c(directions, dtype=np.float64),
        c(max_range, dtype=np.float64),
        table,
        field,
        grid,
        MODES[mode],
        float(step),
        int(halvings),
        out,
    )
    return out
