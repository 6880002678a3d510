"""The online mapper: scans go in one at a time; only the leaves they touch are refitted.

:class:`OnlineMap` is the paper's method made incremental, OctoMap-style:

1. **Scan → training data**: a hit and a free segment per beam
   (:func:`octolgp.training.make_training_data`).
2. **Training data → leaves**: a hit goes to every leaf whose halo box holds it; a
   free segment is clipped to the halo box of every leaf it crosses
   (:mod:`octolgp.mapping.grid`).
3. **Bounded evidence**: a leaf keeps the first hit per voxel and the first free
   piece per voxel of the piece's end (:meth:`octolgp.store.Leaf.add_evidence`).
   Its training set is therefore at most two items per voxel of its halo box, so
   revisiting a place costs nothing once its voxels are observed: a scan that
   brings no new voxel to a leaf leaves that leaf's GP and voxels as they were.
   This is exact for a static world; a changing world keeps its first state.
   Because the rule is "first in time order", inserting scans one by one gives
   bit-for-bit the map of inserting them all at once.
4. **Leaves → local GP → PLSC**: a touched leaf that gained items is refitted
   (one GP on its whole training set, or the paper's iterative k-means clusters
   when it holds more than ``OnlineConfig.max_leaf_items``) and its voxel centres
   are predicted and written into the store as latent mean, variance and
   P(occupied).
5. **Pruning**: a leaf whose voxels are all below ``prune_free`` or all above
   ``prune_occupied`` keeps one value (the least confident one) instead of one
   per voxel.

Hyperparameters are those of ``MapConfig.hyperparameters``; when it is ``None``
the first ``OnlineConfig.learn_scans`` scans are buffered, the hyperparameters are
learnt on them (:func:`octolgp.learning.learn_hyperparameters`) and then held
fixed. To re-learn, call :meth:`OnlineMap.relearn` with the scans to learn from:
every leaf is refitted from its stored evidence with the new values.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from threadpoolctl import ThreadpoolController

from octolgp.batch.gpmap import items_and_targets, quadrature_spacing
from octolgp.batch.lgp import LocalGPMap, fit_clusters
from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_mask, addressable_range, pack_keys
from octolgp.gp.kernels import QuadratureSet, item_covariance, points_set
from octolgp.gp.learning import learn_hyperparameters
from octolgp.gp.plsc import occupancy_probability
from octolgp.gp.regression import fit_predict, jitter_repairs
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments
from octolgp.mapping.store import Leaf, LeafStore
from octolgp.partition import partition
from octolgp.scan import FloatArray, Scan, as_points, check_scan_size
from octolgp.training import IntArray, TrainingData, make_training_data

_CONTROLLER: ThreadpoolController | None = None


def _blas_controller() -> ThreadpoolController:
    """One process-wide controller (finding the BLAS libraries is the slow part)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


@dataclass(frozen=True)
class ScanUpdate:
    """What one :meth:`OnlineMap.insert_scan` did.

    Attributes
    ----------
    scan : int
        Number of the scan in the mission, from 1.
    touched_leaves : int
        Leaves whose box or halo the scan's evidence reached.
    refit_leaves : int
        Touched leaves that gained evidence and were refitted and re-predicted.
    new_items : int
        Training items added over all leaves.
    pruned_leaves : int
        Refitted leaves that were pruned to one value.
    seconds : float
        Wall time of the call.
    stages : dict of str to float
        Seconds per stage: ``training``, ``assign``, ``fit`` (fit and predict),
        ``store``, and ``learning`` when hyperparameters were learnt in this call.
    buffered : bool
        True while scans are buffered to learn hyperparameters; the map is
        unchanged until then.
    n_leaves : int
        Leaves in the map after the call.
    memory_bytes : int
        Bytes held by the leaves after the call.
    repaired : int
        Kernel matrices that were not numerically positive definite (coincident
        items, tiny noise) and were repaired by jitter during this step
        (:func:`octolgp.local_gp.jitter_repairs`; a process-wide count, so concurrent
        maps in one process share it).
    """

    scan: int
    touched_leaves: int
    refit_leaves: int
    new_items: int
    pruned_leaves: int
    seconds: float
    stages: dict[str, float] = field(default_factory=dict)
    buffered: bool = False
    n_leaves: int = 0
    memory_bytes: int = 0
    repaired: int = 0


