"""Leaf → local GP → PLSC: fit one leaf on its evidence and predict its voxels (pure).

A leaf with at most ``OnlineConfig.max_leaf_items`` items is one GP on all of them
(Kim & Kim's local GP on the leaf's halo box); a larger one is split by the paper's
iterative k-means under the cluster cap (:func:`octolgp.partition.partition`) and
each voxel is predicted by its nearest cluster. PLSC then turns the latent mean and
variance into P(occupied) (:func:`octolgp.gp.plsc.latent_occupancy`).
Nothing here touches a map: the same functions run on the map's threads and on Dask
workers.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.gp.clusters import cluster_tree, fit_clusters, predict_nearest
from octolgp.gp.kernels import item_covariance
from octolgp.gp.plsc import latent_occupancy
from octolgp.gp.quadrature import items_and_targets, points_set, quadrature_spacing
from octolgp.gp.regression import fit_predict
from octolgp.gp.sparse import InducingStats, absorb, inducing_posterior
from octolgp.mapping.cache import KernelCache, leaf_blocks
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.partition import partition
from octolgp.scan import FloatArray
from octolgp.training import TrainingData


def predict_leaf(
    leaf: Leaf,
    centres: FloatArray,
    config: MapConfig,
    hp: Hyperparameters,
    cache: KernelCache | None = None,
) -> tuple[FloatArray, FloatArray, int]:
    """Fit a leaf's local GP(s) on its evidence and predict at its voxel centres.

    Parameters
    ----------
    leaf : Leaf
    centres : ndarray of shape (V, d)
        The leaf's voxel centres, metres.
    config : MapConfig
    hp : Hyperparameters
    cache : KernelCache, optional
        Item covariance blocks of earlier fits of this leaf, reused for the items it
        already had (one-GP leaves only); the result does not depend on it.

    Returns
    -------
    mean, var : ndarray of shape (V,)
        Latent posterior (variance without the noise).
    repaired : int
        Kernel matrices that needed a jitter (:func:`octolgp.gp.regression.cholesky`).
    """
    spacing = quadrature_spacing(config, hp.length_scale)
    cap = config.online.max_leaf_items
    hits, fs, fe = leaf.hits, leaf.free_start, leaf.free_end
    if leaf.n_items == 0:
        return np.zeros(centres.shape[0]), np.full(centres.shape[0], hp.signal_variance), 0
    if config.online.inducing_per_axis:  # a DTC sparse GP on an inducing lattice
        items, y = items_and_targets(hits, fs, fe, config, spacing)
        U = inducing_lattice(leaf, config)
        stats = absorb(InducingStats.empty(U.shape[0]), U, items, y, hp)
        ls, sf2 = hp.length_scale, hp.signal_variance
        Kuu = item_covariance(points_set(U), points_set(U), ls, sf2)
        Ksu = item_covariance(points_set(centres), points_set(U), ls, sf2)
        mean, var, repaired = inducing_posterior(stats, Kuu, Ksu, hp)
        return mean, var, int(repaired)
    if leaf.n_items <= cap or hits.shape[0] == 0:
        if leaf.n_items > cap:  # free space only: an even, deterministic thinning
            keep = np.linspace(0, fs.shape[0] - 1, cap).round().astype(np.int64)
            fs, fe = fs[keep], fe[keep]
            cache = None  # the thinned items are not append-only
        items, y = items_and_targets(hits, fs, fe, config, spacing)
        if cache is None:
            mean, var, repaired = fit_predict(items, y, hp, centres)
            return mean, var, int(repaired)
        tc = config.training
        key = (
            hp.length_scale,
            hp.signal_variance,
            spacing,
            float(tc.min_quadrature_nodes),
            float(tc.max_quadrature_nodes),
        )
        K, Ks = leaf_blocks(leaf, items, centres, hp, key, cache)
        mean, var, repaired = fit_predict(items, y, hp, centres, K=K, Ks=Ks)
        return mean, var, int(repaired)
    # the paper's iterative k-means under the cluster cap, nearest-centre prediction
    data = TrainingData(hits, fs, fe, np.full(fs.shape[0], -1, dtype=np.int64))
    # a lattice at the map resolution is fine enough for a leaf's Voronoi cells
    cells = int(np.ceil(float(np.ptp(centres, axis=0).max()) / config.resolution)) + 3
    clusters = partition(data, config, cells=cells)
    gps = fit_clusters(data, clusters, config, hp)
    tree = cluster_tree(clusters, config.dim)
    mean, var = predict_nearest(tree, gps, centres, hp.signal_variance)
    return mean, var, sum(gp.repaired for gp in gps)


def inducing_lattice(leaf: Leaf, config: MapConfig) -> FloatArray:
    """``k**dim`` inducing points at the cell centres of a ``k``-lattice over the halo box.

    ``k`` is ``OnlineConfig.inducing_per_axis``; metres, world frame, shape (k**dim, d).
    """
    grid = LeafGrid.from_config(config)
    k, d = config.online.inducing_per_axis, config.dim
    lo, hi = grid.halo_box(leaf.index[None, :])
    cells = np.stack(np.meshgrid(*[np.arange(k)] * d, indexing="ij"), -1).reshape(-1, d)
    return np.asarray(lo[0] + (cells + 0.5) * ((hi[0] - lo[0]) / k))


@dataclass(frozen=True, slots=True)
class LeafFit:
    """A fitted leaf and what its fit needed.

    Attributes
    ----------
    leaf : Leaf
        The leaf with fresh voxel values.
    repaired : int
        Kernel matrices of this fit that needed a jitter.
    """

    leaf: Leaf
    repaired: int


def fit_leaf(
    leaf: Leaf, config: MapConfig, hp: Hyperparameters, cache: KernelCache | None = None
) -> LeafFit:
    """Fit a leaf on its evidence and return it with fresh voxel values (a pure function).

    The voxel centres follow from ``leaf.index`` and the leaf grid of ``config``; the
    latent mean and variance are predicted there (:func:`predict_leaf`) and PLSC gives
    P(occupied). A leaf whose voxels are all below ``prune_free`` or all above
    ``prune_occupied`` keeps one value, the least confident one, so a pruned leaf never
    overstates. Used by the map's threads and, unchanged, by Dask workers
    (:mod:`octolgp.batch.leafmap`).

    Parameters
    ----------
    leaf : Leaf
        Evidence of one leaf (its value arrays are ignored).
    config : MapConfig
    hp : Hyperparameters
    cache : KernelCache, optional
        Reused kernel blocks (:func:`predict_leaf`); the result does not depend on it.

    Returns
    -------
    LeafFit
        A copy of the leaf with ``mean``, ``var`` (float32, latent) and ``prob``,
        ``pruned`` set and ``refits`` incremented, and the fit's jitter repairs.
    """
    oc = config.online
    centres = LeafGrid.from_config(config).voxel_centres(leaf.index)
    mean, var, repaired = predict_leaf(leaf, centres, config, hp, cache)
    prob = latent_occupancy(mean, var, hp)
    pruned = False
    if oc.prune and (prob.max() < oc.prune_free or prob.min() > oc.prune_occupied):
        at = int(np.argmax(prob) if prob.max() < oc.prune_free else np.argmin(prob))
        mean, var, prob = mean[at : at + 1], var[at : at + 1], prob[at : at + 1]
        pruned = True
    fitted = dataclasses.replace(
        leaf,
        mean=mean.astype(np.float32),
        var=var.astype(np.float32),
        prob=prob.astype(np.float32),
        pruned=pruned,
        refits=leaf.refits + 1,
    )
    return LeafFit(fitted, repaired)


def fit_leaves(
    leaves: list[Leaf],
    config: MapConfig,
    hp: Hyperparameters,
    cache: KernelCache | None = None,
    pool: Executor | None = None,
) -> list[LeafFit]:
    """Fit leaves in order, on ``pool``'s threads when given (BLAS limits are the caller's).

    A Dask task runs it with ``pool=None``; the map runs it on its thread pool.
    """
    if pool is None or len(leaves) < 2:
        return [fit_leaf(leaf, config, hp, cache) for leaf in leaves]
    return list(pool.map(lambda leaf: fit_leaf(leaf, config, hp, cache), leaves))


def batch_bounds(sizes: list[int], items: int) -> Iterator[tuple[int, int]]:
    """``(lo, hi)`` runs of consecutive entries whose sizes sum to about ``items`` each.

    A run closes at the first entry that brings its sum to ``items`` or more; the last
    run may be smaller. Used to cut leaves (or clusters) into batches of work.
    """
    lo = total = 0
    for i, size in enumerate(sizes):  # one iteration per entry
        total += size
        if total >= items:
            yield lo, i + 1
            lo, total = i + 1, 0
    if lo < len(sizes):
        yield lo, len(sizes)


LeafFitter = Callable[[list[int], list[Leaf]], Iterator[tuple[list[int], list[LeafFit]]]]
"""Leaves with evidence → the same leaves fitted, batch by batch (local threads or a
cluster; :meth:`octolgp.mapping.online.OnlineMap.insert_batch`)."""
