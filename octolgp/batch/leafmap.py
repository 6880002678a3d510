"""Whole-log builds into the leaf store: every leaf fitted once, locally or on Dask.

:func:`build_tiled` is the batch counterpart of :class:`~octolgp.online.OnlineMap`:
all scans become training data at once, the evidence is split into the octree leaves
(coarse boxes with overlap halos, :mod:`octolgp.mapping.grid`) with the same first-per-voxel
rule, and each leaf is fitted **once** — the paper's iterative k-means under the
cluster cap inside leaves that hold more than ``OnlineConfig.max_leaf_items`` — and
predicted at its voxel centres. Fitting a leaf is a pure function of its evidence
(:func:`~octolgp.online.fit_leaf`), so the leaves can run

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

import contextlib
import dataclasses
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_hyperparameters
from octolgp.gp.plsc import occupancy_probability
from octolgp.mapping.online import OnlineMap, ScanUpdate, fit_leaf
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan
from octolgp.training import check_scans

__all__ = ["TASK_ITEMS", "build_tiled", "build_voxelized", "fit_leaves"]

CHUNK_BEAMS = 60_000
"""Beams per chunk when gathering a whole log's evidence into leaves."""

TASK_ITEMS = 20_000
"""Training items (summed over leaves) per Dask task: tasks of ~0.1-1 s, few enough
that the scheduler's per-task overhead (~1 ms) stays negligible."""


def fit_leaves(leaves: list[Leaf], config: MapConfig, hp: Hyperparameters) -> list[Leaf]:
    """Fit a batch of leaves in order (a Dask task; BLAS limited to one thread)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return [fit_leaf(leaf, config, hp) for leaf in leaves]


def _scan_list(scans: Iterable[Scan], config: MapConfig) -> list[Scan]:
    """The scans as a checked list of dimension ``config.dim``; refuse none at all."""
    scan_list = check_scans(scans, config.dim)
    if not scan_list:
        raise OctolgpError("scans: no scans to build from")
    return scan_list


def _chunks(scans: list[Scan], beams: int) -> Iterator[list[Scan]]:
    """Consecutive runs of scans holding about ``beams`` beams each (at least one scan)."""
    chunk: list[Scan] = []
    total = 0
    for s in scans:  # one iteration per scan
        chunk.append(s)
        total += len(s)
        if total >= beams:
            yield chunk
            chunk, total = [], 0
    if chunk:
        yield chunk


def _batches(
    keys: list[int], leaves: list[Leaf], items: int
) -> Iterator[tuple[list[int], list[Leaf]]]:
    """Consecutive groups of leaves holding about ``items`` training items each."""
    group_k: list[int] = []
    group_l: list[Leaf] = []
    total = 0
    for key, leaf in zip(keys, leaves, strict=True):  # one iteration per leaf
        group_k.append(key)
        group_l.append(leaf)
        total += leaf.n_items
        if total >= items:
            yield group_k, group_l
            group_k, group_l, total = [], [], 0
    if group_k:
        yield group_k, group_l


@contextlib.contextmanager
def _client(scheduler: Any, workers: int | None) -> Iterator[Any]:
    """A ``distributed.Client`` for ``scheduler``; an embedded cluster is closed after."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise OctolgpError(
            "scheduler: dask.distributed is not installed (pip install 'octolgp[dask]')"
        ) from None
    if isinstance(scheduler, Client):
        yield scheduler
        return
    if not isinstance(scheduler, str) or not scheduler:
        raise OctolgpError(
            f"scheduler must be 'local', a scheduler address or a Client, got {scheduler!r}"
        )
    if scheduler == "local":
        if workers is not None and workers < 1:
            raise OctolgpError(f"workers must be >= 1, got {workers}")
        with (
            LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            ) as cluster,
            Client(cluster) as client,
        ):
            yield client
        return
    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise OctolgpError(f"scheduler {scheduler!r}: cannot connect: {exc}") from None
    with client:
        yield client


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
        ``config.online.learn_scans`` scans, as the online map does.
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
    scan_list = _scan_list(scans, config)
    stats: dict[str, float] = {}
    t0 = time.perf_counter()
    hp = config.hyperparameters
    if hp is None:
        hp = learn_hyperparameters(scan_list[: config.online.learn_scans], config)
    stats["learning"] = time.perf_counter() - t0
    fixed = dataclasses.replace(
        config,
        hyperparameters=hp,
        online=dataclasses.replace(config.online, n_jobs=n_jobs),
    )
    m = OnlineMap(fixed, path)
    # every leaf is fitted once here: no kernel blocks to reuse, so no cache to fill
    cache, m.kernel_cache = m.kernel_cache, None
    try:
        _fill(
            m,
            scan_list,
            lambda keys, leaves: _fitted(m, keys, leaves, scheduler, workers, task_items),
            stats,
            progress,
        )
    except BaseException:
        m.close()
        raise
    m.kernel_cache = cache
    return m


