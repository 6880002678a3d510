"""The online mapper: scans go in one at a time; only the leaves they touch are refitted.

:class:`OnlineMap` is the paper's method made incremental, OctoMap-style. Each
:meth:`OnlineMap.insert_scan` computes first and writes once, as OctoMap's
``computeUpdate`` then ``updateNode``:

1. **Scan → evidence per leaf**: the leaf engine turns the scan into observations and
   adds them to every leaf whose halo box they reach
   (:meth:`octolgp.engines.base.LeafEngine.evidence`). The default lattice engine
   counts, per voxel of a leaf's halo box, the scans that saw it occupied and free, and
   newer evidence wins (:func:`octolgp.observations.newer_evidence_wins`); the exact
   engine keeps the first hit and free piece per voxel. Either way a leaf's evidence is
   bounded by its halo box and is a function of the scans in time order, so inserting
   scans one by one gives the map of inserting them all at once.
2. **Leaves → local GP → PLSC**: the leaves whose GP inputs changed are refitted and
   their voxels re-predicted (:meth:`~octolgp.engines.base.LeafEngine.fit`); a confident
   leaf keeps one value.
3. **Store → file → sink**: the one write path (:meth:`OnlineMap._write`) swaps the new
   leaves into the store (:class:`octolgp.mapping.store.LeafStore`, the only mutable
   state), writes the map file in one transaction, and reports to the sink.

Hyperparameters are those of ``MapConfig.hyperparameters``; when it is ``None`` the
first ``online.learn_scans`` scans are buffered and learnt on
(:class:`octolgp.mapping.bootstrap.Bootstrap`). The map after k scans is a function of
those k scans and the config only: queries, :meth:`~OnlineMap.save`,
:meth:`~OnlineMap.export_octomap`, opening and closing never change it.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager, nullcontext
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import LeafFit, engine_for
from octolgp.errors import OctolgpError
from octolgp.gp.learning import learn_hyperparameters
from octolgp.mapping.bootstrap import Bootstrap
from octolgp.mapping.correction import (
    JournalExtents,
    Replay,
    check_corrections,
    moved_extents,
    plan_replay,
    pose_corrections,
    transform_scan,
)
from octolgp.mapping.evidence import (
    LeafFitter,
    batch_bounds,
    check_scan,
    gather_batch,
    map_scans,
)
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.query import MapReads, leaves_read
from octolgp.mapping.store import (
    STEP_BYTES_PER_HALO_VOXEL,
    Leaf,
    LeafStore,
    MapStorage,
    ScanJournal,
)
from octolgp.mapping.update import ScanUpdate
from octolgp.mapping.workers import Workers, collector_paused
from octolgp.memory import release_free_memory
from octolgp.persist.memory import MemoryJournal
from octolgp.scan import FloatArray, Scan
from octolgp.sinks.base import LeafView, MapChange, NullSink, Sink
from octolgp.training import check_scans

__all__ = ["OnlineMap", "ScanUpdate"]

logger = logging.getLogger(__name__)

CHUNK_BEAMS = 60_000
"""Beams per chunk when :meth:`OnlineMap.insert_batch` gathers evidence
(:func:`octolgp.mapping.evidence.gather_batch`)."""

FIT_BATCH_ITEMS = 160_000
"""Training items (summed over leaves) fitted per batch by :meth:`OnlineMap.insert_batch`
in this process; each batch is stored (and written, uncommitted) before the next."""

LOCAL_QUERY_POINTS = 65_536
"""A query at up to this many points fits only the pending leaves it reads; a larger
one fits them all (working out which it reads would cost about as much)."""

RESERVE_STEPS = 16
"""Steps whose largest the memory budget keeps room for (:meth:`OnlineMap._reserve`)."""

FIT_CHUNK = 2048
"""Leaves of 8³ voxels the engine fits per call (a larger leaf counts as several,
:meth:`~octolgp.mapping.store.LeafStore.leaves_of`): a step's or a settle's leaves are
fitted in chunks of this many, whose stacked counts, returns and values stay small enough
for the caches (a sparse street's 32,000 pending leaves fitted at once took twice as
long)."""

R = TypeVar("R")


def _step_of_state(method: Callable[..., R]) -> Callable[..., R]:
    """Run a method that changes the map as one step: alone, on an open map, all or nothing.

    The call holds the map's lock (calls from several threads run one at a time), runs
    with the cyclic garbage collector paused (:func:`~octolgp.mapping.workers.collector_paused`),
    is refused on a closed, read-only or broken map, and when it raises before any write
    reached the store the map's counters and learning buffer are put back as they
    were and the engine's caches are dropped, so the map is exactly as before the call.
    """

    @functools.wraps(method)
    def step(self: OnlineMap, *args: Any, **kwargs: Any) -> R:
        with self._lock, collector_paused():
            self._check(method.__name__, write=True)
            before = (self.n_scans, self.hyperparameters, list(self._bootstrap.scans))
            writes = self._writes
            try:
                return method(self, *args, **kwargs)
            except BaseException:
                if self._writes == writes:
                    self.n_scans, self.hyperparameters = before[0], before[1]
                    self._bootstrap.restore(before[2])
                    self.engine = engine_for(self.config)  # its caches saw the lost step
                raise

    return step


class OnlineMap(MapReads):
    """A continuous occupancy map built scan by scan.

    Parameters
    ----------
    config : MapConfig, optional
        ``MapConfig()`` when omitted. The map keeps it resolved
        (:meth:`MapConfig.resolve`) as :attr:`config`.
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
    journal : bool, default True
        A map without a file keeps its scans' journal in RAM, so that it can be
        corrected (Notes); ``False`` spares that RAM, and corrections are then
        refused. A map file (or a budget's spill file) keeps the journal whatever
        this says.

    Notes
    -----
    With ``MapConfig.memory_budget_mb`` the least recently used leaves are dropped
    from RAM after each scan once they are in the map file (a temporary spill file
    when ``path`` is ``None``) and loaded back when a scan touches them; reads load
    them without keeping them. The map does not depend on the budget. With a file,
    every ``insert_scan`` is durable when it returns (one SQLite transaction), and
    this map is the file's one writer until :meth:`close`
    (:mod:`octolgp.persist.mapfile` says what the file survives).

    The scans' journal, which pose corrections (:meth:`correct_scans`,
    :meth:`correct_poses`) replay, is kept in the map file (the spill file under a
    budget) or, for a map without either, in RAM
    (:class:`octolgp.persist.memory.MemoryJournal`, in the file's encodings, so a
    correction gives the same map either way). It holds the latest
    ``OnlineConfig.journal_scans`` to twice that many scans, compressed (about 1 to 4
    bytes per beam at ``scan_precision`` 0.01 m, float64 without it), and per checkpoint the
    evidence records of the leaves changed since; :attr:`journal_bytes` says how much.

    Several threads may share a map: its calls take turns (one lock per map), and a
    read sees the map between two calls. After :meth:`close` every call is refused.

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
        journal: bool = True,
    ) -> None:
        if config is None:
            config = MapConfig()
        if not isinstance(config, MapConfig):
            raise OctolgpError(f"config must be a MapConfig, got {type(config).__name__}")
        self.config = config.resolve()
        self.grid = LeafGrid.from_config(self.config)
        self.engine = engine_for(self.config)
        budget = self.config.memory_budget_mb
        self.store = LeafStore(
            None if budget is None else int(budget * 1e6), self.grid.voxels_per_leaf
        )
        self.hyperparameters: Hyperparameters | None = self.config.hyperparameters
        self.n_scans = 0
        self.repaired = 0  # kernel matrices repaired by jitter in this map's fits
        self.build_stats: dict[str, float] = {}
        if recording is not None and sink is None:
            from octolgp.sinks.rerun import RerunSink

            sink = RerunSink(recording)
        self.sink: Sink = NullSink() if sink is None else sink
        self._bootstrap: Bootstrap[OnlineMap] = Bootstrap(self.config)
        self._workers = Workers(self.config.n_jobs)
        self._extents = JournalExtents(self.grid)
        self._ram_journal: MemoryJournal | None = None  # the journal of a map without a file
        self._lock = threading.RLock()
        self._closed = False
        self._broken: str | None = None  # why the map refuses every call
        self._writes = 0  # steps applied to the store
        self._recent_touched: deque[int] = deque(maxlen=RESERVE_STEPS)  # leaves a step touched
        self.read_only = storage is not None and storage.read_only
        self._file: MapStorage | None = storage
        if storage is not None:
            self._resume(storage)
        elif path is not None or budget is not None:
            from octolgp.persist.mapfile import MapFile

            # without a path, a memory budget spills evicted leaves to a temporary file
            self._file = (
                MapFile.create(path, self.config, self.hyperparameters)
                if path is not None
                else MapFile.spill(self.config)
            )
            self.store.attach(self._file, [], self._fitted)
        elif journal:
            self._ram_journal = MemoryJournal(self.config, self.store.peek)

    def _resume(self, storage: MapStorage) -> None:
        """Take over the state recorded in an opened map file."""
        header = storage.header
        self.hyperparameters = header.hyperparameters
        self.n_scans = header.n_scans
        self.store.attach(storage, header.leaf_keys, self._fitted)
        if self.hyperparameters is None and not header.leaf_keys:
            self._bootstrap = Bootstrap(self.config, storage.scans())  # still collecting

    def _fitted(self, leaves: list[Leaf]) -> list[Leaf]:
        """Leaves read from the map file without their voxel values, with them.

        Each fit equals the one the leaf had when written (a fit depends on the leaf's
        evidence and the map's hyperparameters only); refit counts and stamps are kept.
        """
        if not leaves:
            return []
        if self.hyperparameters is None:
            raise OctolgpError(
                f"map file {str(self.path)!r} holds leaves but no hyperparameters to fit them"
            )
        fits = self._fit(leaves)
        return [
            f.leaf.evolve(refits=leaf.refits, touched=leaf.touched)
            for leaf, f in zip(leaves, fits, strict=True)
        ]

    # ------------------------------------------------------------------ life cycle
    @classmethod
    def open(cls, path: str | Path, *, read_only: bool = False) -> OnlineMap:
        """Reopen a map persisted with ``OnlineMap(config, path=...)`` or :meth:`save`.

        The map uses the config stored in the file, whatever this code's defaults are.

        Parameters
        ----------
        path : str or Path
        read_only : bool, optional
            ``False`` (default): this map is the file's one writer until
            :meth:`close`, and goes on inserting into it. ``True``: a reader of the
            file's last committed scan (a snapshot, whatever a writer does meanwhile);
            every write is refused and the file's bytes never change. Read-only
            files and directories open this way.

        Raises
        ------
        MapFileNotFound
            If the file does not exist.
        OctolgpError
            If it is not an octolgp map file or is corrupt, or, to write, when it is
            read-only here or another writer has it open.
        """
        from octolgp.persist.mapfile import MapFile

        f = MapFile.open(path, read_only=read_only)
        try:
            return cls(f.header.config, storage=f)
        except BaseException:
            f.close()
            raise

    def save(self, path: str | Path, *, overwrite: bool = False) -> None:
        """Write the map to a new SQLite map file (a temporary file, then a rename).

        The file holds the map as it is: a map still buffering scans is saved with
        its buffered scans and no hyperparameters, and reopens buffering.

        Parameters
        ----------
        path : str or Path
            A new file; never the map's own file.
        overwrite : bool, optional
            Replace an existing file at ``path`` (not one open for writing).

        Raises
        ------
        OctolgpError
            If ``path`` exists (without ``overwrite``), is the map's own file or
            cannot be written; a file already there is then unchanged.
        """
        from octolgp.persist.mapfile import write_map

        with self._reading():
            f = self._file
            own = None if f is None else f.path
            leaves = self.leaves()  # none while learning: the file keeps the buffered scans
            hp, n = self.hyperparameters, self.n_scans
            kept = self._journal_source
            journal = (
                enumerate(self._bootstrap.scans, start=1)
                if kept is None
                else kept.journal(kept.journal_start)
            )
            write_map(
                path,
                self.config,
                hp,
                n,
                leaves,
                journal,
                checkpoints=None if kept is None else kept.checkpoints,
                checkpoint_rows=() if kept is None else kept.checkpoint_rows(),
                overwrite=overwrite,
                own=own,
            )

    def close(self) -> None:
        """Release worker threads and the map file; every later call is refused.

        Closing twice is harmless.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._workers.close()
            if self._file is not None:
                self._file.close()
                self._file = None

    def _check(self, call: str, *, write: bool = False) -> None:
        """Refuse ``call`` on a closed or broken map (and a write on a read-only one)."""
        if self._closed:
            raise OctolgpError(f"{call}: the map is closed")
        if self._broken is not None:
            raise OctolgpError(f"{call}: {self._broken}")
        if write and self.read_only:
            raise OctolgpError(
                f"{call}: map file {str(self.path)!r} was opened read-only (OnlineMap.open "
                "with read_only=True)"
            )

    @contextmanager
    def _reading(self, points: FloatArray | None = None) -> Iterator[OnlineMap]:
        """The map one read comes from, held alone (the map's lock) for that read.

        This map, or a provisional fit of the buffered scans while it learns its
        hyperparameters. Every read of :class:`~octolgp.mapping.query.MapReads` goes
        through it, after the leaves whose fits inserts deferred are fitted
        (:meth:`settle`): for a query at up to :data:`LOCAL_QUERY_POINTS` ``points``,
        only those it reads (a leaf's fit depends on its own evidence only); a closed
        or broken map refuses.
        """
        with self._lock:
            self._check("read")
            if self.store.n_pending and self.hyperparameters is not None:
                if points is not None and points.shape[0] <= LOCAL_QUERY_POINTS:
                    self._settle(self.store.pending_among(leaves_read(self.grid, points)))
                else:
                    self._settle()
            yield self if not self.provisional else self._bootstrap.provisional(_provisional_map)

    @contextmanager
    def _all_or_nothing(self, call: str) -> Iterator[None]:
        """Several writes as one: one file transaction, or a map that refuses further use.

        The store cannot be rolled back, so when the transaction fails after a write
        reached the store the map is broken: every later call is refused, and the
        file (rolled back) holds the map before ``call``.
        """
        writes = self._writes
        try:
            with self._file.transaction() if self._file is not None else nullcontext():
                yield
        except BaseException as exc:  # a failed commit too, after the writes
            if self._writes != writes:
                self._break(call, exc)
            raise

    def _break(self, call: str, exc: BaseException) -> None:
        """Refuse every later call: the store holds part of a step its file does not."""
        where = (
            f"reopen {str(self._file.path)!r} with OnlineMap.open: it holds the map before "
            "that call"
            if self._file is not None and not self._file.temporary
            else "the map is incomplete"
        )
        self._broken = f"an earlier {call} failed part-way ({exc}); {where}"

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
        """The journaled scans, in order: scans ``journal_start + 1`` to ``n_scans``.

        The journal keeps every scan, or with ``OnlineConfig.journal_scans`` the latest
        ones; a map without a file keeps it in RAM.
        """
        self._check("scans")
        kept = self._journal_source
        if kept is not None:
            return kept.scans(kept.journal_start)
        return iter(list(self._bootstrap.scans))

    @property
    def journal_start(self) -> int:
        """:meth:`scans` begins after this scan (0: with the first)."""
        kept = self._journal_source
        return 0 if kept is None else kept.journal_start

    @property
    def journal_bytes(self) -> int:
        """Bytes of RAM the journal of a map without a file holds (0 with a file)."""
        return 0 if self._ram_journal is None else self._ram_journal.nbytes

    @property
    def _journal_source(self) -> ScanJournal | None:
        """Where the scans' journal is kept: the map file, RAM, or nowhere."""
        return self._file if self._file is not None else self._ram_journal

    @property
    def provisional(self) -> bool:
        """True while scans are buffered to learn hyperparameters.

        Reads then answer from a provisional fit of the buffered scans that is thrown
        away. The map itself holds no leaves until the hyperparameters are learnt, or,
        when it defers its fits (:attr:`defers_fit`), the buffered scans' evidence in
        leaves that wait for them.
        """
        return self.hyperparameters is None and len(self._bootstrap) > 0

    @property
    def buffered_scans(self) -> int:
        """Scans held back until the hyperparameters are learnt."""
        return len(self._bootstrap)

    # ------------------------------------------------------------------ updates
    @_step_of_state
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
            outside the addressable range, and when the map file's commit fails (a
            full disk, an I/O error). The map and its file are then exactly as
            before; so are they after any exception raised before the write.
        """
        t0 = time.perf_counter()
        scan = check_scan(scan, self.config, self.grid)
        index = self.n_scans + 1
        if self.hyperparameters is not None:
            return self._step([scan], [(index, scan)], t0)
        if self.defers_fit:  # evidence needs no hyperparameters: stored now, fitted later
            ready = self._bootstrap.add(scan)
            step = self._step([scan], [(index, scan)], t0, buffered=True)
            return self._learn(step) if ready else step
        if self._bootstrap.add(scan):  # enough scans to learn on
            update = self._learn_and_step([(index, scan)], t0)
            if update is not None:
                return update
        else:
            self._journal([(index, scan)])
        update = self._buffered_update(t0)
        show = getattr(self.sink, "on_provisional", None)  # optional in a sink
        if show is not None:
            show(update, self._provisional_change)
        return update

    def _provisional_change(self) -> MapChange:
        """Every leaf of the provisional map of the buffered scans, as a sink sees leaves."""
        return self._bootstrap.provisional(_provisional_map).full_change()

    def full_change(self) -> MapChange:
        """Every leaf of the map with its values, as a sink sees the leaves a step refitted."""
        return self._change(self.leaves())

    def _journal(self, journal: list[tuple[int, Scan]]) -> None:
        """Journal scans that change no leaf (buffered to learn on), then show them."""
        self._write([], journal=journal, n_scans=journal[-1][0])
        for i, s in journal:  # one iteration per journaled scan
            self.sink.on_scan(s, i)

    def insert_scans(self, scans: Iterable[Scan]) -> list[ScanUpdate]:
        """Insert scans one by one; return their updates."""
        return [self.insert_scan(s) for s in scans]

    @_step_of_state
    def flush(self) -> ScanUpdate | None:
        """Learn hyperparameters from the buffered scans now and insert them.

        The one explicit way to end the learning phase early (the CLI calls it at the
        end of a run shorter than ``learn_scans``); reads never do. Returns ``None``
        when nothing is buffered or the buffer holds no training data yet.
        """
        if not len(self._bootstrap):
            return None
        if self.defers_fit:  # the buffered scans are in the store already
            update = self._learn(self._buffered_update(time.perf_counter()))
            return None if update.buffered else update
        return self._learn_and_step([], time.perf_counter())

    def _learn(self, update: ScanUpdate) -> ScanUpdate:
        """Learn on the buffer of a map whose store holds the buffered scans' evidence.

        ``update`` is the step's record; it comes back unchanged while the buffer holds
        no training data yet, else with the learning's seconds and ``buffered`` false.
        The pending leaves are fitted with the learnt hyperparameters at the next read.
        """
        if not self._bootstrap.can_learn():
            return update
        learning = self._learn_on_buffer()
        self._bootstrap.take()
        release_free_memory()  # the learning's and the buffer's arrays, freed at once
        stages = {**update.stages, "learning": learning}
        return dataclasses.replace(
            update, buffered=False, stages=stages, seconds=update.seconds + learning
        )

    def _learn_and_step(self, journal: list[tuple[int, Scan]], t0: float) -> ScanUpdate | None:
        """Learn on the buffer and insert it; ``None`` (still buffering) without data."""
        if not self._bootstrap.can_learn():
            # nothing to learn from yet (no return, or every beam on its sensor): keep buffering
            if journal:
                self._journal(journal)
            return None
        learning = self._learn_on_buffer()
        update = self._step(self._bootstrap.take(), journal, t0)
        release_free_memory()  # the learning's and the buffer's arrays, freed at once
        update.stages["learning"] = learning
        return update

    def _learn_on_buffer(self) -> float:
        """Learn the hyperparameters on the buffered scans and keep them; the seconds taken."""
        t = time.perf_counter()
        hp = self._bootstrap.learn()
        logger.info("learnt hyperparameters on %d scans: %s", len(self._bootstrap), hp)
        self.hyperparameters = hp
        return time.perf_counter() - t

    def _step(
        self,
        scans: list[Scan],
        journal: list[tuple[int, Scan]],
        t0: float,
        *,
        buffered: bool = False,
    ) -> ScanUpdate:
        """Scans → evidence per leaf → refit the leaves whose GP inputs changed → write.

        With :attr:`defers_fit` the changed leaves are stored pending (their new
        evidence, their old values) and fitted when the map is next read.
        ``buffered``: the scans are also buffered to learn on (the record says so).
        """
        index = journal[-1][0] if journal else self.n_scans
        stages: dict[str, float] = {}
        # 1. scans → the engine's evidence → the leaves it changes (new leaf objects)
        with self._workers.one_blas_thread():
            evidence = self.engine.evidence(
                scans, self.store.get, stages, fresh=not self.defers_fit
            )
        # 2. leaves → local GP → PLSC, on the map's threads (or at the next read)
        if self.defers_fit:
            for _, leaf in evidence.changed:  # new objects: marked, not copied
                leaf.pending = True
            fitted, fits = evidence.changed, []
        else:
            fits = self._fit([leaf for _, leaf in evidence.changed], stages, fresh=evidence.fresh)
            fitted = [(k, f.leaf) for (k, _), f in zip(evidence.changed, fits, strict=True)]
        # 3. the one write: store, file, then the sink; the budget keeps room for a step
        self._reserve(len(evidence.touched))
        t = time.perf_counter()
        self._write(
            [*fitted, *evidence.kept],
            stamp=index,
            touched=evidence.touched,
            journal=journal,
            n_scans=index,
        )
        stages["store"] = time.perf_counter() - t
        for i, s in journal:  # shown once in the map
            self.sink.on_scan(s, i)
        update = self._update(
            index,
            t0,
            stages,
            len(evidence.touched),
            fits,
            new_items=evidence.new_items,
            refit=len(fitted),
            buffered=buffered,
        )
        self.sink.on_update(update, self._change(fitted))
        return update

    @property
    def defers_fit(self) -> bool:
        """Whether inserts leave the changed leaves' fits to the next read.

        ``OnlineConfig.defer_fit`` on a lattice map without a sink (a sink shows every
        step's values, so such a map fits in ``insert_scan``). A map file (or the spill
        file of a memory budget) keeps a lattice leaf's evidence, not its values, so a
        map with one defers too once it has its hyperparameters; while it learns them
        it journals the buffered scans and builds their leaves in the learning step.
        """
        return (
            self.config.online.defer_fit
            and self.config.online.engine == "lattice"
            and (self._file is None or self.hyperparameters is not None)
            and isinstance(self.sink, NullSink)
        )

    def settle(self) -> int:
        """Fit every leaf whose fit an insert deferred (``OnlineConfig.defer_fit``) now.

        Every read does this first, so calling it only chooses when the cost is paid
        (before a time-critical query, say). The map's values are those of fitting at
        every insert. Returns the number of leaves fitted: none while the map still
        learns its hyperparameters (their evidence waits for them).
        """
        with self._lock:
            self._check("settle")
            return self._settle()

    def _settle(self, keys: list[int] | None = None) -> int:
        """Fit pending leaves (``keys``, or all), every tile of each; store them unstamped.

        Leaves are settled a chunk at a time (``FIT_CHUNK``, or the store's batch under
        a budget), so a read after many inserts holds one chunk's fit at a time; a map
        with a file trims the store to its budget after each chunk.
        """
        keys = self.store.pending if keys is None else keys
        if not keys or self.hyperparameters is None:  # nothing to fit with while learning
            return 0
        done = 0
        step = self._fit_chunk
        with collector_paused():
            for lo in range(0, len(keys), step):  # one chunk of pending leaves per iteration
                part = keys[lo : lo + step]
                found = [(k, leaf) for k in part if (leaf := self.store.get(k)) is not None]
                fits = self._fit([leaf for _, leaf in found])
                fitted = [(k, f.leaf) for (k, _), f in zip(found, fits, strict=True)]
                if self._file is None:
                    self._write(fitted, settled=True)
                else:  # the file keeps their unchanged evidence: the values live in RAM
                    self.store.apply(fitted)
                    self.store.persisted([k for k, _ in fitted])
                    self._trim()
                done += len(found)
        return done

    @_step_of_state
    def correct_scans(self, corrections: Mapping[int, ArrayLike]) -> ScanUpdate:
        """Move journaled scans by rigid transforms, as a pose graph's loop closure does.

        The leaves that either version of a corrected scan touches are rebuilt from
        every journaled scan whose extent reaches them, with the corrections applied,
        and refitted; leaves left without evidence are removed. The result is the map
        the corrected scans would have built from the start (with this map's
        hyperparameters), at a cost that grows with the leaves and scans the
        correction reaches, not with the mission. The journal then holds the
        corrected scans; with a map file it is one transaction (a kill leaves the map
        before or after the correction). A map without a file keeps its journal in
        RAM (the class's Notes), so it corrects the same way, to the same map.

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
            rigid, a scan older than the journal (``OnlineConfig.journal_scans``), or a
            map file saved without a journal; the map is then unchanged.
        """
        t0 = time.perf_counter()
        transforms = check_corrections(corrections, self.n_scans, self.config.dim)
        old = self._journaled(list(transforms), "corrections")
        return self._correct(old, transforms, "corrections", t0)

    @_step_of_state
    def correct_poses(self, poses: Mapping[int, ArrayLike]) -> ScanUpdate:
        """Move journaled scans to new absolute sensor poses, as a pose graph optimises them.

        Scan ``i``, inserted from the sensor pose ``T_old`` (:attr:`Scan.pose`: its
        origin and rotation, as journaled), is moved by ``T_new · T_old⁻¹``
        (:func:`~octolgp.mapping.correction.pose_corrections`), which takes it to
        ``T_new``; then as :meth:`correct_scans`, which it equals with those
        corrections. Scans not named keep their poses.

        Parameters
        ----------
        poses : mapping of int to array_like of shape (d+1, d+1)
            Scan number (from 1, as in ``ScanUpdate.scan``) → the sensor's new pose, a
            rigid homogeneous sensor-to-world transform (metres), in the frame the
            scans were inserted in.

        Returns
        -------
        ScanUpdate
            As :meth:`correct_scans`.

        Raises
        ------
        OctolgpError
            As :meth:`correct_scans` (naming ``poses[i]``), and for a scan journaled
            without its sensor rotation (:attr:`Scan.rotation`: a scan made from
            points alone, or a map file written before the journal kept rotations);
            the map is then unchanged.
        """
        t0 = time.perf_counter()
        targets = check_corrections(poses, self.n_scans, self.config.dim, "poses")
        old = self._journaled(list(targets), "poses")
        return self._correct(old, pose_corrections(old, targets), "poses", t0)

    def _correct(
        self, old: dict[int, Scan], transforms: dict[int, FloatArray], name: str, t0: float
    ) -> ScanUpdate:
        """Apply checked corrections to the journaled scans ``old``: rebuild, refit, write."""
        new = self._moved(old, transforms, name)
        storage = self._journal_source
        assert storage is not None  # _journaled refuses a map without a journal
        start, extents = self._extents.read(storage, self.n_scans)  # read before any write
        learning = self.hyperparameters is None
        if learning and not len(self.store):  # still buffering, no leaf: only the journal moves
            self._write([], corrected=list(new.items()))
            self._bootstrap.corrected(new)
            self._extents.replace(moved_extents(extents, start, new, self.grid))
            return self._buffered_update(t0)
        stages: dict[str, float] = {}
        # 1. the leaves either version reaches, and every scan whose extent reaches them
        with self._workers.one_blas_thread():
            replay = plan_replay(storage, start, extents, old, new, self.engine, stages)
            # 2. their evidence as of the journal's start, the corrected scans replayed on
            # it in time order (and kept as of each later checkpoint)
            gathered, checkpointed, new_items = self._replay(storage, replay, stages)
        keys = [k for k in replay.affected if k in gathered]
        removed = [k for k in replay.affected if k not in gathered and k in self.store]
        leaves = [gathered[k] for k in keys]
        del gathered
        self.engine.rebuilt(replay.affected)
        if learning:  # a deferring map's buffered evidence: fitted once it has hyperparameters
            for leaf in leaves:  # new objects: marked, not copied
                leaf.pending = True
            fits, fitted = [], list(zip(keys, leaves, strict=True))
        else:
            fits = self._fit(leaves, stages)
            fitted = [(k, f.leaf) for k, f in zip(keys, fits, strict=True)]
        # 3. the one write: store, then the file in one transaction, then the sink
        t = time.perf_counter()
        self._write(
            fitted,
            stamp=self.n_scans,
            removed=removed,
            corrected=list(new.items()),
            checkpointed=checkpointed,
        )
        if learning:
            self._bootstrap.corrected(new)
        self._extents.replace(replay.extents)
        stages["store"] = time.perf_counter() - t
        stages["replayed_scans"] = float(len(replay.scans))
        update = self._update(
            self.n_scans,
            t0,
            stages,
            len(replay.affected),
            fits,
            new_items,
            len(removed),
            refit=len(fitted),
            buffered=learning,
        )
        self.sink.on_update(update, self._change(fitted, tuple(removed)))
        return update

    def _replay(
        self, storage: ScanJournal, replay: Replay, stages: dict[str, float]
    ) -> tuple[dict[int, Leaf], dict[int, dict[int, Leaf | None]], int]:
        """The affected leaves rebuilt: their state at the journal's start, then its scans.

        Returns the rebuilt leaves (unfitted; a leaf left out has no evidence), their
        state at each checkpoint after the start (``None``: no leaf then) and the
        training items gathered.
        """
        checkpoints = storage.checkpoints
        start = checkpoints[0]
        base = storage.checkpoint_leaves(start, replay.affected) if start else {}
        state: dict[int, Leaf | None] = {}
        for k in replay.affected:  # one iteration per affected leaf
            state[k] = base[k] if k in base else (self.store.get(k) if start else None)
        checkpointed: dict[int, dict[int, Leaf | None]] = {}
        items = 0
        bounds = [c for c in checkpoints[1:] if c < self.n_scans] + [self.n_scans]
        lo = 0
        for c in bounds:  # one stretch of the journal per iteration, up to a checkpoint
            hi = int(np.searchsorted(replay.numbers, c, side="right"))
            if hi > lo:
                gathered, _, n = gather_batch(
                    replay.scans[lo:hi], self.engine, state.get, CHUNK_BEAMS, stages
                )
                state.update(gathered)
                items += n
            lo = hi
            if c < self.n_scans:
                checkpointed[c] = dict(state)
        rebuilt = {k: leaf for k, leaf in state.items() if leaf is not None}
        return rebuilt, checkpointed, items

    def _journaled(self, numbers: list[int], name: str) -> dict[int, Scan]:
        """The journaled scans with these (checked) numbers; reads only.

        Raises
        ------
        OctolgpError
            Naming ``name[i]`` for a scan older than the journal, and for a map without
            one (a map file saved without its journal).
        """
        kept = self._journal_source
        start = 0 if kept is None else kept.journal_start
        folded = [i for i in numbers if i <= start]
        if folded:
            raise OctolgpError(
                f"{name}[{folded[0]}]: scan {folded[0]} is older than the journal, which "
                f"keeps scans {start + 1} to {self.n_scans} (OnlineConfig.journal_scans = "
                f"{self.config.online.journal_scans}); its evidence is folded into the map"
            )
        if kept is None:
            raise OctolgpError(
                f"{name}: this map keeps no journal of its scans to correct (it was made "
                "with journal=False)"
            )
        old = kept.read_scans(numbers)
        if len(old) != len(numbers):
            raise OctolgpError(
                f"map file {str(self.path)!r} holds no journal of its scans (saved by a "
                "version that kept none for a map in memory); it cannot be corrected"
            )
        return old

    def _moved(
        self, old: dict[int, Scan], transforms: dict[int, FloatArray], name: str
    ) -> dict[int, Scan]:
        """The scans ``old`` moved by ``transforms``, as the map keeps them (checked)."""
        new = {}
        for i, T in transforms.items():  # a corrected scan must stay inside the map
            try:
                new[i] = check_scan(transform_scan(old[i], T), self.config, self.grid)
            except OctolgpError as exc:
                raise OctolgpError(f"{name}[{i}] moves the scan out of the map: {exc}") from None
        return new

    @_step_of_state
    def insert_batch(
        self,
        scans: Iterable[Scan],
        *,
        fitter: LeafFitter | None = None,
        progress: Any = None,
    ) -> ScanUpdate:
        """Insert many scans as one step: every touched leaf is fitted once.

        The same map as inserting the scans one by one (each engine's evidence is a
        function of the scans in time order), at a fraction of the cost for a whole
        log. Evidence is gathered in chunks of about :data:`CHUNK_BEAMS` beams, and
        leaves are fitted, stored and committed in batches, so transient memory is
        bounded by the chunk and the batch, not the log.

        Parameters
        ----------
        scans : iterable of Scan
            World-frame scans of dimension ``config.dim``; at least one.
        fitter : callable, optional
            Where the leaves are fitted (:data:`octolgp.mapping.evidence.LeafFitter`):
            by default on this map's threads; :func:`octolgp.batch.leafmap.build_tiled`
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
            On a bad scan (checked before anything changes) or no scans at all. With
            a map file the batch is one transaction: a kill or a failed commit leaves
            the file as before the call (and the map, then out of step with it,
            refuses further calls).
        """
        t0 = time.perf_counter()
        new_scans = [check_scan(s, self.config, self.grid) for s in scans]
        if not new_scans:
            raise OctolgpError("scans: no scans to build from")
        journal = list(enumerate(new_scans, start=self.n_scans + 1))
        index = journal[-1][0]
        stats: dict[str, float] = {"learning": 0.0}
        scan_list = new_scans
        if self.hyperparameters is None and fitter is None:  # learn on the first scans
            buffered = self._bootstrap.take()
            self._learn_first(buffered + new_scans, stats)
            if not self.defers_fit:  # a deferring map holds their evidence already
                scan_list = buffered + new_scans
        # 1. every scan's evidence, chunk by chunk in time order
        with self._workers.one_blas_thread():
            gathered, refit, new_items = gather_batch(
                scan_list, self.engine, self.store.get, CHUNK_BEAMS, stats
            )
        keys = [k for k in gathered if k in refit]
        with self._all_or_nothing("insert_batch"):
            kept = [(k, leaf) for k, leaf in gathered.items() if k not in refit]
            if kept:  # new counts, same GP inputs: stored as they are
                self._write(kept, stamp=index)
            leaves = [gathered[k] for k in keys]
            del gathered, kept
            # 2. fit in batches, each written (then evictable) before the next
            t = time.perf_counter()
            run = self._local_fitter if fitter is None else fitter
            pruned, repaired = self._write_batches(run(keys, leaves), index, len(keys), progress)
            stats["fit"] = time.perf_counter() - t
            # 3. the journal and the scan count, last; the commit makes it all durable
            t = time.perf_counter()
            self._write([], journal=journal, n_scans=index)
        stats["store"] = time.perf_counter() - t
        for i, s in journal:  # shown once in the map
            self.sink.on_scan(s, i)
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

    def _learn_first(self, scans: list[Scan], stats: dict[str, float]) -> None:
        """Learn the hyperparameters on the first ``learn_scans`` scans (``stats["learning"]``)."""
        t = time.perf_counter()
        hp = learn_hyperparameters(scans[: self.config.learn_scans], self.config)
        stats["learning"] = time.perf_counter() - t
        logger.info("learnt hyperparameters on the first scans: %s", hp)
        self.hyperparameters = hp

    def _write_batches(
        self,
        batches: Iterator[tuple[list[int], list[LeafFit]]],
        stamp: int,
        total: int,
        progress: Any,
    ) -> tuple[int, int]:
        """Write fitted batches of leaves one by one; return the pruned and repaired counts."""
        pruned = repaired = done = 0
        for keys, fits in batches:  # one batch of leaves per iteration
            self._write([(k, f.leaf) for k, f in zip(keys, fits, strict=True)], stamp=stamp)
            pruned += sum(f.leaf.pruned for f in fits)
            repaired += self._count_repairs(fits)
            done += len(keys)
            if progress is not None:
                progress(done, total)
        return pruned, repaired

    def _local_fitter(
        self, keys: list[int], leaves: list[Leaf]
    ) -> Iterator[tuple[list[int], list[LeafFit]]]:
        """Fit leaves on this map's threads in batches of about FIT_BATCH_ITEMS items.

        Every leaf is fitted once here, so nothing is worth keeping for a later fit.
        """
        for lo, hi in batch_bounds([leaf.n_items for leaf in leaves], FIT_BATCH_ITEMS):
            yield keys[lo:hi], self._fit(leaves[lo:hi], reuse=False)

    @_step_of_state
    def relearn(self, scans: Iterable[Scan]) -> Hyperparameters:
        """Learn new hyperparameters on ``scans`` and refit every leaf with them."""
        hp = learn_hyperparameters(
            map_scans(check_scans(scans, self.config.dim), self.config), self.config
        )
        self.set_hyperparameters(hp)
        return hp

    @_step_of_state
    def set_hyperparameters(self, hp: Hyperparameters) -> None:
        """Use ``hp`` from now on and refit every leaf from its stored evidence.

        Buffered scans are inserted with ``hp``. Leaves are refitted in batches of
        256 so a map with a memory budget never holds more than that many beyond its
        budget; with a map file it is one transaction (a kill leaves the file before
        or after).
        """
        if not isinstance(hp, Hyperparameters):
            raise OctolgpError(f"hp must be Hyperparameters, got {type(hp).__name__}")
        self.hyperparameters = hp
        with self._all_or_nothing("set_hyperparameters"):
            if len(self._bootstrap):
                buffered = self._bootstrap.take()
                if not self.defers_fit:  # a deferring map holds their evidence already
                    self._step(buffered, [], time.perf_counter())
            keys = list(self.store)
            for lo in range(0, len(keys), 256):  # one batch of leaves per iteration
                batch = [(k, leaf) for k in keys[lo : lo + 256] if (leaf := self.store.peek(k))]
                fits = self._fit([leaf for _, leaf in batch])
                self._count_repairs(fits)
                self._write([(k, f.leaf) for (k, _), f in zip(batch, fits, strict=True)])

    # ------------------------------------------------------------------ the one write path
    def _write(
        self,
        leaves: list[tuple[int, Leaf]],
        *,
        stamp: int | None = None,
        touched: Iterable[int] = (),
        journal: list[tuple[int, Scan]] | None = None,
        n_scans: int | None = None,
        removed: list[int] | None = None,
        corrected: list[tuple[int, Scan]] | None = None,
        checkpointed: dict[int, dict[int, Leaf | None]] | None = None,
        settled: bool = False,
    ) -> None:
        """Write one step's result: the map file in one transaction, then the store.

        The file first: when its commit fails nothing has changed, in RAM or on disk.
        A map without a file records the step in its RAM journal instead, before the
        store changes (it keeps leaves as they were before the step).

        Parameters
        ----------
        leaves : list of (int, Leaf)
            New or replaced leaves.
        stamp : int, optional
            Scan number stamped on ``leaves`` and ``touched`` (least-recently-used
            order); ``None`` keeps their stamps.
        touched : iterable of int
            Leaves the step reached without changing.
        journal : list of (int, Scan), optional
            New journal rows.
        n_scans : int, optional
            The new scan count (``None``: unchanged).
        removed : list of int, optional
            Leaves left without evidence (a correction).
        corrected : list of (int, Scan), optional
            Journal rows rewritten (a correction).
        checkpointed : dict, optional
            A correction's rebuilt leaves as of each checkpoint after the journal's start.
        settled : bool, optional
            ``leaves`` are fits of unchanged evidence (a settle), which no journal records.
        """
        journal, removed, corrected = journal or [], removed or [], corrected or []
        written: list[int] = []
        if self._file is not None:
            if stamp is not None:  # the stamp the store gives them, written with them
                for _, leaf in leaves:  # one iteration per new leaf
                    leaf.touched = stamp
            if corrected or removed:
                written = self._file.correct(leaves, removed, corrected, checkpointed)
            else:
                count = self.n_scans if n_scans is None else n_scans
                written = self._file.commit(leaves, journal, self.hyperparameters, count)
        elif self._ram_journal is not None and not settled:
            keys = [k for k, _ in leaves]
            if corrected or removed:
                self._ram_journal.correct(keys + removed, corrected, checkpointed)
            else:
                count = self.n_scans if n_scans is None else n_scans
                self._ram_journal.record(keys, journal, self.hyperparameters, count)
        try:
            self.store.apply(leaves, touched, stamp)
            self.store.remove(removed)
            if n_scans is not None:
                self.n_scans = n_scans
            self._extents.journaled([s for _, s in journal])
            self.store.persisted(written)
            self._writes += 1
            self._trim()
        except BaseException as exc:  # the file holds the step, the store part of it
            self._writes += 1
            self._break("write", exc)
            raise

    def _reserve(self, touched: int) -> None:
        """Keep room in the budget for a step like the largest of the recent ones.

        A step's working arrays scale with the leaves it touches
        (:data:`~octolgp.mapping.store.STEP_BYTES_PER_HALO_VOXEL` per voxel of their halo
        boxes); the store holds its leaves within the budget less the largest of the
        last :data:`RESERVE_STEPS` steps', so that leaves and a step together stay
        within the budget. The map does not depend on it.
        """
        if self.store.budget_bytes is None:
            return
        self._recent_touched.append(touched)
        box = (self.grid.side + 2 * self.grid.halo_voxels) ** self.grid.dim
        self.store.reserve_bytes = max(self._recent_touched) * box * STEP_BYTES_PER_HALO_VOXEL

    def _trim(self) -> None:
        """Trim the store to its budget, then hand the heap's free pages back.

        A step's arrays and evicted leaves' arrays go back to the C heap, whose free
        pages glibc keeps resident (:mod:`octolgp.memory`): without ``malloc_trim`` a
        budgeted map's process holds them beside its leaves, about as much again as
        the leaves while the map grows to its budget. Under a millisecond a step.
        """
        if self.store.budget_bytes is None:
            return
        self.store.trim()
        release_free_memory()

    def _fit(
        self,
        leaves: list[Leaf],
        stages: dict[str, float] | None = None,
        *,
        reuse: bool = True,
        fresh: NDArray[np.bool_] | None = None,
    ) -> list[LeafFit]:
        """Fit leaves with the map's hyperparameters on its threads (``stages["fit"]``).

        ``fresh``: the step's :attr:`~octolgp.engines.base.Evidence.fresh` tiles.
        """
        hp = self.hyperparameters
        assert hp is not None
        t = time.perf_counter()
        pool = self._workers.pool(len(leaves))
        fits: list[LeafFit] = []
        with self._workers.one_blas_thread():
            size = self._fit_chunk
            for lo in range(0, len(leaves), size):  # one chunk of leaves per iteration
                hi = lo + size
                part = None if fresh is None else fresh[lo:hi]
                fits += self.engine.fit(leaves[lo:hi], hp, pool, reuse=reuse, fresh=part)
        if stages is not None:
            stages["fit"] = stages.get("fit", 0.0) + time.perf_counter() - t
        return fits

    @property
    def _fit_chunk(self) -> int:
        """Leaves fitted per engine call: :data:`FIT_CHUNK`, or under a budget fewer.

        Under a memory budget the store's batch, so that a fit's working set stays
        within a share of the budget.
        """
        if self.store.budget_bytes is None:
            return self.store.leaves_of(FIT_CHUNK)
        return self.store.batch

    def _update(
        self,
        scan: int,
        t0: float,
        stages: dict[str, float],
        touched: int,
        fits: list[LeafFit],
        new_items: int,
        removed: int = 0,
        refit: int | None = None,
        buffered: bool = False,
    ) -> ScanUpdate:
        """The record of a step that refitted ``fits``.

        ``refit``: the leaves whose GP inputs changed, when they are not ``fits`` (a
        deferred fit).
        """
        return ScanUpdate(
            scan=scan,
            touched_leaves=touched,
            refit_leaves=len(fits) if refit is None else refit,
            new_items=new_items,
            pruned_leaves=sum(f.leaf.pruned for f in fits),
            seconds=time.perf_counter() - t0,
            stages=stages,
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
            repaired=self._count_repairs(fits),
            removed_leaves=removed,
            buffered=buffered,
        )

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
    def memory_bytes(self) -> int:
        """Bytes held by the leaves (evidence and voxel values)."""
        return self.store.nbytes

    def __repr__(self) -> str:
        return (
            f"OnlineMap(dim={self.config.dim}, resolution={self.config.resolution:g}, "
            f"scans={self.n_scans}, leaves={len(self.store)})"
        )


def _provisional_map(config: MapConfig, scans: list[Scan]) -> OnlineMap:
    """A throw-away in-memory map of buffered scans (what :meth:`OnlineMap.flush` would make)."""
    provisional = OnlineMap(config, journal=False)  # thrown away: nothing to correct
    if scans:
        provisional.insert_batch(scans)
    return provisional
