"""The map store: one mutable table of leaves keyed by packed OctoMap keys.

A :class:`Leaf` holds its predicted voxels (latent mean, variance and P(occupied),
float32) and its engine's evidence (:class:`LeafEvidence`: the lattice engine's
observation counts, or the exact engine's hits and free pieces; see
:mod:`octolgp.engines`). Each engine bounds its evidence per voxel of the leaf's
halo box, so a leaf does not grow however often the robot comes back.

:class:`LeafStore` is the one mutable structure of an online map; everything
around it is a pure function.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import NDArray

from octolgp.memory import release_free_memory
from octolgp.training import IntArray

if TYPE_CHECKING:
    from octolgp.config import Hyperparameters, MapConfig
    from octolgp.scan import Scan

Float32Array = NDArray[np.float32]


class LeafEvidence(Protocol):
    """What a leaf engine keeps of the observations of one leaf (immutable)."""

    @property
    def n_items(self) -> int:
        """Training inputs of the leaf's GP."""
        ...

    @property
    def nbytes(self) -> int:
        """Bytes held by the evidence's arrays."""
        ...


LEAF_OBJECT_BYTES = 1000
"""The Python objects around a leaf's arrays (the leaf, its evidence, seven array headers,
the store's entries): about 990 bytes measured with ``tracemalloc``, which a memory
budget counts with the arrays."""


NO_VALUES: Float32Array = np.zeros(0, np.float32)
"""The values of a leaf not yet fitted: one empty array that every such leaf shares
(it holds nothing to change), so a step that makes many new leaves makes no arrays for
them."""
NO_VALUES.setflags(write=False)


@dataclass(slots=True)
class Leaf:
    """One leaf of the map: its engine's evidence and its predicted voxels.

    Slotted: a leaf is one object for the cyclic garbage collector, not two (no
    instance dict), which a map of many small leaves pays for at every full collection.

    Attributes
    ----------
    index : ndarray of shape (d,)
        Leaf index per axis (a voxel key shifted right by the leaf's level).
    evidence : LeafEvidence
        The engine's evidence of the leaf's halo box.
    mean, var, prob : ndarray of float32, shape (V,) or (1,)
        Latent mean, latent variance and P(occupied) per voxel, in flat voxel
        order (x fastest), or one value for a pruned leaf. Empty before the first fit.
    pruned : bool
        Whether the voxels were collapsed to one value.
    refits : int
        How many times the leaf's GP was fitted.
    touched : int
        Number of the last scan that touched the leaf (for least-recently-used order).
    pending : bool
        Whether the evidence changed since the voxel values were fitted (a deferred fit,
        ``OnlineConfig.defer_fit``): the values are those of older evidence until the
        map settles (:meth:`octolgp.OnlineMap.settle`), which every read does first.
    fitted : bool
        Whether the values are the engine's fit of the evidence. ``False`` for values
        set another way (a batch method's, :func:`octolgp.batch.voxelized.build_voxelized`,
        or read from a map file that does not say), which a map file must keep; a fit
        makes it ``True``.
    """

    index: IntArray
    evidence: LeafEvidence
    mean: Float32Array = field(default_factory=lambda: NO_VALUES)
    var: Float32Array = field(default_factory=lambda: NO_VALUES)
    prob: Float32Array = field(default_factory=lambda: NO_VALUES)
    pruned: bool = False
    refits: int = 0
    touched: int = 0
    pending: bool = False
    fitted: bool = True

    def evolve(self, **changes: object) -> Leaf:
        """A shallow copy with ``changes`` applied (``dataclasses.replace``, cheaper).

        Unknown field names raise ``TypeError``.
        """
        if not _LEAF_FIELDS.issuperset(changes):
            unknown = changes.keys() - _LEAF_FIELDS
            raise TypeError(f"Leaf has no field {sorted(unknown)[0]!r}")
        fields = {name: getattr(self, name) for name in _LEAF_FIELDS}
        fields.update(changes)
        return Leaf(**fields)

    def with_evidence(self, evidence: LeafEvidence) -> Leaf:
        """A shallow copy holding ``evidence``: ``evolve(evidence=evidence)``, for hot loops."""
        return Leaf(
            self.index,
            evidence,
            self.mean,
            self.var,
            self.prob,
            self.pruned,
            self.refits,
            self.touched,
            self.pending,
            self.fitted,
        )

    def refitted(
        self, mean: Float32Array, var: Float32Array, prob: Float32Array, pruned: bool
    ) -> Leaf:
        """A shallow copy with fresh voxel values and one more refit, for hot loops.

        Equal to ``evolve(mean=mean, var=var, prob=prob, pruned=pruned,
        refits=self.refits + 1, pending=False, fitted=True)``.
        """
        return Leaf(
            self.index, self.evidence, mean, var, prob, pruned, self.refits + 1, self.touched
        )

    @property
    def n_items(self) -> int:
        """Training inputs of the leaf's GP (its evidence's)."""
        return self.evidence.n_items

    @property
    def nbytes(self) -> int:
        """Bytes the leaf holds in RAM: its arrays and :data:`LEAF_OBJECT_BYTES`."""
        values = self.index.nbytes + self.mean.nbytes + self.var.nbytes + self.prob.nbytes
        return LEAF_OBJECT_BYTES + values + self.evidence.nbytes


