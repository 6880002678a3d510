"""Whole-log builds into the leaf store: every leaf fitted once, locally or on Dask.

:func:`build_tiled` is the batch counterpart of :class:`~octolgp.mapping.online.OnlineMap`:
all scans become training data at once, the evidence is split into the octree leaves
(coarse boxes with overlap halos, :mod:`octolgp.mapping.grid`) with the same first-per-voxel
rule, and each leaf is fitted **once** — the paper's iterative k-means under the
cluster cap inside leaves that hold more than ``OnlineConfig.max_leaf_items`` — and
predicted at its voxel centres. Fitting a leaf is a pure function of its evidence
(:func:`~octolgp.mapping.fit.fit_leaf`), so the leaves can run

- in this process, on ``n_jobs`` threads (BLAS pinned to one thread each), or
- as tasks on a ``dask.distributed`` cluster (``scheduler=``): an embedded
  ``LocalCluster`` (``"local"``), an existing scheduler by address
  (``"tcp://host:8786"``) or a ``Client``. Each task receives only its batch of leaves'
  evidence (never the whole data set) and returns their voxel values; the driver
  assembles them into the store as they complete.

Both paths give bit-for-bit the same map (tested), which is also the map an
:class:`OnlineMap` builds when handed all the scans in one step.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from octolgp.batch.dask import dask_client
from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import LeafFit, engine_for
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_hyperparameters
from octolgp.mapping.evidence import LeafFitter, batch_bounds, map_scans
from octolgp.mapping.online import OnlineMap
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan
from octolgp.training import check_scans

__all__ = ["TASK_ITEMS", "build_tiled", "fit_leaves_task"]

TASK_ITEMS = 20_000
"""Training items (summed over leaves) per Dask task: tasks of ~0.1-1 s, few enough
that the scheduler's per-task overhead (~1 ms) stays negligible."""


def fit_leaves_task(leaves: list[Leaf], config: MapConfig, hp: Hyperparameters) -> list[LeafFit]:
    """Fit a batch of leaves in order: a Dask task, with BLAS limited to one thread."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return engine_for(config).fit(leaves, hp, reuse=False)


def build_tiled(
    scans: Iterable[Scan],
    config: MapConfig,
    *,
    path: str | Path | None = None,
    scheduler: Any = None,
    workers: int | None = None,
    n_jobs: int = 1,
    task_items: int = TASK_ITEMS,
    progress: Callable[[int, int], None] | None = None,
) -> OnlineMap:
    """Build a leaf-store map from all scans at once, each leaf fitted once.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim``.
    config : MapConfig
        With ``hyperparameters=None`` they are learnt on the first
        ``config.learn_scans`` scans, as the online map does.
    path : str or Path, optional
        Map file to write (SQLite, as :class:`OnlineMap`); must not exist. ``None``
        keeps the map in memory.
    scheduler : None, "local", str or distributed.Client
        ``None``: fit in this process on ``n_jobs`` threads. ``"local"``: an embedded
        ``LocalCluster`` of ``workers`` processes (default: one per core). An address
        such as ``"tcp://10.0.0.5:8786"``: that cluster. A ``Client``: use it.
    workers : int, optional
        Worker processes of the embedded cluster.
    n_jobs : int
        Threads over leaves for ``scheduler=None``.
    task_items : int
        Training items per Dask task.
    progress : callable, optional
        Called as ``progress(leaves_fitted, leaves_total)`` after each batch of leaves.

    Returns
    -------
    OnlineMap
        Holding every scan (``n_scans``) and every leaf; can take more scans online.
        ``build_stats`` holds the stage timings and sizes.

    Raises
    ------
    OctolgpError
        On bad scans or config, a bad scheduler, or a cluster that cannot be reached.
    """
    if not isinstance(config, MapConfig):
        raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, int) or n_jobs < 1:
        raise OctolgpError(f"n_jobs must be an integer >= 1, got {n_jobs!r}")
    if isinstance(task_items, bool) or not isinstance(task_items, int) or task_items < 1:
        raise OctolgpError(f"task_items must be an integer >= 1, got {task_items!r}")
    scan_list = map_scans(check_scans(scans, config.dim), config)  # learnt on what the map uses
    hp = config.hyperparameters
    if hp is None:
        hp = learn_hyperparameters(scan_list[: config.learn_scans], config)
    fixed = dataclasses.replace(
        config,
        hyperparameters=hp,
        online=dataclasses.replace(config.online, n_jobs=n_jobs),
    )
    m = OnlineMap(fixed, path)
    try:
        fitter = (
            None if scheduler is None else _dask_fitter(fixed, hp, scheduler, workers, task_items)
        )
        m.insert_batch(scan_list, fitter=fitter, progress=progress)
    except BaseException:
        m.close()
        raise
    return m


def _dask_fitter(
    config: MapConfig, hp: Hyperparameters, scheduler: Any, workers: int | None, task_items: int
) -> LeafFitter:
    """Fit batches of leaves as tasks on a Dask cluster, yielding them as they complete."""

    def fitter(keys: list[int], leaves: list[Leaf]) -> Iterator[tuple[list[int], list[LeafFit]]]:
        from distributed import as_completed

        with dask_client(scheduler, workers) as client:
            # the config and hyperparameters travel to every worker once
            config_f, hp_f = client.scatter([config, hp], broadcast=True)
            bounds = batch_bounds([leaf.n_items for leaf in leaves], task_items)
            futures = {
                client.submit(fit_leaves_task, leaves[lo:hi], config_f, hp_f, pure=False): (lo, hi)
                for lo, hi in bounds
            }
            for fut in as_completed(futures):  # one iteration per task
                lo, hi = futures.pop(fut)
                yield keys[lo:hi], fut.result()

    return fitter
