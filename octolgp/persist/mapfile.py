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
    encoding of :func:`encode_leaf` (a fixed header, the voxel values in float32, the
    engine's evidence record, :meth:`octolgp.engines.base.LeafEngine.encode`, and a
    CRC-32 of all of it).
``scans(idx INTEGER PRIMARY KEY, dim, origin BLOB, points BLOB, max_range, stamp, crc, codec, rotation)``
    The journal of inserted scans, in insertion order, each with a CRC-32: the origin
    in float64, the points in float64 or (``codec`` 1) as the rounded scan's steps
    (:mod:`octolgp.persist.journal`), and the sensor's rotation (``d x d`` float64,
    row-major; ``NULL`` for a scan made without one, and in files of version 6 and
    older, which did not keep it).

Guarantees
----------
- **Durable steps.** Every write of an online map (a scan, a batch, a correction, new
  hyperparameters) is one SQLite transaction (WAL journal, ``synchronous=FULL``), so
  after ``kill -9``, a full disk or an I/O error at any moment the file holds exactly
  the steps that returned, and a step in flight is wholly in or wholly out. A failed
  commit raises :class:`OctolgpError` naming the file.
- **One writer.** A writer holds an exclusive lock on the file while it is open
  (:class:`octolgp.persist.lock.WriterLock`); a second writer is refused.
- **Snapshots.** A reader (``read_only=True``) reads inside one read transaction: it
  sees the map as of one committed step, whatever a writer does meanwhile.
- **Checksums.** A leaf record or a journaled scan whose CRC-32 does not match is an
  :class:`OctolgpError` naming it, never a number.
