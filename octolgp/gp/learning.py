"""Hyperparameter learning: kernel by marginal likelihood, PLSC α, β by LOO.

With ``LearningConfig.objective == "lml+loo"`` (opt-in) all five are then refined
jointly by the LOO predictive probability of PLSC (R&W §6.5, eq. 5.13 gradients).

Length scales learnt on one small subset swing widely with the subset, so the log
marginal likelihood is summed over several sets spread over the map, which share the
hyperparameters (each set an independent GP). The sets hold one of two observation
models (``LearningConfig.model``):

- *voxels* (the lattice engine's own model, its default): every observed voxel is a
  point observation, a voxel seen occupied at its kept return (target +1, noise
  ``σn² / h`` for ``h`` counted returns), one seen free at its centre (target −1, noise
  ``σn² / (free_weight f)`` for ``f`` counted free looks, whichever ``free_evidence``
  the leaves fit with); each set is the nearest
  occupied voxels around a seed and the free voxels within the same radius, and the
  scans are observed only in balls around the seeds (most of a long beam's voxels
  are far from every seed). Point kernels only: a set of ``n`` items is an
  ``(n, n)`` matrix.
- *segments* (the exact engine's and the batch map's): hits and free segments with the
  integral kernels of :mod:`octolgp.gp.kernels`, on clusters of
  :func:`octolgp.partition.partition`. The node layout is fixed during the
  optimisation (spacing from the initial length scale, ``10 × resolution``) so the
  objective is smooth.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import (
    KeyRegion,
    coord_to_key,
    key_to_coord,
    pack_keys,
)
from octolgp.gp.kernels import BlockWorkspace
from octolgp.gp.likelihood import log_marginal_likelihood, loo_log_predictive, loo_predictions
from octolgp.gp.plsc import fit_plsc
from octolgp.gp.quadrature import QuadratureSet, cluster_items, points_set, quadrature_spacing
from octolgp.memory import release_free_memory
from octolgp.observations import advance, effective_counts, observe
from octolgp.partition import Cluster, partition
from octolgp.scan import FloatArray, Scan
from octolgp.training import (
    TrainingData,
    check_scans,
    config_beams,
    make_training_data,
    stack_beams,
)

MIN_NOISE_VARIANCE = 1e-2
"""Lower bound of the learnt noise variance ``σn²`` (targets are ±1): on real logs the
likelihood otherwise drives ``σn²`` to ~1e-4 on some subsets, the length scale with it,
and held-out AUC drops (``BENCHMARKS.md``, "Real logs: held-out AUC")."""


@dataclass(frozen=True)
class LearningSet:
    """One independent GP of the learning objective.

    Attributes
    ----------
    items : QuadratureSet
        ``n`` training items (points, or hits and free segments as quadrature nodes).
    y : ndarray of shape (n,)
        Targets: +1 occupied, −1 free.
    noise_scale : ndarray of shape (n,) or None
        Per-item factors of the noise variance (``σn² s_i``); ``None``: all ones.
    """

    items: QuadratureSet
    y: FloatArray
    noise_scale: FloatArray | None = None


def learning_model(config: MapConfig) -> str:
    """The observation model the hyperparameters are learnt on: ``"voxels"`` or ``"segments"``.

    ``LearningConfig.model``, where ``"engine"`` is the online engine's own model:
    voxels for the lattice engine, segments for the exact one.
    """
    model = config.learning.model
    if model == "engine":
        return "voxels" if config.online.engine == "lattice" else "segments"
    return model


def _subsample(
    data: TrainingData,
    cluster: Cluster,
    config: MapConfig,
    spacing: float,
    rng: np.random.Generator,
) -> LearningSet:
    """A cluster's items, randomly thinned to ``learning.max_items_per_cluster``."""
    items, y = cluster_items(data, cluster, config, spacing)
    cap = config.learning.max_items_per_cluster
    if y.size <= cap:
        return LearningSet(items, y)
    keep = np.sort(rng.choice(y.size, size=cap, replace=False))
    return LearningSet(items.subset(keep), y[keep])


def learning_sets(
    data: TrainingData, clusters: list[Cluster], config: MapConfig, spacing: float
) -> list[LearningSet]:
    """Pick up to ``learning.max_clusters`` clusters spread over the map, thinned."""
    rng = np.random.default_rng(config.learning.seed)
    if not clusters:
        return []
    k = min(config.learning.max_clusters, len(clusters))
    # spread: order clusters along their principal direction and take evenly spaced ones
    centres = np.array([c.centre for c in clusters])
    axis = np.argmax(np.ptp(centres, axis=0))
    order = np.argsort(centres[:, axis], kind="stable")
    chosen = order[np.linspace(0, len(clusters) - 1, k).round().astype(int)]
    return [_subsample(data, clusters[i], config, spacing, rng) for i in np.unique(chosen)]