def _fitted(
    m: OnlineMap,
    keys: list[int],
    leaves: list[Leaf],
    scheduler: Any,
    workers: int | None,
    task_items: int,
) -> Iterator[tuple[list[int], list[Leaf]]]:
    """Fitted leaves batch by batch: local threads in key order, or Dask as tasks finish."""
    hp = m.hyperparameters
    assert hp is not None
    if scheduler is None:
        for group_k, group_l in _batches(keys, leaves, 8 * task_items):
            yield group_k, m._fit(group_l)[0]
        return
    from distributed import as_completed

    with _client(scheduler, workers) as client:
        # the config and hyperparameters travel to every worker once
        config_f, hp_f = client.scatter([m.config, hp], broadcast=True)
        futures = {
            client.submit(fit_leaves, group_l, config_f, hp_f, pure=False): group_k
            for group_k, group_l in _batches(keys, leaves, task_items)
        }
        for fut in as_completed(futures):  # one iteration per task
            yield futures.pop(fut), fut.result()


def _gather_all(
    m: OnlineMap, scans: list[Scan], stats: dict[str, float]
) -> tuple[list[int], list[Leaf], int]:
    """Every scan's evidence into the map's leaves (stored unfitted), chunk by chunk.

    Returns the keys of the leaves that gained evidence (in first-touch order), those
    leaves, and the number of items added.
    """
    from octolgp.mapping.online import _blas_controller
    from octolgp.training import make_training_data

    for s in scans:
        m._check_scan(s)
    stats["training"] = stats["assign"] = 0.0
    # Evidence is gathered chunk by chunk in time order (first item per voxel wins, so
    # the leaves end up exactly as from all scans at once), which bounds the transient
    # arrays of the segment-to-leaf assignment by the chunk, not the log.
    first_touch: dict[int, None] = {}
    new_items = 0
    for chunk in _chunks(scans, CHUNK_BEAMS):  # a few hundred thousand beams each
        t = time.perf_counter()
        with _blas_controller().limit(limits=1):
            data = make_training_data(chunk, m._raw_config)
        stats["training"] += time.perf_counter() - t
        t = time.perf_counter()
        changed, _touched, added = m._gather(data)
        del data
        new_items += added
        for key, leaf in changed:  # one iteration per leaf that gained evidence
            m.store.put(key, leaf)
            first_touch.setdefault(key, None)
        del changed
        stats["assign"] += time.perf_counter() - t
    keys = list(first_touch)
    gathered = [m.store.peek(k) for k in keys]
    return keys, [g for g in gathered if g is not None], new_items