@dataclass(frozen=True, slots=True)
class _Blocks:
    """A leaf's item covariance blocks for its first ``n_hits`` hits and ``n_free`` pieces."""

    n_hits: int
    n_free: int
    K: FloatArray  # (n, n) noise-free item covariance, items = hits then pieces
    Ks: FloatArray  # (V, n) voxel centres x items
    key: tuple[float, ...]  # what the blocks depend on besides the items


class KernelCache:
    """Least-recently-used item covariance blocks of leaves, bounded in bytes.

    Thread-safe (the map refits leaves on several threads); each leaf's entry is
    touched by one thread at a time.

    Parameters
    ----------
    max_bytes : int
        Entries are dropped, oldest first, while the total exceeds this.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self._entries: OrderedDict[int, _Blocks] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: int) -> _Blocks | None:
        """The entry of leaf ``key``, or ``None``."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
            return entry

    def put(self, key: int, entry: _Blocks) -> None:
        """Store (or replace) the entry of leaf ``key`` and evict down to the budget."""
        size = entry.K.nbytes + entry.Ks.nbytes
        with self._lock:
            old = self._entries.pop(key, None)
            if old is not None:
                self.bytes -= old.K.nbytes + old.Ks.nbytes
            if size > self.max_bytes:
                return
            self._entries[key] = entry
            self.bytes += size
            while self.bytes > self.max_bytes:  # oldest first
                _, gone = self._entries.popitem(last=False)
                self.bytes -= gone.K.nbytes + gone.Ks.nbytes


def _leaf_blocks(
    leaf: Leaf,
    items: QuadratureSet,
    centres: FloatArray,
    hp: Hyperparameters,
    key: tuple[float, ...],
    cache: KernelCache,
) -> tuple[FloatArray, FloatArray]:
    """The leaf's ``K`` and ``Ks``, reusing its cached blocks for the items it already had.

    Items are the hits then the free pieces, both append-only, so the old items sit at
    known rows. Every entry of an item covariance depends only on its two items (node
    distances, the kernel and the weighted sums over each item's nodes, in a fixed
    order), so the assembled blocks equal freshly computed ones bit for bit.
    """
    packed = int(pack_keys(leaf.index[None, :])[0])
    h, f = leaf.hits.shape[0], leaf.free_start.shape[0]
    old = cache.get(packed)
    ls, sf2 = hp.length_scale, hp.signal_variance
    if old is None or old.key != key or old.n_hits > h or old.n_free > f:
        cache.misses += 1
        K = item_covariance(items, items, ls, sf2)
        Ks = item_covariance(points_set(centres), items, ls, sf2)
    else:
        cache.hits += 1
        h0, f0 = old.n_hits, old.n_free
        old_idx = np.concatenate([np.arange(h0), h + np.arange(f0)])
        new_idx = np.concatenate([np.arange(h0, h), h + np.arange(f0, f)])
        new = items.subset(new_idx)
        K = np.empty((h + f, h + f))
        K[np.ix_(old_idx, old_idx)] = old.K
        K[new_idx, :] = item_covariance(new, items, ls, sf2)
        K[:, new_idx] = item_covariance(items, new, ls, sf2)
        Ks = np.empty((centres.shape[0], h + f))
        Ks[:, old_idx] = old.Ks
        Ks[:, new_idx] = item_covariance(points_set(centres), new, ls, sf2)
    cache.put(packed, _Blocks(h, f, K, Ks, key))
    return K, Ks


