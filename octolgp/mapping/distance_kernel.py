"""Distance to the nearest occupied voxel cube by a compiled search of rings of voxels (numba).

:func:`octolgp.mapping.distance.occupied_distance` answers near queries from a dense
grid of the occupied voxels (bool, over their bounding box): each point's voxel, then
the shells of voxels around it at Chebyshev distance ``r = 1, 2, ...`` (the surface of
the ``(2r + 1)**d`` block, never its inside again: the block's columns along the last
axis, whole where they lie on the shell, else their two ends). Every voxel of shell ``r`` lies at
least ``(r - 1) * resolution`` from the point, so the search is exact once that bound
reaches the nearest cube found, or passes ``bound`` (answers beyond it are not
wanted). A point whose search would go past ``rings`` shells is left unsettled, for the
KD-tree.

This module imports numba: import it only where numba is installed (it is imported on
the first distance read, not with the package).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = ["ring_search"]

_jit: Callable[[Any], Any] = njit(cache=True, nogil=True)


@_jit
def _search(
    X: FloatArray,
    occupied: np.ndarray,
    shape: IntArray,
    low: IntArray,
    res: float,
    origin: float,
    bound: float,
    rings: int,
    out: FloatArray,
    settled: np.ndarray,
) -> None:  # pragma: no cover - compiled; tested through the compiled form
    """Fill ``out`` and ``settled`` (see :func:`ring_search`)."""
    n, d = X.shape
    half = 0.5 * res
    own = np.empty(d, dtype=np.int64)
    cell = np.empty(d, dtype=np.int64)
    stride = np.ones(d, dtype=np.int64)
    for a in range(d - 2, -1, -1):  # C order: the last axis varies fastest
        stride[a] = stride[a + 1] * shape[a + 1]
    for q in range(n):  # one point per iteration
        for a in range(d):
            own[a] = math.floor((X[q, a] - origin) / res) - low[a]
        best = np.inf
        done = False
        for r in range(rings + 1):  # the shell of voxels at Chebyshev distance r
            floor_r = max(r - 1, 0) * res
            if floor_r >= best or floor_r > bound:
                done = True
                break
            side = 2 * r + 1
            last = d - 1
            for j in range(side**last):  # the first d - 1 axes over the whole block
                rest = j
                outer_shell = r == 0
                inside = True
                flat = 0
                for a in range(last):
                    off = rest % side - r
                    rest //= side
                    outer_shell = outer_shell or off == r or off == -r
                    cell[a] = own[a] + off
                    inside = inside and 0 <= cell[a] < shape[a]
                    flat += cell[a] * stride[a]
                if not inside:
                    continue
                # the last axis: the whole block's column on the shell, else its two ends
                jump = 1 if outer_shell else max(2 * r, 1)
                for off in range(-r, r + 1, jump):
                    cell[last] = own[last] + off
                    if cell[last] < 0 or cell[last] >= shape[last]:
                        continue
                    if not occupied[flat + cell[last]]:
                        continue
                    gap2 = 0.0
                    for a in range(d):
                        centre = origin + (cell[a] + low[a] + 0.5) * res
                        g = abs(X[q, a] - centre) - half
                        if g > 0:
                            gap2 += g * g
                    dist = math.sqrt(gap2)
                    if dist < best:
                        best = dist
        if not done:  # the last shell searched: settled only if it bounds the rest
            floor_r = rings * res
            done = floor_r >= best or floor_r > bound
        out[q] = best
        settled[q] = done


def ring_search(
    X: FloatArray,
    occupied: np.ndarray,
    low: IntArray,
    resolution: float,
    origin: float,
    bound: float,
    rings: int,
) -> tuple[FloatArray, np.ndarray]:
    """Distance from points to the nearest occupied voxel cube, searching shells of voxels.

    Parameters
    ----------
    X : ndarray of shape (q, d)
        Points, metres, world frame.
    occupied : ndarray of bool, d dimensions
        The occupied voxels over their bounding box; cell ``i`` holds the voxel with
        per-axis key ``low + i``.
    low : ndarray of int64, shape (d,)
    resolution : float
    origin : float
        Coordinate of voxel key 0, metres.
    bound : float
        Metres (``inf``: none): no search goes past shells beyond it.
    rings : int
        Most shells searched around each point's voxel.

    Returns
    -------
    distance : ndarray of shape (q,)
        Metres: the exact distance where settled and it is at most ``bound``
        (``inf``: no occupied voxel within ``bound``).
    settled : ndarray of bool, shape (q,)
        Whether the search settled the point (else the shells ran out first).
    """
    out = np.empty(X.shape[0])
    settled = np.empty(X.shape[0], dtype=bool)
    shape = np.array(occupied.shape, dtype=np.int64)
    c = np.ascontiguousarray
    _search(
        c(X, dtype=np.float64),
        c(occupied).reshape(-1),
        shape,
        c(low, dtype=np.int64),
        float(resolution),
        float(origin),
        float(bound),
        int(rings),
        out,
        settled,
    )
    return out, settled
