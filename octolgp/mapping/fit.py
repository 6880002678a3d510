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

import functools
import itertools
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.geometry.keys import unpack_keys
from octolgp.gp.clusters import cluster_tree, fit_clusters, predict_nearest
from octolgp.gp.lattice import (
    HitPoints,
    LatticeGeometry,
    LatticeTables,
    inducing_per_axis,
    lattice_posterior,
    lattice_tables,
)
from octolgp.gp.plsc import latent_occupancy
from octolgp.gp.quadrature import items_and_targets, quadrature_spacing
from octolgp.gp.regression import fit_predict
from octolgp.mapping.cache import KernelCache, leaf_blocks
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.observations import effective_counts
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
    fitted = leaf.evolve(
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

    A Dask task runs it with ``pool=None``; the map runs it on its thread pool. The
    lattice engine fits all the leaves together (:func:`fit_lattice_leaves`).
    """
    if config.online.engine == "lattice":
        return fit_lattice_leaves(leaves, config, hp, pool)
    if pool is None or len(leaves) < 2:
        return [fit_leaf(leaf, config, hp, cache) for leaf in leaves]
    return list(pool.map(lambda leaf: fit_leaf(leaf, config, hp, cache), leaves))


def lattice_geometry(config: MapConfig, hp: Hyperparameters) -> LatticeGeometry:
    """The lattice of a map's leaves: leaf and halo in voxels, lattice points per axis."""
    grid = LeafGrid.from_config(config)
    oc = config.online
    k_max = oc.max_inducing_per_axis or (12 if config.dim == 2 else 4)
    box = grid.side + 2 * grid.halo_voxels
    k_min = min(k_max, box // 3)  # at least one lattice point per 3 voxels
    edge = box * grid.resolution
    k = inducing_per_axis(edge, hp.length_scale, config.inducing_spacing, k_min, k_max)
    return LatticeGeometry(config.dim, grid.side, grid.halo_voxels, k, grid.resolution)


@functools.lru_cache(maxsize=8)
def map_tables(config: MapConfig, hp: Hyperparameters) -> LatticeTables:
    """The lattice tables of a map (:func:`octolgp.gp.lattice.lattice_tables`), memoised.

    A pure function of its frozen arguments; the cache only saves recomputing them.
    """
    return lattice_tables(lattice_geometry(config, hp), hp)


def fit_lattice_leaves(
    leaves: list[Leaf],
    config: MapConfig,
    hp: Hyperparameters,
    pool: Executor | None = None,
) -> list[LeafFit]:
    """Fit lattice-engine leaves on their observation counts, all at once (pure).

    Each leaf's latent posterior at its voxel centres comes from
    :func:`octolgp.gp.lattice.lattice_posterior`, then PLSC and pruning as in
    :func:`fit_leaf`. With ``pool`` the leaves are split into ``config.n_jobs`` runs.

    Returns
    -------
    list of LeafFit
        One per leaf, in order (a lattice fit never needs a jitter repair).
    """
    if not leaves:
        return []
    oc = config.online
    tables = map_tables(config, hp)
    stored = np.stack([leaf.counts for leaf in leaves])
    hits, frees = effective_counts(stored[:, 0], stored[:, 1], oc.evidence_cap, config.clear_scans)
    n_halo = tables.phi.shape[0]
    if stored.shape[2] != n_halo:
        raise ValueError(f"lattice leaves hold {stored.shape[2]} voxels, expected {n_halo}")
    points = return_points(leaves, LeafGrid.from_config(config), tables, oc.evidence_cap)
    runs = 1 if pool is None else min(len(leaves), config.n_jobs)
    bounds = np.linspace(0, len(leaves), runs + 1).round().astype(int)
    parts = [(hits[lo:hi], frees[lo:hi], points[lo:hi]) for lo, hi in itertools.pairwise(bounds)]

    def run(part: tuple[np.ndarray, np.ndarray, HitPoints]) -> tuple[np.ndarray, np.ndarray]:
        return lattice_posterior(tables, part[0], part[1], oc.free_weight, part[2])

    results = [run(p) for p in parts] if pool is None or runs < 2 else list(pool.map(run, parts))
    mean = np.concatenate([r[0] for r in results])
    var = np.concatenate([r[1] for r in results])
    prob = latent_occupancy(mean, var, hp)
    pmax, pmin = prob.max(axis=1), prob.min(axis=1)
    free, occupied = pmax < oc.prune_free, pmin > oc.prune_occupied
    pruned = oc.prune & (free | occupied)
    at = np.where(free, prob.argmax(axis=1), prob.argmin(axis=1))
    out = []
    for j, leaf in enumerate(leaves):  # one iteration per leaf: build its record
        sl = slice(int(at[j]), int(at[j]) + 1) if pruned[j] else slice(None)
        fitted = leaf.evolve(
            mean=mean[j, sl].astype(np.float32),
            var=var[j, sl].astype(np.float32),
            prob=prob[j, sl].astype(np.float32),
            pruned=bool(pruned[j]),
            refits=leaf.refits + 1,
        )
        out.append(LeafFit(fitted, 0))
    return out


def return_points(
    leaves: list[Leaf], grid: LeafGrid, tables: LatticeTables, evidence_cap: int
) -> HitPoints:
    """Each lattice leaf's returns at their measured positions, with their weights.

    A voxel seen occupied contributes one point of weight ``min(counts[0, v],
    evidence_cap)``: the return the leaf kept for it (``Leaf.hits``), or the voxel
    centre if it has none (leaves written before positions were kept). Positions are
    relative to the leaf's lower corner, metres.
    """
    box, halo, d = tables.geometry.box, grid.halo_voxels, grid.dim
    n_kept = np.array([leaf.hit_keys.size for leaf in leaves])
    n_occupied = np.array([np.count_nonzero(leaf.counts[0]) for leaf in leaves])
    # every leaf made by gather_observations keeps one return per occupied voxel
    out: HitPoints = []
    if (n_kept == n_occupied).all():
        index = np.stack([leaf.index for leaf in leaves])
        owner = np.repeat(np.arange(len(leaves)), n_kept)
        keys = np.concatenate([leaf.hit_keys for leaf in leaves])
        local = unpack_keys(keys, d) - (index[owner] * grid.side - halo)
        flat = local @ (box ** np.arange(d, dtype=np.int64))
        counts = np.concatenate([leaf.counts[0] for leaf in leaves]).reshape(len(leaves), -1)
        weights = np.minimum(counts[owner, flat], evidence_cap).astype(np.float64)
        lo, _ = grid.box(index)
        pos = np.concatenate([leaf.hits for leaf in leaves]) - lo[owner]
        cuts = np.cumsum(n_kept)[:-1]
        return list(zip(np.split(pos, cuts), np.split(weights, cuts), strict=True))
    centres = tables.geometry.halo_centres()
    for leaf in leaves:  # leaves from files without positions: returns at voxel centres
        occupied = np.flatnonzero(leaf.counts[0])
        weights = np.minimum(leaf.counts[0, occupied], evidence_cap).astype(np.float64)
        out.append((centres[occupied], weights))
    return out


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