def predict_leaf(
    leaf: Leaf,
    centres: FloatArray,
    config: MapConfig,
    hp: Hyperparameters,
    cache: KernelCache | None = None,
) -> tuple[FloatArray, FloatArray]:
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
    """
    spacing = quadrature_spacing(config, hp.length_scale)
    cap = config.online.max_leaf_items
    hits, fs, fe = leaf.hits, leaf.free_start, leaf.free_end
    if leaf.n_items == 0:
        return np.zeros(centres.shape[0]), np.full(centres.shape[0], hp.signal_variance)
    if leaf.n_items <= cap or hits.shape[0] == 0:
        if leaf.n_items > cap:  # free space only: an even, deterministic thinning
            keep = np.linspace(0, fs.shape[0] - 1, cap).round().astype(np.int64)
            fs, fe = fs[keep], fe[keep]
            cache = None  # the thinned items are not append-only
        items, y = items_and_targets(hits, fs, fe, config, spacing)
        if cache is None:
            return fit_predict(items, y, hp, centres)
        tc = config.training
        key = (
            hp.length_scale,
            hp.signal_variance,
            spacing,
            float(tc.min_quadrature_nodes),
            float(tc.max_quadrature_nodes),
        )
        K, Ks = _leaf_blocks(leaf, items, centres, hp, key, cache)
        return fit_predict(items, y, hp, centres, K=K, Ks=Ks)
    # the paper's iterative k-means under the cluster cap, nearest-centre prediction
    data = TrainingData(hits, fs, fe, np.full(fs.shape[0], -1, dtype=np.int64))
    # a lattice at the map resolution is fine enough for a leaf's Voronoi cells
    cells = int(np.ceil(float(np.ptp(centres, axis=0).max()) / config.resolution)) + 3
    clusters = partition(data, config, cells=cells)
    gps = fit_clusters(data, clusters, config, hp)
    return LocalGPMap(config, hp, clusters=clusters, gps=gps)._latent_nearest(centres)


def fit_leaf(
    leaf: Leaf, config: MapConfig, hp: Hyperparameters, cache: KernelCache | None = None
) -> Leaf:
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
    Leaf
        A copy with ``mean``, ``var`` (float32, latent) and ``prob``, ``pruned`` set and
        ``refits`` incremented.
    """
    oc = config.online
    centres = LeafGrid.from_config(config).voxel_centres(leaf.index)
    mean, var = predict_leaf(leaf, centres, config, hp, cache)
    prob = occupancy_probability(mean, var + hp.noise_variance, hp.alpha, hp.beta)
    pruned = False
    if oc.prune and (prob.max() < oc.prune_free or prob.min() > oc.prune_occupied):
        at = int(np.argmax(prob) if prob.max() < oc.prune_free else np.argmin(prob))
        mean, var, prob = mean[at : at + 1], var[at : at + 1], prob[at : at + 1]
        pruned = True
    return dataclasses.replace(
        leaf,
        mean=mean.astype(np.float32),
        var=var.astype(np.float32),
        prob=prob.astype(np.float32),
        pruned=pruned,
        refits=leaf.refits + 1,
    )


class NullSink:
    """Where map events go when nothing listens: every method does nothing.

    The map calls its sink unconditionally (no branches in the pipeline); a
    :class:`octolgp.sinks.rerun.RerunSink` logs the same events to Rerun.
    """

    def on_scan(self, m: OnlineMap, scan: Scan, index: int) -> None:
        """An accepted scan (before buffering or integration)."""

    def on_update(self, m: OnlineMap, update: ScanUpdate, keys: list[int]) -> None:
        """Leaves ``keys`` were refitted by the update."""


