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

Every function here only reads the map.
"""

from __future__ import annotations

import math

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.mapping.field import QUERY_CHUNK, ReadableMap, occupancy_field
from octolgp.scan import FloatArray

__all__ = ["MAX_BLOCK_STEPS", "UNKNOWN_MODES", "raycast", "segment_free"]

UNKNOWN_MODES = ("stop", "free", "occupied")
"""What a ray does in unknown space: ends without a hit (NaN), passes, or hits."""

MAX_BLOCK_STEPS = 256
"""Most steps a ray marches in one block: rays that hit early stop costing early."""

BISECTION_TOL = 1e-3
"""Width, in voxels, that bisection narrows each first bracket to."""


def _events(
    m: ReadableMap, X: FloatArray, threshold: float, stop_unknown: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Where a ray stops at ``X``: ``(event, known)``, both bool of shape (q,)."""
    prob, known = occupancy_field(m, X)
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
    n = origins.shape[0]
    stop_unknown = unknown != "free"
    out = np.full(n, np.inf)
    if n == 0:
        return out
    # the origins first: a ray starting in an obstacle (or unknown space) stops at 0
    event, known = _events(m, origins, threshold, stop_unknown)
    out[event] = np.where(known[event] | (unknown == "occupied"), 0.0, np.nan)
    active = np.flatnonzero(~event & (max_range > 0))
    done = np.zeros(0, dtype=np.int64)
    s0 = np.zeros(n)  # distance of each active ray's last sample below the threshold
    lo_s, hi_s = np.zeros(n), np.zeros(n)
    res = m.config.resolution
    while active.size:  # one block of steps for every ray still marching
        steps = int(np.clip(QUERY_CHUNK // (3 * active.size), 4, MAX_BLOCK_STEPS))
        s = block_samples(
            origins[active], directions[active], s0[active], max_range[active], step, steps, res
        )  # (a, k): every voxel the block passes through holds a sample
        pts = origins[active, None, :] + s[:, :, None] * directions[active, None, :]
        ev, _ = _events(m, pts.reshape(-1, pts.shape[2]), threshold, stop_unknown)
        ev = ev.reshape(s.shape)
        hit = ev.any(axis=1)
        first = np.argmax(ev, axis=1)
        rows = np.arange(active.size)
        prev = np.where(first > 0, s[rows, np.maximum(first - 1, 0)], s0[active])
        lo_s[active[hit]], hi_s[active[hit]] = prev[hit], s[rows, first][hit]
        done = np.concatenate([done, active[hit]])
        end = s[:, -1] >= max_range[active]
        s0[active] = s[:, -1]
        active = active[~hit & ~end]
    if done.size:
        out[done] = _bisect(
            m, origins[done], directions[done], lo_s[done], hi_s[done], threshold, unknown, step
        )
    return out


def block_samples(
    origins: FloatArray,
    directions: FloatArray,
    start: FloatArray,
    max_range: FloatArray,
    step: float,
    steps: int,
    resolution: float,
) -> FloatArray:
    """Distances ``(a, k)``, ascending, at which a block of ray marching reads the field.

    The block runs from ``start`` (read already) to ``min(start + steps * step,
    max_range)``. Its breakpoints are ``start``, the steps and every crossing of a voxel
    face (planes ``x_j = i * resolution``); the samples are the midpoints of
    consecutive breakpoints and the block's end. So consecutive samples lie at most
    a step apart, and every voxel the ray passes through over a length > 0 holds a
    sample: an unknown voxel is never stepped over.
    """
    end = np.minimum(start + steps * step, max_range)
    ticks = np.minimum(start[:, None] + step * np.arange(1, steps + 1)[None, :], end[:, None])
    planes = math.ceil(steps * step / resolution) + 1  # face crossings per axis, at most
    k = np.arange(planes)[None, :]
    crossings = [ticks]
    for j in range(origins.shape[1]):  # one axis at a time (2 or 3)
        o, u = origins[:, j : j + 1], directions[:, j : j + 1]
        x = (o + start[:, None] * u) / resolution  # in voxels
        ahead = np.where(u > 0, np.floor(x) + 1 + k, np.ceil(x) - 1 - k)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ahead * resolution - o) / u
        crossings.append(
            np.where((u != 0) & (t > start[:, None]), np.minimum(t, end[:, None]), end[:, None])
        )
    bp = np.sort(np.concatenate([start[:, None], *crossings], axis=1), axis=1)
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
) -> FloatArray:
    """Narrow brackets ``[lo, hi]`` (no event at ``lo``, one at ``hi``) to the event.

    Returns ``hi`` once the brackets are ``BISECTION_TOL`` voxels wide, or NaN where
    the event is unknown space and ``unknown == "stop"``.
    """
    stop_unknown = unknown != "free"
    width = BISECTION_TOL * m.config.resolution
    for _ in range(max(1, math.ceil(math.log2(max(step, width) / width)))):  # ~9 halvings
        mid = 0.5 * (lo + hi)
        ev, _ = _events(m, origins + mid[:, None] * directions, threshold, stop_unknown)
        hi = np.where(ev, mid, hi)
        lo = np.where(ev, lo, mid)
    _, known = _events(m, origins + hi[:, None] * directions, threshold, stop_unknown)
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
