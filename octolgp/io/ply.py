"""Streaming reader for PLY point clouds (Stanford polygon format), one file per scan.

Format (Paul Bourke / Greg Turk's PLY description): ``ply``, ``format ascii 1.0`` |
``binary_little_endian 1.0`` | ``binary_big_endian 1.0``, ``comment``/``obj_info`` lines,
``element NAME COUNT`` blocks of ``property TYPE NAME`` or ``property list CTYPE ITYPE NAME``,
``end_header``; then each element's instances in header order (ASCII: one per line).

- The ``vertex`` element's ``x``, ``y``, ``z`` properties are the points (any scalar type);
  its other scalar properties are ignored. A ``vertex`` list property is not supported.
- Other elements (faces, edges...) before ``vertex`` are skipped, list properties included;
  elements after it are never read.
- The points are in the world frame, metres. The sensor origin is, in order: a
  ``comment origin X Y Z`` or ``obj_info origin X Y Z`` header line; the reader's ``origin=``
  argument; ``(0, 0, 0)``.
- Every vertex must be finite: PLY has no organised-cloud convention, so a NaN or inf
  coordinate is a malformed point (raised, or skipped with ``skip_bad``).
- Size limits, checked from the header before the data are read: the ``vertex`` count is at
  most :data:`~octolgp.io.limits.MAX_SCAN_POINTS`, and the elements up to it must fit in the
  bytes that follow the header (at least one byte per ASCII instance, one record's scalars
  and list counts per binary instance).
"""

from __future__ import annotations

import io
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import IO

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.io import limits
from octolgp.io.pointcloud import (
    CHUNK_POINTS,
    READ_ERRORS,
    CloudReader,
    has_cloud_files,
    list_cloud_files,
    parse_ascii,
    read_exact_lines,
    read_header,
)
from octolgp.scan import FloatArray, Scan

__all__ = ["PlyElement", "PlyHeader", "PlyReader", "looks_like_ply", "read_ply", "read_ply_header"]

_TYPES = MappingProxyType({
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
})  # fmt: skip
_FORMATS = MappingProxyType({"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"})
_MAX_HEADER_LINES = 4096
_MAX_LINE = 1 << 16


@dataclass(frozen=True)
class PlyElement:
    """One ``element``: its name, count and ``(name, type, list_count_type | None)`` properties."""

    name: str
    count: int
    properties: tuple[tuple[str, str, str | None], ...]

    def dtype(self, order: str) -> np.dtype[np.void]:
        """The packed record of one instance (scalar properties only)."""
        return np.dtype(
            [(f"p{i}", order + _TYPES[t]) for i, (_, t, _) in enumerate(self.properties)]
        )

    def min_record(self) -> int:
        """Fewest bytes of one binary instance: its scalars and list counts (empty lists)."""
        return sum(
            np.dtype(_TYPES[t if count is None else count]).itemsize
            for _, t, count in self.properties
        )


@dataclass(frozen=True)
class PlyHeader:
    """A parsed PLY header: ``format`` (``ascii``/``binary_*``), elements, header origin."""

    format: str
    elements: tuple[PlyElement, ...]
    origin: tuple[float, float, float] | None
    data_offset: int
    header_lines: int


