"""Offline batch build: ``build_map(scans, config, method)`` for OM_LGP and baselines."""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import Any

from threadpoolctl import threadpool_limits

from octolgp.batch.gp import GlobalGPMap, fit_global_gp
from octolgp.batch.gpmap import GPMap
from octolgp.batch.lgp import LocalGPMap, fit_clusters
from octolgp.batch.mgp import MixtureGPMap, make_gate
from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_from_clusters
from octolgp.partition import partition
from octolgp.scan import Scan
from octolgp.training import check_scans, make_training_data

METHODS = ("lgp", "gp", "mgp", "ogm")


def build_map(
    scans: Iterable[Scan],
    config: MapConfig,
    method: str = "lgp",
    scheduler: Any = None,
    n_jobs: int = 1,
) -> Any:
    """Build a map offline from all scans at once.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim``.
    config : MapConfig
        With ``hyperparameters=None`` they are learnt first (timed as ``learning``).
    method : {"lgp", "gp", "mgp", "ogm"}
        ``"lgp"`` the paper's overlapping local GPs; ``"gp"`` one global GP;
        ``"mgp"`` a mixture of GP experts; ``"ogm"`` a log-odds occupancy grid.
    scheduler : None, "local", str or distributed.Client
        ``None``: build in this process. Otherwise ``"lgp"`` runs as the tiled build
        (:func:`octolgp.tiled.build_tiled`): the octree leaves (coarse boxes with
        overlap halos) are fitted as tasks on ``dask.distributed`` — ``"local"`` an
        embedded ``LocalCluster``, an address such as ``"tcp://host:8786"`` an
        existing cluster, or a ``Client`` — and the result is an
        :class:`~octolgp.online.OnlineMap` holding the voxel values (the same map as
        ``build_tiled(scans, config)`` in this process, bit for bit).
    n_jobs : int
        Threads over clusters for ``"lgp"`` (over leaves for the tiled build).

    Returns
    -------
    map
        An object with ``occupancy(points)``, ``latent(points)`` and ``timings``.

    Raises
    ------
    OctolgpError
        On an unknown method, bad scans or a bad config.
    """
    if not isinstance(config, MapConfig):
        raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
    if method not in METHODS:
        raise OctolgpError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if scheduler is not None:
        if method != "lgp":
            raise OctolgpError(f"scheduler: only method 'lgp' runs on Dask, got {method!r}")
        from octolgp.batch.leafmap import build_tiled

        return build_tiled(scans, config, scheduler=scheduler, n_jobs=n_jobs)
    scan_list = check_scans(scans, config.dim)
    if method == "ogm":
        from octolgp.batch.ogm import build_ogm

        return build_ogm(scan_list, config)

    # Local GPs are small: one BLAS/OpenMP thread each, parallelism across clusters.
    with threadpool_limits(limits=1 if method != "gp" else None):
        return _build_gp_map(scan_list, config, method, n_jobs)


def _build_gp_map(scan_list: list[Scan], config: MapConfig, method: str, n_jobs: int) -> GPMap:
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
    result: GPMap
    if method == "lgp":
        gps = fit_clusters(data, clusters, config, hp, n_jobs=n_jobs)
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
