"""Ray casts and segment checks on the continuous occupancy field, for planners.

:func:`raycast` finds, per ray, the first point where P(occupied) reaches a
threshold: it marches the field (:func:`~octolgp.mapping.field.occupancy_field`, the
interpolated read of :meth:`~octolgp.mapping.query.MapReads.occupancy`) at steps of
at most half a voxel, all rays of a block at once, then refines the first bracket
of each ray by bisection on the same field. :func:`segment_free` is a ray cast
along each segment.

What unknown space (a voxel no leaf holds a value for; it reads 0.5) does to a ray
is a choice, :data:`UNKNOWN_MODES`:

- ``"stop"``: the ray ends there without a hit, and its distance is NaN;
- ``"free"``: the ray passes through, as through free space;
- ``"occupied"``: the ray hits where it enters unknown space (a planner's
  conservative answer).

Where numba is installed (:data:`COMPILED`) and the rays read a table of the voxels,
the march runs compiled, one ray at a time (:mod:`octolgp.mapping.march_kernel`),
with the same samples and rules; its answers agree with the numpy march within the
bisection's width.

Every function here only reads the map.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
from scipy.special import ndtri

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range
from octolgp.mapping.field import QUERY_CHUNK, ReadableMap, Reader, held_at, occupancy_field
from octolgp.mapping.voxel_table import dense_box, table_pays, voxel_table
from octolgp.scan import FloatArray

__all__ = ["MAX_BLOCK_STEPS", "UNKNOWN_MODES", "raycast", "segment_free"]

UNKNOWN_MODES = ("stop", "free", "occupied")
"""What a ray does in unknown space: ends without a hit (NaN), passes, or hits."""

MAX_BLOCK_STEPS = 256
"""Most steps a ray marches in one block: rays that hit early stop costing early."""

RAY_CHUNK = 1 << 14
"""Rays marched together: the temporaries of a block stay tens of megabytes."""

BISECTION_TOL = 1e-3
"""Width, in voxels, that bisection narrows each first bracket to."""

COMPILED = importlib.util.find_spec("numba") is not None
"""Whether ray casts that read a voxel table march compiled (numba is installed)."""


def _events(
    m: ReadableMap, X: FloatArray, threshold: float, stop_unknown: bool, read: Reader | None
) -> tuple[np.ndarray, np.ndarray]:
    """Where a ray stops at ``X``: ``(event, known)``, both bool of shape (q,)."""
    prob, known = occupancy_field(m, X, read)
    event = np.where(known, prob >= threshold, stop_unknown)
    return event, known


def raycast(
    m: ReadableMap,
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    threshold: float,
    unknown: str,
    step: float,
) -> FloatArray:
    """Distance along each ray to the first point with P(occupied) >= ``threshold``.

    Parameters
    ----------
    m : ReadableMap
    origins : ndarray of shape (n, d)
        Ray origins, metres, world frame (addressable).
    directions : ndarray of shape (n, d)
        Unit directions.
    max_range : ndarray of shape (n,)
        Metres (>= 0) each ray is cast; the last sample lies exactly there.
    threshold : float
        In (0, 1).
    unknown : str
        One of :data:`UNKNOWN_MODES`.
    step : float
        Marching step, metres (half a voxel or less finds every crossing that stays
        above the threshold for longer than a step).

    Returns
    -------
    ndarray of shape (n,)
        The distance, metres, within ``BISECTION_TOL`` voxels of the crossing (0
        when the origin is at or above the threshold); ``inf`` where the field stays
        below the threshold up to ``max_range``; NaN where the ray enters unknown
        space first and ``unknown == "stop"``.
    """
    out = np.full(origins.shape[0], np.inf)
    if origins.shape[0] == 0:
        return out
    box = _table_box(m, origins, directions, max_range, step)
    if COMPILED and box is not None:
        return _compiled_cast(m, box, origins, directions, max_range, threshold, unknown, step)
    read = None if box is None else voxel_table(m, *box)
    for lo in range(0, origins.shape[0], RAY_CHUNK):  # bounded temporaries, chunk by chunk
        at = slice(lo, lo + RAY_CHUNK)
        rays = (origins[at], directions[at], max_range[at])
        out[at] = _march(m, *rays, threshold, unknown, step, read)
    return out


def _halvings(step: float, resolution: float) -> int:
    """Bisection steps that narrow a bracket of ``step`` to ``BISECTION_TOL`` voxels."""
    width = BISECTION_TOL * resolution
    return max(1, math.ceil(math.log2(max(step, width) / width)))


def _compiled_cast(
    m: ReadableMap,
    box: tuple[FloatArray, FloatArray],
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    threshold: float,
    unknown: str,
    step: float,
) -> FloatArray:
    """:func:`raycast` by the compiled march (:mod:`octolgp.mapping.march_kernel`).

    The voxels of the box are read into a dense array of their box where they fill
    enough of it (:func:`~octolgp.mapping.voxel_table.dense_box`), else into a table
    by key.
    """
    from octolgp.mapping import march_kernel  # imports numba: on the first ray cast

    depth, res = m.config.tree_depth, m.config.resolution
    hp = m.hyperparameters
    fields = ("prob", "prob") if hp is None else ("mean", "var")
    dense = dense_box(m, *box, fields)
    if dense is not None:
        low, shape, values = dense
        tables = (True, shape, low, np.zeros(0, dtype=np.int64), values)
    else:
        table = voxel_table(m, *box)
        tables = march_kernel.keyed_table(
            table.low, table.keys, getattr(table, fields[0]), getattr(table, fields[1])
        )
    if hp is None:  # the stored value of each point's voxel
        field = (False, 1.0, 0.0, 1.0, 0.0, threshold)
    else:
        field = (
            True,
            float(hp.signal_variance),
            float(hp.noise_variance),
            float(hp.alpha),
            float(hp.beta),
            float(ndtri(threshold)),  # P >= threshold where the PLSC argument reaches this
        )
    half = 1 << (depth - 1)
    grid = (res, float(half), -float(half) * res, 1 << depth, half)
    return march_kernel.cast(
        origins, directions, max_range, tables, field, grid, unknown, step, _halvings(step, res)
    )


def _march(
    m: ReadableMap,
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    threshold: float,
    unknown: str,
    step: float,
    read: Reader | None,
) -> FloatArray:
    """:func:`raycast` of one chunk of rays, reading the voxels through ``read``."""
    n = origins.shape[0]
    stop_unknown = unknown != "free"
    out = np.full(n, np.inf)
    # the origins first: a ray starting in an obstacle (or unknown space) stops at 0
    event, known = _events(m, origins, threshold, stop_unknown, read)
    out[event] = np.where(known[event] | (unknown == "occupied"), 0.0, np.nan)
    active = np.flatnonzero(~event & (max_range > 0))
    done = np.zeros(0, dtype=np.int64)
    s0 = np.zeros(n)  # distance of each active ray's last sample below the threshold
    lo_s, hi_s = np.zeros(n), np.zeros(n)
    res = m.config.resolution
    while active.size:  # one block of steps for every ray still marching
        steps = int(np.clip(QUERY_CHUNK // active.size, 4, MAX_BLOCK_STEPS))
        o, u, start = origins[active], directions[active], s0[active]
        end = np.minimum(start + steps * step, max_range[active])
        ticks = np.minimum(start[:, None] + step * np.arange(1, steps + 1), end[:, None])
        ev = _events(m, _along(o, u, ticks), threshold, stop_unknown, read)[0]
        ev = ev.reshape(ticks.shape)
        first = np.where(ev.any(axis=1), ticks[np.arange(ticks.shape[0]), np.argmax(ev, 1)], np.inf)
        if stop_unknown:  # a sample in every voxel passed: unknown ones are never skipped
            mids = voxel_samples(o, u, start, end, res)
            unknown_here = ~held_at(m, _along(o, u, mids), read).reshape(mids.shape)
            first_unknown = np.where(unknown_here, mids, np.inf).min(axis=1)
            first = np.minimum(first, first_unknown)
        hit = np.isfinite(first)
        below = np.where(ticks < first[:, None], ticks, -np.inf).max(axis=1)
        lo_s[active[hit]] = np.maximum(below, start)[hit]
        hi_s[active[hit]] = first[hit]
        done = np.concatenate([done, active[hit]])
        s0[active] = end
        active = active[~hit & (end < max_range[active])]
    if done.size:
        rays = (origins[done], directions[done], lo_s[done], hi_s[done])
        out[done] = _bisect(m, *rays, threshold, unknown, step, read)
    return out


def _table_box(
    m: ReadableMap,
    origins: FloatArray,
    directions: FloatArray,
    max_range: FloatArray,
    step: float,
) -> tuple[FloatArray, FloatArray] | None:
    """The box of the voxels the rays may read, where reading it at once pays (else ``None``)."""
    if origins.shape[0] == 0:
        return None
    res = m.config.resolution
    low, high = addressable_range(res, m.config.tree_depth)
    ends = origins + max_range[:, None] * directions
    lo = np.maximum(np.minimum(origins, ends).min(axis=0) - res, low)
    hi = np.minimum(np.maximum(origins, ends).max(axis=0) + res, high - 1e-6 * res)
    corners = (1 << origins.shape[1]) + 4  # reads per step: the cell's corners, its own, voxels
    samples = float(np.sum(max_range)) / step
    if not table_pays(m, lo, hi, samples * corners):
        return None
    return lo, hi


def _along(origins: FloatArray, directions: FloatArray, s: FloatArray) -> FloatArray:
    """Points ``(a * k, d)`` at distances ``s`` ``(a, k)`` along rays ``(a, d)``."""
    pts = origins[:, None, :] + s[:, :, None] * directions[:, None, :]
    return np.asarray(pts.reshape(-1, origins.shape[1]))


def voxel_samples(
    origins: FloatArray,
    directions: FloatArray,
    start: FloatArray,
    end: FloatArray,
    resolution: float,
) -> FloatArray:
    """Distances ``(a, k)``: one in every voxel each ray passes through on ``(start, end]``.

    The midpoints of consecutive crossings of voxel faces (planes ``x_j = i *
    resolution``), with ``start`` and ``end`` among them, and ``end`` itself; a voxel
    the ray only touches at a corner or an edge (length 0) has none. Rows are padded
    with ``end``.
    """
    planes = math.ceil(float(np.max(end - start, initial=0.0)) / resolution) + 1
    k = np.arange(planes)[None, :]
    crossings = [start[:, None], end[:, None]]
    for j in range(origins.shape[1]):  # one axis at a time (2 or 3)
        o, u = origins[:, j : j + 1], directions[:, j : j + 1]
        x = (o + start[:, None] * u) / resolution  # in voxels
        ahead = np.where(u > 0, np.floor(x) + 1 + k, np.ceil(x) - 1 - k)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ahead * resolution - o) / u
        crossings.append(
            np.where((u != 0) & (t > start[:, None]), np.minimum(t, end[:, None]), end[:, None])
        )
    bp = np.sort(np.concatenate(crossings, axis=1), axis=1)
    return np.concatenate([0.5 * (bp[:, :-1] + bp[:, 1:]), bp[:, -1:]], axis=1)


def _bisect(
    m: ReadableMap,
    origins: FloatArray,
    directions: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    threshold: float,
    unknown: str,
    step: float,
    read: Reader | None,
) -> FloatArray:
    """Narrow brackets ``[lo, hi]`` (no event at ``lo``, one at ``hi``) to the event.

    Returns ``hi`` once the brackets are ``BISECTION_TOL`` voxels wide, or NaN where
    the event is unknown space and ``unknown == "stop"``.
    """
    stop_unknown = unknown != "free"
    for _ in range(_halvings(step, m.config.resolution)):  # ~9 halvings
        mid = 0.5 * (lo + hi)
        ev, _ = _events(m, origins + mid[:, None] * directions, threshold, stop_unknown, read)
        hi = np.where(ev, mid, hi)
        lo = np.where(ev, lo, mid)
    _, known = _events(m, origins + hi[:, None] * directions, threshold, stop_unknown, read)
    if unknown == "stop":
        return np.where(known, hi, np.nan)
    return hi


def segment_free(
    m: ReadableMap,
    a: FloatArray,
    b: FloatArray,
    threshold: float,
    unknown_is_free: bool,
    step: float,
) -> np.ndarray:
    """Whether each segment ``a -> b`` stays below ``threshold`` along its whole length.

    Parameters
    ----------
    m : ReadableMap
    a, b : ndarray of shape (n, d)
        Segment ends, metres, world frame (addressable).
    threshold : float
        In (0, 1).
    unknown_is_free : bool
        ``False``: a segment touching unknown space is not free.
    step : float
        Sampling step, metres (as :func:`raycast`).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    delta = b - a
    length = np.linalg.norm(delta, axis=1)
    unit = np.zeros_like(delta)
    unit[:, 0] = 1.0  # any direction serves a segment of length 0
    moving = length > 0
    unit[moving] = delta[moving] / length[moving, None]
    mode = "free" if unknown_is_free else "occupied"
    return np.asarray(np.isinf(raycast(m, a, unit, length, threshold, mode, step)))


