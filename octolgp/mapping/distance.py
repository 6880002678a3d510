"""Distance to the nearest occupied voxel: exact, over the voxel cubes, with a KD-tree.

The occupied set is the union of the cubes (squares in 2D) of edge ``resolution`` of
the voxels whose stored P(occupied) is at least a threshold. The distance from a
point to that set is exact, not the distance to voxel centres: a KD-tree
(:class:`scipy.spatial.cKDTree`) over the occupied centres gives each point's ``k``
nearest centres, the distance to each one's cube is
``|| max(|p - c| - r/2, 0) ||``, and the minimum over them is the answer once the
``k``-th centre lies beyond that minimum plus the half-diagonal ``r sqrt(d) / 2``
(no farther cube can then be nearer); the few points where it does not get more
neighbours, rounds of ``4 k``, until it does.

Against the true geometry the occupied cubes cover each observed surface point
with a cube at most one voxel across, so the distance is within a voxel diagonal
below the true distance to observed surfaces (measured in BENCHMARKS.md), and 0
inside an occupied voxel. The tree is built per call over the occupied voxels of
the map, or, with a finite ``max_distance``, of the queries' bounding box grown by
it (a box read, :func:`~octolgp.mapping.coarse.box_voxels`): its cost is that of
reading those voxels plus ``O(n log n)`` for ``n`` occupied ones.

Every function here only reads the map.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range
from octolgp.mapping.coarse import box_voxels
from octolgp.mapping.field import QUERY_CHUNK, ReadableMap
from octolgp.scan import FloatArray

__all__ = ["check_max_distance", "cube_distance", "occupied_distance"]

FIRST_NEIGHBOURS = 8
"""Centres a point's first KD-tree query asks for."""


def cube_distance(X: FloatArray, centres: FloatArray, half: float) -> FloatArray:
    """Distance from points ``(q, d)`` to axis-aligned cubes ``(q, k, d)`` of half-edge ``half``.

    Returns an array of shape ``(q, k)``, metres; 0 inside a cube.
    """
    gap = np.maximum(np.abs(X[:, None, :] - centres) - half, 0.0)
    return np.asarray(np.sqrt((gap * gap).sum(axis=2)))


def nearest_cube(tree: cKDTree, cubes: FloatArray, X: FloatArray, half: float) -> FloatArray:
    """Exact distance from each point to the nearest cube of the tree's centres."""
    n = cubes.shape[0]
    slack = half * math.sqrt(X.shape[1])
    out = np.full(X.shape[0], np.inf)
    todo = np.arange(X.shape[0])
    k = min(FIRST_NEIGHBOURS, n)
    while todo.size:  # rounds of more neighbours for the few points not settled
        dist, idx = tree.query(X[todo], k=k)
        dist, idx = dist.reshape(todo.size, k), idx.reshape(todo.size, k)
        best = cube_distance(X[todo], cubes[idx], half).min(axis=1)
        out[todo] = best
        settled = (k == n) | (dist[:, -1] > best + slack)
        todo = todo[~settled]
        k = min(4 * k, n)
    return out


def occupied_distance(
    m: ReadableMap, X: FloatArray, threshold: float, max_distance: float
) -> FloatArray:
    """Distance from each point to the nearest voxel with P(occupied) >= ``threshold``.

    Parameters
    ----------
    m : ReadableMap
    X : ndarray of shape (q, d)
        Validated points, metres, world frame.
    threshold : float
        In (0, 1).
    max_distance : float
        Metres, > 0 or ``inf``; farther answers are ``inf``, and a finite value
        limits the voxels read to the queries' box grown by it.

    Returns
    -------
    ndarray of shape (q,)
        Metres; 0 inside an occupied voxel, ``inf`` where no occupied voxel lies
        within ``max_distance``.
    """
    res = m.config.resolution
    out = np.full(X.shape[0], np.inf)
    if X.shape[0] == 0:
        return out
    lo = hi = None
    if math.isfinite(max_distance):
        low, high = addressable_range(res, m.config.tree_depth)
        grow = max_distance + res
        lo = np.maximum(X.min(axis=0) - grow, low)
        hi = np.minimum(X.max(axis=0) + grow, high - 1e-9 * res)
    centres, prob = box_voxels(m, lo, hi, m.config.tree_depth)
    cubes = centres[prob >= threshold]
    if cubes.shape[0] == 0:
        return out
    tree = cKDTree(cubes)
    for lo in range(0, X.shape[0], QUERY_CHUNK):  # bounded temporaries, chunk by chunk
        out[lo : lo + QUERY_CHUNK] = nearest_cube(tree, cubes, X[lo : lo + QUERY_CHUNK], 0.5 * res)
    return np.where(out <= max_distance, out, np.inf)


def check_max_distance(max_distance: object) -> float:
    """``max_distance`` as a float > 0 (``None``: ``inf``), else :class:`OctolgpError`."""
    if max_distance is None:
        return math.inf
    ok = isinstance(max_distance, int | float | np.floating) and not isinstance(max_distance, bool)
    if not ok or not float(max_distance) > 0:  # type: ignore[arg-type]
        raise OctolgpError(f"max_distance must be a number > 0, got {max_distance!r}")
    return float(max_distance)  # type: ignore[arg-type]
