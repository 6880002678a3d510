"""The single-file map: an embedded SQLite database (standard library ``sqlite3``).

Tables
------
``meta(key TEXT PRIMARY KEY, value TEXT)``
    ``format`` (``"octolgp-map"``), ``version``, ``config`` (JSON of the resolved
    :meth:`MapConfig.to_dict`: every derived default filled in, so the file means the
    same whatever defaults the code that opens it has), ``hyperparameters`` (JSON or
    ``null``), ``n_scans``.
``leaves(key INTEGER PRIMARY KEY, data BLOB)``
    One row per leaf, keyed by its packed OctoMap key; ``data`` is the leaf in the
    encoding of :func:`encode_leaf` (a fixed header, the voxel values in float32, then
    the engine's evidence record, :meth:`octolgp.engines.base.LeafEngine.encode`).
``scans(idx INTEGER PRIMARY KEY, dim, origin BLOB, points BLOB, max_range, stamp)``
    The journal of inserted scans, float64, in insertion order (empty in a file
    saved from an in-memory map, which keeps no scans).

Durability
----------
Every ``OnlineMap.insert_scan`` of a map with a file ends in one SQLite
transaction (WAL journal, ``synchronous=FULL``) that writes the scan's journal row,
every leaf it changed and the scan count, so after ``kill -9`` at any moment the
file holds exactly the scans whose ``insert_scan`` returned, and a scan in flight
is wholly in or wholly out. Opening never modifies a file that is not an
octolgp map.

This module reads and writes map state (config, hyperparameters, scan count, leaves,
journal); it never constructs or inspects a map object. The map holds a
:class:`MapFile` through the :class:`octolgp.mapping.store.MapStorage` protocol.
"""

from __future__ import annotations

import json
import os
import sqlite3
import struct
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import engine_for
from octolgp.engines.base import LeafEngine, read_arrays
from octolgp.engines.exact import ExactEvidence
from octolgp.engines.lattice import LatticeEvidence
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.keys import pack_keys
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf, LeafEvidence, MapHeader
from octolgp.scan import Scan

FORMAT = "octolgp-map"
VERSION = 3
READABLE_VERSIONS = ("2", "3")
"""File versions this code opens (2: before the engines owned their leaf records)."""
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER = struct.Struct("<4sBBxxqqqq")  # magic, version, dim, values, pruned, refits, touched
_OLD_HEADER = struct.Struct("<4sBBxxqqqqqq")  # records 1 and 2: h, s, v, pruned, refits, touched
_LEAF_MAGIC = b"OLGL"
_RECORD = 3
_COUNTS = struct.Struct("<q")  # record 2: halo voxels of the count arrays


def encode_leaf(leaf: Leaf, engine: LeafEngine) -> bytes:
    """A leaf as bytes: a header, its index and voxel values, then its engine's evidence.

    Little-endian: the 40-byte header (magic, record version, dimension, number of
    voxel values, pruned, refits, touched), the index (int64), mean, variance and
    P(occupied) (float32), then :meth:`LeafEngine.encode` of the evidence.
    """
    d, v = int(leaf.index.size), leaf.prob.size
    head = _HEADER.pack(_LEAF_MAGIC, _RECORD, d, v, int(leaf.pruned), leaf.refits, leaf.touched)
    parts = (
        leaf.index.astype("<i8"),
        leaf.mean.astype("<f4"),
        leaf.var.astype("<f4"),
        leaf.prob.astype("<f4"),
    )
    return head + b"".join(p.tobytes() for p in parts) + engine.encode(leaf.evidence)


