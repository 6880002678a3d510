"""The journal of a map without a file, in RAM: what a pose correction needs, as a file keeps it.

A map made without a path (and without a memory budget, whose spill file journals)
keeps its journal here so that :meth:`octolgp.OnlineMap.correct_scans` works on it too.
It keeps what a map file's journal keeps, in the same encodings, so a correction of a
map in RAM equals that of the same map in a file, bit for bit:

- the latest scans (``OnlineConfig.journal_scans``, :func:`~octolgp.persist.journal.next_checkpoints`),
  with ``scan_precision`` as the zlib-compressed steps of
  :func:`~octolgp.persist.journal.encode_points` (else the scans' float64 arrays), each
  with its origin, ``max_range``, ``stamp`` and sensor rotation;
- per checkpoint after the first, the record (:func:`~octolgp.persist.mapfile.encode_leaves`)
  of every leaf changed since, as it was then.

The RAM it holds is :attr:`MemoryJournal.nbytes`. It never reads or builds a map object:
the map hands it each step's leaves and scans, and a function that reads a leaf as it
is before the step.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import engine_for
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf
from octolgp.persist.journal import decode_points, encode_points, next_checkpoints
from octolgp.persist.mapfile import decode_leaf, encode_leaves
from octolgp.scan import Scan

__all__ = ["MemoryJournal"]

ROW_OVERHEAD = 200
"""Bytes of Python objects per journaled scan besides its blob and pose (measured with
``tracemalloc``: the row, two ``bytes`` headers, the dict entry)."""


@dataclass(frozen=True, slots=True)
class _Row:
    """One journaled scan: its points' blob and its pose.

    The points as the steps' blob (or, unrounded, the scan itself); the pose as float64
    bytes, the origin then the rotation when it has one.
    """

    blob: bytes | None
    scan: Scan | None
    pose: bytes
    max_range: float | None
    stamp: float | None

    @property
    def nbytes(self) -> int:
        held = len(self.blob) if self.blob is not None else 0
        if self.scan is not None:
            held += self.scan.points.nbytes
        return held + len(self.pose) + ROW_OVERHEAD


def _row(scan: Scan, precision: float | None) -> _Row:
    if precision is None:  # kept as given: the scan's read-only arrays
        return _Row(None, scan, b"", scan.max_range, scan.stamp)
    pose = scan.origin.astype("<f8").tobytes()
    if scan.rotation is not None:
        pose += scan.rotation.astype("<f8").tobytes()
    return _Row(encode_points(scan, precision), None, pose, scan.max_range, scan.stamp)


def _scan(row: _Row, dim: int) -> Scan:
    if row.scan is not None:
        return row.scan
    assert row.blob is not None
    pose = np.frombuffer(row.pose, "<f8")
    origin = pose[:dim]
    rotation = pose[dim:].reshape(dim, dim) if pose.size > dim else None
    points = decode_points(row.blob, origin, dim)
    return Scan(origin, points, row.max_range, row.stamp, rotation)


class MemoryJournal:
    """A map's journal and checkpoints in RAM (:class:`~octolgp.mapping.store.ScanJournal`).

    Parameters
    ----------
    config : MapConfig
        The map's resolved config: ``scan_precision`` and ``journal_scans``.
    current : callable
        ``current(key)``: the map's leaf ``key`` as it is before the step being
        recorded, or ``None`` (what a map file reads from its ``leaves`` table).

    Notes
    -----
    Its writes (:meth:`record`, :meth:`correct`) mirror
    :meth:`octolgp.persist.mapfile.MapFile.commit` and
    :meth:`~octolgp.persist.mapfile.MapFile.correct` without the leaves themselves,
    which live in the map's store.
    """

    def __init__(self, config: MapConfig, current: Callable[[int], Leaf | None]) -> None:
        self._engine = engine_for(config)
        self._grid = LeafGrid.from_config(config)
        self._dim = config.dim
        self._precision = config.online.scan_precision
        self._window = config.online.journal_scans
        self._current = current
        self._rows: dict[int, _Row] = {}  # by scan number, in insertion order
        self._kept: dict[int, dict[int, bytes | None]] = {}  # checkpoint → key → record
        self._checkpoints = [0]
        self._n_scans = 0

    # ------------------------------------------------------------------ reads
    @property
    def checkpoints(self) -> list[int]:
        """Scan counts at which the journal keeps the leaves changed since, ascending."""
        return list(self._checkpoints)

    @property
    def journal_start(self) -> int:
        """The journal holds the scans after this one."""
        return self._checkpoints[0]

    @property
    def nbytes(self) -> int:
        """RAM held, bytes: :attr:`scan_bytes` and :attr:`leaf_bytes`."""
        return self.scan_bytes + self.leaf_bytes

    @property
    def scan_bytes(self) -> int:
        """Bytes of the journaled scans: blobs (or arrays), poses, :data:`ROW_OVERHEAD` each."""
        return sum(r.nbytes for r in self._rows.values())

    @property
    def leaf_bytes(self) -> int:
        """Bytes of the leaf records kept as of the checkpoints."""
        return sum(len(b) for c in self._kept.values() for b in c.values() if b is not None)

    def scans(self, start: int = 0) -> Iterator[Scan]:
        """The journaled scans with number > ``start``, in order."""
        for _, scan in self.journal(start):  # one scan per row
            yield scan

    def journal(self, start: int = 0) -> Iterator[tuple[int, Scan]]:
        """``(number, scan)`` of the journaled scans with number > ``start``, in order."""
        for i, row in list(self._rows.items()):  # one scan per row
            if i > start:
                yield i, _scan(row, self._dim)

    def read_scans(self, indices: list[int]) -> dict[int, Scan]:
        """The journaled scans with these numbers (absent numbers are left out)."""
        return {
            int(i): _scan(self._rows[int(i)], self._dim) for i in indices if int(i) in self._rows
        }

    def checkpoint_rows(self) -> Iterator[tuple[int, int, bytes | None]]:
        """Every ``(checkpoint, key, record)`` kept (``None``: no leaf then)."""
        for c, rows in list(self._kept.items()):  # a few checkpoints
            for key, blob in list(rows.items()):  # one row per kept leaf
                yield c, key, blob

    def checkpoint_leaves(self, checkpoint: int, keys: list[int]) -> dict[int, Leaf | None]:
        """The leaves ``keys`` as of a checkpoint where they changed since.

        ``None``: no leaf then; a key left out is unchanged since the checkpoint.
        """
        rows = self._kept.get(checkpoint, {})
        out: dict[int, Leaf | None] = {}
        for k in keys:  # one lookup per leaf
            if int(k) in rows:
                blob = rows[int(k)]
                out[int(k)] = None if blob is None else decode_leaf(blob, self._engine, self._grid)
        return out

    # ------------------------------------------------------------------ writes
    def record(
        self,
        keys: list[int],
        journal: Iterable[tuple[int, Scan]],
        hyperparameters: Hyperparameters | None,
        n_scans: int,
    ) -> None:
        """A step: the leaves ``keys`` are about to change, ``journal`` is inserted.

        As :meth:`octolgp.persist.mapfile.MapFile.commit`: the leaves' state is kept as of
        every checkpoint that does not have it yet, the scans are journaled, and the
        checkpoints advance (:func:`~octolgp.persist.journal.next_checkpoints`).
        """
        rows = [(int(i), _row(s, self._precision)) for i, s in journal]  # encoded first
        self._keep(keys)
        self._rows.update(rows)
        checkpoints = next_checkpoints(
            self._checkpoints, n_scans, self._window, hyperparameters is None
        )
        start = checkpoints[0]
        if start > self._checkpoints[0]:  # what no correction can reach any more
            self._rows = {i: r for i, r in self._rows.items() if i > start}
            self._kept = {c: rows for c, rows in self._kept.items() if c >= start}
        self._checkpoints, self._n_scans = checkpoints, n_scans

    def correct(
        self,
        keys: list[int],
        journal: Iterable[tuple[int, Scan]],
        checkpointed: Mapping[int, Mapping[int, Leaf | None]] | None = None,
    ) -> None:
        """A pose correction: the leaves ``keys`` are rebuilt or removed, ``journal`` rewritten.

        As :meth:`octolgp.persist.mapfile.MapFile.correct`: ``checkpointed`` holds, per
        checkpoint after the journal's start, the rebuilt leaves as of it (``None``: no
        leaf then); at the latest checkpoint, if not among them, the leaves' state is
        kept as a step keeps it.
        """
        checkpointed = checkpointed or {}
        rows = [(int(i), _row(s, self._precision)) for i, s in journal]
        records = {c: self._records(leaves.items()) for c, leaves in checkpointed.items()}
        before = {c: dict(kept) for c, kept in self._kept.items()}
        try:  # all or nothing, as the file's transaction
            for c, rebuilt in records.items():  # one checkpoint per iteration
                self._kept.setdefault(c, {}).update(rebuilt)
            if self._checkpoints[-1] == self._n_scans:  # the rebuilt leaves are its state
                latest = self._kept.get(self._n_scans, {})
                for k in keys:  # one row dropped per leaf
                    latest.pop(int(k), None)
            self._keep(keys, skip=[*checkpointed, self._n_scans])
        except BaseException:
            self._kept = before
            raise
        self._rows.update(rows)

    def _keep(self, keys: list[int], skip: Iterable[int] = ()) -> None:
        """Before leaves change: keep their state as of every checkpoint, once each.

        A leaf without a record for a checkpoint is unchanged since. Checkpoint 0 is the
        empty map; ``skip``: checkpoints whose records the caller writes.
        """
        if self._window is None or not keys:
            return
        skipped = {0, *skip}
        for c in self._checkpoints:  # at most three: the journal's start and later ones
            if c in skipped:
                continue
            kept = self._kept.setdefault(c, {})
            missing = [int(k) for k in keys if int(k) not in kept]
            kept.update(self._records((k, self._current(k)) for k in missing))

    def _records(self, leaves: Iterable[tuple[int, Leaf | None]]) -> dict[int, bytes | None]:
        """Leaf records by key, encoded together (``None``: no leaf)."""
        pairs = [(int(k), leaf) for k, leaf in leaves]
        held = [(k, leaf) for k, leaf in pairs if leaf is not None]
        out: dict[int, bytes | None] = {k: None for k, _ in pairs}
        blobs = encode_leaves([leaf for _, leaf in held], self._engine)
        out.update((k, blob) for (k, _), blob in zip(held, blobs, strict=True))
        return out
