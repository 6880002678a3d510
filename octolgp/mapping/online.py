"""The online mapper: scans go in one at a time; only the leaves they touch are refitted.

:class:`OnlineMap` is the paper's method made incremental, OctoMap-style. Each
:meth:`OnlineMap.insert_scan` computes first and writes once, as OctoMap's
``computeUpdate`` then ``updateNode``:

1. **Scan → training data**: a hit and a free segment per beam
   (:func:`octolgp.training.make_training_data`).
2. **Training data → leaves**: a hit goes to every leaf whose halo box holds it; a
   free segment is clipped to the halo box of every leaf it crosses
   (:func:`octolgp.mapping.evidence.gather_evidence`).
3. **Bounded evidence**: a leaf keeps the first hit per voxel and the first free
   piece per voxel of the piece's end (:meth:`octolgp.mapping.store.Leaf.with_evidence`).
   Its training set is therefore at most two items per voxel of its halo box, so
   revisiting a place costs nothing once its voxels are observed: a scan that
   brings no new voxel to a leaf leaves that leaf's GP and voxels as they were.
   This is exact for a static world; a changing world keeps its first state.
   Because the rule is "first in time order", inserting scans one by one gives
   bit-for-bit the map of inserting them all at once.
4. **Leaves → local GP → PLSC**: a touched leaf that gained items is refitted
   (:func:`octolgp.mapping.fit.fit_leaf`: one GP on its whole training set, or the
   paper's iterative k-means clusters when it holds more than
   ``OnlineConfig.max_leaf_items``); its voxel centres get latent mean, variance and
   P(occupied); a leaf all below ``prune_free`` or all above ``prune_occupied``
   keeps one value.
5. **Store → file → sink**: the new leaves are swapped into the store
   (:meth:`octolgp.mapping.store.LeafStore.apply`, the only writer), written to the
   map file in one transaction, and reported to the sink.

Hyperparameters are those of ``MapConfig.hyperparameters``. When it is ``None`` the
first ``MapConfig.learn_scans`` scans (40 in 2D, 5 in 3D) are buffered, the hyperparameters are
learnt on them (:func:`octolgp.gp.learning.learn_hyperparameters`) and then held
fixed. The map after k scans is a function of those k scans and the config only:
queries, :meth:`~OnlineMap.save`, :meth:`~OnlineMap.export_octomap`,
:meth:`~OnlineMap.voxels`, opening and closing never learn. While scans are
buffered, reads answer *provisionally* (:attr:`OnlineMap.provisional`): from a map
fitted on the buffered scans with hyperparameters learnt on them, computed for the
read and thrown away (kept only until the next insert). :meth:`OnlineMap.flush` is
the one explicit way to learn early. To re-learn later, call
:meth:`OnlineMap.relearn`: every leaf is refitted from its stored evidence.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Iterable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from threadpoolctl import ThreadpoolController

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import unpack_keys
from octolgp.gp.learning import learn_hyperparameters
from octolgp.mapping.cache import KernelCache
from octolgp.mapping.correction import (
    check_corrections,
    overlapping_scans,
    scan_extents,
    transform_scan,
)
from octolgp.mapping.evidence import check_scan, gather_batch, step_evidence
from octolgp.mapping.fit import LeafFit, LeafFitter, batch_bounds, fit_leaves
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.query import MapReads
from octolgp.mapping.store import Leaf, LeafStore, MapStorage
from octolgp.mapping.update import ScanUpdate
from octolgp.scan import Scan
from octolgp.sinks.base import LeafView, MapChange, NullSink, Sink
from octolgp.training import make_training_data

__all__ = ["OnlineMap", "ScanUpdate"]

logger = logging.getLogger(__name__)

CHUNK_BEAMS = 60_000
"""Beams per chunk when :meth:`OnlineMap.insert_batch` gathers evidence
(:func:`octolgp.mapping.evidence.gather_batch`)."""

FIT_BATCH_ITEMS = 160_000
"""Training items (summed over leaves) fitted per batch by :meth:`OnlineMap.insert_batch`
in this process; each batch is stored and committed before the next."""


class OnlineMap(MapReads):
    """A continuous occupancy map built scan by scan.

    Parameters
    ----------
    config : MapConfig, optional
        ``MapConfig()`` when omitted.
    path : str or Path, optional
        With a path the map is persisted in that SQLite file (which must not
        exist yet) after every :meth:`insert_scan`; see :mod:`octolgp.persist.mapfile`.
    recording : rerun.RecordingStream, optional
        Stream every scan and every refitted leaf to this Rerun recording
        (:class:`octolgp.sinks.rerun.RerunSink` with its defaults).
    sink : Sink, optional
        Any object with the methods of :class:`octolgp.sinks.base.Sink` (for
        example a ``RerunSink`` with options); overrides ``recording``.
    storage : MapStorage, optional
        An opened map file whose state this map takes over (what :meth:`open`
        passes); ``config`` must be the file's.

    Notes
    -----
    With ``MapConfig.memory_budget_mb`` the least recently used leaves are dropped
    from RAM after each scan once they are in the map file (a temporary spill file
    when ``path`` is ``None``) and loaded back when a scan touches them; reads load
    them without keeping them. The map does not depend on the budget. With a file,
    every ``insert_scan`` is durable when it returns (one SQLite transaction).

    Examples
    --------
    >>> import numpy as np
    >>> from octolgp import MapConfig, OnlineMap, Scan, Hyperparameters
    >>> hp = Hyperparameters(length_scale=0.5, alpha=5.0)
    >>> m = OnlineMap(MapConfig(dim=2, resolution=0.1, hyperparameters=hp))
    >>> wall = np.c_[np.full(20, 2.0), np.linspace(-1, 1, 20)]
    >>> update = m.insert_scan(Scan(origin=[0.0, 0.0], points=wall))
    >>> update.refit_leaves > 0
    True
    >>> bool(m.occupancy([[2.0, 0.0]])[0] > 0.5 > m.occupancy([[1.0, 0.0]])[0])
    True
    """

    def __init__(
        self,
        config: MapConfig | None = None,
        path: str | Path | None = None,
        *,
        recording: Any = None,
        sink: Sink | None = None,
        storage: MapStorage | None = None,
    ) -> None:
        if config is None:
            config = MapConfig()
        if not isinstance(config, MapConfig):
            raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
        self.config = config
        self.grid = LeafGrid.from_config(config)
        budget = config.memory_budget_mb
        self.store = LeafStore(None if budget is None else int(budget * 1e6))
        self.hyperparameters: Hyperparameters | None = config.hyperparameters
        self.n_scans = 0
        self.repaired = 0  # kernel matrices repaired by jitter in this map's fits
        self.build_stats: dict[str, float] = {}
        cache_mb = config.online.kernel_cache_mb
        self.kernel_cache = None if cache_mb == 0 else KernelCache(int(cache_mb * 1e6))
        if recording is not None and sink is None:
            from octolgp.sinks.rerun import RerunSink

            sink = RerunSink(recording)
        self.sink: Sink = NullSink() if sink is None else sink
        self._buffer: list[Scan] = []  # scans awaiting the hyperparameters
        self._provisional: tuple[int, OnlineMap] | None = None  # a read's throw-away fit
        self._pool: ThreadPoolExecutor | None = None
        self._blas: ThreadpoolController | None = None
        self._extents: np.ndarray | None = None  # journaled scans' key boxes, once corrected
        # Evidence is deduplicated per leaf (Leaf.with_evidence), in time order, so a
        # scan-level dedup would only make one-by-one and all-at-once insertion differ.
        self._raw_config = dataclasses.replace(
            config, training=dataclasses.replace(config.training, dedup=False)
        )
        self._file: MapStorage | None = storage
        if storage is not None:
            self._resume(storage)
        elif path is not None or budget is not None:
            from octolgp.persist.mapfile import MapFile

            # without a path, a memory budget spills evicted leaves to a temporary file
            self._file = (
                MapFile.create(path, config, self.hyperparameters)
                if path is not None
                else MapFile.spill(config)
            )
            self.store.attach(self._file, [])

    def _resume(self, storage: MapStorage) -> None:
        """Take over the state recorded in an opened map file."""
        header = storage.header
        self.hyperparameters = header.hyperparameters
        self.n_scans = header.n_scans
        self.store.attach(storage, header.leaf_keys)
        if self.hyperparameters is None and not header.leaf_keys:
            self._buffer = list(storage.scans())  # still collecting scans to learn from

    # ------------------------------------------------------------------ life cycle
    @classmethod
    def open(cls, path: str | Path) -> OnlineMap:
        """Reopen a map persisted with ``OnlineMap(config, path=...)`` or :meth:`save`.

        Raises
        ------
        MapFileNotFound
            If the file does not exist.
        OctolgpError
            If it is not an octolgp map file or is corrupt.
        """
        from octolgp.persist.mapfile import MapFile

        f = MapFile.open(path)
        return cls(f.header.config, storage=f)

    def save(self, path: str | Path) -> None:
        """Write the map to a new SQLite map file, replacing ``path`` atomically.

        The file holds the map as it is: a map still buffering scans is saved with
        its buffered scans and no hyperparameters, and reopens buffering.
        """
        from octolgp.persist.mapfile import write_map

        journal = self._file.scans() if self._file is not None else iter(self._buffer)
        write_map(
            path, self.config, self.hyperparameters, self.n_scans, self.store.items(), journal
        )

    def close(self) -> None:
        """Release worker threads and the map file."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self._file is not None:
            self._file.close()
            self._file = None
        self._provisional = None

    def __enter__(self) -> OnlineMap:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def path(self) -> Path | None:
        """The map file (a temporary spill file for a budgeted in-memory map), or ``None``."""
        return None if self._file is None else self._file.path

    def scans(self) -> Iterator[Scan]:
        """The inserted scans, in order, from the map file's journal.

        A map without a file keeps only the scans it is still buffering.
        """
        return self._file.scans() if self._file is not None else iter(list(self._buffer))

    @property
    def provisional(self) -> bool:
        """True while scans are buffered to learn hyperparameters.

        Reads then answer from a provisional fit of the buffered scans that is thrown
        away; the map itself holds no leaves until the hyperparameters are learnt.
        """
        return self.hyperparameters is None and bool(self._buffer)

    @property
    def buffered_scans(self) -> int:
        """Scans held back until the hyperparameters are learnt."""
        return len(self._buffer)

    # ------------------------------------------------------------------ updates
    def insert_scan(self, scan: Scan) -> ScanUpdate:
        """Add one scan: refit and re-predict only the leaves it brings new evidence to.

        Parameters
        ----------
        scan : Scan
            World-frame scan of dimension ``config.dim``.

        Returns
        -------
        ScanUpdate

        Raises
        ------
        OctolgpError
            On a value that is not a :class:`Scan`, a wrong dimension or a point
            outside the addressable range. The map is then exactly as before.
        """
        t0 = time.perf_counter()
        scan = check_scan(scan, self.config, self.grid)
        index = self.n_scans + 1
        self.sink.on_scan(scan, index)
        if self.hyperparameters is not None:
            return self._step([scan], [(index, scan)], t0)
        self._buffer.append(scan)
        self._provisional = None
        if len(self._buffer) >= self.config.learn_scans:
            update = self._learn_and_step([(index, scan)], t0)
            if update is not None:
                return update
        else:
            self._commit([], [(index, scan)], index)
        return self._buffered_update(t0)

    def insert_scans(self, scans: Iterable[Scan]) -> list[ScanUpdate]:
        """Insert scans one by one; return their updates."""
        return [self.insert_scan(s) for s in scans]

    def flush(self) -> ScanUpdate | None:
        """Learn hyperparameters from the buffered scans now and insert them.

        The one explicit way to end the learning phase early (the CLI calls it at the
        end of a run shorter than ``learn_scans``); reads never do. Returns ``None``
        when nothing is buffered or the buffer holds no training data yet.
        """
        if not self._buffer:
            return None
        return self._learn_and_step([], time.perf_counter())

    def _learn_and_step(self, journal: list[tuple[int, Scan]], t0: float) -> ScanUpdate | None:
        """Learn on the buffer and insert it; ``None`` (still buffering) without data."""
        if not self._can_learn():
            # nothing to learn from yet (no return, or every beam on its sensor): keep buffering
            if journal:
                self._commit([], journal, journal[-1][0])
            return None
        t1 = time.perf_counter()
        hp = learn_hyperparameters(self._buffer, self.config)
        learning = time.perf_counter() - t1
        logger.info("learnt hyperparameters on %d scans: %s", len(self._buffer), hp)
        self.hyperparameters = hp
        buffered, self._buffer, self._provisional = self._buffer, [], None
        update = self._step(buffered, journal, t0)
        update.stages["learning"] = learning
        return update

    def _step(self, scans: list[Scan], journal: list[tuple[int, Scan]], t0: float) -> ScanUpdate:
        """Scans → evidence per leaf → refit the leaves that gained any → store → file → sink."""
        hp = self.hyperparameters
        assert hp is not None
        index = journal[-1][0] if journal else self.n_scans
        stages: dict[str, float] = {}
        with self._blas_limit():
            # 1-3. scan → training data → the leaves it changes (new leaf objects)
            evidence = step_evidence(scans, self.grid, self._raw_config, self.store.get, stages)
            # 4. leaves → local GP → PLSC, on the map's threads
            t = time.perf_counter()
            leaves = [leaf for _, leaf in evidence.changed]
            fits = fit_leaves(leaves, self.config, hp, self.kernel_cache, self._threads(leaves))
            stages["fit"] = time.perf_counter() - t
        # 5. the one write: store, file, then the sink
        t = time.perf_counter()
        keys = [k for k, _ in evidence.changed]
        fitted = [(k, f.leaf) for k, f in zip(keys, fits, strict=True)]
        self.store.apply([*fitted, *evidence.kept], evidence.touched, index)
        self._commit(sorted([*keys, *(k for k, _ in evidence.kept)]), journal, index)
        stages["store"] = time.perf_counter() - t
        repaired = self._count_repairs(fits)
        update = ScanUpdate(
            scan=index,
            touched_leaves=len(evidence.touched),
            refit_leaves=len(keys),
            new_items=evidence.new_items,
            pruned_leaves=sum(f.leaf.pruned for f in fits),
            seconds=time.perf_counter() - t0,
            stages=stages,
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
            repaired=repaired,
        )
        self.sink.on_update(update, self._change(fitted))
        return update

    def correct_scans(self, corrections: Mapping[int, ArrayLike]) -> ScanUpdate:
        """Move journaled scans by rigid transforms, as a pose graph's loop closure does.

        The leaves that either version of a corrected scan touches are rebuilt from
        every journaled scan whose extent reaches them, with the corrections applied,
        and refitted; leaves left without evidence are removed. The result is the map
        the corrected scans would have built from the start (with this map's
        hyperparameters), at a cost that grows with the leaves and scans the
        correction reaches, not with the mission. The journal then holds the
        corrected scans; with a map file it is one transaction (a kill leaves the map
        before or after the correction).

        Parameters
        ----------
        corrections : mapping of int to array_like of shape (d+1, d+1)
            Scan number (from 1, as in ``ScanUpdate.scan``) → rigid homogeneous
            transform applied to that scan's world-frame origin and points.

        Returns
        -------
        ScanUpdate
            ``scan`` is the map's scan count; ``refit_leaves`` the rebuilt leaves,
            ``removed_leaves`` those dropped.

        Raises
        ------
        OctolgpError
            On an unknown scan number, a matrix of the wrong size, non-finite or not
            rigid, or a map without a journal (one made without a ``path`` and without
            a memory budget keeps no scans); the map is then unchanged.
        """
        t0 = time.perf_counter()
        transforms = check_corrections(corrections, self.n_scans, self.config.dim)
        if self._file is None:
            raise OctolgpError(
                "correct_scans needs the scans' journal: make the map with a path "
                "(OnlineMap(config, path=...)), which journals every scan"
            )
        storage = self._file
        stages: dict[str, float] = {}
        old = storage.read_scans(list(transforms))
        if len(old) != len(transforms):
            raise OctolgpError(
                f"map file {str(storage.path)!r} holds no journal of its scans (saved from "
                "memory); only a map made with a path can be corrected"
            )
        new = {i: transform_scan(old[i], T) for i, T in transforms.items()}
        for i, scan in new.items():  # a corrected scan must stay inside the map
            try:
                check_scan(scan, self.config, self.grid)
            except OctolgpError as exc:
                raise OctolgpError(
                    f"corrections[{i}] moves the scan out of the map: {exc}"
                ) from None
        extents = self._journal_extents(storage)  # read before any write
        rows, moved_extents = np.array(list(new)) - 1, scan_extents(list(new.values()), self.grid)
        if self.hyperparameters is None:  # still buffering: only the journal moves
            storage.correct([], [], list(new.items()))
            self._buffer = [new.get(i, scan) for i, scan in enumerate(self._buffer, start=1)]
            self._provisional = None
            extents[rows] = moved_extents
            return self._buffered_update(t0)
        hp = self.hyperparameters
        with self._blas_limit():
            # 1. the leaves either version of the corrected scans reaches
            moved = [*old.values(), *new.values()]
            reach = step_evidence(moved, self.grid, self._raw_config, lambda _: None, stages)
            affected = sorted(reach.touched)
            # 2. every scan whose extent reaches them, corrected, replayed in time order
            corrected_extents = extents.copy()
            corrected_extents[rows] = moved_extents
            index = unpack_keys(np.asarray(affected, dtype=np.int64), self.config.dim)
            near = np.flatnonzero(overlapping_scans(corrected_extents, index, self.grid)) + 1
            journal = storage.read_scans(near.tolist())
            replay = [new.get(i, journal[i]) for i in near.tolist()]
            gathered, _, new_items = gather_batch(
                replay, self.grid, self._raw_config, lambda _: None, CHUNK_BEAMS, stages
            )
            keys = [k for k in affected if k in gathered]
            leaves = [gathered[k] for k in keys]
            removed = [k for k in affected if k not in gathered and k in self.store]
            del gathered
            if self.kernel_cache is not None:  # rebuilt items are not the cached ones
                self.kernel_cache.discard(affected)
            t = time.perf_counter()
            fits = fit_leaves(leaves, self.config, hp, self.kernel_cache, self._threads(leaves))
            stages["fit"] = time.perf_counter() - t
        # 3. the one write: store, then the file in one transaction, then the sink
        t = time.perf_counter()
        fitted = [(k, f.leaf) for k, f in zip(keys, fits, strict=True)]
        self.store.apply(fitted, (), self.n_scans)
        self.store.remove(removed)
        written = storage.correct(fitted, removed, list(new.items()))
        self.store.persisted(written)
        self.store.trim()
        extents[:] = corrected_extents
        stages["store"] = time.perf_counter() - t
        update = ScanUpdate(
            scan=self.n_scans,
            touched_leaves=len(affected),
            refit_leaves=len(keys),
            new_items=new_items,
            pruned_leaves=sum(f.leaf.pruned for f in fits),
            seconds=time.perf_counter() - t0,
            stages={**stages, "replayed_scans": float(len(replay))},
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
            repaired=self._count_repairs(fits),
            removed_leaves=len(removed),
        )
        self.sink.on_update(update, self._change(fitted, tuple(removed)))
        return update

    def insert_batch(
        self,
        scans: Iterable[Scan],
        *,
        fitter: LeafFitter | None = None,
        progress: Any = None,
    ) -> ScanUpdate:
        """Insert many scans as one step: every touched leaf is fitted once.

        The same map as inserting the scans one by one (the evidence rule is "first
        in time order"), at a fraction of the cost for a whole log. Evidence is
        gathered in chunks of about :data:`CHUNK_BEAMS` beams, and leaves are fitted,
        stored and committed in batches, so transient memory is bounded by the chunk
        and the batch, not the log.

        Parameters
        ----------
        scans : iterable of Scan
            World-frame scans of dimension ``config.dim``; at least one.
        fitter : callable, optional
            Where the leaves are fitted (:data:`octolgp.mapping.fit.LeafFitter`): by
            default on this map's threads; :func:`octolgp.batch.leafmap.build_tiled`
            passes one that runs batches on a Dask cluster. It decides where the work
            runs, never what is computed. With the default fitter and no
            hyperparameters yet, they are learnt first on the first ``learn_scans``
            scans (buffered ones included).
        progress : callable, optional
            Called as ``progress(leaves_fitted, leaves_total)`` after each batch.

        Returns
        -------
        ScanUpdate
            For the whole batch; ``build_stats`` holds the stage timings and sizes.

        Raises
        ------
        OctolgpError
            On a bad scan (checked before anything changes) or no scans at all.
        """
        t0 = time.perf_counter()
        new_scans = [check_scan(s, self.config, self.grid) for s in scans]
        if not new_scans:
            raise OctolgpError("scans: no scans to build from")
        for i, s in enumerate(new_scans, start=self.n_scans + 1):
            self.sink.on_scan(s, i)
        journal = list(enumerate(new_scans, start=self.n_scans + 1))
        index = journal[-1][0]
        scan_list = new_scans
        stats: dict[str, float] = {"learning": 0.0}
        if self.hyperparameters is None and fitter is None:  # learn on the first scans
            scan_list = self._buffer + new_scans
            t = time.perf_counter()
            hp = learn_hyperparameters(scan_list[: self.config.learn_scans], self.config)
            stats["learning"] = time.perf_counter() - t
            logger.info("learnt hyperparameters on the first scans: %s", hp)
            self.hyperparameters, self._buffer, self._provisional = hp, [], None
        with self._blas_limit():
            gathered, refit, new_items = gather_batch(
                scan_list, self.grid, self._raw_config, self.store.get, CHUNK_BEAMS, stats
            )
        kept = [(k, leaf) for k, leaf in gathered.items() if k not in refit]
        if kept:  # new counts, same GP inputs: stored as they are
            self.store.apply(kept, (), index)
            self._commit([k for k, _ in kept], [], self.n_scans)
        keys = [k for k in gathered if k in refit]
        leaves = [gathered[k] for k in keys]
        del gathered, kept
        t = time.perf_counter()
        pruned = repaired = done = 0
        run = self._local_fitter if fitter is None else fitter
        for group_k, group_f in run(keys, leaves):  # one batch of leaves per iteration
            self.store.apply(
                [(k, f.leaf) for k, f in zip(group_k, group_f, strict=True)], (), index
            )
            pruned += sum(f.leaf.pruned for f in group_f)
            repaired += self._count_repairs(group_f)
            self._commit(group_k, [], self.n_scans)  # each batch durable, then evictable
            done += len(group_k)
            if progress is not None:
                progress(done, len(keys))
        stats["fit"] = time.perf_counter() - t
        t = time.perf_counter()
        self._commit([], journal, index)
        stats["store"] = time.perf_counter() - t
        self.build_stats = {
            **stats,
            "leaves": float(len(keys)),
            "items": float(new_items),
            "voxels": float(len(keys) * self.grid.voxels_per_leaf),
        }
        update = ScanUpdate(
            scan=index,
            touched_leaves=len(keys),
            refit_leaves=len(keys),
            new_items=new_items,
            pruned_leaves=pruned,
            seconds=time.perf_counter() - t0,
            stages=stats,
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
            repaired=repaired,
        )
        self.sink.on_update(update, self._change((k, self.store.peek(k)) for k in keys))
        return update

    def _local_fitter(
        self, keys: list[int], leaves: list[Leaf]
    ) -> Iterator[tuple[list[int], list[LeafFit]]]:
        """Fit leaves on this map's threads in batches of about FIT_BATCH_ITEMS items.

        Every leaf is fitted once here, so there are no kernel blocks worth caching.
        """
        hp = self.hyperparameters
        assert hp is not None
        for lo, hi in batch_bounds([leaf.n_items for leaf in leaves], FIT_BATCH_ITEMS):
            group = leaves[lo:hi]
            with self._blas_limit():
                fits = fit_leaves(group, self.config, hp, None, self._threads(group))
            yield keys[lo:hi], fits

    def relearn(self, scans: Iterable[Scan]) -> Hyperparameters:
        """Learn new hyperparameters on ``scans`` and refit every leaf with them."""
        hp = learn_hyperparameters(scans, self.config)
        self.set_hyperparameters(hp)
        return hp

    def set_hyperparameters(self, hp: Hyperparameters) -> None:
        """Use ``hp`` from now on and refit every leaf from its stored evidence.

        Buffered scans are inserted with ``hp``. Leaves are refitted in batches of
        256 so a map with a memory budget never holds more than that many beyond its
        budget.
        """
        if not isinstance(hp, Hyperparameters):
            raise OctolgpError(f"hp must be Hyperparameters, got {type(hp).__name__}")
        self.hyperparameters = hp
        if self._buffer:
            buffered, self._buffer, self._provisional = self._buffer, [], None
            self._step(buffered, [], time.perf_counter())
        keys = list(self.store)
        for lo in range(0, len(keys), 256):  # one batch of leaves per iteration
            batch = [(k, leaf) for k in keys[lo : lo + 256] if (leaf := self.store.peek(k))]
            with self._blas_limit():
                leaves = [leaf for _, leaf in batch]
                fits = fit_leaves(leaves, self.config, hp, self.kernel_cache, self._threads(leaves))
            self._count_repairs(fits)
            fitted = [(k, f.leaf) for (k, _), f in zip(batch, fits, strict=True)]
            self.store.apply(fitted)  # each leaf keeps its last-use stamp
            self._commit([k for k, _ in fitted], [], self.n_scans)

    # ------------------------------------------------------------------ plumbing
    def _buffered_update(self, t0: float) -> ScanUpdate:
        """The update of a step that only buffered or journaled scans (no leaf changed)."""
        return ScanUpdate(
            scan=self.n_scans,
            touched_leaves=0,
            refit_leaves=0,
            new_items=0,
            pruned_leaves=0,
            seconds=time.perf_counter() - t0,
            buffered=True,
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
        )

    def _journal_extents(self, storage: MapStorage) -> np.ndarray:
        """Each journaled scan's extent in voxel keys, (n_scans, 2, d), kept up to date.

        Read from the journal once (the first correction), then extended as scans are
        committed: a correction then reads only the scans that reach what it moves.
        """
        if self._extents is None or self._extents.shape[0] != self.n_scans:
            boxes = [scan_extents([s], self.grid) for s in storage.scans()]
            d = self.config.dim
            self._extents = np.concatenate(boxes) if boxes else np.zeros((0, 2, d), np.int64)
        return self._extents

    def _commit(self, keys: list[int], journal: list[tuple[int, Scan]], n_scans: int) -> None:
        """Set the scan count, make the step durable (map file, if any), trim RAM."""
        self.n_scans = n_scans
        if self._extents is not None and journal:  # keep the correction index current
            self._extents = np.concatenate(
                [self._extents, scan_extents([s for _, s in journal], self.grid)]
            )
        if self._file is not None:
            leaves = [(k, leaf) for k in keys if (leaf := self.store.get(k)) is not None]
            written = self._file.commit(leaves, journal, self.hyperparameters, n_scans)
            self.store.persisted(written)
        self.store.trim()

    def _threads(self, leaves: list[Leaf]) -> ThreadPoolExecutor | None:
        """The map's thread pool when ``n_jobs > 1`` and there is more than one leaf."""
        n_jobs = self.config.n_jobs
        if n_jobs <= 1 or len(leaves) < 2:
            return None
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=n_jobs)
        return self._pool

    def _blas_limit(self) -> Any:
        """One BLAS thread per leaf fit: small matrices, parallelism is over leaves."""
        if self._blas is None:  # finding the BLAS libraries is the slow part: once per map
            self._blas = ThreadpoolController()
        return self._blas.limit(limits=1)

    def _count_repairs(self, fits: list[LeafFit]) -> int:
        repaired = sum(f.repaired for f in fits)
        if repaired:
            logger.info("%d leaf kernel matrices repaired by jitter", repaired)
        self.repaired += repaired
        return repaired

    def _change(
        self, leaves: Iterable[tuple[int, Leaf | None]], removed: tuple[int, ...] = ()
    ) -> MapChange:
        """What a sink sees of refitted leaves: boxes, voxel centres and values."""
        hp = self.hyperparameters
        grid = self.grid

        def views() -> Iterator[LeafView]:
            for k, leaf in leaves:  # one iteration per refitted leaf
                if leaf is None:
                    continue
                lo, hi = grid.box(leaf.index[None, :])
                centres = grid.voxel_centres(leaf.index)
                yield LeafView(
                    k, lo[0], hi[0], centres, leaf.prob, leaf.mean, leaf.var, leaf.pruned
                )

        return MapChange(
            dim=self.config.dim,
            resolution=self.config.resolution,
            side=self.grid.side,
            signal_variance=1.0 if hp is None else hp.signal_variance,
            leaves=views(),
            removed=removed,
        )

    # ------------------------------------------------------------------ reads
    def _readable(self) -> OnlineMap:
        """The map reads come from: this one, or a provisional fit while buffering.

        Every read of :class:`~octolgp.mapping.query.MapReads` goes through it.
        """
        if not self.provisional:
            return self
        if self._provisional is None or self._provisional[0] != len(self._buffer):
            self._provisional = (len(self._buffer), self._provisional_map())
        return self._provisional[1]

    def _provisional_map(self) -> OnlineMap:
        """A throw-away in-memory map of the buffered scans (what :meth:`flush` would make)."""
        if not self._can_learn():
            return OnlineMap(dataclasses.replace(self.config, memory_budget_mb=None))
        hp = learn_hyperparameters(self._buffer, self.config)
        config = dataclasses.replace(self.config, hyperparameters=hp, memory_budget_mb=None)
        provisional = OnlineMap(config)
        provisional.insert_batch(self._buffer)
        return provisional

    def _can_learn(self) -> bool:
        """Whether the buffered scans hold training data to learn from."""
        return make_training_data(self._buffer, self._raw_config).n_items > 0

    def memory_bytes(self) -> int:
        """Bytes held by the leaves (evidence and voxel values)."""
        return self.store.nbytes

    def __repr__(self) -> str:
        return (
            f"OnlineMap(dim={self.config.dim}, resolution={self.config.resolution:g}, "
            f"scans={self.n_scans}, leaves={len(self.store)})"
        )
