"""Ray traversal through the voxel grid (Amanatides & Woo, as OctoMap's ``computeRayKeys``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError
from octolgp.geometry.keys import coord_to_key, key_to_coord
from octolgp.scan import as_points

IntArray = NDArray[np.int64]


def traverse_voxels(
    origins: ArrayLike, ends: ArrayLike, resolution: float, tree_depth: int = 16
) -> tuple[IntArray, IntArray]:
    """Return the voxels each ray passes through, as OctoMap's ``computeRayKeys``.

    Amanatides & Woo (1987) voxel traversal, vectorised over rays: each step
    advances every ray that still has voxels to visit. A ray yields its origin's
    voxel, then every voxel it enters, and stops before its end's voxel; a ray
    that starts and ends in one voxel yields nothing. Ties (a ray through an edge
    or corner) step the last tied axis first, as OctoMap does.

    Parameters
    ----------
    origins, ends : array_like of shape (b, d)
        Ray start and end points in the world frame, metres; ``d`` is 2 or 3.
    resolution : float
        Voxel edge, metres.
    tree_depth : int, optional
        OctoMap key depth.

    Returns
    -------
    beam_index : ndarray of int64, shape (k,)
        Ray of each voxel, ascending.
    keys : ndarray of int64, shape (k, d)
        OctoMap keys, each ray's voxels in traversal order.

    Raises
    ------
    OctolgpError
        On bad shapes or values, or a point outside the addressable range.
    """
    o = as_points(origins, "origins")
    e = as_points(ends, "ends", dim=o.shape[1])
    if o.shape != e.shape:
        raise OctolgpError(f"origins {o.shape} and ends {e.shape} must have equal shapes")
    key_o = coord_to_key(o, resolution, tree_depth, name="origins")
    key_e = coord_to_key(e, resolution, tree_depth, name="ends")
    n, dim = o.shape

    # A&W initialisation: step direction, t (0 at origin, 1 at end) of the first
    # voxel border per axis (t_max) and t between borders (t_delta).
    d = e - o
    step = np.sign(d).astype(np.int64)
    remaining = np.abs(key_e - key_o)  # borders still to cross, per axis
    total = remaining.sum(axis=1)  # voxels yielded per ray
    border = key_to_coord(key_o, resolution, tree_depth) + step * (0.5 * resolution)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t_max = (border - o) / d
        t_delta = resolution / np.abs(d)
    t_max[remaining == 0] = np.inf  # an axis without borders to cross never steps

    # Longest rays first, so the rays still active at step j are a prefix. Arrays
    # are axis-major, shape (d, b): flat index of (axis, ray) is axis * b + ray.
    order = np.argsort(-total, kind="stable")
    start = (np.cumsum(total) - total)[order]  # each ray's first row in the output
    cur = np.ascontiguousarray(key_o[order].T)
    t_now = np.ascontiguousarray(t_max[order].T)
    cur_f, t_now_f = cur.reshape(-1), t_now.reshape(-1)
    step_f = step[order].T.reshape(-1)
    rem_f = remaining[order].T.reshape(-1)
    t_delta_f = t_delta[order].T.reshape(-1)
    n_steps = int(total.max()) if n else 0
    active = np.searchsorted(-total[order], -np.arange(n_steps + 1), side="left")
    rays = np.arange(n, dtype=np.int64)

    out = np.empty((dim, int(total.sum())), dtype=np.int64)
    for j in range(n_steps):
        out[:, start[: active[j]] + j] = cur[:, : active[j]]
        a = active[j + 1]
        if a == 0:
            break
        # A&W incremental traversal: cross the nearest border (smallest t_max);
        # on ties the last axis wins, as in OctoMap.
        near = np.zeros(a, dtype=np.int64)
        best = t_now[0, :a]
        for axis in range(1, dim):
            near[t_now[axis, :a] <= best] = axis
            best = np.minimum(best, t_now[axis, :a])
        idx = near * n + rays[:a]
        cur_f[idx] += step_f[idx]
        rem_f[idx] -= 1
        t_now_f[idx] = np.where(rem_f[idx] > 0, t_now_f[idx] + t_delta_f[idx], np.inf)
    return np.repeat(rays, total), out.T