def decode_leaf(blob: bytes, engine: LeafEngine, grid: LeafGrid) -> Leaf:
    """Inverse of :func:`encode_leaf` (records 1 and 2 too); ``OctolgpError`` if corrupt."""
    if len(blob) < 5:
        raise OctolgpError("leaf record is truncated")
    if blob[:4] != _LEAF_MAGIC:
        raise OctolgpError("leaf record has a bad header")
    if blob[4] in (1, 2):
        return _decode_old(blob, engine, grid)
    if len(blob) < _HEADER.size:
        raise OctolgpError("leaf record is truncated")
    _, version, d, v, pruned, refits, touched = _HEADER.unpack_from(blob)
    if version != _RECORD or d not in (2, 3) or v < 0:
        raise OctolgpError("leaf record has a bad header")
    at = _HEADER.size + 8 * d + 12 * v
    if len(blob) < at:
        raise OctolgpError("leaf record is truncated")
    specs = [(d, "<i8"), (v, "<f4"), (v, "<f4"), (v, "<f4")]
    index, mean, var, prob = read_arrays(blob[:at], _HEADER.size, specs)
    evidence = engine.decode(blob[at:], d)
    return Leaf(index, evidence, mean, var, prob, bool(pruned), int(refits), int(touched))


def _decode_old(blob: bytes, engine: LeafEngine, grid: LeafGrid) -> Leaf:
    """A record 1 or 2 leaf (both engines' arrays in one record) as the engine's leaf.

    A lattice leaf written before returns kept their positions gets its returns at its
    occupied voxels' centres, as such leaves were fitted.
    """
    if len(blob) < _OLD_HEADER.size:
        raise OctolgpError("leaf record is truncated")
    _, version, d, h, s, v, pruned, refits, touched = _OLD_HEADER.unpack_from(blob)
    if d not in (2, 3) or min(h, s, v) < 0:
        raise OctolgpError("leaf record has a bad header")
    at = _OLD_HEADER.size
    n_counts = 0
    if version == 2:
        if len(blob) < at + _COUNTS.size:
            raise OctolgpError("leaf record is truncated")
        (n_counts,) = _COUNTS.unpack_from(blob, at)
        at += _COUNTS.size
        if n_counts < 0:
            raise OctolgpError("leaf record has a bad header")
    specs = [(d, "<i8"), (h * d, "<f8"), (h, "<i8"), (s * d, "<f8"), (s * d, "<f8")]
    specs += [(s, "<i8"), (v, "<f4"), (v, "<f4"), (v, "<f4"), (2 * n_counts, "u1")]
    index, hits, hit_keys, fs, fe, free_keys, mean, var, prob, counts = read_arrays(blob, at, specs)
    hits = hits.reshape(h, d)
    evidence: LeafEvidence
    if isinstance(engine.empty(d), ExactEvidence):
        evidence = ExactEvidence(hits, hit_keys, fs.reshape(s, d), fe.reshape(s, d), free_keys)
    else:
        counts = counts.reshape(2, n_counts)
        occupied = np.flatnonzero(counts[0])
        if hit_keys.size != occupied.size:  # returns at their voxels' centres
            box = grid.side + 2 * grid.halo_voxels
            local = np.stack(np.unravel_index(occupied, (box,) * d, order="F"), axis=1)
            keys = index * grid.side - grid.halo_voxels + local
            hit_keys = pack_keys(keys)
            hits = ((keys - (1 << (grid.tree_depth - 1)) + 0.5) * grid.resolution).astype(float)
        evidence = LatticeEvidence(counts, hit_keys, hits)
    return Leaf(index, evidence, mean, var, prob, bool(pruned), int(refits), int(touched))


def stored_config(stored: dict[str, Any], clear_scans: str | None) -> MapConfig:
    """The resolved config of a map file from its ``config`` JSON.

    Files of version 3 store the resolved config whole. Older ones dropped derived
    fields: their engine is ``"exact"`` when absent (files from before the lattice
    engine) and their ``clear_scans`` the ``clear_scans`` meta row (0 where absent,
    files from before forgetting); the other derived fields take the defaults they had
    when those files were written, which are today's.
    """
    online = stored.setdefault("online", {})
    online.setdefault("engine", "exact")
    if "clear_scans" not in online:
        written = int(clear_scans or "0")
        if MapConfig.from_dict(stored).clear_scans != written:
            online["clear_scans"] = written
    return MapConfig.from_dict(stored).resolve()


