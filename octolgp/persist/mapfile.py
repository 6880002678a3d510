"""The single-file map: an embedded SQLite database (standard library ``sqlite3``).

Tables
------
``meta(key TEXT PRIMARY KEY, value TEXT)``
    ``format`` (``"octolgp-map"``), ``version``, ``config`` (JSON of
    :meth:`MapConfig.to_dict`), ``hyperparameters`` (JSON or ``null``), ``n_scans``.
``leaves(key INTEGER PRIMARY KEY, data BLOB)``
    One row per leaf, keyed by its packed OctoMap key; ``data`` is the leaf in the
    compact encoding of :func:`encode_leaf` (a fixed header, then the raw arrays:
    evidence in float64, voxel values in float32).
``scans(idx INTEGER PRIMARY KEY, dim, origin BLOB, points BLOB, max_range, stamp)``
    The journal of inserted scans, float64, in insertion order (empty in a file
    saved from an in-memory map, which keeps no scans).

Durability
----------
Every :meth:`OnlineMap.insert_scan` of a map with a file ends in one SQLite
transaction (WAL journal, ``synchronous=FULL``) that writes the scan's journal row,
every leaf it changed and the scan count, so after ``kill -9`` at any moment the
file holds exactly the scans whose ``insert_scan`` returned, and a scan in flight
is wholly in or wholly out. Opening never modifies a file that is not an
octolgp map.
"""

from __future__ import annotations

import json
import os
import sqlite3
import struct
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan

if TYPE_CHECKING:
    from octolgp.mapping.online import OnlineMap

FORMAT = "octolgp-map"
VERSION = 2
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER = struct.Struct("<4sBBxxqqqqqq")  # magic, version, dim, h, s, v, pruned, refits, touched
_LEAF_MAGIC = b"OLGL"


def encode_leaf(leaf: Leaf) -> bytes:
    """A leaf as bytes: a 56-byte header, then its arrays back to back (little-endian)."""
    d = int(leaf.index.size)
    h, s, v = leaf.hits.shape[0], leaf.free_start.shape[0], leaf.prob.size
    head = _HEADER.pack(_LEAF_MAGIC, 1, d, h, s, v, int(leaf.pruned), leaf.refits, leaf.touched)
    parts = [
        leaf.index.astype("<i8"),
        leaf.hits.astype("<f8"),
        leaf.hit_keys.astype("<i8"),
        leaf.free_start.astype("<f8"),
        leaf.free_end.astype("<f8"),
        leaf.free_keys.astype("<i8"),
        leaf.mean.astype("<f4"),
        leaf.var.astype("<f4"),
        leaf.prob.astype("<f4"),
    ]
    return head + b"".join(p.tobytes() for p in parts)


