"""The planning reads of a map: ray casts, segment checks, gradients, distance, surfaces.

:class:`PlanningReads` is the part of :class:`~octolgp.mapping.query.MapReads` that
answers a planner: each method validates its arguments, holds the map for the read
(``_reading``, as every read of :class:`~octolgp.mapping.query.MapReads`) and calls
the pure function of its module (:mod:`~octolgp.mapping.planning`,
:mod:`~octolgp.mapping.gradient`, :mod:`~octolgp.mapping.distance`,
:mod:`~octolgp.mapping.surface`). None of them changes the map.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import cast

import numpy as np

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.mapping import coarse, distance, gradient, planning
from octolgp.mapping.field import ReadableMap, query_points
from octolgp.mapping.surface import level_set
from octolgp.scan import FloatArray, as_points

__all__ = ["PlanningReads"]


class PlanningReads:
    """Ray casts, segment checks, gradients, distance and surfaces of a map.

    A subclass provides ``config`` and ``_reading`` (see
    :class:`~octolgp.mapping.query.MapReads`).
    """

    config: MapConfig
    _occupied: distance.OccupiedIndex | None = None

    def _reading(self, points: FloatArray | None = None) -> AbstractContextManager[ReadableMap]:
        """The map one read comes from; ``points``: the read is a query at these points."""
        raise NotImplementedError

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
        at most half a voxel, all rays at once, with a sample in every voxel passed
        besides (so unknown space is never stepped over), and the first bracket that
        reaches the threshold is refined by bisection to a thousandth of a voxel
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
        distance to the observed surfaces. The occupied centres are kept leaf by leaf
        between reads (recomputed for the leaves whose values changed since), and
        the tree while its leaves stay the same: a planner's read in a window
        (``max_distance``) after each insert costs the leaves near it, not the map.

        Parameters
        ----------
        points : array_like of shape (q, d)
            World frame, metres.
        threshold : float, optional
            In (0, 1); a voxel whose stored P(occupied) reaches it is occupied.
        max_distance : float, optional
            Metres > 0: farther answers are ``inf``, and only the leaves overlapping
            the points' bounding box grown by it are read (faster on a large map).
            Default: no bound (every leaf is read).

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
            if cast(object, m) is not self:  # a provisional map, while this one learns
                return distance.occupied_distance(m, X, thr, limit)
            if self._occupied is None:
                self._occupied = distance.OccupiedIndex()
            return distance.occupied_distance(m, X, thr, limit, self._occupied)

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
        thr = planning.check_threshold(threshold)
        lo, hi = coarse.check_bbox(bbox, self.config)
        with self._reading() as m:
            return level_set(m, thr, lo, hi)
