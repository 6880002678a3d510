"""The single-file map: an embedded SQLite database (standard library ``sqlite3``).

Tables
------
``meta(key TEXT PRIMARY KEY, value TEXT)``
    ``format`` (``"octolgp-map"``), ``version``, ``config`` (JSON of
    :meth:`MapConfig.to_dict`), ``hyperparameters`` (JSON or ``null``), ``n_scans``.
``leaves(key INTEGER PRIMARY KEY, data BLOB)``
    One row per leaf, keyed by its packed OctoMap key; ``data`` is an uncompressed
    ``.npz`` of the leaf's arrays (evidence and float32 voxel values).

A map opened with a path writes the leaves each scan changed, and the scan
count, in one transaction per :meth:`OnlineMap.insert_scan` (WAL journal,
``synchronous=FULL``), so a killed process loses at most the scan in flight.
"""

from __future__ import annotations

import io
import json
import os
import sqlite3
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.store import Leaf

if TYPE_CHECKING:
    from octolgp.online import OnlineMap

FORMAT = "octolgp-map"
VERSION = 1
_ARRAYS = (
    "index",
    "hits",
    "hit_keys",
    "free_start",
    "free_end",
    "free_keys",
    "mean",
    "var",
    "prob",
)


def encode_leaf(leaf: Leaf) -> bytes:
    """A leaf as uncompressed ``.npz`` bytes."""
    buf = io.BytesIO()
    arrays = {name: getattr(leaf, name) for name in _ARRAYS}
    counters = np.array([int(leaf.pruned), leaf.refits, leaf.touched], dtype=np.int64)
    np.savez(buf, counters=counters, **arrays)
    return buf.getvalue()


def decode_leaf(blob: bytes) -> Leaf:
    """Inverse of :func:`encode_leaf`."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        arrays = {name: np.array(z[name]) for name in _ARRAYS}
        pruned, refits, touched = (int(v) for v in z["counters"])
    return Leaf(**arrays, pruned=bool(pruned), refits=refits, touched=touched)


def _connect(path: Path) -> sqlite3.Connection:
    con = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")
    return con


def _hp_json(hp: Hyperparameters | None) -> str:
    if hp is None:
        return "null"
    return json.dumps({f: getattr(hp, f) for f in hp.__dataclass_fields__})


def _init_schema(con: sqlite3.Connection, m: OnlineMap) -> None:
    con.execute("BEGIN IMMEDIATE")
    con.execute("CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)")
    con.execute("CREATE TABLE leaves(key INTEGER PRIMARY KEY, data BLOB NOT NULL)")
    rows = [
        ("format", FORMAT),
        ("version", str(VERSION)),
        ("config", json.dumps(m.config.to_dict())),
        ("hyperparameters", _hp_json(m.hyperparameters)),
        ("n_scans", str(m.n_scans)),
    ]
    con.executemany("INSERT INTO meta VALUES (?, ?)", rows)
    con.executemany(
        "INSERT INTO leaves VALUES (?, ?)", ((k, encode_leaf(leaf)) for k, leaf in m.store.items())
    )
    con.execute("COMMIT")


class MapFile:
    """Write-through persistence of an :class:`OnlineMap` in one SQLite file."""

    def __init__(self, path: Path, con: sqlite3.Connection) -> None:
        self.path = path
        self._con = con

    @classmethod
    def create(cls, path: str | Path, m: OnlineMap) -> MapFile:
        """Start a new map file for ``m``; refuses to overwrite an existing file."""
        p = Path(path)
        if p.exists():
            raise OctolgpError(
                f"path {str(p)!r} already exists; reopen it with OnlineMap.open or remove it"
            )
        try:
            con = _connect(p)
            _init_schema(con, m)
        except sqlite3.Error as exc:
            raise OctolgpError(f"path {str(p)!r}: cannot create the map file ({exc})") from None
        return cls(p, con)

    @classmethod
    def open(cls, path: str | Path) -> OnlineMap:
        """Load a map file and keep writing through to it."""
        from octolgp.online import OnlineMap

        p = Path(path)
        if not p.is_file():
            raise MapFileNotFound(f"map file {str(p)!r} does not exist")
        with p.open("rb") as fh:
            if fh.read(16) != b"SQLite format 3\x00":
                raise OctolgpError(f"map file {str(p)!r} is not an octolgp map (not SQLite)")
        try:
            con = _connect(p)
            meta = dict(con.execute("SELECT key, value FROM meta").fetchall())
            if meta.get("format") != FORMAT:
                raise OctolgpError(f"map file {str(p)!r} is not an octolgp map")
            if int(meta.get("version", "0")) != VERSION:
                raise OctolgpError(
                    f"map file {str(p)!r} has version {meta.get('version')}, expected {VERSION}"
                )
            config = MapConfig.from_dict(json.loads(meta["config"]))
            hp_data = json.loads(meta["hyperparameters"])
            m = OnlineMap(config)
            m.hyperparameters = None if hp_data is None else Hyperparameters(**hp_data)
            m.n_scans = int(meta["n_scans"])
            for key, blob in con.execute("SELECT key, data FROM leaves ORDER BY key"):
                m.store.put(int(key), decode_leaf(blob))
        except OctolgpError:
            raise
        except (sqlite3.Error, KeyError, ValueError, TypeError, OSError) as exc:
            raise OctolgpError(f"map file {str(p)!r} is corrupt: {exc}") from None
        m._file = cls(p, con)
        return m

    def write_meta(self, m: OnlineMap) -> None:
        """Update the hyperparameters and scan count."""
        with self._transaction() as con:
            self._meta(con, m)

    def _meta(self, con: sqlite3.Connection, m: OnlineMap) -> None:
        con.execute(
            "UPDATE meta SET value=? WHERE key='hyperparameters'", (_hp_json(m.hyperparameters),)
        )
        con.execute("UPDATE meta SET value=? WHERE key='n_scans'", (str(m.n_scans),))

    def write_leaves(self, m: OnlineMap, keys: list[int], n_scans: int, scans: Any) -> None:
        """Upsert the given leaves and the scan count in one transaction."""
        with self._transaction() as con:
            con.executemany(
                "INSERT OR REPLACE INTO leaves VALUES (?, ?)",
                ((k, encode_leaf(leaf)) for k in keys if (leaf := m.store.get(k)) is not None),
            )
            self._meta(con, m)

    def _transaction(self) -> _Transaction:
        return _Transaction(self._con)

    def close(self) -> None:
        """Close the connection."""
        self._con.close()


class _Transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT``, rolled back on an exception."""

    def __init__(self, con: sqlite3.Connection) -> None:
        self._con = con

    def __enter__(self) -> sqlite3.Connection:
        self._con.execute("BEGIN IMMEDIATE")
        return self._con

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self._con.execute("ROLLBACK" if exc_type is not None else "COMMIT")


def save_map(m: OnlineMap, path: str | Path) -> None:
    """Write ``m`` to a new file at ``path``, atomically (temporary file, then rename)."""
    p = Path(path)
    m.flush()
    tmp = p.with_name(p.name + ".tmp")
    tmp.unlink(missing_ok=True)
    try:
        con = _connect(tmp)
        _init_schema(con, m)
        con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        con.execute("PRAGMA journal_mode=DELETE")
        con.close()
        os.replace(tmp, p)
    except (sqlite3.Error, OSError) as exc:
        tmp.unlink(missing_ok=True)
        raise OctolgpError(f"path {str(p)!r}: cannot write the map ({exc})") from None