def build_voxelized(
    scans: Iterable[Scan],
    config: MapConfig,
    method: str,
    *,
    path: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> OnlineMap:
    """A map file of another batch method: its values at the voxel centres of every leaf.

    ``build_map(scans, config, method)`` (``"gp"``, ``"mgp"`` or ``"ogm"``) is built in
    memory, then evaluated at the voxel centres of every leaf the scans bring evidence to
    (the leaves of :func:`build_tiled`); the map file stores those values, so ``query``,
    ``export`` and ``OnlineMap.open`` read it like any map. GP methods store their latent
    mean and variance (and PLSC's P); the grid stores its P (mean 0 and variance 1 as
    placeholders, no hyperparameters, so queries read voxel values, not interpolations).
    Scans inserted later refit the leaves they touch with the local GPs.

    Raises
    ------
    OctolgpError
        On an unknown method (use :func:`build_tiled` for ``"lgp"``) or bad input.
    """
    from octolgp.batch.build import build_map

    if method not in ("gp", "mgp", "ogm"):
        raise OctolgpError(f"method must be one of gp, mgp, ogm here, got {method!r}")
    scan_list = _scan_list(scans, config)
    gmap = build_map(scan_list, config, method=method)
    hp = getattr(gmap, "hyperparameters", None)
    m = OnlineMap(dataclasses.replace(config, hyperparameters=hp), path)

    def values(keys: list[int], leaves: list[Leaf]) -> Iterator[tuple[list[int], list[Leaf]]]:
        for lo in range(0, len(keys), 512):  # batches of leaves
            out = []
            for leaf in leaves[lo : lo + 512]:  # one iteration per leaf
                centres = m.grid.voxel_centres(leaf.index)
                if hp is None:
                    prob = np.asarray(gmap.occupancy(centres), dtype=np.float64)
                    mean, var = np.zeros_like(prob), np.ones_like(prob)
                else:
                    mean, var = gmap.latent(centres)
                    prob = occupancy_probability(mean, var + hp.noise_variance, hp.alpha, hp.beta)
                out.append(
                    dataclasses.replace(
                        leaf,
                        mean=mean.astype(np.float32),
                        var=var.astype(np.float32),
                        prob=prob.astype(np.float32),
                        refits=1,
                    )
                )
            yield keys[lo : lo + 512], out

    try:
        _fill(m, scan_list, values, {}, progress)
    except BaseException:
        m.close()
        raise
    return m


Fitter = Callable[[list[int], list[Leaf]], Iterator[tuple[list[int], list[Leaf]]]]
"""Leaves with evidence -> the same leaves with voxel values, batch by batch."""


def _fill(
    m: OnlineMap,
    scans: list[Scan],
    fitter: Fitter,
    stats: dict[str, float],
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Gather all evidence, give every leaf its values (``fitter``), store and commit."""
    keys, leaves, new_items = _gather_all(m, scans, stats)
    t = time.perf_counter()
    index = len(scans)
    pruned = done = 0
    for group_k, group_l in fitter(keys, leaves):
        for key, leaf in zip(group_k, group_l, strict=True):  # one iteration per leaf
            leaf.touched = index
            pruned += leaf.pruned
            m.store.put(key, leaf)
        # persist each batch so a memory budget can evict it (no scans yet: n_scans 0)
        m._commit(group_k, [])
        done += len(group_k)
        if progress is not None:
            progress(done, len(keys))
    stats["fit"] = time.perf_counter() - t
    t = time.perf_counter()
    m.n_scans = index
    m._commit([], list(enumerate(scans, start=1)))
    stats["store"] = time.perf_counter() - t
    m.build_stats = {
        **stats,
        "leaves": float(len(keys)),
        "items": float(new_items),
        "voxels": float(len(keys) * m.grid.voxels_per_leaf),
    }
    update = ScanUpdate(
        scan=index,
        touched_leaves=len(keys),
        refit_leaves=len(keys),
        new_items=new_items,
        pruned_leaves=pruned,
        seconds=sum(stats.values()),
        stages=stats,
        n_leaves=len(m.store),
        memory_bytes=m.memory_bytes(),
    )
    m.sink.on_update(m, update, keys)
