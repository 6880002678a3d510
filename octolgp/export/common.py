"""Argument checks and file output shared by the exporters (OctoMap, PLY, PCD, PNG).

Every file octolgp writes outside a map file goes through :func:`replacing`: it is
written under a temporary name in its own directory and renamed onto its path once
complete, so a full disk or a killed process never leaves half a file at the path
and never destroys the file that was there.
"""

from __future__ import annotations

import contextlib
import io
import os
import secrets
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from octolgp.errors import OctolgpError

FloatArray = NDArray[np.float64]
PathLike = str | os.PathLike[str]


def per_voxel(values: ArrayLike, count: int, name: str) -> NDArray[Any]:
    """Return ``values`` as a ``(count,)`` array, or raise naming ``name``."""
    v = np.asarray(values)
    if v.shape != (count,):
        raise OctolgpError(f"{name} must have shape ({count},), one per key, got {v.shape}")
    return v


def as_finite(values: ArrayLike, count: int, name: str) -> FloatArray:
    """Return ``values`` as ``(count,)`` finite float64, or raise naming ``name``."""
    v = per_voxel(values, count, name)
    if v.dtype.kind not in "biuf":
        raise OctolgpError(f"{name} must be real numbers, got dtype {v.dtype}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise OctolgpError(f"{name} must be finite, got {int((~np.isfinite(v)).sum())} bad values")
    return v


def as_centres(centres: ArrayLike, dims: tuple[int, ...]) -> FloatArray:
    """Return ``centres`` as finite float64 of shape ``(k, d)``, ``d`` in ``dims``, or raise."""
    c = np.asarray(centres)
    if c.ndim != 2 or c.shape[1] not in dims or c.dtype.kind not in "biuf":
        raise OctolgpError(f"centres must be a real array of shape (k, {dims}), got {c.shape}")
    c = c.astype(np.float64)
    if not np.isfinite(c).all():
        raise OctolgpError("centres must be finite")
    return c


def as_prob(prob: ArrayLike, count: int) -> FloatArray:
    """Return ``prob`` as ``(count,)`` float64 in [0, 1], or raise."""
    p = as_finite(prob, count, "prob")
    if p.size and (p.min() < 0.0 or p.max() > 1.0):
        raise OctolgpError(f"prob must lie in [0, 1], got [{p.min():g}, {p.max():g}]")
    return p


def xyz_prob_body(centres: ArrayLike, prob: ArrayLike, *, binary: bool) -> tuple[int, bytes]:
    """Voxel centres and P(occupied) as float32 ``x y z prob`` records, the body PLY and PCD share.

    Parameters
    ----------
    centres : array_like of float, shape (k, 3) or (k, 2)
        Voxel centres in the world frame, metres; 2D centres get ``z = 0``.
    prob : array_like of float, shape (k,)
        P(occupied) per centre, in [0, 1].
    binary : bool
        Packed little-endian records, or one text row per point with 9 significant digits
        (which round-trip float32).

    Returns
    -------
    count : int
        ``k``, the number of records.
    body : bytes

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value, or ``prob`` outside [0, 1].
    """
    c = as_centres(centres, (2, 3))
    p = as_prob(prob, c.shape[0])
    if c.shape[1] == 2:
        c = np.column_stack([c, np.zeros(c.shape[0])])
    record = np.empty(c.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("prob", "<f4")])
    for axis, name in enumerate("xyz"):
        record[name] = c[:, axis]
    record["prob"] = p
    if binary:
        return c.shape[0], record.tobytes()
    text = io.StringIO()
    rows = np.column_stack([record[name] for name in ("x", "y", "z", "prob")])
    np.savetxt(text, rows, fmt="%.9g")
    return c.shape[0], text.getvalue().encode("ascii")