_LEAF_FIELDS = frozenset(
    (
        "index",
        "evidence",
        "mean",
        "var",
        "prob",
        "pruned",
        "refits",
        "touched",
        "pending",
        "fitted",
    )
)


READ_BATCH = 512
"""Evicted leaves read (and fitted, where stored without values) together when iterating."""

STEP_BYTES_PER_HALO_VOXEL = 21
"""About the bytes of a step's working arrays per voxel of the halo box of each leaf it
touches (its voxel observations, the (voxel, leaf) copies, the touched leaves' stacked
counts: 25 MB for a 720-beam lidar scan to 20 m touching 1,200 leaves of 10³ halo voxels;
measured with ``tracemalloc``), which a budget keeps free of leaves
(:attr:`LeafStore.reserve_bytes`)."""

FIT_BYTES_PER_LEAF = 54_000
"""About the bytes fitting one leaf of :data:`UNIT_LEAF_VOXELS` voxels holds while it runs
(a 3D lattice leaf of 8³: its tiles' counts, returns and posteriors; measured), which sizes
:attr:`LeafStore.batch` under a budget; a larger leaf holds proportionally more."""

UNIT_LEAF_VOXELS = 512
"""The leaf size the store's working-set constants are measured for (8³ voxels): a leaf of
``n`` voxels counts as ``max(1, n // UNIT_LEAF_VOXELS)`` such leaves
(:attr:`LeafStore.units`)."""


class LeafBacking(Protocol):
    """Where evicted leaves live: the map file (:class:`octolgp.persist.mapfile.MapFile`)."""

    def read_leaf(self, key: int) -> Leaf:
        """The persisted leaf ``key``.

        ``pending`` and without values where the file keeps only its evidence.
        """
        ...


@dataclass(frozen=True)
class MapHeader:
    """The map state a map file records besides its leaves and journal.

    Attributes
    ----------
    config : MapConfig
    hyperparameters : Hyperparameters or None
        ``None`` while the map is still buffering scans to learn them.
    n_scans : int
        Scans inserted.
    leaf_keys : list of int
        Packed keys of the persisted leaves.
    checkpoints : list of int
        Scan counts at which the file keeps the evidence of the leaves changed since
        (``OnlineConfig.journal_scans``), ascending; the journal holds the scans after
        the first.
    """

    config: MapConfig
    hyperparameters: Hyperparameters | None
    n_scans: int
    leaf_keys: list[int]
    checkpoints: list[int] = field(default_factory=lambda: [0])