def _parse_header(fh: IO[bytes]) -> PlyHeader:
    """Parse a header from the start of ``fh``; errors start ``line: why``."""
    if fh.read(4) not in (b"ply\n", b"ply\r"):
        raise OctolgpError("1: not a PLY file (no 'ply' magic line)")
    fh.seek(0)
    fh.readline(_MAX_LINE)
    fmt: str | None = None
    origin: tuple[float, float, float] | None = None
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]] = []
    line_no = 1
    while True:
        line_no += 1
        tokens = _header_tokens(fh, line_no)
        if not tokens:
            continue
        key = tokens[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            if len(tokens) == 5 and tokens[1] == "origin":
                origin = _origin(tokens[2:], line_no)
        elif key == "format":
            if fmt is not None or len(tokens) != 3 or tokens[1] not in _FORMATS:
                raise OctolgpError(f"{line_no}: bad format line {' '.join(tokens)[:60]!r}")
            fmt = tokens[1]
        elif key == "element":
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise OctolgpError(f"{line_no}: bad element line {' '.join(tokens)[:60]!r}")
            if tokens[1] == "vertex":
                try:
                    limits.check_points(int(tokens[2]), "element vertex")
                except OctolgpError as exc:
                    raise OctolgpError(f"{line_no}: {exc}") from None
            elements.append((tokens[1], int(tokens[2]), []))
        elif key == "property":
            _add_property(elements, tokens, line_no)
        else:
            raise OctolgpError(f"{line_no}: unknown PLY header keyword {key[:40]!r}")
    if fmt is None:
        raise OctolgpError(f"{line_no}: no format line")
    elems = tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements)
    _check_vertex(elems, line_no)
    return PlyHeader(fmt, elems, origin, fh.tell(), line_no)


def _header_tokens(fh: IO[bytes], line_no: int) -> list[str]:
    """The words of header line ``line_no``, read from ``fh``; empty for a blank line.

    A header that ends (or runs past :data:`_MAX_HEADER_LINES`) before ``end_header``,
    or a line that is not ASCII, raises.
    """
    raw = fh.readline(_MAX_LINE)
    if not raw or line_no > _MAX_HEADER_LINES:
        raise OctolgpError(f"{line_no}: no end_header line")
    try:
        return raw.decode("ascii").split()
    except UnicodeDecodeError:
        raise OctolgpError(f"{line_no}: binary bytes in the header") from None


def _origin(words: list[str], line_no: int) -> tuple[float, float, float]:
    """The sensor origin ``X Y Z`` of a ``comment``/``obj_info origin X Y Z`` line, finite."""
    try:
        x, y, z = (float(t) for t in words)
    except ValueError:
        raise OctolgpError(f"{line_no}: non-numeric origin") from None
    if not all(map(math.isfinite, (x, y, z))):
        raise OctolgpError(f"{line_no}: non-finite origin")
    return (x, y, z)


def _add_property(
    elements: list[tuple[str, int, list[tuple[str, str, str | None]]]],
    tokens: list[str],
    line_no: int,
) -> None:
    """Append a ``property`` line to the last element as ``(name, type, list_count_type)``.

    A scalar property has no count type (``None``); a list property's type is that of
    its items.
    """
    if not elements:
        raise OctolgpError(f"{line_no}: property before any element")
    if len(tokens) == 3 and tokens[1] in _TYPES:
        elements[-1][2].append((tokens[2], tokens[1], None))
    elif len(tokens) == 5 and tokens[1] == "list" and {*tokens[2:4]} <= _TYPES.keys():
        elements[-1][2].append((tokens[4], tokens[3], tokens[2]))
    else:
        raise OctolgpError(f"{line_no}: bad property line {' '.join(tokens)[:60]!r}")


def _check_vertex(elems: tuple[PlyElement, ...], line_no: int) -> None:
    """Require one ``vertex`` element with one scalar ``x``, ``y`` and ``z`` property each."""
    vertex = [e for e in elems if e.name == "vertex"]
    if len(vertex) != 1:
        raise OctolgpError(f"{line_no}: needs one vertex element, found {len(vertex)}")
    names = [p[0] for p in vertex[0].properties]
    for axis in "xyz":
        if names.count(axis) != 1:
            raise OctolgpError(f"{line_no}: vertex needs one property {axis!r}")
    if any(p[2] is not None for p in vertex[0].properties):
        raise OctolgpError(f"{line_no}: vertex list properties are not supported")


def read_ply_header(path: str | Path) -> PlyHeader:
    """Read and validate the header of a PLY file.

    Raises
    ------
    OctolgpError
        On a malformed header (``PLY path:line: why``) or an unreadable file.
    """
    return read_header(path, _parse_header, "PLY")


