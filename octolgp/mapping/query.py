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
from octolgp.geometry.keys import KEY_BITS
from octolgp.gp.plsc import latent_occupancy
from octolgp.mapping import coarse
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
from octolgp.mapping.planning_reads import PlanningReads
from octolgp.mapping.store import Leaf, LeafStore
from octolgp.scan import FloatArray

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


class MapReads(PlanningReads):
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
            lo, hi = coarse.check_bbox(bbox, self.config)
            with self._reading() as m:
                return coarse.box_voxels(m, lo, hi, level)
        chunks = list(self.voxel_chunks())
        if not chunks:
            return np.zeros((0, self.config.dim)), np.zeros(0)
        return np.concatenate([c for c, _ in chunks]), np.concatenate([p for _, p in chunks])

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
        pruned as OctoMap does. Provisional while scans are buffered. The map is read a
        chunk of leaves at a time (:meth:`voxel_chunks`): what is held is a chunk and
        the file's bytes.

        Returns
        -------
        int
            Nodes written (OctoMap's ``size()``).
        """
        from octolgp.export.octomap import write_map_voxel_chunks

        ok = isinstance(threshold, int | float) and not isinstance(threshold, bool)
        if not ok or not 0.0 < threshold < 1.0:
            raise OctolgpError(f"threshold must be a number in (0, 1), got {threshold!r}")
        split = KEY_BITS - (self.grid.side.bit_length() - 1)  # a leaf's subtree in the file
        res, depth = self.config.resolution, self.config.tree_depth
        return write_map_voxel_chunks(path, self.voxel_chunks(), res, depth, split, threshold)