def write_xyz_prob_stream(
    path: PathLike,
    header_of: Callable[[int], bytes],
    chunks: Iterable[tuple[ArrayLike, ArrayLike]],
    *,
    binary: bool,
) -> int:
    """Write ``header_of(count)`` then the records of every chunk, one chunk in memory at a time.

    Chunks given as a list are in memory already: their records are written after the
    header at once (:func:`write_bytes`). Other iterables are streamed: the records
    (:func:`xyz_prob_body`) go to a temporary file beside ``path`` first, since the
    header needs their count; then header and records become ``path`` through
    :func:`replacing`. Returns the count.

    Raises
    ------
    OctolgpError
        As :func:`xyz_prob_body` for a bad chunk, or naming ``path`` when it cannot be
        written; the file that was there is kept.
    """
    if isinstance(chunks, list):
        bodies = [xyz_prob_body(centres, prob, binary=binary) for centres, prob in chunks]
        n = sum(k for k, _ in bodies)
        write_bytes(path, [header_of(n), *(body for _, body in bodies)])
        return n
    n = 0
    target = Path(path)
    where = target.parent if target.parent.is_dir() else None
    try:
        with tempfile.TemporaryFile(dir=where) as body:
            for centres, prob in chunks:  # one chunk of records per iteration
                k, records = xyz_prob_body(centres, prob, binary=binary)
                body.write(records)
                n += k
            body.seek(0)
            with replacing(path) as tmp, open(tmp, "wb") as out:
                out.write(header_of(n))
                shutil.copyfileobj(body, out, 1 << 20)
    except OSError as exc:
        raise OctolgpError(f"cannot write {os.fspath(path)!r}: {exc}") from None
    return n


SQLITE_SIDECARS = ("-journal", "-wal", "-shm")
"""The files SQLite keeps beside a database: removed with a temporary map file."""


def _remove(path: Path, sidecars: tuple[str, ...]) -> None:
    """Delete ``path`` and its sidecars where they exist."""
    for suffix in ("", *sidecars):  # one iteration per file of the temporary output
        with contextlib.suppress(OSError):
            Path(str(path) + suffix).unlink(missing_ok=True)


def _sync_rename(tmp: Path, target: Path) -> None:
    """Flush ``tmp`` to disk, rename it onto ``target``, then flush the directory entry."""
    fd = os.open(tmp, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, target)
    with contextlib.suppress(OSError):  # a file system without directory fsync
        dir_fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


@contextlib.contextmanager
def replacing(path: PathLike, *, sidecars: tuple[str, ...] = ()) -> Iterator[Path]:
    """A temporary path beside ``path`` that replaces ``path`` once the block succeeds.

    The block writes a new file at the yielded path, which does not exist yet and lies in
    ``path``'s directory with ``path``'s suffix (writers that choose the format by the
    extension choose the same one). When the block ends normally the file is flushed to
    disk and renamed onto ``path`` (``os.replace``, atomic on POSIX): readers see the old
    file or the whole new one. When the block raises, the temporary file (and its
    ``sidecars``) is removed and ``path`` is untouched, so a full disk never destroys the
    earlier file; a killed process leaves at most the hidden temporary file, never a part
    at ``path``. A symbolic link is followed: the file it points to is replaced. A path that
    exists and is not a regular file (``/dev/null``, a FIFO) is written in place.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write.
    sidecars : tuple of str, optional
        Suffixes of files the writer may leave beside the temporary file, removed with it
        when the block raises (:data:`SQLITE_SIDECARS` for a map file, which the block
        closes before it ends).

    Yields
    ------
    Path
        Where the block writes the file.

    Raises
    ------
    OctolgpError
        Naming ``path``, when the block raises :class:`OSError` (a full disk, a directory
        that does not exist or cannot be written) or the flush or rename fails.
    """
    target = Path(os.path.realpath(path))
    if target.exists() and not target.is_file():
        yield target
        return
    tmp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part{target.suffix}")
    try:
        yield tmp
        _sync_rename(tmp, target)
    except OSError as exc:
        _remove(tmp, sidecars)
        raise OctolgpError(f"path {os.fspath(path)!r} cannot be written: {exc}") from exc
    except BaseException:
        _remove(tmp, sidecars)
        raise


def write_chunks(path: PathLike, chunks: Sequence[bytes | memoryview]) -> None:
    """Write ``chunks`` to a new file ``path`` (no rename; see :func:`write_bytes`)."""
    with open(path, "wb") as f:
        for chunk in chunks:  # one write per chunk
            f.write(chunk)


def write_bytes(path: PathLike, chunks: Sequence[bytes | memoryview]) -> None:
    """Write ``chunks`` to ``path`` through a temporary file (:func:`replacing`).

    Raises
    ------
    OctolgpError
        Naming ``path`` when it cannot be written; the file that was there is kept.
    """
    with replacing(path) as tmp:
        write_chunks(tmp, chunks)
