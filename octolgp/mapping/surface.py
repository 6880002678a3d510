"""The P(occupied) = threshold level set as a mesh: marching tetrahedra (3D), triangles (2D).

The lattice is that of the voxel centres, where the map's field takes its stored
values. Each cell of ``2**d`` centres that all hold a value is split into simplices
along its main diagonal (six tetrahedra in 3D, two triangles in 2D; neighbouring cells
split their common face the same way, so the surface has no cracks), and each simplex
whose corners lie on both sides of the threshold gets a piece of the surface: a
triangle or two in 3D, a segment in 2D. Each vertex lies on a lattice edge (an axis,
face or body diagonal of a cell) where the interpolated field
(:func:`~octolgp.mapping.field.occupancy_field`, what
:meth:`~octolgp.mapping.query.MapReads.occupancy` reads) crosses the threshold, found by
bisection to :data:`VERTEX_TOL` voxels; vertices are shared between the simplices of an
edge. Cells with a corner in unknown space have no surface. Triangles are oriented so
that their normals (right-hand rule) point out of obstacles, towards lower P.

No table-driven marching cubes (and no scikit-image): the simplex split needs no
case table, at the cost of about twice as many triangles.
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from octolgp.geometry.keys import addressable_range, unpack_keys
from octolgp.mapping.field import QUERY_CHUNK, ReadableMap, Reader, occupancy_field
from octolgp.mapping.voxel_table import voxel_table
from octolgp.scan import FloatArray
from octolgp.training import IntArray

__all__ = ["VERTEX_TOL", "level_set"]

VERTEX_TOL = 1e-3
"""Width, in voxels, that bisection narrows each vertex's edge bracket to."""

# Cell corners as bits (x = 1, y = 2, z = 4); simplices along the diagonal 0 -> 2**d - 1.
_SIMPLICES = MappingProxyType(
    {
        2: ((0, 1, 3), (0, 3, 2)),
        3: ((0, 1, 3, 7), (0, 3, 2, 7), (0, 2, 6, 7), (0, 6, 4, 7), (0, 4, 5, 7), (0, 5, 1, 7)),
    }
)