def _scan_row(index: int, scan: Scan) -> tuple[Any, ...]:
    return (
        index,
        scan.dim,
        scan.origin.astype("<f8").tobytes(),
        scan.points.astype("<f8").tobytes(),
        scan.max_range,
        scan.stamp,
    )


def _row_scan(row: tuple[Any, ...]) -> Scan:
    _, dim, origin, points, max_range, stamp = row
    o = np.frombuffer(origin, dtype="<f8").astype(np.float64)
    p = np.frombuffer(points, dtype="<f8").astype(np.float64).reshape(-1, int(dim))
    return Scan(origin=o, points=p, max_range=max_range, stamp=stamp)


def _hp_json(hp: Hyperparameters | None) -> str:
    if hp is None:
        return "null"
    return json.dumps({f: getattr(hp, f) for f in hp.__dataclass_fields__})


def _durable(con: sqlite3.Connection) -> None:
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")


class _Transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back on an exception."""

    def __init__(self, con: sqlite3.Connection) -> None:
        self._con = con

    def __enter__(self) -> sqlite3.Connection:
        self._con.execute("BEGIN IMMEDIATE")
        return self._con

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self._con.execute("ROLLBACK" if exc_type is not None else "COMMIT")


class MapFile:
    """Write-through persistence of an online map in one SQLite file.

    It is also the store's :class:`~octolgp.mapping.store.LeafBacking`: evicted leaves
    are read back from it.

    Attributes
    ----------
    path : Path
    header : MapHeader
        The state recorded when the file was created or opened.
    temporary : bool
        A spill file, deleted on :meth:`close`.
    """

    def __init__(
        self, path: Path, con: sqlite3.Connection, header: MapHeader, temporary: bool = False
    ) -> None:
        self.path = path
        self._con = con
        self.header = header
        self.temporary = temporary
        self._engine = engine_for(header.config)
        self._grid = LeafGrid.from_config(header.config)

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(
        cls,
        path: str | Path,
        config: MapConfig,
        hyperparameters: Hyperparameters | None = None,
        n_scans: int = 0,
        leaves: Iterable[tuple[int, Leaf]] = (),
        temporary: bool = False,
    ) -> MapFile:
        """Start a new map file; refuses to overwrite an existing file.

        Raises
        ------
        OctolgpError
            If ``path`` exists or cannot be created.
        """
        p = Path(path)
        config = config.resolve()
        engine = engine_for(config)
        if p.exists() and not temporary:
            raise OctolgpError(
                f"path {str(p)!r} already exists; reopen it with OnlineMap.open or remove it"
            )
        keys: list[int] = []
        try:
            con = sqlite3.connect(str(p), isolation_level=None, check_same_thread=False)
            _durable(con)
            with _Transaction(con):
                con.execute("CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)")
                con.execute("CREATE TABLE leaves(key INTEGER PRIMARY KEY, data BLOB NOT NULL)")
                con.execute(
                    "CREATE TABLE scans(idx INTEGER PRIMARY KEY, dim INTEGER NOT NULL, "
                    "origin BLOB NOT NULL, points BLOB NOT NULL, max_range REAL, stamp REAL)"
                )
                rows = [
                    ("format", FORMAT),
                    ("version", str(VERSION)),
                    ("config", json.dumps(config.to_dict())),
                    ("hyperparameters", _hp_json(hyperparameters)),
                    ("n_scans", str(n_scans)),
                ]
                con.executemany("INSERT INTO meta VALUES (?, ?)", rows)
                for k, leaf in leaves:  # one row per leaf
                    con.execute("INSERT INTO leaves VALUES (?, ?)", (k, encode_leaf(leaf, engine)))
                    keys.append(k)
        except sqlite3.Error as exc:
            raise OctolgpError(f"path {str(p)!r}: cannot create the map file ({exc})") from None
        return cls(p, con, MapHeader(config, hyperparameters, n_scans, keys), temporary)

    @classmethod
    def spill(cls, config: MapConfig) -> MapFile:
        """A spill file for an in-memory map with a memory budget (deleted on close)."""
        fd, name = tempfile.mkstemp(prefix="octolgp-", suffix=".octolgp")
        os.close(fd)
        os.unlink(name)
        return cls.create(name, config, temporary=True)

    @classmethod
    def open(cls, path: str | Path) -> MapFile:
        """Open a map file (leaves are read lazily); its state is in :attr:`header`.

        Raises
        ------
        MapFileNotFound
            If the file does not exist.
        OctolgpError
            If it is not an octolgp map file or is corrupt.
        """
        p = Path(path)
        if not p.is_file():
            raise MapFileNotFound(f"map file {str(p)!r} does not exist")
        with p.open("rb") as fh:
            if fh.read(16) != _SQLITE_MAGIC:
                raise OctolgpError(f"map file {str(p)!r} is not an octolgp map (not SQLite)")
        try:
            con = sqlite3.connect(str(p), isolation_level=None, check_same_thread=False)
            try:
                meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
            except sqlite3.Error:
                raise OctolgpError(f"map file {str(p)!r} is not an octolgp map") from None
            if meta.get("format") != FORMAT:
                raise OctolgpError(f"map file {str(p)!r} is not an octolgp map")
            if meta.get("version") not in READABLE_VERSIONS:
                raise OctolgpError(
                    f"map file {str(p)!r} has version {meta.get('version')}, expected "
                    f"{' or '.join(READABLE_VERSIONS)}"
                )
            config = stored_config(json.loads(meta["config"]), meta.get("clear_scans"))
            hp_data = json.loads(meta["hyperparameters"])
            hp = None if hp_data is None else Hyperparameters(**hp_data)
            n_scans = int(meta["n_scans"])
            keys = [int(k) for (k,) in con.execute("SELECT key FROM leaves")]
            journal = int(con.execute("SELECT COUNT(*) FROM scans").fetchone()[0])
            if journal not in (0, n_scans):  # 0: saved from memory, without a journal
                raise OctolgpError(
                    f"map file {str(p)!r} is corrupt: {journal} journaled scans, n_scans {n_scans}"
                )
            _durable(con)
        except OctolgpError:
            raise
        except (sqlite3.Error, KeyError, ValueError, TypeError, OSError) as exc:
            raise OctolgpError(f"map file {str(p)!r} is corrupt: {exc}") from None
        return cls(p, con, MapHeader(config, hp, n_scans, keys))

    # ------------------------------------------------------------------ reads
    def read_leaf(self, key: int) -> Leaf:
        """The persisted leaf ``key``."""
        try:  # leaves are read lazily: a damaged file can fail here, long after open()
            row = self._con.execute("SELECT data FROM leaves WHERE key=?", (int(key),)).fetchone()
        except sqlite3.Error as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None
        if row is None:
            raise OctolgpError(f"map file {str(self.path)!r} lacks leaf {key}")
        try:
            return decode_leaf(row[0], self._engine, self._grid)
        except OctolgpError as exc:
            raise OctolgpError(f"map file {str(self.path)!r}, leaf {key}: {exc}") from None

    def scans(self, start: int = 0) -> Iterator[Scan]:
        """The journaled scans with index > ``start``, in order."""
        try:
            cur = self._con.execute(
                "SELECT idx, dim, origin, points, max_range, stamp FROM scans WHERE idx > ? "
                "ORDER BY idx",
                (start,),
            )
            for row in cur:  # one scan per row
                yield _row_scan(row)
        except (sqlite3.Error, ValueError, TypeError, ZeroDivisionError) as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None

    def read_scans(self, indices: list[int]) -> dict[int, Scan]:
        """The journaled scans with these numbers (absent numbers are left out)."""
        out: dict[int, Scan] = {}
        try:
            for lo in range(0, len(indices), 500):  # bounded IN lists
                part = [int(i) for i in indices[lo : lo + 500]]
                cur = self._con.execute(
                    "SELECT idx, dim, origin, points, max_range, stamp FROM scans WHERE idx IN "
                    f"({','.join('?' * len(part))})",
                    part,
                )
                for row in cur:  # one scan per row
                    out[int(row[0])] = _row_scan(row)
        except (sqlite3.Error, ValueError, TypeError, ZeroDivisionError) as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None
        return out

    # ------------------------------------------------------------------ writes
    def commit(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        journal: Iterable[tuple[int, Scan]],
        hyperparameters: Hyperparameters | None,
        n_scans: int,
    ) -> list[int]:
        """Write scans, leaves, hyperparameters and the scan count in one transaction.

        Returns the keys written.
        """
        written = []
        engine = self._engine
        with _Transaction(self._con) as con:
            con.execute("UPDATE meta SET value=? WHERE key='version'", (str(VERSION),))
            con.executemany(
                "INSERT INTO scans VALUES (?, ?, ?, ?, ?, ?)",
                (_scan_row(i, s) for i, s in journal),
            )
            for k, leaf in leaves:  # one row per changed leaf
                con.execute(
                    "INSERT OR REPLACE INTO leaves VALUES (?, ?)", (k, encode_leaf(leaf, engine))
                )
                written.append(k)
            con.execute(
                "UPDATE meta SET value=? WHERE key='hyperparameters'", (_hp_json(hyperparameters),)
            )
            con.execute("UPDATE meta SET value=? WHERE key='n_scans'", (str(n_scans),))
        return written

    def correct(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        removed: Iterable[int],
        journal: Iterable[tuple[int, Scan]],
    ) -> list[int]:
        """Apply a pose correction in one transaction: a kill leaves the map before or after.

        Replaces the journaled scans ``journal`` (by number) and the leaves ``leaves``,
        and deletes the leaves ``removed``. Returns the leaf keys written.
        """
        written = []
        engine = self._engine
        with _Transaction(self._con) as con:
            con.execute("UPDATE meta SET value=? WHERE key='version'", (str(VERSION),))
            for i, s in journal:  # one row per corrected scan
                row = _scan_row(i, s)
                con.execute(
                    "UPDATE scans SET dim=?, origin=?, points=?, max_range=?, stamp=? WHERE idx=?",
                    (*row[1:], i),
                )
            con.executemany("DELETE FROM leaves WHERE key=?", ((int(k),) for k in removed))
            for k, leaf in leaves:  # one row per rebuilt leaf
                con.execute(
                    "INSERT OR REPLACE INTO leaves VALUES (?, ?)", (k, encode_leaf(leaf, engine))
                )
                written.append(k)
        return written

    def finish(self) -> None:
        """Fold the write-ahead log into the file and leave it in rollback-journal mode."""
        self._con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self._con.execute("PRAGMA journal_mode=DELETE")

    def close(self) -> None:
        """Close the connection (and delete a temporary spill file)."""
        self._con.close()
        if self.temporary:
            for suffix in ("", "-wal", "-shm"):
                Path(str(self.path) + suffix).unlink(missing_ok=True)


def write_map(
    path: str | Path,
    config: MapConfig,
    hyperparameters: Hyperparameters | None,
    n_scans: int,
    leaves: Iterable[tuple[int, Leaf]],
    scans: Iterable[Scan] = (),
) -> None:
    """Write a whole map to a new file at ``path``, atomically (temporary file, then rename).

    Parameters
    ----------
    path : str or Path
        Replaced if it exists.
    config, hyperparameters, n_scans
        The map's state.
    leaves : iterable of (int, Leaf)
        Every leaf, by packed key.
    scans : iterable of Scan
        The journal (scans 1, 2, ...): all ``n_scans`` of them, or none.

    Raises
    ------
    OctolgpError
        If the file cannot be written.
    """
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    for suffix in ("", "-wal", "-shm"):
        Path(str(tmp) + suffix).unlink(missing_ok=True)
    try:
        f = MapFile.create(tmp, config, hyperparameters, n_scans, leaves, temporary=True)
        f.temporary = False
        f.commit([], enumerate(scans, start=1), hyperparameters, n_scans)
        f.finish()
        f.close()
        os.replace(tmp, p)
    except (sqlite3.Error, OSError) as exc:
        tmp.unlink(missing_ok=True)
        raise OctolgpError(f"path {str(p)!r}: cannot write the map ({exc})") from None