- **Reads never write.** Opening, reading and closing without a write leave every
  byte of the file as it was (the WAL journal mode is set at the first write and a
  writer's :meth:`MapFile.close` returns the file to a rollback journal); read-only
  files and directories can be read.

This module reads and writes map state (config, hyperparameters, scan count, leaves,
journal); it never constructs or inspects a map object. The map holds a
:class:`MapFile` through the :class:`octolgp.mapping.store.MapStorage` protocol.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import sqlite3
import struct
import tempfile
import zlib
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np

from octolgp.config import Hyperparameters, MapConfig
from octolgp.engines import engine_for
from octolgp.engines.base import LeafEngine, read_arrays
from octolgp.engines.exact import ExactEvidence
from octolgp.engines.lattice import LatticeEvidence
from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.keys import pack_keys, unpack_keys
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import Leaf, LeafEvidence, MapHeader
from octolgp.persist.journal import decode_points, encode_points, next_checkpoints
from octolgp.persist.lock import WriterLock, held_by_a_writer
from octolgp.scan import Scan

FORMAT = "octolgp-map"
VERSION = 10
READABLE_VERSIONS = ("2", "3", "4", "5", "6", "7", "8", "9", "10")
"""File versions this code opens (2: before the engines owned their leaf records;
3: before checksums; 4: before compact records; 5: before every beam was rounded and
journaled beams were sorted; 6: before the journal kept each scan's sensor rotation;
7: before lattice leaves kept the voxels swept between beams; 8: before exact leaves
kept their seen masks, so an exact leaf of such a file counts every voxel as seen;
9: before lattice leaves could keep their voxels' summed chord shares, so a lattice
leaf of such a file keeps none)."""
_SQLITE_MAGIC = b"SQLite format 3\x00"
_HEADER = struct.Struct("<4sBBxxqqqq")  # magic, version, dim, values, pruned, refits, touched
_OLD_HEADER = struct.Struct("<4sBBxxqqqqqq")  # records 1 and 2: h, s, v, pruned, refits, touched
_CRC = struct.Struct("<I")
_LEAF_MAGIC = b"OLGL"
_RECORD = 5
_FULL_RECORD = 4  # every leaf's voxel values, its evidence at full precision
_COMPACT_HEADER = struct.Struct("<4sBBBxqqq")  # magic, record, dim, flags, key, refits, touched
_VALUES = 1  # flag: the voxel values are stored (engines whose fits are not cheap)
_PRUNED = 2  # flag: the stored values are one value
_FOREIGN = 4  # flag: the stored values are not the engine's fit of the evidence
_COUNT = struct.Struct("<q")  # record 2: halo voxels of the counts; 5: voxel values
_SCAN_COLUMNS = "idx, dim, origin, points, max_range, stamp"
_INSERT_SCAN = (
    f"INSERT INTO scans({_SCAN_COLUMNS}, crc, codec, rotation) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)"
)
ENCODE_BATCH = 4096
"""Leaves encoded together when a step writes them (bounded temporaries)."""
_CHECKPOINT_TABLE = (
    "CREATE TABLE checkpoint_leaves(checkpoint INTEGER NOT NULL, key INTEGER NOT NULL, "
    "data BLOB, PRIMARY KEY (checkpoint, key)) WITHOUT ROWID"
)
_STEPS = 1  # a journal row's codec: the steps of a rounded scan (octolgp.persist.journal)


def encode_leaf(leaf: Leaf, engine: LeafEngine) -> bytes:
    """:func:`encode_leaves` of one leaf."""
    return encode_leaves([leaf], engine)[0]


def encode_leaves(leaves: list[Leaf], engine: LeafEngine) -> list[bytes]:
    """Leaves as bytes: a header, the voxel values where they must be kept, the evidence.

    Per leaf, little-endian: the 32-byte header (magic, record 5, dimension, flags, the
    leaf's packed key, refits, touched); with the ``_VALUES`` flag the number of voxel
    values (int64) and the mean, variance and P(occupied) (float32); the engine's record
    of the evidence (:meth:`LeafEngine.records`, all leaves at once) compressed with
    zlib; the CRC-32 of everything before it (uint32). An engine whose values are a
    function of its evidence (:attr:`LeafEngine.values_from_evidence`) keeps no values:
    a leaf read back is fitted again, and a leaf waiting for its fit (``leaf.pending``)
    can be written; values set another way (``leaf.fitted`` false) are kept with the
    ``_FOREIGN`` flag. An engine that keeps values refuses a pending leaf (``ValueError``).
    """
    if not leaves:
        return []
    indices = np.stack([leaf.index for leaf in leaves]).astype(np.int64)
    keys = pack_keys(indices).tolist()
    evidence = engine.records([leaf.evidence for leaf in leaves], indices)
    out = []
    for leaf, key, record in zip(leaves, keys, evidence, strict=True):  # one record each
        foreign = not leaf.fitted and not leaf.pending
        keep_values = foreign or not engine.values_from_evidence
        if keep_values and leaf.pending:
            raise ValueError("a leaf whose fit is pending cannot be written")
        flags = _VALUES | (_PRUNED if leaf.pruned else 0) | (_FOREIGN if foreign else 0)
        flags = flags if keep_values else 0
        head = _COMPACT_HEADER.pack(
            _LEAF_MAGIC, _RECORD, int(leaf.index.size), flags, key, leaf.refits, leaf.touched
        )
        parts = [head]
        if keep_values:
            parts.append(_COUNT.pack(leaf.prob.size))
            parts += [a.astype("<f4").tobytes() for a in (leaf.mean, leaf.var, leaf.prob)]
        parts.append(zlib.compress(record, 6))
        body = b"".join(parts)
        out.append(body + _CRC.pack(zlib.crc32(body)))
    return out


def decode_leaf(blob: bytes, engine: LeafEngine, grid: LeafGrid) -> Leaf:
    """Inverse of :func:`encode_leaf` (records 1 to 4 too); ``OctolgpError`` if corrupt.

    A leaf stored without its voxel values comes back with none and ``pending`` set:
    the map fits it before reading it.
    """
    if len(blob) < 5:
        raise OctolgpError("leaf record is truncated")
    if blob[:4] != _LEAF_MAGIC:
        raise OctolgpError("leaf record has a bad header")
    if blob[4] in (1, 2):
        return _decode_old(blob, engine, grid)
    if blob[4] in (_RECORD, _FULL_RECORD):
        if len(blob) < 5 + _CRC.size:
            raise OctolgpError("leaf record is truncated")
        blob, (crc,) = blob[: -_CRC.size], _CRC.unpack_from(blob, len(blob) - _CRC.size)
        if zlib.crc32(blob) != crc:
            raise OctolgpError("leaf record fails its checksum")
        if blob[4] == _RECORD:
            return _decode_compact(blob, engine, grid)
    elif blob[4] != 3:  # record 3: record 4's layout without the checksum
        raise OctolgpError("leaf record has a bad header")
    if len(blob) < _HEADER.size:
        raise OctolgpError("leaf record is truncated")
    _, _, d, v, pruned, refits, touched = _HEADER.unpack_from(blob)
    if d not in (2, 3) or v < 0:
        raise OctolgpError("leaf record has a bad header")
    at = _HEADER.size + 8 * d + 12 * v
    if len(blob) < at:
        raise OctolgpError("leaf record is truncated")
    specs = [(d, "<i8"), (v, "<f4"), (v, "<f4"), (v, "<f4")]
    index, mean, var, prob = read_arrays(blob[:at], _HEADER.size, specs)
    evidence = engine.decode(blob[at:], d)  # values of unknown provenance: kept when rewritten
    return Leaf(
        index, evidence, mean, var, prob, bool(pruned), int(refits), int(touched), False, False
    )


def _decode_compact(blob: bytes, engine: LeafEngine, grid: LeafGrid) -> Leaf:
    """A record 5 leaf (checksum already checked)."""
    if len(blob) < _COMPACT_HEADER.size:
        raise OctolgpError("leaf record is truncated")
    _, _, d, flags, key, refits, touched = _COMPACT_HEADER.unpack_from(blob)
    if d != grid.dim or flags & ~(_VALUES | _PRUNED | _FOREIGN) or key < 0:
        raise OctolgpError("leaf record has a bad header")
    index = unpack_keys(np.array([key], dtype=np.int64), d)[0]
    at = _COMPACT_HEADER.size
    empty = np.zeros(0, np.float32)
    mean = var = prob = empty
    if flags & _VALUES:
        if len(blob) < at + _COUNT.size:
            raise OctolgpError("leaf record is truncated")
        (v,) = _COUNT.unpack_from(blob, at)
        at += _COUNT.size
        if v < 0 or len(blob) < at + 12 * v:
            raise OctolgpError("leaf record is truncated")
        mean, var, prob = read_arrays(blob[: at + 12 * v], at, [(v, "<f4")] * 3)
        at += 12 * v
    try:
        record = zlib.decompress(blob[at:])
    except zlib.error:
        raise OctolgpError("leaf record's evidence does not decompress") from None
    evidence = engine.from_record(record, index)
    pending, fitted = not flags & _VALUES, not flags & _FOREIGN
    pruned = bool(flags & _PRUNED)
    return Leaf(
        index, evidence, mean, var, prob, pruned, int(refits), int(touched), pending, fitted
    )


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
        if len(blob) < at + _COUNT.size:
            raise OctolgpError("leaf record is truncated")
        (n_counts,) = _COUNT.unpack_from(blob, at)
        at += _COUNT.size
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
    return Leaf(
        index, evidence, mean, var, prob, bool(pruned), int(refits), int(touched), False, False
    )


def stored_config(stored: object, clear_scans: str | None) -> MapConfig:
    """The resolved config of a map file from its ``config`` JSON.

    Files of version 3 and later store the resolved config whole. Older ones dropped
    derived fields: their engine is ``"exact"`` when absent (files from before the
    lattice engine) and their ``clear_scans`` the ``clear_scans`` meta row (0 where
    absent, files from before forgetting), a 3D lattice map's ``leaf_depth`` that of
    leaves of 4 voxels a side. Files from before lattice tiles (no ``lattice.tile_voxels``)
    fitted each leaf as one tile on a 2D lattice spacing of 0.3, and files from before
    ``lattice.min_inducing_per_axis`` one lattice point per 3 voxels of the halo box at
    least; the config keeps both, files from before ``learning.max_beams`` learnt on
    every beam, and files from before ``online.scan_precision`` kept scans as given and
    every scan in the journal (``online.journal_scans``), and files from before
    ``training.no_return_range`` kept every beam whole and, before
    ``lattice.fill_voxels``, filled every voxel of a leaf, and files from before
    ``lattice.sweep_angle`` swept nothing between beams, and files from before
    ``lattice.free_evidence`` weighed every free look alike. The other derived fields
    take the defaults they had when those files were written, which are today's.

    Raises
    ------
    OctolgpError
        If ``stored`` is not a config object.
    """
    if not isinstance(stored, dict) or not isinstance(stored.get("online", {}), dict):
        raise OctolgpError(f"config is not a JSON object of MapConfig fields: {stored!r:.60}")
    online = stored.setdefault("online", {})
    online.setdefault("engine", "exact")
    if "leaf_depth" not in online and online["engine"] == "lattice" and stored.get("dim", 3) == 3:
        # 3D lattice leaves had 4 voxels a side before leaves held 8 in tiles of 4
        online["leaf_depth"] = int(stored.get("tree_depth", 16)) - 2
    lattice = stored.setdefault("lattice", {})
    if online["engine"] == "lattice" and isinstance(lattice, dict) and "tile_voxels" not in lattice:
        config = MapConfig.from_dict(stored)  # leaves fitted whole before tiles existed
        lattice["tile_voxels"] = 1 << (config.tree_depth - config.leaf_depth)
        if config.dim == 2 and "inducing_spacing" not in {*lattice, *online}:
            lattice["inducing_spacing"] = 0.3  # the 2D default of whole leaves
    old = isinstance(lattice, dict) and "min_inducing_per_axis" not in lattice
    if online["engine"] == "lattice" and old:  # one lattice point per 3 voxels, as then
        config = MapConfig.from_dict(stored)
        box = config.tile_voxels + 2 * config.tile_halo_voxels
        lattice["min_inducing_per_axis"] = max(2, min(config.max_inducing_per_axis, box // 3))
    if "scan_precision" not in online:
        online["scan_precision"] = None  # scans kept as given, as then
    if "journal_scans" not in online:
        online["journal_scans"] = None  # every scan journaled, as then
    if isinstance(lattice, dict) and "fill_voxels" not in lattice:
        lattice["fill_voxels"] = -1  # every voxel of a leaf filled, as then
    if isinstance(lattice, dict) and "sweep_angle" not in lattice:
        lattice["sweep_angle"] = 0.0  # nothing swept between beams, as then
    if isinstance(lattice, dict) and "free_evidence" not in lattice:
        lattice["free_evidence"] = "looks"  # each free look weighed alike, as then
    training = stored.setdefault("training", {})
    if isinstance(training, dict) and "no_return_range" not in training:
        training["no_return_range"] = math.inf  # every beam whole, as then
    learning = stored.setdefault("learning", {})
    if isinstance(learning, dict) and "max_beams" not in learning:
        learning["max_beams"] = None  # learnt on every beam, as then
    if "clear_scans" not in online:
        written = int(clear_scans or "0")
        if MapConfig.from_dict(stored).clear_scans != written:
            online["clear_scans"] = written
    return MapConfig.from_dict(stored).resolve()


def _scan_crc(
    dim: int,
    origin: bytes,
    points: bytes,
    max_range: object,
    stamp: object,
    rotation: bytes | None = None,
) -> int:
    """CRC-32 of a journal row's values (floats by their exact ``repr``).

    The rotation's bytes count when the row has one, so rows without one keep the
    checksum older files gave them.
    """
    crc = zlib.crc32(
        points, zlib.crc32(origin, zlib.crc32(f"{dim}|{max_range!r}|{stamp!r}".encode()))
    )
    return crc if rotation is None else zlib.crc32(rotation, crc)


def _scan_row(index: int, scan: Scan, precision: float | None) -> tuple[Any, ...]:
    """A journal row: float64 points, or with ``precision`` the rounded scan's steps."""
    origin = scan.origin.astype("<f8").tobytes()
    if precision is None:
        points, codec = scan.points.astype("<f8").tobytes(), None
    else:
        points, codec = encode_points(scan, precision), _STEPS
    rotation = None if scan.rotation is None else scan.rotation.astype("<f8").tobytes()
    crc = _scan_crc(scan.dim, origin, points, scan.max_range, scan.stamp, rotation)
    return (index, scan.dim, origin, points, scan.max_range, scan.stamp, crc, codec, rotation)


def _row_scan(row: tuple[Any, ...]) -> Scan:
    index, dim, origin, points, max_range, stamp, crc, codec, rotation = row
    if crc is not None and _scan_crc(dim, origin, points, max_range, stamp, rotation) != crc:
        raise OctolgpError(f"journaled scan {index} fails its checksum")
    o = np.frombuffer(origin, dtype="<f8").astype(np.float64)
    if codec == _STEPS:
        p = decode_points(points, o, int(dim))
    elif codec is None:
        p = np.frombuffer(points, dtype="<f8").astype(np.float64).reshape(-1, int(dim))
    else:
        raise OctolgpError(f"journaled scan {index} has an unknown encoding {codec!r}")
    R = None if rotation is None else np.frombuffer(rotation, "<f8").reshape(int(dim), int(dim))
    return Scan(o, p, max_range, stamp, R)


def _hp_json(hp: Hyperparameters | None) -> str:
    if hp is None:
        return "null"
    return json.dumps({f: getattr(hp, f) for f in hp.__dataclass_fields__})


def _hp_of(text: str) -> Hyperparameters | None:
    data = json.loads(text)
    if data is None:
        return None
    if not isinstance(data, dict):
        raise OctolgpError(f"hyperparameters are not a JSON object: {text:.60}")
    return Hyperparameters(**data)


def _connect(p: Path, read_only: bool) -> sqlite3.Connection:
    """A connection in autocommit mode; a reader's never writes (``mode=ro``).

    A file nobody can write (a read-only file or directory, where SQLite cannot make
    its shared-memory file) is opened ``immutable``: no writer can be changing it.
    """
    if not read_only:
        con = sqlite3.connect(str(p), isolation_level=None, check_same_thread=False)
        con.execute("PRAGMA synchronous=FULL")
        return con
    uri = p.resolve().as_uri()
    writable = os.access(p, os.W_OK) and os.access(p.parent, os.W_OK)
    mode = "?mode=ro" if writable else "?immutable=1"
    return sqlite3.connect(uri + mode, uri=True, isolation_level=None, check_same_thread=False)


class MapFile:
    """Write-through persistence of an online map in one SQLite file.

    It is also the store's :class:`~octolgp.mapping.store.LeafBacking`: evicted leaves
    are read back from it. Open it with :meth:`create`, :meth:`open` or :meth:`spill`.

    Attributes
    ----------
    path : Path
    header : MapHeader
        The state recorded when the file was created or opened.
    temporary : bool
        A spill file, deleted on :meth:`close`.
    read_only : bool
        Opened to read a snapshot; every write is refused.
    """

    def __init__(
        self,
        path: Path,
        con: sqlite3.Connection,
        header: MapHeader,
        *,
        lock: WriterLock | None = None,
        temporary: bool = False,
        created: bool = False,
    ) -> None:
        self.path = path
        self._con = con
        self._lock = lock
        self.header = header
        self.temporary = temporary
        self.read_only = lock is None
        self._engine = engine_for(header.config)
        self._grid = LeafGrid.from_config(header.config)
        self._depth = 0  # open write transactions (nested ones join the outer)
        self._n_scans = header.n_scans
        self._checkpoint_table = _has_table(con, "checkpoint_leaves")
        self._checkpoints = list(header.checkpoints)
        self._window = header.config.online.journal_scans
        self._wrote = created  # a writer that wrote leaves the file in rollback-journal mode
        self._crc_column, self._codec_column, self._rotation_column = _scan_columns(con)
        self._precision = header.config.online.scan_precision

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
        """Start a new map file, locked for writing; refuses to overwrite an existing file.

        Raises
        ------
        OctolgpError
            If ``path`` exists or cannot be created.
        """
        p = Path(path)
        config = config.resolve()
        engine = engine_for(config)
        lock = WriterLock(p, create=True)
        keys: list[int] = []
        try:
            con = _connect(p, read_only=False)
            con.execute("PRAGMA journal_mode=WAL")
            con.execute("BEGIN IMMEDIATE")
            con.execute("CREATE TABLE meta(key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            con.execute("CREATE TABLE leaves(key INTEGER PRIMARY KEY, data BLOB NOT NULL)")
            con.execute(
                "CREATE TABLE scans(idx INTEGER PRIMARY KEY, dim INTEGER NOT NULL, "
                "origin BLOB NOT NULL, points BLOB NOT NULL, max_range REAL, stamp REAL, "
                "crc INTEGER, codec INTEGER, rotation BLOB)"
            )
            con.execute(_CHECKPOINT_TABLE)
            rows = [
                ("format", FORMAT),
                ("version", str(VERSION)),
                ("config", json.dumps(config.to_dict())),
                ("hyperparameters", _hp_json(hyperparameters)),
                ("n_scans", str(n_scans)),
                ("checkpoints", "[0]"),
            ]
            con.executemany("INSERT INTO meta VALUES (?, ?)", rows)
            keys = _insert_leaves(con, "INSERT", list(leaves), engine)
            con.execute("COMMIT")
        except sqlite3.Error as exc:
            lock.release()
            _remove(p)
            raise OctolgpError(f"path {str(p)!r}: cannot create the map file ({exc})") from None
        header = MapHeader(config, hyperparameters, n_scans, keys, [0])
        return cls(p, con, header, lock=lock, temporary=temporary, created=True)

    @classmethod
    def spill(cls, config: MapConfig) -> MapFile:
        """A spill file for an in-memory map with a memory budget (deleted on close)."""
        name = Path(tempfile.gettempdir()) / f"octolgp-{secrets.token_hex(8)}.octolgp"
        return cls.create(name, config, temporary=True)

    @classmethod
    def open(cls, path: str | Path, *, read_only: bool = False) -> MapFile:
        """Open a map file (leaves are read lazily); its state is in :attr:`header`.

        Parameters
        ----------
        path : str or Path
        read_only : bool
            ``False``: the one writer (an exclusive lock until :meth:`close`).
            ``True``: a reader of the last committed step, a snapshot held until
            :meth:`close`; no lock, and the file is never written.

        Raises
        ------
        MapFileNotFound
            If the file does not exist.
        OctolgpError
            If it is not an octolgp map file, is corrupt, or (a writer) is read-only
            here or open for writing elsewhere.
        """
        p = Path(path)
        if not p.is_file():
            raise MapFileNotFound(f"map file {str(p)!r} does not exist")
        try:
            with p.open("rb") as fh:
                magic = fh.read(16)
        except OSError as exc:
            raise OctolgpError(f"map file {str(p)!r} cannot be read: {exc}") from None
        if magic != _SQLITE_MAGIC:
            raise OctolgpError(f"map file {str(p)!r} is not an octolgp map (not SQLite)")
        lock = None if read_only else WriterLock(p)
        try:
            con = _connect(p, read_only)
            try:
                if read_only:
                    con.execute("BEGIN")  # the snapshot, held until close()
                header = _read_header(p, con)
                return cls(p, con, header, lock=lock)
            except BaseException:
                con.close()
                raise
        except BaseException as exc:
            if lock is not None:
                lock.release()
            if isinstance(exc, sqlite3.Error):
                raise OctolgpError(
                    f"map file {str(p)!r} is not an octolgp map or cannot be read ({exc})"
                ) from None
            raise

    # ------------------------------------------------------------------ reads
    @property
    def checkpoints(self) -> list[int]:
        """Scan counts at which the file keeps the leaves changed since, ascending."""
        return list(self._checkpoints)

    @property
    def journal_start(self) -> int:
        """The journal holds the scans after this one (a correction reaches them)."""
        return self._checkpoints[0]

    def read_leaf(self, key: int) -> Leaf:
        """The persisted leaf ``key``.

        Raises
        ------
        OctolgpError
            If the record is missing, fails its checksum or is another leaf's.
        """
        try:  # leaves are read lazily: a damaged file can fail here, long after open()
            row = self._con.execute("SELECT data FROM leaves WHERE key=?", (int(key),)).fetchone()
        except sqlite3.Error as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None
        if row is None:
            raise OctolgpError(f"map file {str(self.path)!r} lacks leaf {key}")
        try:
            leaf = decode_leaf(row[0], self._engine, self._grid)
            if leaf.index.size != self._grid.dim or int(pack_keys(leaf.index[None])[0]) != key:
                raise OctolgpError(f"leaf record holds leaf {leaf.index.tolist()}")
        except OctolgpError as exc:
            raise OctolgpError(f"map file {str(self.path)!r}, leaf {key}: {exc}") from None
        return leaf

    def scans(self, start: int = 0) -> Iterator[Scan]:
        """The journaled scans with index > ``start``, in order."""
        for _, scan in self.journal(start):  # one scan per row
            yield scan

    def journal(self, start: int = 0) -> Iterator[tuple[int, Scan]]:
        """``(number, scan)`` of the journaled scans with number > ``start``, in order."""
        try:
            cur = self._con.execute(
                f"SELECT {self._scan_select} FROM scans WHERE idx > ? ORDER BY idx", (start,)
            )
            for row in cur:  # one scan per row
                yield int(row[0]), _row_scan(row)
        except (sqlite3.Error, OctolgpError, ValueError, TypeError, ZeroDivisionError) as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None

    def checkpoint_rows(self) -> Iterator[tuple[int, int, bytes | None]]:
        """Every ``(checkpoint, key, record)`` the file keeps (``None``: no leaf then)."""
        if not self._checkpoint_table:
            return
        try:
            cur = self._con.execute("SELECT checkpoint, key, data FROM checkpoint_leaves")
            for c, key, data in cur:  # one row per kept leaf
                yield int(c), int(key), data
        except sqlite3.Error as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None

    def write_history(
        self,
        journal: Iterable[tuple[int, Scan]],
        checkpoints: list[int],
        rows: Iterable[tuple[int, int, bytes | None]],
    ) -> None:
        """Write a journal and checkpoints as another file kept them (a copy of a map).

        Only for a new file (:func:`write_map`): nothing is checked against its leaves.
        """
        with self.transaction() as con:
            con.executemany(
                _INSERT_SCAN,
                (_scan_row(i, s, self._precision) for i, s in journal),
            )
            con.executemany("INSERT INTO checkpoint_leaves VALUES (?, ?, ?)", rows)
            con.execute(
                "UPDATE meta SET value=? WHERE key='checkpoints'", (json.dumps(checkpoints),)
            )
        self._checkpoints = list(checkpoints)

    def read_scans(self, indices: list[int]) -> dict[int, Scan]:
        """The journaled scans with these numbers (absent numbers are left out)."""
        out: dict[int, Scan] = {}
        try:
            for lo in range(0, len(indices), 500):  # bounded IN lists
                part = [int(i) for i in indices[lo : lo + 500]]
                cur = self._con.execute(
                    f"SELECT {self._scan_select} FROM scans WHERE idx IN "
                    f"({','.join('?' * len(part))})",
                    part,
                )
                for row in cur:  # one scan per row
                    out[int(row[0])] = _row_scan(row)
        except (sqlite3.Error, OctolgpError, ValueError, TypeError, ZeroDivisionError) as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None
        return out

    @property
    def _scan_select(self) -> str:
        crc = ", crc" if self._crc_column else ", NULL"
        codec = ", codec" if self._codec_column else ", NULL"
        return _SCAN_COLUMNS + crc + codec + (", rotation" if self._rotation_column else ", NULL")

    # ------------------------------------------------------------------ writes
    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """One write transaction; writes inside it (nested ones too) commit together.

        On any exception it is rolled back: the file is as before it began.

        Raises
        ------
        OctolgpError
            If the file is read-only, or a write or the commit fails (a full disk, an
            I/O error); the file then holds the state before the transaction.
        """
        if self.read_only:
            raise OctolgpError(f"map file {str(self.path)!r} is open read-only")
        if self._depth:
            yield self._con
            return
        con = self._con
        try:
            con.execute("PRAGMA journal_mode=WAL")
            con.execute("BEGIN IMMEDIATE")
        except sqlite3.Error as exc:
            raise self._failed(exc) from None
        self._depth = 1
        try:
            if not self._crc_column:  # a file from before checksums gains the column
                con.execute("ALTER TABLE scans ADD COLUMN crc INTEGER")
                self._crc_column = True
            if not self._codec_column:  # a file from before compact journals, too
                con.execute("ALTER TABLE scans ADD COLUMN codec INTEGER")
                self._codec_column = True
            if not self._rotation_column:  # and from before journaled rotations
                con.execute("ALTER TABLE scans ADD COLUMN rotation BLOB")
                self._rotation_column = True
            if not self._checkpoint_table:  # and checkpoints
                con.execute(_CHECKPOINT_TABLE)
                con.execute("INSERT OR IGNORE INTO meta VALUES ('checkpoints', '[0]')")
                self._checkpoint_table = True
            con.execute("UPDATE meta SET value=? WHERE key='version'", (str(VERSION),))
            yield con
            con.execute("COMMIT")
            self._wrote = True
        except BaseException as exc:
            if con.in_transaction:
                with suppress(sqlite3.Error):  # a failed commit may have rolled back already
                    con.execute("ROLLBACK")
            self._crc_column, self._codec_column, self._rotation_column = _scan_columns(con)
            self._checkpoint_table = _has_table(con, "checkpoint_leaves")
            if isinstance(exc, sqlite3.Error):
                raise self._failed(exc) from None
            raise
        finally:
            self._depth = 0

    def _failed(self, exc: sqlite3.Error) -> OctolgpError:
        return OctolgpError(
            f"map file {str(self.path)!r}: the write failed and was rolled back ({exc}); "
            "the file holds the map before it"
        )

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
        engine = self._engine
        leaves = list(leaves)
        with self.transaction() as con:
            con.executemany(
                _INSERT_SCAN,
                (_scan_row(i, s, self._precision) for i, s in journal),
            )
            self._keep_checkpoint(con, [k for k, _ in leaves])
            written = _insert_leaves(con, "INSERT OR REPLACE", leaves, engine)
            con.execute(
                "UPDATE meta SET value=? WHERE key='hyperparameters'", (_hp_json(hyperparameters),)
            )
            con.execute("UPDATE meta SET value=? WHERE key='n_scans'", (str(n_scans),))
            checkpoints = self._advance(con, n_scans, hyperparameters)
        self._n_scans, self._checkpoints = n_scans, checkpoints
        return written

    def _keep_checkpoint(
        self, con: sqlite3.Connection, keys: list[int], skip: Iterable[int] = ()
    ) -> None:
        """Before leaves change: keep their rows as of every checkpoint, once each.

        A leaf without a row for a checkpoint is unchanged since, so its row now is its
        state then (none: no leaf then). Checkpoint 0 is the empty map; ``skip``:
        checkpoints whose rows the caller writes.
        """
        if self._window is None or not keys:
            return
        skipped = {0, *skip}
        for c in self._checkpoints:  # at most three: the journal's start and later ones
            if c in skipped:
                continue
            con.executemany(
                "INSERT OR IGNORE INTO checkpoint_leaves(checkpoint, key, data) "
                "VALUES (?, ?, (SELECT data FROM leaves WHERE key = ?))",
                ((c, int(k), int(k)) for k in keys),
            )

    def _advance(
        self, con: sqlite3.Connection, n_scans: int, hyperparameters: Hyperparameters | None
    ) -> list[int]:
        """Mark a checkpoint every ``journal_scans`` scans and drop what no correction needs.

        The journal keeps the scans after the latest checkpoint at least
        ``journal_scans`` scans back (none while the map learns: it learns on them).
        Returns the checkpoints after the step.
        """
        checkpoints = next_checkpoints(
            self._checkpoints, n_scans, self._window, hyperparameters is None
        )
        start = checkpoints[0]
        if start > self._checkpoints[0]:
            con.execute("DELETE FROM scans WHERE idx <= ?", (start,))
            con.execute("DELETE FROM checkpoint_leaves WHERE checkpoint < ?", (start,))
        if checkpoints != self._checkpoints:
            con.execute(
                "UPDATE meta SET value=? WHERE key='checkpoints'", (json.dumps(checkpoints),)
            )
        return checkpoints

    def checkpoint_leaves(self, checkpoint: int, keys: list[int]) -> dict[int, Leaf | None]:
        """The leaves ``keys`` as of a checkpoint where they changed since.

        ``None``: no leaf then; a key left out is unchanged since the checkpoint.
        """
        out: dict[int, Leaf | None] = {}
        try:
            for lo in range(0, len(keys), 500):  # bounded IN lists
                part = [int(k) for k in keys[lo : lo + 500]]
                cur = self._con.execute(
                    "SELECT key, data FROM checkpoint_leaves WHERE checkpoint = ? AND key IN "
                    f"({','.join('?' * len(part))})",
                    [checkpoint, *part],
                )
                for key, data in cur:  # one row per leaf
                    out[int(key)] = (
                        None if data is None else decode_leaf(data, self._engine, self._grid)
                    )
        except (sqlite3.Error, OctolgpError) as exc:
            raise OctolgpError(f"map file {str(self.path)!r} is corrupt: {exc}") from None
        return out

    def correct(
        self,
        leaves: Iterable[tuple[int, Leaf]],
        removed: Iterable[int],
        journal: Iterable[tuple[int, Scan]],
        checkpointed: Mapping[int, Mapping[int, Leaf | None]] | None = None,
    ) -> list[int]:
        """Apply a pose correction in one transaction: a kill leaves the map before or after.

        Replaces the journaled scans ``journal`` (by number) and the leaves ``leaves``,
        and deletes the leaves ``removed``. ``checkpointed``: per checkpoint after the
        journal's start, the rebuilt leaves as of it (``None``: no leaf then); at the
        latest checkpoint, if not among them, the leaves' rows are kept as a step keeps
        them. Returns the leaf keys written.
        """
        engine = self._engine
        leaves, removed = list(leaves), [int(k) for k in removed]
        checkpointed = checkpointed or {}
        with self.transaction() as con:
            for c, rows in checkpointed.items():  # one checkpoint per iteration
                held = [(int(k), leaf) for k, leaf in rows.items() if leaf is not None]
                blobs = encode_leaves([leaf for _, leaf in held], engine)
                data: dict[int, bytes | None] = {int(k): None for k in rows}
                data.update((k, blob) for (k, _), blob in zip(held, blobs, strict=True))
                con.executemany(
                    "INSERT OR REPLACE INTO checkpoint_leaves VALUES (?, ?, ?)",
                    ((c, k, blob) for k, blob in data.items()),
                )
            keys = [k for k, _ in leaves] + removed
            if self._checkpoints[-1] == self._n_scans:  # the rebuilt rows are its state
                con.executemany(
                    "DELETE FROM checkpoint_leaves WHERE checkpoint = ? AND key = ?",
                    ((self._n_scans, int(k)) for k in keys),
                )
            self._keep_checkpoint(con, keys, skip=[*checkpointed, self._n_scans])
            for i, s in journal:  # one row per corrected scan
                row = _scan_row(i, s, self._precision)
                con.execute(
                    "UPDATE scans SET dim=?, origin=?, points=?, max_range=?, stamp=?, crc=?, "
                    "codec=?, rotation=? WHERE idx=?",
                    (*row[1:], i),
                )
            con.executemany("DELETE FROM leaves WHERE key=?", ((int(k),) for k in removed))
            written = _insert_leaves(con, "INSERT OR REPLACE", leaves, engine)
        return written

    def close(self) -> None:
        """Close the connection, then release the lock (and delete a temporary spill file).

        A writer that wrote folds the write-ahead log into the file and leaves it in
        rollback-journal mode (skipped, harmlessly, while a reader holds a snapshot).
        """
        try:
            if self._wrote and not self.temporary and not self._con.in_transaction:
                self._con.execute("PRAGMA busy_timeout=0")
                busy, _, _ = self._con.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
                if not busy:
                    self._con.execute("PRAGMA journal_mode=DELETE")
        except sqlite3.Error:
            pass  # the file stays a valid WAL-mode database
        finally:
            self._con.close()
            if self._lock is not None:
                self._lock.release()
        if self.temporary:
            _remove(self.path)


def _insert_leaves(
    con: sqlite3.Connection, verb: str, leaves: list[tuple[int, Leaf]], engine: LeafEngine
) -> list[int]:
    """Write leaf rows (``verb``: ``INSERT`` or ``INSERT OR REPLACE``), encoded in batches."""
    written: list[int] = []
    for lo in range(0, len(leaves), ENCODE_BATCH):  # one batch of leaves per iteration
        part = leaves[lo : lo + ENCODE_BATCH]
        keys = [int(k) for k, _ in part]
        blobs = encode_leaves([leaf for _, leaf in part], engine)
        con.executemany(f"{verb} INTO leaves VALUES (?, ?)", zip(keys, blobs, strict=True))
        written += keys
    return written


def _has_table(con: sqlite3.Connection, name: str) -> bool:
    """Whether the database has the table ``name``."""
    row = con.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name=?", (name,))
    return row.fetchone() is not None


def _scan_columns(con: sqlite3.Connection) -> tuple[bool, bool, bool]:
    """Whether the journal table has the ``crc``, ``codec`` and ``rotation`` columns."""
    names = {r[1] for r in con.execute("PRAGMA table_info(scans)")}
    return "crc" in names, "codec" in names, "rotation" in names


def _read_header(p: Path, con: sqlite3.Connection) -> MapHeader:
    """The state a map file records besides leaves and journal, checked."""
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
    try:
        config = stored_config(json.loads(meta["config"]), meta.get("clear_scans"))
        hp = _hp_of(meta["hyperparameters"])
        n_scans = int(meta["n_scans"])
        keys = [int(k) for (k,) in con.execute("SELECT key FROM leaves")]
        journal = int(con.execute("SELECT COUNT(*) FROM scans").fetchone()[0])
        checkpoints = [int(c) for c in json.loads(meta.get("checkpoints", "[0]"))]
    except (sqlite3.Error, OctolgpError, KeyError, ValueError, TypeError) as exc:
        raise OctolgpError(f"map file {str(p)!r} is corrupt: {exc}") from None
    if not checkpoints or checkpoints != sorted(checkpoints) or checkpoints[-1] > n_scans:
        raise OctolgpError(f"map file {str(p)!r} is corrupt: checkpoints {checkpoints}")
    if journal not in (0, n_scans - checkpoints[0]):  # 0: saved from memory by version 6 or older
        raise OctolgpError(
            f"map file {str(p)!r} is corrupt: {journal} journaled scans, n_scans {n_scans}"
        )
    return MapHeader(config, hp, n_scans, keys, checkpoints)


def _remove(p: Path) -> None:
    """Delete a database file and its journals."""
    for suffix in ("", "-wal", "-shm", "-journal"):
        Path(str(p) + suffix).unlink(missing_ok=True)


def check_output(path: str | Path, *, overwrite: bool, own: Path | None = None) -> Path:
    """The path a new map file may be written to, or ``OctolgpError`` saying why not.

    Parameters
    ----------
    path : str or Path
    overwrite : bool
        Whether an existing file may be replaced.
    own : Path, optional
        The file of the map being written, never replaced by it.
    """
    p = Path(path)
    if own is not None and p.exists() and os.path.samefile(p, own):
        raise OctolgpError(f"path {str(p)!r} is the map's own file; save to another path")
    if p.exists() and not overwrite:
        raise OctolgpError(f"path {str(p)!r} already exists; pass overwrite=True to replace it")
    if p.exists() and held_by_a_writer(p):
        raise OctolgpError(f"path {str(p)!r} is a map open for writing elsewhere")
    if p.is_dir():
        raise OctolgpError(f"path {str(p)!r} is a directory")
    return p


def write_map(
    path: str | Path,
    config: MapConfig,
    hyperparameters: Hyperparameters | None,
    n_scans: int,
    leaves: Iterable[tuple[int, Leaf]],
    journal: Iterable[tuple[int, Scan]] = (),
    *,
    checkpoints: list[int] | None = None,
    checkpoint_rows: Iterable[tuple[int, int, bytes | None]] = (),
    overwrite: bool = False,
    own: Path | None = None,
) -> None:
    """Write a whole map to a new file at ``path`` (a temporary file, then a rename).

    Parameters
    ----------
    path : str or Path
        Where; an existing file is replaced only with ``overwrite``, and never when it
        is ``own`` or open for writing.
    config, hyperparameters, n_scans
        The map's state.
    leaves : iterable of (int, Leaf)
        Every leaf, by packed key.
    journal : iterable of (int, Scan)
        The journal: scans by number, those after the first checkpoint, or none.
    checkpoints, checkpoint_rows
        The checkpoints (``[0]`` when omitted) and the leaves kept as of them
        (:meth:`MapFile.checkpoint_rows`).
    overwrite : bool
        Replace an existing file.
    own : Path, optional
        The file of the map being saved.

    Raises
    ------
    OctolgpError
        If the path is refused or the file cannot be written; an existing file at
        ``path`` is then unchanged.
    """
    p = check_output(path, overwrite=overwrite, own=own)
    tmp = p.with_name(f".{p.name}.{secrets.token_hex(4)}.tmp")
    try:
        f = MapFile.create(tmp, config, hyperparameters, n_scans, leaves)
        try:
            f.write_history(journal, checkpoints or [0], checkpoint_rows)
        finally:
            f.close()
        for suffix in ("-wal", "-shm"):  # a killed writer's log must not meet the new file
            Path(str(p) + suffix).unlink(missing_ok=True)
        os.replace(tmp, p)
        _sync_dir(p.parent)
    except (OctolgpError, OSError) as exc:
        _remove(tmp)
        raise OctolgpError(f"path {str(p)!r}: cannot write the map ({exc})") from None


def _sync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (where directories can be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