class ScanJournal(Protocol):
    """What a pose correction reads of a map's journal: its scans and checkpoints.

    A map file keeps it (:class:`octolgp.persist.mapfile.MapFile`), a map without one
    in RAM (:class:`octolgp.persist.memory.MemoryJournal`).
    """

    @property
    def checkpoints(self) -> list[int]:
        """Scan counts at which the journal keeps the leaves changed since, ascending."""
        ...

    @property
    def journal_start(self) -> int:
        """The journal holds the scans after this one."""
        ...

    def scans(self, start: int = 0) -> Iterator[Scan]:
        """The journaled scans with index > ``start``, in order."""
        ...

    def journal(self, start: int = 0) -> Iterator[tuple[int, Scan]]:
        """``(number, scan)`` of the journaled scans with number > ``start``, in order."""
        ...

    def checkpoint_rows(self) -> Iterator[tuple[int, int, bytes | None]]:
        """Every ``(checkpoint, key, record)`` kept (``None``: no leaf then)."""
        ...

    def read_scans(self, indices: list[int]) -> dict[int, Scan]:
        """The journaled scans with these numbers (absent numbers are left out)."""
        ...

    def checkpoint_leaves(self, checkpoint: int, keys: list[int]) -> dict[int, Leaf | None]:
        """The leaves ``keys`` as of a checkpoint, where they changed since.

        ``None``: no leaf then; a key left out is unchanged since (the leaf as it is now).
        """
        ...


class MapStorage(LeafBacking, ScanJournal, Protocol):
    """What an online map needs of its file (:class:`octolgp.persist.mapfile.MapFile`).

    The file records the map's state; it never reads or builds a map object.
    """

    path: Path
    header: MapHeader
    read_only: bool
    temporary: bool

    def transaction(self) -> AbstractContextManager[object]:
        """One write transaction that the writes inside it join (all or nothing)."""
        ...

    def commit(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        journal: Iterable[tuple[int, Scan]],
        hyperparameters: Hyperparameters | None,
        n_scans: int,
    ) -> list[int]:
        """Write one step durably (all or nothing); returns the leaf keys written."""
        ...

    def correct(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        removed: Iterable[int],
        journal: Iterable[tuple[int, Scan]],
        checkpointed: Mapping[int, Mapping[int, Leaf | None]] | None = None,
    ) -> list[int]:
        """Replace leaves, delete ``removed`` and rewrite journaled scans, all or nothing.

        ``checkpointed``: per later checkpoint, the rebuilt evidence of leaves as of it
        (``None``: no leaf then). Returns the leaf keys written.
        """
        ...

    def close(self) -> None:
        """Release the file (a temporary spill file is deleted)."""
        ...


