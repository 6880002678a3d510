"""Offline batch builds: ``build_map(scans, config, method)`` for OM_LGP, the leaf map and baselines.

Which to use: ``"leaf"`` gives the online map's own map in one step (the same map as
inserting the scans one by one, so it can take more scans, be saved and exported);
``"lgp"`` is the paper's method as published (k-means clusters over the whole log),
for reproducing its figures and comparing against it.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any, TypeAlias

from threadpoolctl import threadpool_limits

from octolgp.batch.dask import dask_client
from octolgp.batch.gp import GlobalGPMap, fit_global_gp
from octolgp.batch.leafmap import TASK_ITEMS, build_tiled
from octolgp.batch.lgp import LocalGPMap
from octolgp.batch.mgp import MixtureGPMap, make_gate
from octolgp.batch.ogm import OccupancyGridMap, build_ogm
from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.gp.clusters import fit_clusters
from octolgp.gp.learning import learn_from_clusters
from octolgp.gp.quadrature import QuadratureSet, cluster_items, quadrature_spacing
from octolgp.gp.regression import LocalGP, fit_local_gp
from octolgp.mapping.evidence import batch_bounds
from octolgp.mapping.online import OnlineMap
from octolgp.partition import Cluster, partition
from octolgp.scan import FloatArray, Scan
from octolgp.training import TrainingData, check_scans, make_training_data

METHODS = ("lgp", "leaf", "gp", "mgp", "ogm")
"""Batch methods, in the order of Kim & Kim's Table II plus the leaf map."""

SCHEDULED = ("lgp", "leaf")
"""Methods that accept a Dask ``scheduler`` (the same map in-process and on a cluster)."""

BatchMap: TypeAlias = LocalGPMap | GlobalGPMap | MixtureGPMap | OccupancyGridMap | OnlineMap
"""What :func:`build_map` returns: each has ``occupancy(points)`` and ``latent(points)``."""


def build_map(
    scans: Iterable[Scan],
    config: MapConfig,
    method: str = "lgp",
    scheduler: Any = None,
    n_jobs: int = 1,
) -> BatchMap:
    """Build a map offline from all scans at once.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim``.
    config : MapConfig
        With ``hyperparameters=None`` they are learnt first (timed as ``learning``).
    method : {"lgp", "leaf", "gp", "mgp", "ogm"}
        ``"lgp"``: the paper's overlapping local GPs on iterative k-means clusters
        (Kim & Kim's OM_LGP; hyperparameters learnt on several clusters together).
        ``"leaf"``: the online map's octree leaves with overlap halos, each fitted
        once (:func:`octolgp.batch.leafmap.build_tiled`; hyperparameters learnt on
        the first ``learn_scans`` scans, as the online map does); it returns an
        :class:`~octolgp.mapping.online.OnlineMap` that can take more scans.
        ``"gp"``: one global GP; ``"mgp"``: a mixture of GP experts; ``"ogm"``: a
        log-odds occupancy grid.
    scheduler : None, "local", str or distributed.Client
        Where the work runs, for ``"lgp"`` (the clusters' GPs as tasks) and
        ``"leaf"`` (batches of leaves as tasks): ``None`` in this process;
        ``"local"`` an embedded ``LocalCluster``; an address such as
        ``"tcp://host:8786"`` an existing cluster; or a ``Client``. It never changes
        what is computed: the same call gives the same map either way.
    n_jobs : int
        Threads over clusters (``"lgp"``, ``"mgp"``) or leaves (``"leaf"``).

    Returns
    -------
    BatchMap
        An object with ``occupancy(points)`` and ``latent(points)``.

    Raises
    ------
    OctolgpError
        On an unknown method, a scheduler for a method that takes none, bad scans or
        a bad config.
    """
    if not isinstance(config, MapConfig):
        raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
    if method not in METHODS:
        raise OctolgpError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if scheduler is not None and method not in SCHEDULED:
        raise OctolgpError(
            f"scheduler: only methods {', '.join(SCHEDULED)} run on Dask, got {method!r}"
        )
    if method == "leaf":
        return build_tiled(scans, config, scheduler=scheduler, n_jobs=n_jobs)
    scan_list = check_scans(scans, config.dim)
    if method == "ogm":
        return build_ogm(scan_list, config)

    # Local GPs are small: one BLAS/OpenMP thread each, parallelism across clusters.
    with threadpool_limits(limits=1 if method != "gp" else None):
        return _build_gp_map(scan_list, config, method, n_jobs, scheduler)


def fit_item_sets(
    sets: list[tuple[QuadratureSet, FloatArray]], hp: Hyperparameters
) -> list[LocalGP]:
    """Fit one GP per ``(items, targets)`` in order (a Dask task; one BLAS thread)."""
    with threadpool_limits(limits=1):
        return [fit_local_gp(items, y, hp) for items, y in sets]


def _fit_clusters_on(
    scheduler: Any,
    data: TrainingData,
    clusters: list[Cluster],
    config: MapConfig,
    hp: Hyperparameters,
) -> list[LocalGP]:
    """:func:`fit_clusters` with the clusters' GPs fitted as tasks on a Dask cluster.

    Each task gets only its clusters' items (never the whole data set); the GPs come
    back in cluster order, equal to the in-process fits.
    """
    spacing = quadrature_spacing(config, hp.length_scale)
    sets = [cluster_items(data, c, config, spacing) for c in clusters]
    bounds = batch_bounds([items.n_items for items, _ in sets], TASK_ITEMS)
    with dask_client(scheduler, None) as client:
        hp_f = client.scatter(hp, broadcast=True)
        futures = [client.submit(fit_item_sets, sets[lo:hi], hp_f, pure=False) for lo, hi in bounds]
        return [gp for fut in futures for gp in fut.result()]


def _build_gp_map(
    scan_list: list[Scan], config: MapConfig, method: str, n_jobs: int, scheduler: Any = None
) -> LocalGPMap | GlobalGPMap | MixtureGPMap:
    """Training data, clustering, learning (if needed) and fitting, each timed."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    data = make_training_data(scan_list, config)
    timings["training_data"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    clusters = partition(data, config, overlap=0.0 if method == "mgp" else None)
    timings["clustering"] = time.perf_counter() - t0
    hp = config.hyperparameters
    t0 = time.perf_counter()
    if hp is None:
        hp = learn_from_clusters(data, clusters, config)
    timings["learning"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    result: LocalGPMap | GlobalGPMap | MixtureGPMap
    if method == "lgp":
        if scheduler is None:
            gps = fit_clusters(data, clusters, config, hp, n_jobs=n_jobs)
        else:
            gps = _fit_clusters_on(scheduler, data, clusters, config, hp)
        result = LocalGPMap(config, hp, clusters=clusters, gps=gps, n_jobs=n_jobs)
    elif method == "gp":
        result = GlobalGPMap(config, hp, gp=fit_global_gp(data, config, hp))
    else:
        gps = fit_clusters(data, clusters, config, hp, n_jobs=n_jobs)
        gate = make_gate(data, clusters, config.partition.box_size)
        result = MixtureGPMap(config, hp, gps=gps, gate=gate)
    timings["fitting"] = time.perf_counter() - t0
    result.timings.update(timings)
    return result