Objective = Callable[[FloatArray], tuple[float, FloatArray]]


def _negated_sum(
    term: Callable[..., tuple[float, FloatArray]],
    sets: list[LearningSet],
    n_params: int,
    scale: float,
    work: BlockWorkspace | None = None,
    **options: bool,
) -> Objective:
    """``−scale · Σ term(items, y, x, work, noise_scale, **options)`` and its gradient.

    Node distances are recomputed block by block at every evaluation rather than
    kept (the eight sets' ``(N, N)`` matrices took 125 MB on 40 FR079 scans), in
    ``work`` (:class:`~octolgp.gp.kernels.BlockWorkspace`, 12 MiB; by default one
    that lives as long as the objective).
    """
    work = BlockWorkspace() if work is None else work

    def objective(x: FloatArray) -> tuple[float, FloatArray]:
        value, grad = 0.0, np.zeros(n_params)
        for part in sets:
            v, g = term(part.items, part.y, x, work, part.noise_scale, **options)
            value += v
            grad += g
        if not np.isfinite(value):
            return 1e300, np.zeros(n_params)
        return -value * scale, -grad * scale

    return objective


def fit_kernel(
    sets: list[LearningSet],
    initial: Hyperparameters,
    min_noise_variance: float = 1e-4,
    work: BlockWorkspace | None = None,
    shifts: tuple[float, ...] = (0.0, float(np.log(3.0))),
) -> tuple[float, float, float]:
    """Maximise the summed log marginal likelihood over log-parameters (L-BFGS-B).

    The noise variance is kept at or above ``min_noise_variance``
    (the map learns with :data:`MIN_NOISE_VARIANCE`). ``work``: the kernel's node blocks, to
    reuse. ``shifts``: the starts, ``initial`` with its log length scale shifted by each;
    the best optimum wins.

    Returns
    -------
    length_scale, signal_variance, noise_variance : float
    """
    objective = _negated_sum(log_marginal_likelihood, sets, n_params=3, scale=1.0, work=work)

    x0 = np.log([initial.length_scale, initial.signal_variance, initial.noise_variance])
    floor = np.log(min_noise_variance)
    bounds = [(np.log(1e-2), np.log(1e2)), (np.log(1e-2), np.log(1e3)), (floor, np.log(1e2))]
    x0[2] = max(x0[2], floor)
    best = None
    for shift in shifts:  # a few starts in the length scale
        start = x0 + np.array([shift, 0.0, 0.0])
        res = minimize(objective, start, jac=True, method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    ell, sf2, sn2 = np.exp(best.x)
    return float(ell), float(sf2), float(sn2)


def learn_from_clusters(
    data: TrainingData, clusters: list[Cluster], config: MapConfig
) -> Hyperparameters:
    """Learn the kernel on several clusters together, then α, β by LOO on the same sets.

    Every kernel evaluation shares one :class:`~octolgp.gp.kernels.BlockWorkspace`,
    freed on return.
    """
    work = BlockWorkspace()
    initial = Hyperparameters(length_scale=10.0 * config.resolution)
    spacing = quadrature_spacing(config, initial.length_scale)
    sets = learning_sets(data, clusters, config, spacing)
    ell, sf2, sn2 = fit_kernel(sets, initial, MIN_NOISE_VARIANCE, work)
    spacing = quadrature_spacing(config, ell)
    sets = learning_sets(data, clusters, config, spacing)
    return _with_plsc(sets, ell, sf2, sn2, config, work)


def _with_plsc(
    sets: list[LearningSet],
    ell: float,
    sf2: float,
    sn2: float,
    config: MapConfig,
    work: BlockWorkspace | None = None,
    latent: bool = False,
) -> Hyperparameters:
    """The kernel with PLSC α, β fitted by LOO on ``sets`` (and the optional refinement).

    ``latent``: the LOO variances are those of the latent function (see
    :func:`~octolgp.gp.likelihood.loo_predictions`), not of a noisy observation.
    """
    hp = Hyperparameters(length_scale=ell, signal_variance=sf2, noise_variance=sn2)
    mus, vs, ys = [], [], []
    for part in sets:
        mu, var = loo_predictions(part.items, part.y, hp, work, part.noise_scale, latent)
        mus.append(mu)
        vs.append(var)
        ys.append(part.y)
    alpha, beta = fit_plsc(
        np.concatenate(mus),
        np.concatenate(vs),
        np.concatenate(ys),
    )
    hp = Hyperparameters(ell, sf2, sn2, alpha, beta)
    if config.learning.objective == "lml+loo":
        hp = refine_by_loo(sets, hp, work, latent)
    return hp


def refine_by_loo(
    sets: list[LearningSet],
    start: Hyperparameters,
    work: BlockWorkspace | None = None,
    latent: bool = False,
) -> Hyperparameters:
    """Maximise the summed LOO log predictive probability over all five parameters.

    ``latent``: LOO variances of the latent function (as in :func:`_with_plsc`).
    """
    n_total = max(sum(part.y.size for part in sets), 1)
    # per-item mean: sane first steps for L-BFGS-B
    objective = _negated_sum(loo_log_predictive, sets, 5, 1.0 / n_total, work, latent=latent)

    x0 = np.array(
        [
            np.log(start.length_scale),
            np.log(start.signal_variance),
            np.log(start.noise_variance),
            start.alpha,
            start.beta,
        ]
    )
    bounds = [
        (np.log(1e-2), np.log(1e2)),
        (np.log(1e-2), np.log(1e3)),
        (np.log(1e-4), np.log(1e2)),
        (1e-3, 1e3),
        (-1e2, 1e2),
    ]
    res = minimize(objective, x0, jac=True, method="L-BFGS-B", bounds=bounds)
    ell, sf2, sn2 = np.exp(res.x[:3])
    return Hyperparameters(float(ell), float(sf2), float(sn2), float(res.x[3]), float(res.x[4]))


def voxel_observations(
    scans: Iterable[Scan], config: MapConfig, region: KeyRegion | None = None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Every voxel the scans observe (in ``region``), as the lattice engine sees it after them.

    The counts are those a map's leaves hold after the scans
    (:func:`octolgp.observations.advance` from nothing, then
    :func:`~octolgp.observations.effective_counts`): a voxel with a return is occupied,
    at its kept return, weighing its return count; one seen only free is free, at its
    centre, weighing ``lattice.free_weight`` times its free count. The sets weigh free
    voxels so whichever ``lattice.free_evidence`` the leaves fit with, for the kernel and
    for α, β alike: a chord share is a voxel's part of a chord through the 16-voxel box
    holding it, and a learning set is a ball spanning several boxes, so chord weights
    would tie the sets' balance of free and occupied evidence to where the box borders
    fall. On sparse scans, where most chords cross a box whole and each voxel's share is
    small, that balance leaves too little free evidence to bound the length scale, and
    α, β calibrated by LOO on chord-weighted sets give the maps' held-out probabilities a
    worse Brier score than those calibrated on looks (BENCHMARKS.md). Where later free looks
    forgot every return (a world that changed while the scans were taken), the voxels
    with returns count as occupied anyway, so that there is something to learn from.
    With a ``region`` (:func:`octolgp.observations.observe`'s) only its voxels are
    observed, each as in the whole result.

    Returns
    -------
    points : ndarray of shape (n, d)
        Metres, world frame: the occupied voxels, then the free ones.
    y : ndarray of shape (n,)
        +1 occupied, −1 free.
    weights : ndarray of shape (n,)
        ``w`` of the observation noise ``σn² / w``.
    """
    looks = dataclasses.replace(config.lattice, free_evidence="looks")
    obs = observe(scans, dataclasses.replace(config, lattice=looks), region)
    cap = config.lattice.evidence_cap
    zero = np.zeros(obs.n_voxels, dtype=np.int64)
    state = advance(zero, zero, obs, np.arange(obs.n_voxels), cap)
    hits, frees = effective_counts(state.hits, state.frees, cap, config.clear_scans)
    kept = state.position
    if not np.any(hits) and np.any(obs.hits):  # every return forgotten
        hits, kept = np.minimum(obs.hits, cap), obs.first_hit
        frees = np.where(hits > 0, 0, frees)
    centres = key_to_coord(obs.keys, config.resolution, config.tree_depth)
    occupied = hits > 0
    free = ~occupied & (frees > 0)
    at = np.where(np.isnan(kept[occupied]), centres[occupied], kept[occupied])
    points = np.concatenate([at, centres[free]])
    y = np.concatenate([np.ones(int(occupied.sum())), -np.ones(int(free.sum()))])
    free_weight = config.lattice.free_weight
    weights = np.concatenate([hits[occupied].astype(np.float64), free_weight * frees[free]])
    return points, y, weights


def voxel_learning_sets(
    points: FloatArray, y: FloatArray, weights: FloatArray, config: MapConfig
) -> list[LearningSet]:
    """Up to ``learning.max_clusters`` sets of voxel observations spread over the map.

    Seeds are occupied voxels evenly spaced in their order along the axis of largest
    extent (:func:`spread_seeds`); each set is :func:`voxel_sets`' around its seed.

    Parameters
    ----------
    points, y, weights : ndarray of shape (n, d), (n,), (n,)
        As returned by :func:`voxel_observations`, with at least one occupied voxel.
    config : MapConfig

    Returns
    -------
    list of LearningSet
        Point items, noise scales ``1 / w``.
    """
    seeds = spread_seeds(points[y > 0], config.learning.max_clusters)
    return voxel_sets(points, y, weights, seeds, config)


def spread_seeds(hit_points: FloatArray, count: int) -> FloatArray:
    """Up to ``count`` of ``hit_points`` evenly spaced in their order along the widest axis.

    Parameters
    ----------
    hit_points : ndarray of shape (n, d)
        Metres, at least one.
    count : int

    Returns
    -------
    ndarray of shape (k, d)
        Distinct picks, ``k <= count``.
    """
    axis = int(np.argmax(np.ptp(hit_points, axis=0)))
    order = np.argsort(hit_points[:, axis], kind="stable")
    k = min(count, hit_points.shape[0])
    picks = np.unique(order[np.linspace(0, hit_points.shape[0] - 1, k).round().astype(int)])
    seeds: FloatArray = hit_points[picks]
    return seeds


def voxel_sets(
    points: FloatArray, y: FloatArray, weights: FloatArray, seeds: FloatArray, config: MapConfig
) -> list[LearningSet]:
    """One learning set per seed: its nearest occupied voxels and the free ones around.

    A set holds the ``max_items_per_cluster // 2`` occupied voxels nearest its seed and
    the free voxels within the distance of the farthest of them, randomly thinned
    (``learning.seed``) to fill ``max_items_per_cluster`` items.

    Parameters
    ----------
    points, y, weights : ndarray of shape (n, d), (n,), (n,)
        As returned by :func:`voxel_observations`, with at least one occupied voxel.
    seeds : ndarray of shape (k, d)
        Metres.
    config : MapConfig

    Returns
    -------
    list of LearningSet
        Point items, noise scales ``1 / w``.
    """
    lc = config.learning
    rng = np.random.default_rng(lc.seed)
    occupied, free = np.flatnonzero(y > 0), np.flatnonzero(y < 0)
    hit_points, free_points = points[occupied], points[free]
    cap = lc.max_items_per_cluster
    n_near = min(cap // 2, occupied.size)
    sets = []
    for seed in seeds:  # one iteration per set, a few
        d2 = np.sum((hit_points - seed) ** 2, axis=1)
        near = np.argsort(d2, kind="stable")[:n_near]
        inside = np.flatnonzero(np.sum((free_points - seed) ** 2, axis=1) <= d2[near[-1]])
        if inside.size > cap - n_near:
            inside = np.sort(rng.choice(inside, size=cap - n_near, replace=False))
        idx = np.concatenate([occupied[near], free[inside]])
        sets.append(LearningSet(points_set(points[idx]), y[idx], 1.0 / weights[idx]))
    return sets


def learning_voxel_sets(scans: list[Scan], config: MapConfig) -> list[LearningSet]:
    """:func:`voxel_learning_sets` of the scans, observing only the voxels the sets need.

    Two reads of the scans in regions (:class:`~octolgp.geometry.keys.KeyRegion`), each
    exactly the whole observation there: first the blocks holding a return, which hold
    every occupied voxel, for the seeds and each set's radius; then the balls of those
    radii around the seeds. The sets are those of every observed voxel, while the
    voxels far from every return and every seed (most of a long beam's) are dropped as
    they are walked instead of counted.

    Raises
    ------
    OctolgpError
        On scans that observe no voxel or hold no return.
    """
    res, depth, dim = config.resolution, config.tree_depth, config.dim
    origins, ends, max_range = stack_beams(check_scans(scans, dim))
    returns = ends[config_beams(origins, ends, max_range, config).is_hit]
    if returns.shape[0] == 0:
        _, y, _ = voxel_observations(scans, config)
        raise _no_return() if y.size else _no_data()
    holding = KeyRegion.holding(np.unique(pack_keys(coord_to_key(returns, res, depth))), dim)
    points, y, _ = voxel_observations(scans, config, holding)
    occupied = points[y > 0]  # every occupied voxel is one holding a return
    seeds = spread_seeds(occupied, config.learning.max_clusters)
    n_near = min(config.learning.max_items_per_cluster // 2, occupied.shape[0])
    d2 = np.sum((occupied[None, :, :] - seeds[:, None, :]) ** 2, axis=2)  # (k, voxels)
    reach = np.sqrt(np.partition(d2, n_near - 1, axis=1)[:, n_near - 1])
    # a set holds the occupied voxels within ``reach`` of its seed and the free ones
    # whose centres are: a kept return lies within half a voxel diagonal of its centre
    ball = reach + 0.5 * res * np.sqrt(dim)
    points, y, weights = voxel_observations(
        scans, config, KeyRegion.around(seeds, ball, res, depth)
    )
    return voxel_sets(points, y, weights, seeds, config)


def thinned(scans: list[Scan], max_beams: int | None) -> list[Scan]:
    """Every k-th beam of each scan, the smallest k leaving at most ``max_beams`` in all.

    The scans themselves when they hold no more (or ``max_beams`` is ``None``).
    """
    total = sum(len(s) for s in scans)
    if max_beams is None or total <= max_beams:
        return scans
    k = -(-total // max_beams)
    return [dataclasses.replace(s, points=s.points[::k]) for s in scans]


def learn_from_voxels(scans: Iterable[Scan], config: MapConfig) -> Hyperparameters:
    """Learn on voxel observations: the kernel by LML on :func:`voxel_learning_sets`, then α, β.

    α, β are fitted by LOO on the same sets with the latent LOO variances, as the map
    applies PLSC to its latent posterior.

    Raises
    ------
    OctolgpError
        On scans that observe no voxel or hold no return.
    """
    sets = learning_voxel_sets(thinned(list(scans), config.learning.max_beams), config)
    work = BlockWorkspace()
    initial = Hyperparameters(length_scale=10.0 * config.resolution)
    # one start: from a third and three times the initial length scale the optimum is
    # the same to 1e-5 on Intel, FR079 and the lidar room
    ell, sf2, sn2 = fit_kernel(sets, initial, MIN_NOISE_VARIANCE, work, shifts=(0.0,))
    return _with_plsc(sets, ell, sf2, sn2, config, work, latent=True)


def _no_data() -> OctolgpError:
    return OctolgpError(
        "learn_hyperparameters: the scans give no training data (every beam has zero "
        "length); pass MapConfig.hyperparameters or scans with real beams"
    )


def _no_return() -> OctolgpError:
    return OctolgpError(
        "learn_hyperparameters: the scans hold no return (every beam is a no-return, "
        "so nothing is occupied to learn from); pass MapConfig.hyperparameters or "
        "scans that hit something"
    )


def learn_hyperparameters(scans: Iterable[Scan], config: MapConfig) -> Hyperparameters:
    """Learn kernel hyperparameters and PLSC α, β from scans.

    Parameters
    ----------
    scans : iterable of Scan
    config : MapConfig
        ``learning.model`` chooses the observation model (:func:`learning_model`:
        by default the online engine's own, voxel observations for the lattice
        engine, hits and free segments with integral kernels for the exact one), and
        ``learning`` the subset: ``max_clusters`` sets of at most
        ``max_items_per_cluster`` items each.

    Returns
    -------
    Hyperparameters
        Pass it on with ``MapConfig(..., hyperparameters=hp)``.

    Notes
    -----
    Time: on the voxel model the sets are ``(n, n)`` point kernels (n = 300 by
    default), so the optimisation costs about as much as turning the scans into voxel
    observations (each a few tenths of a second on 40 Intel scans or 5 lidar scans).
    Memory: the segment model's kernel matrices are built from node blocks of at most
    4 MiB (:func:`octolgp.gp.kernels.covariance_with_grad`), and either model hands the
    freed heap back to the OS at the end (:func:`octolgp.memory.release_free_memory`).
    On the first 40 FR079 scans the segment model's RSS rises ~30 MB during the
    learning and ~5 MB stay after it, besides ~52 MB for importing scikit-learn's
    k-means (its partition); the voxel model imports no scikit-learn.

    Raises
    ------
    OctolgpError
        On bad scans, scans that give no training data (every beam on its sensor) or
        no return (every beam a no-return).
    """
    if learning_model(config) == "voxels":
        with threadpool_limits(limits=1):  # small matrices: one BLAS thread is fastest
            hp = learn_from_voxels(scans, config)
        release_free_memory()
        return hp
    data = make_training_data(scans, config)
    if data.n_items == 0:
        raise _no_data()
    if data.hits.shape[0] == 0:
        raise _no_return()
    with threadpool_limits(limits=1):  # small matrices: one BLAS thread is fastest
        hp = learn_from_clusters(data, partition(data, config), config)
    del data
    release_free_memory()  # the freed kernel blocks would otherwise stay resident (glibc)
    return hp