def looks_like_ply(path: str | Path) -> bool:
    """Tell whether ``path`` starts with the ``ply`` magic line or is a directory of ``*.ply``."""
    p = Path(path)
    if p.is_dir():
        return has_cloud_files(p, ".ply")
    try:
        with open(p, "rb") as fh:
            return fh.read(4) in (b"ply\n", b"ply\r")
    except OSError:
        return False


def _check_sizes(fh: IO[bytes], header: PlyHeader, path: Path) -> None:
    """Refuse, before reading, elements up to ``vertex`` that cannot fit in the file.

    Each ASCII instance takes at least one byte, each binary one at least
    :meth:`PlyElement.min_record` bytes; the counts are checked against the bytes that
    follow the header, so a header claiming 10¹² instances fails at once.
    """
    here = fh.tell()
    follow = fh.seek(0, io.SEEK_END) - here
    fh.seek(here)
    need = 0
    for element in header.elements:
        per = 1 if header.format == "ascii" else max(element.min_record(), 1)
        need += element.count * per
        if need > follow:
            kind = "" if header.format == "ascii" else "binary "
            raise OctolgpError(
                f"PLY {path}: truncated {kind}data: element {element.name!r} claims "
                f"{element.count} instances (at least {per} bytes each), but the data hold "
                f"{follow} bytes"
            )
        if element.name == "vertex":
            return


def _skip_binary(fh: IO[bytes], element: PlyElement, order: str, path: Path) -> None:
    """Skip a binary element's instances (record by record if it has list properties)."""
    if all(p[2] is None for p in element.properties):
        size = element.dtype(order).itemsize * element.count
        start = fh.tell()
        if fh.seek(0, io.SEEK_END) - start < size:
            raise OctolgpError(f"PLY {path}: truncated in element {element.name!r}")
        fh.seek(start + size)
        return
    for i in range(element.count):
        for _, t, count_type in element.properties:
            width = np.dtype(_TYPES[t]).itemsize
            if count_type is not None:
                raw = fh.read(np.dtype(_TYPES[count_type]).itemsize)
                if not raw:
                    raise OctolgpError(f"PLY {path}: truncated in {element.name!r} {i}")
                n = int(np.frombuffer(raw, dtype=order + _TYPES[count_type])[0])
                width *= n
            if len(fh.read(width)) < width:
                raise OctolgpError(f"PLY {path}: truncated in {element.name!r} {i}")