def decode_leaf(blob: bytes) -> Leaf:
    """Inverse of :func:`encode_leaf`; raises ``OctolgpError`` on a corrupt blob."""
    if len(blob) < _HEADER.size:
        raise OctolgpError("leaf record is truncated")
    magic, version, d, h, s, v, pruned, refits, touched = _HEADER.unpack_from(blob)
    if magic != _LEAF_MAGIC or version != 1 or d not in (2, 3) or min(h, s, v) < 0:
        raise OctolgpError("leaf record has a bad header")
    sizes = [(d, "<i8"), (h * d, "<f8"), (h, "<i8"), (s * d, "<f8"), (s * d, "<f8")]
    sizes += [(s, "<i8"), (v, "<f4"), (v, "<f4"), (v, "<f4")]
    need = _HEADER.size + sum(n * np.dtype(t).itemsize for n, t in sizes)
    if len(blob) != need:
        raise OctolgpError(f"leaf record has {len(blob)} bytes, expected {need}")
    out, at = [], _HEADER.size
    for n, t in sizes:  # nine arrays
        arr = np.frombuffer(blob, dtype=t, count=n, offset=at)
        out.append(arr.astype(np.dtype(t).newbyteorder("=")))
        at += n * arr.itemsize
    index, hits, hit_keys, fs, fe, free_keys, mean, var, prob = out
    return Leaf(
        index=index,
        hits=hits.reshape(h, d),
        hit_keys=hit_keys,
        free_start=fs.reshape(s, d),
        free_end=fe.reshape(s, d),
        free_keys=free_keys,
        mean=mean,
        var=var,
        prob=prob,
        pruned=bool(pruned),
        refits=int(refits),
        touched=int(touched),
    )


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
    """Write-through persistence of an :class:`OnlineMap` in one SQLite file.

    It is also the map's :class:`~octolgp.store.LeafBacking`: evicted leaves are
    read back from it.
    """

    def __init__(self, path: Path, con: sqlite3.Connection, temporary: bool = False) -> None:
        self.path = path
        self._con = con
        self.temporary = temporary

    # ------------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: str | Path, m: OnlineMap, temporary: bool = False) -> MapFile:
        """Start a new map file for ``m``; refuses to overwrite an existing file."""
        p = Path(path)
        if p.exists() and not temporary:
            raise OctolgpError(
                f"path {str(p)!r} already exists; reopen it with OnlineMap.open or remove it"
            )
        try:
            con = sqlite3.connect(str(p), isolation_level=None, check_same_thread=False)
            _durable(con)
            cls._schema(con, m)
        except sqlite3.Error as exc:
            raise OctolgpError(f"path {str(p)!r}: cannot create the map file ({exc})") from None
        return cls(p, con, temporary)

    @classmethod
    def spill(cls, m: OnlineMap) -> MapFile:
        """A spill file for an in-memory map with a memory budget (deleted on close)."""
        fd, name = tempfile.mkstemp(prefix="octolgp-", suffix=".octolgp")
        os.close(fd)
        os.unlink(name)
        return cls.create(name, m, temporary=True)

    @staticmethod
    def _schema(con: sqlite3.Connection, m: OnlineMap) -> None:
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
                ("config", json.dumps(m.config.to_dict())),
                ("hyperparameters", _hp_json(m.hyperparameters)),
                ("n_scans", str(m.n_scans)),
            ]
            con.executemany("INSERT INTO meta VALUES (?, ?)", rows)
            con.executemany(
                "INSERT INTO leaves VALUES (?, ?)",
                ((k, encode_leaf(leaf)) for k, leaf in m.store.items()),
            )

    @classmethod
    def open(cls, path: str | Path) -> OnlineMap:
        """Load a map file (leaves lazily) and keep writing through to it."""
        from octolgp.mapping.online import OnlineMap

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
            if meta.get("version") != str(VERSION):
                raise OctolgpError(
                    f"map file {str(p)!r} has version {meta.get('version')}, expected {VERSION}"
                )
            config = MapConfig.from_dict(json.loads(meta["config"]))
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
        m = OnlineMap(config, _opened=True)  # no spill file: this file is the backing
        m.hyperparameters = hp
        m.n_scans = n_scans
        f = cls(p, con)
        m._file = f
        m.store.attach(f, keys)
        if m.hyperparameters is None and not keys:  # the scans were buffered for learning
            m._buffer = list(f.scans())
        return m

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
            return decode_leaf(row[0])
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

    # ------------------------------------------------------------------ writes
    def commit(
        self, m: OnlineMap, keys: Iterable[int], journal: Iterable[tuple[int, Scan]]
    ) -> list[int]:
        """Write scans, leaves, hyperparameters and the scan count in one transaction.

        Returns the keys written.
        """
        written = []
        with _Transaction(self._con) as con:
            con.executemany(
                "INSERT INTO scans VALUES (?, ?, ?, ?, ?, ?)",
                (_scan_row(i, s) for i, s in journal),
            )
            for k in keys:  # one row per changed leaf
                leaf = m.store.get(k)
                if leaf is not None:
                    con.execute(
                        "INSERT OR REPLACE INTO leaves VALUES (?, ?)", (k, encode_leaf(leaf))
                    )
                    written.append(k)
            con.execute(
                "UPDATE meta SET value=? WHERE key='hyperparameters'",
                (_hp_json(m.hyperparameters),),
            )
            con.execute("UPDATE meta SET value=? WHERE key='n_scans'", (str(m.n_scans),))
        return written

    def close(self) -> None:
        """Close the connection (and delete a temporary spill file)."""
        self._con.close()
        if self.temporary:
            for suffix in ("", "-wal", "-shm"):
                Path(str(self.path) + suffix).unlink(missing_ok=True)


def save_map(m: OnlineMap, path: str | Path) -> None:
    """Write ``m`` to a new file at ``path``, atomically (temporary file, then rename)."""
    p = Path(path)
    m.flush()
    tmp = p.with_name(p.name + ".tmp")
    for suffix in ("", "-wal", "-shm"):
        Path(str(tmp) + suffix).unlink(missing_ok=True)
    try:
        f = MapFile.create(tmp, m, temporary=True)
        f.temporary = False
        src = m._file
        if src is not None:  # copy the scan journal (an in-memory map keeps none)
            f.commit(m, [], ((i + 1, s) for i, s in enumerate(src.scans())))
        f._con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        f._con.execute("PRAGMA journal_mode=DELETE")
        f.close()
        os.replace(tmp, p)
    except (sqlite3.Error, OSError) as exc:
        tmp.unlink(missing_ok=True)
        raise OctolgpError(f"path {str(p)!r}: cannot write the map ({exc})") from None