def _group(packed: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Sort order, unique values and run bounds of packed keys."""
    order = np.argsort(packed, kind="stable")
    s = packed[order]
    starts = np.flatnonzero(np.r_[True, s[1:] != s[:-1]]) if s.size else np.zeros(0, np.int64)
    return order, s[starts], np.append(starts, s.size).astype(np.int64)


class OnlineMap:
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
    sink : object, optional
        Any object with the methods of :class:`NullSink` (for example a
        ``RerunSink`` with options); overrides ``recording``.

    Notes
    -----
    With ``MapConfig.memory_budget_mb`` the least recently used leaves are dropped
    from RAM after each scan once they are in the map file (a temporary spill file
    when ``path`` is ``None``) and loaded back when a scan or query touches them;
    the map does not depend on the budget. With a file, every ``insert_scan`` is
    durable when it returns (one SQLite transaction; see :mod:`octolgp.persist.mapfile`).

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
        sink: Any = None,
        _opened: bool = False,
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
        self._buffer: list[Scan] = []
        self._pool: ThreadPoolExecutor | None = None
        self._file: Any = None
        self.build_stats: dict[str, float] = {}
        cache_mb = config.online.kernel_cache_mb
        self.kernel_cache = None if cache_mb == 0 else KernelCache(int(cache_mb * 1e6))
        if recording is not None:
            from octolgp.sinks.rerun import RerunSink

            sink = RerunSink(recording)
        self.sink: Any = NullSink() if sink is None else sink
        # Evidence is deduplicated per leaf (Leaf.add_evidence), in time order, so a
        # scan-level dedup would only make one-by-one and all-at-once insertion differ.
        self._raw_config = dataclasses.replace(
            config, training=dataclasses.replace(config.training, dedup=False)
        )
        if not _opened and (path is not None or budget is not None):
            from octolgp.persist.mapfile import MapFile

            # without a path, a memory budget spills evicted leaves to a temporary file
            self._file = MapFile.create(path, self) if path is not None else MapFile.spill(self)
            self.store.attach(self._file, [])

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

        return MapFile.open(path)

    def save(self, path: str | Path) -> None:
        """Write the whole map to a new SQLite map file (replacing ``path`` atomically)."""
        from octolgp.persist.mapfile import save_map

        save_map(self, path)

    def close(self) -> None:
        """Release worker threads and the map file."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> OnlineMap:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ updates
    def _check_scan(self, scan: object) -> Scan:
        if not isinstance(scan, Scan):
            raise OctolgpError(f"scan must be a Scan, got {type(scan).__name__}")
        check_scan_size(scan, self.config.online.max_scan_points)
        if scan.dim != self.config.dim:
            raise OctolgpError(f"scan is {scan.dim}D but MapConfig.dim is {self.config.dim}")
        res, depth = self.config.resolution, self.config.tree_depth
        # the halo of a leaf at the edge of the tree must stay addressable too
        low, high = addressable_range(res, depth)
        margin = 2 * self.grid.edge
        for name, pts in (("scan.origin", scan.origin[None, :]), ("scan.points", scan.points)):
            bad = (pts < low + margin) | (pts >= high - margin)
            if bad.any():
                row = int(np.flatnonzero(bad.any(axis=1))[0])
                raise OctolgpError(
                    f"{name} row {row} ({pts[row].tolist()}) is outside the addressable range "
                    f"[{low + margin:g}, {high - margin:g}) m of this map"
                )
        return scan

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
        scan = self._check_scan(scan)
        index = self.n_scans + 1
        self.sink.on_scan(self, scan, index)
        if self.hyperparameters is None:
            self._buffer.append(scan)
            if len(self._buffer) >= self.config.online.learn_scans:
                update = self._learn_and_flush(t0, journal=[(index, scan)])
                if update is not None:
                    return update
            else:
                self.n_scans = index
                self._commit([], [(index, scan)])
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
        return self._integrate([scan], t0, index, journal=[(index, scan)])

    def insert_scans(self, scans: Iterable[Scan]) -> list[ScanUpdate]:
        """Insert scans one by one; return their updates."""
        return [self.insert_scan(s) for s in scans]

    def flush(self) -> ScanUpdate | None:
        """Learn hyperparameters from the buffered scans now and insert them.

        Queries call it, so a map with fewer than ``learn_scans`` scans still
        answers from what it has. Returns ``None`` when nothing is buffered.
        """
        if not self._buffer:
            return None
        return self._learn_and_flush(time.perf_counter(), journal=[])

    def _learn_and_flush(self, t0: float, journal: list[tuple[int, Scan]]) -> ScanUpdate | None:
        """Learn on the buffer and insert it; ``None`` (still buffering) without data."""
        if make_training_data(self._buffer, self._raw_config).n_items == 0:
            # nothing to learn from yet (every beam on its sensor): keep buffering
            if journal:
                self.n_scans = journal[-1][0]
                self._commit([], journal)
            return None
        t1 = time.perf_counter()
        hp = learn_hyperparameters(self._buffer, self.config)
        learning = time.perf_counter() - t1
        self.hyperparameters = hp
        buffered, self._buffer = self._buffer, []
        index = journal[-1][0] if journal else self.n_scans
        update = self._integrate(buffered, t0, index, journal)
        update.stages["learning"] = learning
        return update

    def relearn(self, scans: Iterable[Scan]) -> Hyperparameters:
        """Learn new hyperparameters on ``scans`` and refit every leaf with them."""
        hp = learn_hyperparameters(scans, self.config)
        self.set_hyperparameters(hp)
        return hp

    def set_hyperparameters(self, hp: Hyperparameters) -> None:
        """Use ``hp`` from now on and refit every leaf from its stored evidence.

        Leaves are refitted in batches of 256 so a map with a memory budget never
        holds more than that many beyond its budget.
        """
        if not isinstance(hp, Hyperparameters):
            raise OctolgpError(f"hp must be Hyperparameters, got {type(hp).__name__}")
        self.flush()
        self.hyperparameters = hp
        keys = list(self.store)
        for lo in range(0, len(keys), 256):  # one batch of leaves per iteration
            batch = keys[lo : lo + 256]
            leaves = [self.store.peek(k) for k in batch]
            fitted, _ = self._fit([leaf for leaf in leaves if leaf is not None])
            for key, leaf in zip(batch, fitted, strict=True):
                self.store.put(key, leaf)
            self._commit(batch, [])

    def _commit(self, keys: list[int], journal: list[tuple[int, Scan]]) -> None:
        """Make the step durable (map file, if any) and trim RAM to the budget."""
        if self._file is not None:
            self.store.persisted(self._file.commit(self, keys, journal))
        self.store.trim()

    def _integrate(
        self, scans: list[Scan], t0: float, index: int, journal: list[tuple[int, Scan]]
    ) -> ScanUpdate:
        """Scans → evidence per leaf → refit the leaves that gained any → store → file."""
        stages: dict[str, float] = {}
        with _blas_controller().limit(limits=1):
            t = time.perf_counter()
            data = make_training_data(scans, self._raw_config)
            stages["training"] = time.perf_counter() - t

            t = time.perf_counter()
            changed, touched, new_items = self._gather(data)
            stages["assign"] = time.perf_counter() - t

            t = time.perf_counter()
            keys = [k for k, _ in changed]
            repairs = jitter_repairs()
            fitted, pruned = self._fit([leaf for _, leaf in changed])
            repairs = jitter_repairs() - repairs
            stages["fit"] = time.perf_counter() - t

        t = time.perf_counter()
        self.n_scans = index
        for key in touched:
            leaf = self.store.get(key)
            if leaf is not None:
                leaf.touched = index
        for key, leaf in zip(keys, fitted, strict=True):
            leaf.touched = index
            self.store.put(key, leaf)
        self._commit(keys, journal)
        stages["store"] = time.perf_counter() - t
        update = ScanUpdate(
            scan=index,
            touched_leaves=len(touched),
            refit_leaves=len(keys),
            new_items=new_items,
            pruned_leaves=pruned,
            seconds=time.perf_counter() - t0,
            stages=stages,
            n_leaves=len(self.store),
            memory_bytes=self.memory_bytes(),
            repaired=repairs,
        )
        self.sink.on_update(self, update, keys)
        return update

    def _gather(self, data: TrainingData) -> tuple[list[tuple[int, Leaf]], list[int], int]:
        """Copies of the touched leaves with the new evidence added (the store is untouched).

        Returns the leaves that gained items (key, new leaf), the keys of all
        touched leaves, and the number of items added.
        """
        grid = self.grid
        h_idx, h_leaf = assign_points(grid, data.hits)
        _, s_leaf, a, b = assign_segments(
            grid, data.seg_start, data.seg_end, 0.5 * self.config.resolution
        )
        hits = data.hits[h_idx]
        hit_keys = grid.voxel_keys(hits)
        free_keys = grid.voxel_keys(b, self.config.online.free_voxels)
        h_order, h_keys, h_bounds = _group(grid.pack(h_leaf))
        s_order, s_keys, s_bounds = _group(grid.pack(s_leaf))
        touched = np.union1d(h_keys, s_keys)
        changed: list[tuple[int, Leaf]] = []
        new_items = 0
        hi = np.searchsorted(h_keys, touched)
        si = np.searchsorted(s_keys, touched)
        for j, key in enumerate(touched.tolist()):  # one iteration per touched leaf
            hsel = np.zeros(0, dtype=np.int64)
            ssel = np.zeros(0, dtype=np.int64)
            if hi[j] < h_keys.size and h_keys[hi[j]] == key:
                hsel = h_order[h_bounds[hi[j]] : h_bounds[hi[j] + 1]]
            if si[j] < s_keys.size and s_keys[si[j]] == key:
                ssel = s_order[s_bounds[si[j]] : s_bounds[si[j] + 1]]
            old = self.store.get(key)
            if old is None:
                index = h_leaf[hsel[0]] if hsel.size else s_leaf[ssel[0]]
                leaf = Leaf.empty(index)
            else:
                leaf = dataclasses.replace(old)
            added = leaf.add_evidence(hits[hsel], hit_keys[hsel], a[ssel], b[ssel], free_keys[ssel])
            if added:
                new_items += added
                changed.append((key, leaf))
        return changed, touched.tolist(), new_items

    def _fit(self, leaves: list[Leaf]) -> tuple[list[Leaf], int]:
        """Refit and re-predict leaves (threads over leaves); returns new leaves and pruned count."""
        hp = self.hyperparameters
        assert hp is not None
        n_jobs = self.config.online.n_jobs
        cache = self.kernel_cache
        # one BLAS thread per leaf: small matrices, parallelism is over leaves
        with _blas_controller().limit(limits=1):
            if n_jobs > 1 and len(leaves) > 1:
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(max_workers=n_jobs)
                out = list(
                    self._pool.map(lambda leaf: fit_leaf(leaf, self.config, hp, cache), leaves)
                )
            else:
                out = [fit_leaf(leaf, self.config, hp, cache) for leaf in leaves]
        return out, sum(leaf.pruned for leaf in out)

    # ------------------------------------------------------------------ queries
    def _points(self, points: object) -> FloatArray:
        X = as_points(points, "points", dim=self.config.dim)
        inside = addressable_mask(X, self.config.resolution, self.config.tree_depth)
        if not inside.all():
            low, high = addressable_range(self.config.resolution, self.config.tree_depth)
            row = int(np.flatnonzero(~inside)[0])
            raise OctolgpError(
                f"points row {row} ({X[row].tolist()}) is outside the addressable range "
                f"[{low:g}, {high:g}) m"
            )
        return X

    def _lookup(self, X: FloatArray, fields: tuple[str, ...]) -> list[np.ndarray]:
        """Stored voxel values at points; NaN where no leaf holds the point."""
        out = [np.full(X.shape[0], np.nan) for _ in fields]
        if X.shape[0] == 0 or len(self.store) == 0:
            return out
        leaf_idx = self.grid.leaf_of(X)
        order, keys, bounds = _group(self.grid.pack(leaf_idx))
        for j, key in enumerate(keys.tolist()):  # one iteration per leaf queried
            leaf = self.store.get(key)
            if leaf is None or leaf.prob.size == 0:
                continue
            sel = order[bounds[j] : bounds[j + 1]]
            flat = np.zeros(sel.size, dtype=np.int64)
            if not leaf.pruned:
                flat = self.grid.voxel_index(X[sel], leaf.index)
            for arr, name in zip(out, fields, strict=True):
                arr[sel] = getattr(leaf, name)[flat]
        return out

    def _interpolated(self, X: FloatArray) -> tuple[FloatArray, FloatArray, np.ndarray]:
        """Multilinear interpolation of the voxel latent mean and variance at points.

        The ``2**d`` voxel centres around each point are weighted by the usual
        bilinear/trilinear weights; a corner no leaf holds (or outside the addressable
        range) contributes the GP prior ``(0, σf²)``. Also returns which points lie in
        a voxel that holds a value.
        """
        d = self.config.dim
        res = self.config.resolution
        prior = 1.0 if self.hyperparameters is None else self.hyperparameters.signal_variance
        (own,) = self._lookup(X, ("mean",))
        u = X / res - 0.5
        base = np.floor(u)
        frac = u - base
        corners = np.array(list(np.ndindex(*(2,) * d)), dtype=np.float64)  # (2^d, d)
        weights = np.prod(np.where(corners[:, None, :] == 1, frac, 1.0 - frac), axis=2)
        centres = ((base[None, :, :] + corners[:, None, :] + 0.5) * res).reshape(-1, d)
        inside = addressable_mask(centres, res, self.config.tree_depth)
        mean = np.full(centres.shape[0], np.nan)
        var = np.full(centres.shape[0], np.nan)
        mean[inside], var[inside] = self._lookup(centres[inside], ("mean", "var"))
        known = ~np.isnan(mean)
        mean = np.where(known, mean, 0.0).reshape(weights.shape)
        var = np.where(known, var, prior).reshape(weights.shape)
        return (weights * mean).sum(axis=0), (weights * var).sum(axis=0), ~np.isnan(own)

    def occupancy(self, points: object, *, interpolate: bool = True) -> FloatArray:
        """P(occupied) at query points.

        Parameters
        ----------
        points : array_like of shape (q, d)
            World frame, metres.
        interpolate : bool, optional
            ``True`` (default): a continuous map. The latent mean and variance stored
            at the ``2**d`` voxel centres around each point are interpolated
            multilinearly (unknown corners count as the GP prior) and PLSC turns them
            into a probability; at a voxel centre this is the voxel's own value.
            ``False``: the stored value of the voxel holding the point (OctoMap's
            semantics, piecewise constant).

        Returns
        -------
        ndarray of shape (q,)
            In [0, 1]; exactly 0.5 where the voxel holding the point has no value.

        Raises
        ------
        OctolgpError
            On a bad shape, a non-finite value or a point outside the addressable range.
        """
        X = self._points(points)
        self.flush()
        if not interpolate or self.hyperparameters is None:
            (prob,) = self._lookup(X, ("prob",))
            return np.where(np.isnan(prob), 0.5, prob)
        mean, var, known = self._interpolated(X)
        hp = self.hyperparameters
        prob = occupancy_probability(mean, var + hp.noise_variance, hp.alpha, hp.beta)
        return np.where(known, prob, 0.5)

    def latent(self, points: object, *, interpolate: bool = True) -> tuple[FloatArray, FloatArray]:
        """GP latent mean and variance at query points.

        ``interpolate`` as in :meth:`occupancy` (multilinear between voxel centres, or
        the voxel holding each point).

        Returns
        -------
        mean, var : ndarray of shape (q,)
            The prior ``(0, σf²)`` where the voxel holding the point has no value
            (``σf² = 1`` before hyperparameters exist).
        """
        X = self._points(points)
        self.flush()
        prior = 1.0 if self.hyperparameters is None else self.hyperparameters.signal_variance
        if not interpolate:
            mean, var = self._lookup(X, ("mean", "var"))
            return np.where(np.isnan(mean), 0.0, mean), np.where(np.isnan(var), prior, var)
        mean, var, known = self._interpolated(X)
        return np.where(known, mean, 0.0), np.where(known, var, prior)

    def voxel_centres(self, leaf: Leaf) -> FloatArray:
        """Centres of a leaf's voxels, shape (V, d), in the order of its value arrays."""
        return self.grid.voxel_centres(leaf.index)

    def leaves(self) -> Iterator[tuple[int, Leaf]]:
        """``(packed leaf key, leaf)`` for every leaf, in key order."""
        return self.store.items()

    def voxels(self) -> tuple[FloatArray, FloatArray]:
        """Centres and P(occupied) of every predicted voxel (pruned leaves expanded).

        Returns
        -------
        centres : ndarray of shape (k, d)
        prob : ndarray of shape (k,)
        """
        self.flush()
        cs, ps = [], []
        for _, leaf in self.store.items():  # one iteration per leaf
            if leaf.prob.size == 0:
                continue
            cs.append(self.voxel_centres(leaf))
            ps.append(np.broadcast_to(leaf.prob, (cs[-1].shape[0],)).astype(np.float64))
        if not cs:
            return np.zeros((0, self.config.dim)), np.zeros(0)
        return np.concatenate(cs), np.concatenate(ps)

    def occupied_voxels(self, threshold: float = 0.5) -> tuple[FloatArray, FloatArray]:
        """Centres and P(occupied) of the voxels above ``threshold``."""
        centres, prob = self.voxels()
        keep = prob > threshold
        return centres[keep], prob[keep]

    def export_octomap(self, path: str | Path, threshold: float = 0.5) -> int:
        """Write the map as an OctoMap file that the OctoMap library reads.

        ``.bt`` (default) is OctoMap's maximum-likelihood binary format: every
        predicted voxel is occupied when P(occupied) > ``threshold``, else free;
        voxels no leaf predicts stay unknown. ``.ot`` is the full format with each
        voxel's log-odds ``log(P / (1 − P))``. A 2D map is one layer of voxels whose
        z key is 32768 (z in ``[0, resolution)``). Identical sibling voxels are
        pruned as OctoMap does.

        Returns
        -------
        int
            Nodes written (OctoMap's ``size()``).
        """
        from octolgp.export.octomap import write_bt, write_ot
        from octolgp.geometry.keys import coord_to_key

        ok = isinstance(threshold, int | float) and not isinstance(threshold, bool)
        if not ok or not 0.0 < threshold < 1.0:
            raise OctolgpError(f"threshold must be a number in (0, 1), got {threshold!r}")
        centres, prob = self.voxels()
        keys = coord_to_key(centres, self.config.resolution, self.config.tree_depth)
        p = Path(path)
        if p.suffix == ".ot":
            q = np.clip(prob, 1e-6, 1.0 - 1e-6)
            return write_ot(p, keys, np.log(q / (1.0 - q)), self.config.resolution)
        return write_bt(p, keys, prob > threshold, self.config.resolution)

    def memory_bytes(self) -> int:
        """Bytes held by the leaves (evidence and voxel values)."""
        return self.store.nbytes

    def __repr__(self) -> str:
        return (
            f"OnlineMap(dim={self.config.dim}, resolution={self.config.resolution:g}, "
            f"scans={self.n_scans}, leaves={len(self.store)})"
        )