class PlyReader(CloudReader):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over PLY files, one scan per file.

    Parameters
    ----------
    path : str or Path
        A ``.ply`` file, or a directory whose ``*.ply`` files are read in name order.
    origin : array_like of shape (3,), optional
        Sensor origin in the world frame (metres) for files whose header gives none; else
        ``(0, 0, 0)``. A ``comment origin X Y Z`` header line takes precedence.
    skip_bad : bool
        Skip and count malformed vertices and unreadable files instead of raising.
    max_range : float, optional
        Passed to each :class:`~octolgp.scan.Scan`, metres.

    Attributes
    ----------
    files : tuple of Path
        The files, in order.
    skipped, bad_lines, bad_scans
        See :class:`~octolgp.io.pointcloud.CloudReader`.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, on a bad ``origin`` or a directory without ``.ply`` files; while
        iterating, on a malformed file, naming it and the line (ASCII) or vertex index.
    """

    kind = "PLY"

    def __init__(
        self,
        path: str | Path,
        *,
        origin: Sequence[float] | np.ndarray | None = None,
        skip_bad: bool = False,
        max_range: float | None = None,
    ) -> None:
        super().__init__(path, skip_bad=skip_bad, max_range=max_range)
        if origin is None:
            self.origin: FloatArray = np.zeros(3)
        else:
            o = np.asarray(origin, dtype=np.float64)
            if o.shape != (3,) or not np.isfinite(o).all():
                raise OctolgpError(f"PlyReader.origin must be 3 finite numbers, got {origin!r}")
            self.origin = o
        self.files = list_cloud_files(self.path, ".ply", "PLY")

    def _generate(self) -> Generator[Scan, None, None]:
        yield from self._read_files(self.files)

    def _read_file(self, path: Path) -> Scan:
        header = read_ply_header(path)
        try:
            with open(path, "rb") as fh:
                fh.seek(header.data_offset)
                _check_sizes(fh, header, path)
                if header.format == "ascii":
                    blocks = self._read_ascii(fh, path, header)
                else:
                    blocks = self._read_binary(fh, path, header)
        except READ_ERRORS as exc:
            raise OctolgpError(f"PLY {path}: unreadable: {exc}") from None
        origin = self.origin if header.origin is None else np.array(header.origin)
        return self.make_scan(path, "", origin, blocks)

    def _read_ascii(self, fh: IO[bytes], path: Path, header: PlyHeader) -> list[FloatArray]:
        text = io.TextIOWrapper(fh, encoding="utf-8", errors="replace")
        try:
            return self._parse_text(text, path, header)
        finally:
            text.detach()  # the caller closes fh

    def _parse_text(self, text: IO[str], path: Path, header: PlyHeader) -> list[FloatArray]:
        line_no = header.header_lines + 1
        for element in header.elements:
            if element.name != "vertex":
                for chunk, first in read_exact_lines(text, element.count, path, line_no, "PLY"):
                    line_no = first + len(chunk)
                continue
            names = [p[0] for p in element.properties]
            xyz = [names.index(a) for a in "xyz"]
            blocks: list[FloatArray] = []
            for chunk, first in read_exact_lines(text, element.count, path, line_no, "PLY"):
                blocks += parse_ascii(self, chunk, path, first, ncols=len(names), xyz=xyz)
            # Values are what the declared type holds: float text becomes float32.
            f4 = [i for i, c in enumerate(xyz) if _TYPES[element.properties[c][1]] == "f4"]
            for block in blocks:
                block[:, f4] = block[:, f4].astype(np.float32)
            return blocks
        raise AssertionError("unreachable: the header has a vertex element")  # pragma: no cover

    def _read_binary(self, fh: IO[bytes], path: Path, header: PlyHeader) -> list[FloatArray]:
        order = _FORMATS[header.format]
        for element in header.elements:
            if element.name != "vertex":
                _skip_binary(fh, element, order, path)
                continue
            dtype = element.dtype(order)
            names = [p[0] for p in element.properties]
            fields = [f"p{names.index(a)}" for a in "xyz"]
            blocks: list[FloatArray] = []
            done = 0
            while done < element.count:
                k = min(CHUNK_POINTS, element.count - done)
                start = fh.tell()
                buf = fh.read(k * dtype.itemsize)
                if len(buf) < k * dtype.itemsize:
                    got = done + len(buf) // dtype.itemsize
                    raise OctolgpError(
                        f"PLY {path}: byte {start + len(buf)}: truncated binary data: "
                        f"{got} of {element.count} vertices"
                    )
                rec = np.frombuffer(buf, dtype=dtype)
                with np.errstate(invalid="ignore"):  # a signalling NaN; caught as NaN below
                    pts = np.stack([rec[f].astype(np.float64) for f in fields], axis=1)
                rows = np.flatnonzero(~np.isfinite(pts).all(axis=1))
                for r in rows:
                    self.bad_line(path, done + int(r), "NaN or inf in x/y/z", unit="vertex ")
                blocks.append(np.delete(pts, rows, axis=0) if rows.size else pts)
                done += k
            return blocks
        raise AssertionError("unreachable: the header has a vertex element")  # pragma: no cover


def read_ply(
    path: str | Path,
    *,
    origin: Sequence[float] | np.ndarray | None = None,
    skip_bad: bool = False,
    max_range: float | None = None,
) -> PlyReader:
    """Open PLY files as a stream of scans in the world frame; see :class:`PlyReader`."""
    return PlyReader(path, origin=origin, skip_bad=skip_bad, max_range=max_range)
