"""Queries: read voxel values from the store, at voxels or interpolated between them.

:class:`MapReads` is the read side of the online map (occupancy, latent, voxels,
export); :class:`~octolgp.mapping.online.OnlineMap` adds the writes.

Every function here only reads the store (a query never changes a map). A map
with a memory budget loads evicted leaves for reading without making them
resident, so a query does not change which leaves stay in RAM either.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping import coarse, distance, gradient, planning
from octolgp.mapping.field import (
    QUERY_CHUNK,
    ReadableMap,
    interpolate,
    interpolate_latent,
    leaves_read,
    lookup,
    query_points,
)
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf, LeafStore
from octolgp.scan import FloatArray, as_points

__all__ = [
    "QUERY_CHUNK",
    "MapReads",
    "ReadableMap",
    "interpolate",
    "interpolate_latent",
    "leaves_read",
    "lookup",
    "query_points",
]


class MapReads:
    """The reads of an online map; none of them changes the map.

    A subclass provides ``config`` and :meth:`_reading`, a context holding the map the
    reads come from (itself, or a provisional fit while it buffers scans to learn
    hyperparameters) for the length of one read.
    """

    config: MapConfig
    grid: LeafGrid
    store: LeafStore
    hyperparameters: Hyperparameters | None

    def _reading(self, points: FloatArray | None = None) -> AbstractContextManager[ReadableMap]:
        """The map one read comes from; ``points``: the read is a query at these points."""
        raise NotImplementedError

    def occupancy(
        self, points: object, *, interpolate: bool = True, depth: int | None = None
    ) -> FloatArray:
        """P(occupied) at query points.

        Parameters
        ----------
        points : array_like of shape (q, d)
            World frame, metres.
        interpolate : bool, optional
            ``True`` (default): a continuous map. The latent mean and variance stored
            at the ``2**d`` voxel centres around each point are interpolated
            multilinearly (unknown corners count as the GP prior) and PLSC turns them
            into a probability; at a voxel centre this is the voxel's own value.
            ``False``: the stored value of the voxel holding the point (OctoMap's
            semantics, piecewise constant).
        depth : int, optional
            Octree depth in ``1..tree_depth`` (default: ``tree_depth``, the voxels).
            Coarser, each point reads the node at that depth holding it, as
            OctoMap's ``search(point, depth)``: the max P of the voxels inside the
            node that hold a value (0.5 if none); ``interpolate`` is then unused.

        Returns
        -------
        ndarray of shape (q,)
            In [0, 1]; exactly 0.5 where the voxel holding the point has no value.
            While :attr:`provisional`, from a fit of the buffered scans that is thrown
            away (the map does not change).

        Raises
        ------
        OctolgpError
            On a bad shape, a non-finite value or a point outside the addressable range.
        """
        X = query_points(points, self.config)
        level = coarse.check_depth(depth, self.config)
        if level < self.config.tree_depth:
            with self._reading() as m:
                return coarse.depth_occupancy(m, X, level)
        out = np.empty(X.shape[0])
        with self._reading(X) as m:
            hp = m.hyperparameters
            for lo in range(0, X.shape[0], QUERY_CHUNK):  # bounded temporaries, chunk by chunk
                part = X[lo : lo + QUERY_CHUNK]
                if not interpolate or hp is None:
                    (prob,) = lookup(m.store, m.grid, part, ("prob",))
                    out[lo : lo + QUERY_CHUNK] = np.where(np.isnan(prob), 0.5, prob)
                else:
                    mean, var, known = interpolate_latent(m, part)
                    prob = latent_occupancy(mean, var, hp)
                    out[lo : lo + QUERY_CHUNK] = np.where(known, prob, 0.5)
        return out

    def latent(self, points: object, *, interpolate: bool = True) -> tuple[FloatArray, FloatArray]:
        """GP latent mean and variance at query points.

        ``interpolate`` as in :meth:`occupancy` (multilinear between voxel centres, or
        the voxel holding each point); provisional while scans are buffered.

        Returns
        -------
        mean, var : ndarray of shape (q,)
            The prior ``(0, σf²)`` where the voxel holding the point has no value
            (``σf² = 1`` before hyperparameters exist).
        """
        X = query_points(points, self.config)
        mean, var = np.empty(X.shape[0]), np.empty(X.shape[0])
        with self._reading(X) as m:
            prior = 1.0 if m.hyperparameters is None else m.hyperparameters.signal_variance
            for lo in range(0, X.shape[0], QUERY_CHUNK):  # bounded temporaries, chunk by chunk
                part, at = X[lo : lo + QUERY_CHUNK], slice(lo, lo + QUERY_CHUNK)
                if not interpolate:
                    mu, s2 = lookup(m.store, m.grid, part, ("mean", "var"))
                    mean[at], var[at] = (
                        np.where(np.isnan(mu), 0.0, mu),
                        np.where(np.isnan(s2), prior, s2),
                    )
                else:
                    mu, s2, known = interpolate_latent(m, part)
                    mean[at], var[at] = np.where(known, mu, 0.0), np.where(known, s2, prior)
        return mean, var

    def voxel_centres(self, leaf: Leaf) -> FloatArray:
        """Centres of a leaf's voxels, shape (V, d), in the order of its value arrays."""
        return self.grid.voxel_centres(leaf.index)

    def leaves(self) -> Iterator[tuple[int, Leaf]]:
        """``(packed leaf key, leaf)`` for every leaf, in key order.

        None while the map learns its hyperparameters (a map that defers its fits
        holds the buffered scans' evidence then, in leaves not fitted yet). The map is
        checked when the iterator is made; a writer changing the map while it is
        consumed may be seen part-way.
        """
        with self._reading():
            return self.store.items() if self.hyperparameters is not None else iter(())

    def voxels(
        self, *, depth: int | None = None, bbox: tuple[object, object] | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """Centres and P(occupied) of every predicted voxel (pruned leaves expanded).

        Voxels a leaf holds no value for (too far from any observation:
        ``LatticeConfig.fill_voxels``) are left out, as space outside every leaf is.
        Provisional while scans are buffered (see :attr:`provisional`).

        Parameters
        ----------
        depth : int, optional
            Octree depth in ``1..tree_depth`` (default ``tree_depth``: voxels).
            Coarser, the nodes at that depth holding a voxel with a value, each with
            the max P of its voxels (OctoMap's inner-node occupancy).
        bbox : (lo, hi), optional
            Box corners, each of shape (d,), metres, world frame, ``lo <= hi``: only
            the cells (at ``depth``) that overlap the box, as OctoMap's
            ``begin_leafs_bbx``, reading only the leaves that overlap it.

        Returns
        -------
        centres : ndarray of shape (k, d)
            Cell centres (OctoMap's ``keyToCoord`` at ``depth``).
        prob : ndarray of shape (k,)
        """
        if depth is not None or bbox is not None:
            level = coarse.check_depth(depth, self.config)
            lo, hi = self._bbox(bbox)
            with self._reading() as m:
                return coarse.box_voxels(m, lo, hi, level)
        chunks = list(self.voxel_chunks())
        if not chunks:
            return np.zeros((0, self.config.dim)), np.zeros(0)
        return np.concatenate([c for c, _ in chunks]), np.concatenate([p for _, p in chunks])

    def _bbox(self, bbox: tuple[object, object] | None) -> tuple[FloatArray | None, ...]:
        """Validated box corners ``lo, hi`` of shape (d,), or ``(None, None)``."""
        if bbox is None:
            return None, None
        if not isinstance(bbox, tuple | list) or len(bbox) != 2:
            raise OctolgpError("bbox must be a pair (lo, hi) of points of shape (d,)")
        try:
            corners = np.asarray(bbox, dtype=np.float64)
        except (TypeError, ValueError):
            raise OctolgpError("bbox must be a pair (lo, hi) of points of shape (d,)") from None
        if corners.shape != (2, self.config.dim):
            raise OctolgpError(
                f"bbox must be a pair (lo, hi) of points of shape ({self.config.dim},), "
                f"got shape {corners.shape}"
            )
        lo, hi = query_points(corners, self.config, "bbox")
        if (lo > hi).any():
            raise OctolgpError(f"bbox lo {lo.tolist()} must be <= hi {hi.tolist()} on every axis")
        return lo, hi

    def raycast(
        self,
        origins: object,
        directions: object,
        max_range: object,
        threshold: float = 0.5,
        *,
        unknown: str = "stop",
        step: float | None = None,
    ) -> FloatArray:
        """Distance along each ray to where P(occupied) first reaches ``threshold``.

        The continuous field (:meth:`occupancy`, interpolated) is marched at steps of
        at most half a voxel, all rays at once, and the first step that reaches the
        threshold is refined by bisection to a thousandth of a voxel
        (:func:`octolgp.mapping.planning.raycast`).

        Parameters
        ----------
        origins : array_like of shape (n, d)
            Ray origins, metres, world frame.
        directions : array_like of shape (n, d)
            Ray directions, world frame, not zero (normalised here).
        max_range : float or array_like of shape (n,)
            Metres (>= 0) along each ray.
        threshold : float, optional
            P(occupied) in (0, 1) that counts as a hit (0.5).
        unknown : {"stop", "free", "occupied"}, optional
            What a ray does on entering unknown space (a voxel with no value):
            ``"stop"`` (default) ends it there with NaN, ``"free"`` lets it pass,
            ``"occupied"`` makes it a hit there (a planner's conservative answer).
        step : float, optional
            Marching step, metres, in ``(0, resolution]`` (default half a voxel). A
            crossing thinner than a step may be missed.

        Returns
        -------
        ndarray of shape (n,)
            Metres from each origin: the hit (0 when the origin is at or above the
            threshold); ``inf`` when there is none up to ``max_range``; NaN when the
            ray meets unknown space first (``unknown="stop"``).

        Raises
        ------
        OctolgpError
            Naming the bad argument (shape, non-finite value, zero direction, an
            origin outside the addressable range, ``threshold``, ``unknown``).
        """
        start = query_points(origins, self.config, "origins")
        heading = as_points(directions, "directions", dim=self.config.dim)
        heading, reach = planning.check_rays(start, heading, max_range, self.config.dim)
        thr = planning.check_threshold(threshold)
        if unknown not in planning.UNKNOWN_MODES:
            raise OctolgpError(
                f"unknown must be one of {', '.join(planning.UNKNOWN_MODES)}, got {unknown!r}"
            )
        h = planning.check_step(step, self.config.resolution)
        with self._reading() as m:
            return planning.raycast(m, start, heading, reach, thr, unknown, h)

    def segment_free(
        self,
        a: object,
        b: object,
        threshold: float = 0.5,
        *,
        unknown_is_free: bool = False,
        step: float | None = None,
    ) -> np.ndarray:
        """Whether each straight segment ``a -> b`` stays below ``threshold`` all along.

        The segment is sampled as :meth:`raycast` marches (at most half a voxel
        apart, both ends included).

        Parameters
        ----------
        a, b : array_like of shape (n, d)
            Segment ends, metres, world frame.
        threshold : float, optional
            P(occupied) in (0, 1) that blocks a segment (0.5).
        unknown_is_free : bool, optional
            ``False`` (default): a segment through unknown space is not free.
        step : float, optional
            As in :meth:`raycast`.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        ends_a = query_points(a, self.config, "a")
        ends_b = query_points(b, self.config, "b")
        if ends_a.shape != ends_b.shape:
            raise OctolgpError(f"b must have the shape of a {ends_a.shape}, got {ends_b.shape}")
        if not isinstance(unknown_is_free, bool):
            raise OctolgpError(f"unknown_is_free must be a bool, got {unknown_is_free!r}")
        thr = planning.check_threshold(threshold)
        h = planning.check_step(step, self.config.resolution)
        with self._reading() as m:
            return planning.segment_free(m, ends_a, ends_b, thr, unknown_is_free, h)

    def gradient(self, points: object) -> FloatArray:
        """Gradient of P(occupied) (the interpolated :meth:`occupancy`) at points.

        Analytic: the derivative of the multilinear latent mean and variance through
        PLSC (:mod:`octolgp.mapping.gradient`), so it is the derivative of what
        :meth:`occupancy` reads.

        Parameters
        ----------
        points : array_like of shape (q, d)
            World frame, metres.

        Returns
        -------
        ndarray of shape (q, d)
            ``∂P/∂x`` per metre along the world axes; points into obstacles. 0
            where the point's voxel is unknown (there P is the constant 0.5).
        """
        X = query_points(points, self.config)
        with self._reading(X) as m:
            return gradient.occupancy_gradient(m, X)

    def latent_gradient(self, points: object) -> tuple[FloatArray, FloatArray]:
        """Gradients of the interpolated latent mean and variance (:meth:`latent`).

        Returns
        -------
        grad_mean, grad_var : ndarray of shape (q, d)
            Per metre along the world axes; 0 where the point's voxel is unknown.
        """
        X = query_points(points, self.config)
        with self._reading(X) as m:
            _, _, g_mean, g_var, known = gradient.latent_gradient(m, X)
        return np.where(known[:, None], g_mean, 0.0), np.where(known[:, None], g_var, 0.0)

    def normals(self, points: object) -> FloatArray:
        """Unit normals ``-∇P / |∇P|`` (:meth:`gradient`), pointing out of obstacles.

        Returns
        -------
        ndarray of shape (q, d)
            NaN where the gradient is 0.
        """
        g = self.gradient(points)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(norm > 0, -g / norm, np.nan)

    def distance(
        self, points: object, threshold: float = 0.5, *, max_distance: float | None = None
    ) -> FloatArray:
        """Distance from each point to the nearest occupied voxel (P >= ``threshold``).

        Exact to the union of the occupied voxels' cubes (KD-tree over their
        centres, :mod:`octolgp.mapping.distance`); within a voxel diagonal of the
        distance to the observed surfaces.

        Parameters
        ----------
        points : array_like of shape (q, d)
            World frame, metres.
        threshold : float, optional
            In (0, 1); a voxel whose stored P(occupied) reaches it is occupied.
        max_distance : float, optional
            Metres > 0: farther answers are ``inf``, and only the voxels in the
            points' bounding box grown by it are read (faster on a large map).
            Default: no bound (every voxel is read).

        Returns
        -------
        ndarray of shape (q,)
            Metres; 0 inside an occupied voxel; ``inf`` when there is none (within
            ``max_distance``).
        """
        X = query_points(points, self.config)
        thr = planning.check_threshold(threshold)
        limit = distance.check_max_distance(max_distance)
        with self._reading() as m:
            return distance.occupied_distance(m, X, thr, limit)

    def surface(
        self, threshold: float = 0.5, *, bbox: tuple[object, object] | None = None
    ) -> tuple[FloatArray, np.ndarray]:
        """The level set ``P(occupied) = threshold`` as a mesh (3D) or polyline (2D).

        Marching tetrahedra (triangles in 2D) on the lattice of voxel centres, each
        vertex placed where :meth:`occupancy` crosses the threshold along its lattice
        edge, to a thousandth of a voxel (:mod:`octolgp.mapping.surface`). Space next
        to unknown voxels has no surface.

        Parameters
        ----------
        threshold : float, optional
            In (0, 1).
        bbox : (lo, hi), optional
            Mesh only the cells whose lower corner lies in this box (metres).

        Returns
        -------
        vertices : ndarray of shape (v, d)
            Metres, world frame.
        faces : ndarray of int64, shape (f, d)
            Triangles (3D) with normals (right-hand rule) pointing out of obstacles,
            or segments (2D) with the obstacle on their left.
        """
        from octolgp.mapping.surface import level_set

        thr = planning.check_threshold(threshold)
        lo, hi = self._bbox(bbox)
        with self._reading() as m:
            return level_set(m, thr, lo, hi)

    def voxel_chunks(self, size: int = QUERY_CHUNK) -> Iterator[tuple[FloatArray, FloatArray]]:
        """:meth:`voxels` in chunks of about ``size`` voxels, leaf by leaf in key order.

        Holds one chunk (and the store's batch of evicted leaves read back) at a time, so
        an export of a large map is bounded by the chunk, not the map; the chunks
        concatenated are :meth:`voxels`. The map is held for reads until the iterator is
        exhausted or closed.
        """
        with self._reading() as m:
            cs: list[FloatArray] = []
            ps: list[FloatArray] = []
            held = 0
            for _, leaf in m.store.items():  # one iteration per leaf
                if leaf.prob.size == 0:
                    continue
                centres = m.grid.voxel_centres(leaf.index)
                prob = np.broadcast_to(leaf.prob, (centres.shape[0],)).astype(np.float64)
                known = ~np.isnan(prob)
                cs.append(centres[known])
                ps.append(prob[known])
                held += int(known.sum())
                if held >= size:
                    yield np.concatenate(cs), np.concatenate(ps)
                    cs, ps, held = [], [], 0
            if cs:
                yield np.concatenate(cs), np.concatenate(ps)

    def occupied_voxels(self, threshold: float = 0.5) -> tuple[FloatArray, FloatArray]:
        """Centres and P(occupied) of the voxels above ``threshold``."""
        centres, prob = self.voxels()
        keep = prob > threshold
        return centres[keep], prob[keep]

    def export_octomap(self, path: str | Path, threshold: float = 0.5) -> int:
        """Write the map as an OctoMap file that the OctoMap library reads.

        ``.bt`` (default) is OctoMap's maximum-likelihood binary format: every
        predicted voxel is occupied when P(occupied) > ``threshold``, else free;
        voxels no leaf predicts stay unknown. ``.ot`` is the full format with each
        voxel's log-odds ``log(P / (1 − P))``. A 2D map is one layer of voxels whose
        z key is 32768 (z in ``[0, resolution)``). Identical sibling voxels are
        pruned as OctoMap does. Provisional while scans are buffered.

        Returns
        -------
        int
            Nodes written (OctoMap's ``size()``).
        """
        from octolgp.export.octomap import write_map_voxels

        ok = isinstance(threshold, int | float) and not isinstance(threshold, bool)
        if not ok or not 0.0 < threshold < 1.0:
            raise OctolgpError(f"threshold must be a number in (0, 1), got {threshold!r}")
        centres, prob = self.voxels()
        return write_map_voxels(
            path, centres, prob, self.config.resolution, self.config.tree_depth, threshold
        )