class LeafStore:
    """Leaves by packed leaf key; the map's only mutable state besides counters.

    Without a budget every leaf stays in RAM. With ``budget_bytes`` and a
    ``backing`` (the map file, which holds every leaf after each scan),
    :meth:`trim` drops the least recently used leaves from RAM until the RAM
    held is within the budget; :meth:`get` loads an evicted leaf back
    transparently. Eviction never loses data: a leaf is only dropped once it is
    in the file (``persisted``).
    """

    def __init__(
        self, budget_bytes: int | None = None, leaf_voxels: int = UNIT_LEAF_VOXELS
    ) -> None:
        self._leaves: OrderedDict[int, Leaf] = OrderedDict()  # in RAM, LRU first
        self._keys: set[int] = set()  # every key, in RAM or in the file
        self._dirty: set[int] = set()  # in RAM and not yet in the file
        self._sizes: dict[int, int] = {}  # each RAM leaf's nbytes, as _nbytes counts it
        self._pending: set[int] = set()  # leaves whose values wait for a fit
        self._nbytes = 0
        self.budget_bytes = budget_bytes
        self.units = max(1, leaf_voxels // UNIT_LEAF_VOXELS)  # working-set units a leaf
        self.reserve_bytes = 0  # of the budget, kept free for a step's working arrays
        self.backing: LeafBacking | None = None
        self._fit: Callable[[list[Leaf]], list[Leaf]] | None = None
        self.loads = 0
        self.evictions = 0

    def attach(
        self,
        backing: LeafBacking,
        keys: Iterable[int],
        fit: Callable[[list[Leaf]], list[Leaf]] | None = None,
    ) -> None:
        """Use ``backing`` for the persisted leaves ``keys`` (not loaded now).

        ``fit`` gives values to leaves the backing returns without them (``pending``:
        a map file keeps only the evidence of an engine whose values are a function of
        it): a leaf :meth:`get` loads stays pending until the map settles it, one that
        :meth:`peek` or :meth:`items` reads is fitted as it is read.
        """
        self.backing = backing
        self._fit = fit
        self._keys.update(int(k) for k in keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._keys

    def __iter__(self) -> Iterator[int]:
        return iter(sorted(self._keys))

    def get(self, key: int) -> Leaf | None:
        """The leaf with this packed key (loaded from the file if evicted), or ``None``."""
        key = int(key)
        leaf = self._leaves.get(key)
        if leaf is not None:
            self._leaves.move_to_end(key)
            return leaf
        if key not in self._keys or self.backing is None:
            return None
        leaf = self.backing.read_leaf(key)
        self._leaves[key] = leaf
        size = self._sizes[key] = leaf.nbytes
        self._nbytes += size
        self.loads += 1
        if leaf.pending:  # read without its values: fitted when the map is next read
            self._pending.add(key)
        return leaf

    @property
    def batch(self) -> int:
        """Leaves read or fitted together: :data:`READ_BATCH`, or under a budget fewer.

        Counted in leaves of :data:`UNIT_LEAF_VOXELS` voxels (a larger leaf counts as
        :attr:`units` of them). Under a budget at least 16 such leaves (and one leaf), and
        so many that fitting them holds at most an eighth of the budget.
        """
        if self.budget_bytes is None:
            return self.leaves_of(READ_BATCH)
        fit = self.budget_bytes // (8 * FIT_BYTES_PER_LEAF)
        return self.leaves_of(max(16, min(READ_BATCH, fit)))

    def leaves_of(self, unit_leaves: int) -> int:
        """Leaves of this store (at least one) worth ``unit_leaves`` leaves of 8³ voxels.

        Each leaf counts as :attr:`units` leaves of :data:`UNIT_LEAF_VOXELS` voxels.
        """
        return max(unit_leaves // self.units, 1)

    def peek_many(self, keys: list[int]) -> list[Leaf | None]:
        """:meth:`peek` of many leaves: the evicted ones read and fitted together.

        Under a budget the heap's free pages go back to the OS first (the leaves of an
        earlier batch, dropped by the reader: :func:`octolgp.memory.release_free_memory`).
        """
        out = [self._leaves.get(int(k)) for k in keys]
        missing = [j for j, leaf in enumerate(out) if leaf is None and int(keys[j]) in self._keys]
        if missing and self.backing is not None:
            if self.budget_bytes is not None:
                release_free_memory()
            read = self._with_values([self.backing.read_leaf(int(keys[j])) for j in missing])
            for j, leaf in zip(missing, read, strict=True):
                out[j] = leaf
        return out

    def peek(self, key: int) -> Leaf | None:
        """The leaf without making it resident (a read for iteration)."""
        key = int(key)
        leaf = self._leaves.get(key)
        if leaf is not None or key not in self._keys or self.backing is None:
            return leaf
        return self._with_values([self.backing.read_leaf(key)])[0]

    def _with_values(self, leaves: list[Leaf]) -> list[Leaf]:
        """Leaves read from the backing, those read without values fitted (in one call)."""
        bare = [j for j, leaf in enumerate(leaves) if leaf.pending]
        if bare and self._fit is not None:
            for j, leaf in zip(bare, self._fit([leaves[j] for j in bare]), strict=True):
                leaves[j] = leaf
        return leaves

    def apply(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        touched: Iterable[int] = (),
        scan: int | None = None,
    ) -> None:
        """Write one step's result: swap in new leaves and mark touched ones as used.

        The only writer of leaf state. ``leaves`` are inserted or replaced and, with a
        ``scan`` number, stamped ``touched = scan``; the other ``touched`` keys get the
        stamp only (it orders least-recently-used eviction under a memory budget).
        """
        leaves = list(leaves)
        if scan is not None:
            get, replaced = self.get, {int(key) for key, _ in leaves}
            for key in touched:  # one iteration per touched leaf not replaced below
                if key in replaced:
                    continue
                leaf = get(key)
                if leaf is not None:
                    leaf.touched = scan
        resident, sizes, move = self._leaves, self._sizes, self._leaves.move_to_end
        keys, dirty, pending = self._keys, self._dirty, self._pending
        total = self._nbytes
        for key, leaf in leaves:  # one iteration per new leaf
            key = int(key)
            if scan is not None:
                leaf.touched = scan
            size = leaf.nbytes
            total += size - sizes.get(key, 0)
            sizes[key] = size
            resident[key] = leaf
            move(key)
            keys.add(key)
            dirty.add(key)
            if leaf.pending:
                pending.add(key)
            else:
                pending.discard(key)
        self._nbytes = total

    def remove(self, keys: Iterable[int]) -> None:
        """Drop leaves from the map (a correction left them without evidence)."""
        for key in keys:  # one iteration per removed leaf
            key = int(key)
            if self._leaves.pop(key, None) is not None:
                self._nbytes -= self._sizes.pop(key)
            self._keys.discard(key)
            self._dirty.discard(key)
            self._pending.discard(key)

    def persisted(self, keys: Iterable[int]) -> None:
        """Mark leaves as written to the backing file."""
        self._dirty.difference_update(int(k) for k in keys)

    @property
    def pending(self) -> list[int]:
        """Keys of leaves whose voxel values wait for a fit (:attr:`Leaf.pending`)."""
        return sorted(self._pending)

    @property
    def n_pending(self) -> int:
        """How many leaves wait for a fit (no list is made)."""
        return len(self._pending)

    def pending_among(self, keys: set[int]) -> list[int]:
        """The keys of ``keys`` whose leaves wait for a fit, ascending."""
        return sorted(self._pending.intersection(keys))

    @property
    def dirty(self) -> list[int]:
        """Keys of leaves changed in RAM and not yet in the file."""
        return sorted(self._dirty)

    def trim(self) -> int:
        """Evict least recently used, persisted leaves until RAM is within budget.

        Within budget means at most ``budget_bytes - reserve_bytes`` (at least nothing):
        the map keeps :attr:`reserve_bytes` of its budget for the working arrays of its
        next step.

        An evicted leaf no longer waits for a fit: the backing gives it back as the file
        holds it, and values it reads without are fitted then (:meth:`attach`).
        Returns the number of leaves evicted.
        """
        if self.budget_bytes is None or self.backing is None:
            return 0
        evicted, room = 0, max(self.budget_bytes - self.reserve_bytes, 0)
        for key in list(self._leaves):  # LRU first; stops once within budget
            if self._nbytes <= room:
                break
            if key in self._dirty:
                continue
            del self._leaves[key]
            self._nbytes -= self._sizes.pop(key)
            self._pending.discard(key)
            evicted += 1
        self.evictions += evicted
        return evicted

    def items(self) -> Iterator[tuple[int, Leaf]]:
        """``(key, leaf)`` in ascending key order; evicted leaves are read, not kept.

        Evicted leaves are read in batches of :attr:`batch` (:meth:`peek_many`).
        """
        keys, size = sorted(self._keys), self.batch
        for lo in range(0, len(keys), size):  # one batch of keys per iteration
            batch = keys[lo : lo + size]
            for key, leaf in zip(batch, self.peek_many(batch), strict=True):  # one per leaf
                if leaf is not None:
                    yield key, leaf

    @property
    def resident(self) -> int:
        """Leaves held in RAM."""
        return len(self._leaves)

    @property
    def nbytes(self) -> int:
        """Bytes held in RAM by the resident leaves' arrays (a running total)."""
        return self._nbytes
