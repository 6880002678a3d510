"""Hyperparameter learning: kernel by marginal likelihood, PLSC α, β by LOO.

With ``LearningConfig.objective == "lml+loo"`` (opt-in) all five are then refined
jointly by the LOO predictive probability of PLSC (R&W §6.5, eq. 5.13 gradients).

Length scales learnt on one small subset swing widely with the subset, so the log
marginal likelihood is summed over several clusters spread over the map, which
share the hyperparameters (each cluster an independent GP). The node layout of
the integral kernels is fixed during the optimisation (spacing from the initial
length scale, ``10 × resolution``) so the objective is smooth.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.gp.kernels import BlockWorkspace
from octolgp.gp.likelihood import log_marginal_likelihood, loo_log_predictive, loo_predictions
from octolgp.gp.plsc import fit_plsc
from octolgp.gp.quadrature import QuadratureSet, cluster_items, quadrature_spacing
from octolgp.memory import release_free_memory
from octolgp.partition import Cluster, partition
from octolgp.scan import FloatArray, Scan
from octolgp.training import TrainingData, make_training_data

MIN_NOISE_VARIANCE = 1e-2
"""Lower bound of the learnt noise variance ``σn²`` (targets are ±1): on real logs the
likelihood otherwise drives ``σn²`` to ~1e-4 on some subsets, the length scale with it,
and held-out AUC drops (``BENCHMARKS.md``, "Real logs: held-out AUC")."""


def _subsample(
    data: TrainingData,
    cluster: Cluster,
    config: MapConfig,
    spacing: float,
    rng: np.random.Generator,
) -> tuple[QuadratureSet, FloatArray]:
    """A cluster's items, randomly thinned to ``learning.max_items_per_cluster``."""
    items, y = cluster_items(data, cluster, config, spacing)
    cap = config.learning.max_items_per_cluster
    if y.size <= cap:
        return items, y
    keep = np.sort(rng.choice(y.size, size=cap, replace=False))
    return items.subset(keep), y[keep]


def learning_sets(
    data: TrainingData, clusters: list[Cluster], config: MapConfig, spacing: float
) -> list[tuple[QuadratureSet, FloatArray]]:
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
    sets: list[tuple[QuadratureSet, FloatArray]],
    n_params: int,
    scale: float,
    work: BlockWorkspace | None = None,
) -> Objective:
    """``−scale · Σ term(items, y, x, work)`` and its gradient.

    Node distances are recomputed block by block at every evaluation rather than
    kept (the eight sets' ``(N, N)`` matrices took 125 MB on 40 FR079 scans), in
    ``work`` (:class:`~octolgp.gp.kernels.BlockWorkspace`, 12 MiB; by default one
    that lives as long as the objective).
    """
    work = BlockWorkspace() if work is None else work

    def objective(x: FloatArray) -> tuple[float, FloatArray]:
        value, grad = 0.0, np.zeros(n_params)
        for items, y in sets:
            v, g = term(items, y, x, work)
            value += v
            grad += g
        if not np.isfinite(value):
            return 1e300, np.zeros(n_params)
        return -value * scale, -grad * scale

    return objective


def fit_kernel(
    sets: list[tuple[QuadratureSet, FloatArray]],
    initial: Hyperparameters,
    min_noise_variance: float = 1e-4,
    work: BlockWorkspace | None = None,
) -> tuple[float, float, float]:
    """Maximise the summed log marginal likelihood over log-parameters (L-BFGS-B).

    The noise variance is kept at or above ``min_noise_variance``
    (the map learns with :data:`MIN_NOISE_VARIANCE`). ``work``: the kernel's node blocks, to
    reuse.

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
    for shift in (0.0, np.log(3.0)):  # two starts in the length scale
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
    sets: list[tuple[QuadratureSet, FloatArray]],
    ell: float,
    sf2: float,
    sn2: float,
    config: MapConfig,
    work: BlockWorkspace | None = None,
) -> Hyperparameters:
    """The kernel with PLSC α, β fitted by LOO on ``sets`` (and the optional refinement)."""
    hp = Hyperparameters(length_scale=ell, signal_variance=sf2, noise_variance=sn2)
    mus, vs, ys = [], [], []
    for items, y in sets:
        mu, var = loo_predictions(items, y, hp, work)
        mus.append(mu)
        vs.append(var)
        ys.append(y)
    alpha, beta = fit_plsc(
        np.concatenate(mus),
        np.concatenate(vs),
        np.concatenate(ys),
    )
    hp = Hyperparameters(ell, sf2, sn2, alpha, beta)
    if config.learning.objective == "lml+loo":
        hp = refine_by_loo(sets, hp, work)
    return hp


def refine_by_loo(
    sets: list[tuple[QuadratureSet, FloatArray]],
    start: Hyperparameters,
    work: BlockWorkspace | None = None,
) -> Hyperparameters:
    """Maximise the summed LOO log predictive probability over all five parameters."""
    n_total = max(sum(y.size for _, y in sets), 1)
    # per-item mean: sane first steps for L-BFGS-B
    objective = _negated_sum(loo_log_predictive, sets, 5, 1.0 / n_total, work)

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


def learn_hyperparameters(scans: Iterable[Scan], config: MapConfig) -> Hyperparameters:
    """Learn kernel hyperparameters and PLSC α, β from scans.

    Parameters
    ----------
    scans : iterable of Scan
    config : MapConfig
        ``learning`` chooses the data subset: ``max_clusters`` clusters of at most
        ``max_items_per_cluster`` items each. Both online engines use the
        hyperparameters learnt here, on hits and free segments with integral
        kernels (the paper's model).

    Returns
    -------
    Hyperparameters
        Pass it on with ``MapConfig(..., hyperparameters=hp)``.

    Notes
    -----
    Memory: the kernel matrices are built from node blocks of at most 4 MiB
    (:func:`octolgp.gp.kernels.covariance_with_grad`), and the freed heap is handed
    back to the OS at the end (:func:`octolgp.memory.release_free_memory`). On the
    first 40 FR079 scans the RSS rises ~30 MB during the learning and ~5 MB stay
    after it (it was ~245 MB and ~70 MB with whole ``(N, N)`` node matrices kept per
    cluster), besides ~52 MB for importing scikit-learn's k-means (the partition).

    Raises
    ------
    OctolgpError
        On bad scans, scans that give no training data (every beam on its sensor) or
        no return (every beam a no-return).
    """
    data = make_training_data(scans, config)
    if data.n_items == 0:
        raise OctolgpError(
            "learn_hyperparameters: the scans give no training data (every beam has zero "
            "length); pass MapConfig.hyperparameters or scans with real beams"
        )
    if data.hits.shape[0] == 0:
        raise OctolgpError(
            "learn_hyperparameters: the scans hold no return (every beam is a no-return, "
            "so nothing is occupied to learn from); pass MapConfig.hyperparameters or "
            "scans that hit something"
        )
    with threadpool_limits(limits=1):  # small matrices: one BLAS thread is fastest
        hp = learn_from_clusters(data, partition(data, config), config)
    del data
    release_free_memory()  # the freed kernel blocks would otherwise stay resident (glibc)
    return hp