def check_rays(
    origins: FloatArray, directions: FloatArray, max_range: object, dim: int
) -> tuple[FloatArray, FloatArray]:
    """Validated unit directions and per-ray ``max_range`` (metres, finite, >= 0).

    Raises
    ------
    OctolgpError
        Naming ``directions`` (a shape unlike ``origins``'s, or a zero row) or
        ``max_range``.
    """
    if directions.shape != origins.shape:
        raise OctolgpError(
            f"directions must have the shape of origins {origins.shape}, got {directions.shape}"
        )
    norm = np.linalg.norm(directions, axis=1)
    if (norm == 0).any():
        raise OctolgpError(f"directions row {int(np.flatnonzero(norm == 0)[0])} is zero")
    if isinstance(max_range, bool):
        raise OctolgpError("max_range must be a number or an array of shape (n,), got a bool")
    try:
        r = np.asarray(max_range, dtype=np.float64)
    except (TypeError, ValueError):
        raise OctolgpError(f"max_range must be a number, got {max_range!r}") from None
    if r.ndim > 1 or (r.ndim == 1 and r.shape[0] != origins.shape[0]):
        raise OctolgpError(f"max_range must be a number or of shape ({origins.shape[0]},)")
    if not (np.isfinite(r).all() and (r >= 0).all()):
        raise OctolgpError("max_range must be finite and >= 0")
    return directions / norm[:, None], np.broadcast_to(r, (origins.shape[0],)).copy()


def check_threshold(threshold: object) -> float:
    """``threshold`` as a float in (0, 1), else :class:`OctolgpError` naming it."""
    ok = isinstance(threshold, int | float | np.floating) and not isinstance(threshold, bool)
    if not ok or not 0.0 < float(threshold) < 1.0:  # type: ignore[arg-type]
        raise OctolgpError(f"threshold must be a number in (0, 1), got {threshold!r}")
    return float(threshold)  # type: ignore[arg-type]


def check_step(step: object, resolution: float) -> float:
    """The marching step: half a voxel for ``None``, else a number in (0, resolution]."""
    if step is None:
        return 0.5 * resolution
    ok = isinstance(step, int | float | np.floating) and not isinstance(step, bool)
    if not ok or not 0.0 < float(step) <= resolution:  # type: ignore[arg-type]
        raise OctolgpError(f"step must be a number in (0, {resolution:g}] m, got {step!r}")
    return float(step)  # type: ignore[arg-type]