def level_set(
    m: ReadableMap, threshold: float, lo: FloatArray | None = None, hi: FloatArray | None = None
) -> tuple[FloatArray, IntArray]:
    """Vertices and simplices of the level set ``P(occupied) = threshold``.

    Parameters
    ----------
    m : ReadableMap
    threshold : float
        In (0, 1).
    lo, hi : ndarray of shape (d,), optional
        A box (metres, addressable) to mesh; default the whole map.

    Returns
    -------
    vertices : ndarray of shape (v, d)
        Metres, world frame.
    faces : ndarray of int64, shape (f, d)
        Triangles (3D) or segments (2D), indices into ``vertices``.
    """
    d = m.config.dim
    res = m.config.resolution
    low, high = addressable_range(res, m.config.tree_depth)
    if lo is None or hi is None:
        lo, hi = np.full(d, low), np.full(d, high - 2 * res)
    table = voxel_table(m, lo, np.minimum(hi + res, high - 1e-6 * res))  # the cells' upper corners
    read: Reader = table
    known = ~np.isnan(table.mean)
    centres_all = _key_centres(m, table.keys, d)
    inside_box = ((centres_all >= lo) & (centres_all <= hi)).all(axis=1)
    base = centres_all[known & inside_box]  # each known centre is a cell's lower corner
    offsets = np.array(list(np.ndindex(*(2,) * d)))[:, ::-1]  # bit j of the index is axis j
    simplices = np.array(_SIMPLICES[d])
    edge_a: list[FloatArray] = []
    edge_b: list[FloatArray] = []
    pieces: list[tuple[IntArray, IntArray, np.ndarray]] = []
    n_edges = 0
    step = max(1, QUERY_CHUNK // (1 << d))
    for start in range(0, base.shape[0], step):  # cells a chunk at a time
        corner = base[start : start + step, None, :] + offsets[None, :, :] * res  # (c, 2^d, d)
        stored, mean = read.at_points(
            corner.reshape(-1, d), ("prob", "mean")
        )  # the field at centres
        prob, held = stored.reshape(corner.shape[:2]), ~np.isnan(mean).reshape(corner.shape[:2])
        full = held.all(axis=1) & ((prob >= threshold).any(axis=1)) & (prob < threshold).any(axis=1)
        corner, prob = corner[full], prob[full]
        for simplex in simplices:  # 2 or 6 simplices per cell
            verts = corner[:, simplex, :]  # (c, d+1, d)
            above = prob[:, simplex] >= threshold
            count = above.sum(axis=1)
            cut = (count > 0) & (count < d + 1)
            if not cut.any():
                continue
            verts, above = verts[cut], above[cut]
            pairs = [(i, j) for i in range(d + 1) for j in range(i + 1, d + 1)]
            crossing = np.stack([above[:, i] != above[:, j] for i, j in pairs], axis=1)
            ids = np.full(crossing.shape, -1, dtype=np.int64)
            for e, (i, j) in enumerate(pairs):  # the simplex's edges (3 or 6)
                rows = np.flatnonzero(crossing[:, e])
                a, b = verts[rows, i], verts[rows, j]
                swap = ~above[rows, i]  # every edge runs from above the threshold to below
                edge_a.append(np.where(swap[:, None], b, a))
                edge_b.append(np.where(swap[:, None], a, b))
                ids[rows, e] = n_edges + np.arange(rows.size)
                n_edges += rows.size
            pieces.append((ids, above.astype(np.int64), verts))
    if n_edges == 0:
        return np.zeros((0, d)), np.zeros((0, d), dtype=np.int64)
    a_all, b_all = np.concatenate(edge_a), np.concatenate(edge_b)
    # one vertex per lattice edge: edges are keyed by their two ends
    ends = np.round(np.concatenate([a_all, b_all], axis=1) / (0.5 * res)).astype(np.int64)
    _, first, which = np.unique(ends, axis=0, return_index=True, return_inverse=True)
    vertices = _refine(m, a_all[first], b_all[first], threshold, read)
    which = which.ravel()
    faces = [
        _faces(np.where(ids >= 0, which[np.maximum(ids, 0)], -1), above, verts, vertices, d)
        for ids, above, verts in pieces
    ]
    return vertices, np.concatenate(faces).astype(np.int64)


def _key_centres(m: ReadableMap, packed: IntArray, d: int) -> FloatArray:
    """Voxel centres of packed voxel keys, metres."""
    origin = -float(1 << (m.config.tree_depth - 1)) * m.config.resolution
    return np.asarray(origin + (unpack_keys(packed, d) + 0.5) * m.config.resolution)


def _refine(
    m: ReadableMap, a: FloatArray, b: FloatArray, threshold: float, read: Reader
) -> FloatArray:
    """Points on segments ``a -> b`` (P >= threshold at ``a``, below at ``b``) at the crossing."""
    lo, hi = np.zeros(a.shape[0]), np.ones(a.shape[0])
    length = np.linalg.norm(b - a, axis=1).max(initial=0.0)
    iterations = int(np.ceil(np.log2(max(length, 1e-12) / (VERTEX_TOL * m.config.resolution))))
    for _ in range(max(iterations, 1)):  # ~11 halvings
        mid = 0.5 * (lo + hi)
        prob, _ = occupancy_field(m, a + mid[:, None] * (b - a), read)
        up = prob >= threshold
        lo = np.where(up, mid, lo)
        hi = np.where(up, hi, mid)
    t = 0.5 * (lo + hi)
    return np.asarray(a + t[:, None] * (b - a))


def _faces(
    ids: IntArray, above: IntArray, verts: FloatArray, vertices: FloatArray, d: int
) -> IntArray:
    """Faces of the cut simplices: a segment (2D), one or two triangles (3D), oriented."""
    count = above.sum(axis=1)
    inside = (above[:, :, None] * verts).sum(axis=1) / np.maximum(count, 1)[:, None]
    outside = ((1 - above)[:, :, None] * verts).sum(axis=1) / np.maximum(d + 1 - count, 1)[:, None]
    out_dir = outside - inside  # towards lower P
    crossing = ids >= 0
    if d == 2:  # two of the triangle's three edges cross
        seg = np.sort(np.where(crossing, ids, np.iinfo(np.int64).max), axis=1)[:, :2]
        return _orient_segments(seg, vertices, out_dir)
    tri = []
    lone = (count == 1) | (count == 3)
    if lone.any():  # three edges cross
        t = np.sort(np.where(crossing[lone], ids[lone], np.iinfo(np.int64).max), axis=1)[:, :3]
        tri.append(_orient(t, vertices, out_dir[lone]))
    pair = count == 2
    if pair.any():  # four edges cross: a quad in their cyclic order
        # edges (0,1) (0,2) (0,3) (1,2) (1,3) (2,3); with two vertices above the crossing
        # edges form the cycle e.g. (0,2) (0,3) (1,3) (1,2) when 0 and 1 are above
        q = ids[pair]
        order = _quad_order(above[pair])
        cyc = np.take_along_axis(q, order, axis=1)
        tri.append(_orient(cyc[:, [0, 1, 2]], vertices, out_dir[pair]))
        tri.append(_orient(cyc[:, [0, 2, 3]], vertices, out_dir[pair]))
    return np.concatenate(tri) if tri else np.zeros((0, 3), dtype=np.int64)


_EDGES3 = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def _quad_order(above: IntArray) -> IntArray:
    """Edge columns ``(n, 4)`` of the quad of tetrahedra with two corners above, in cycle order."""
    out = np.empty((above.shape[0], 4), dtype=np.int64)
    idx = {e: k for k, e in enumerate(_EDGES3)}
    for split in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):  # the 6 two-above cases
        p, q = split
        r, s = [v for v in range(4) if v not in split]
        rows = (above[:, p] == 1) & (above[:, q] == 1)
        cycle = [
            (min(p, r), max(p, r)),
            (min(p, s), max(p, s)),
            (min(q, s), max(q, s)),
            (min(q, r), max(q, r)),
        ]
        out[rows] = [idx[e] for e in cycle]
    return out


def _orient(tri: IntArray, vertices: FloatArray, out_dir: FloatArray) -> IntArray:
    """Triangles whose right-hand normal points along ``out_dir`` (flipped where not)."""
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    flip = (np.cross(b - a, c - a) * out_dir).sum(axis=1) < 0
    return np.where(flip[:, None], tri[:, [0, 2, 1]], tri)


def _orient_segments(seg: IntArray, vertices: FloatArray, out_dir: FloatArray) -> IntArray:
    """2D segments whose right-hand normal ``(dy, -dx)`` points along ``out_dir``."""
    v = vertices[seg[:, 1]] - vertices[seg[:, 0]]
    flip = (v[:, 1] * out_dir[:, 0] - v[:, 0] * out_dir[:, 1]) < 0
    return np.where(flip[:, None], seg[:, ::-1], seg)
