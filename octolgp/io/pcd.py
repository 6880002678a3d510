"""Streaming reader for PCD point clouds (Point Cloud Library), one file per scan.

Format (PCL ``doc/tutorials/content/pcd_file_format.rst``, ``io/src/pcd_io.cpp``): a text
header of ``VERSION``, ``FIELDS``, ``SIZE``, ``TYPE``, ``COUNT``, ``WIDTH``, ``HEIGHT``,
``VIEWPOINT``, ``POINTS`` and ``DATA`` lines (``#`` comments allowed), then the data:

- ``DATA ascii``: one point per line, the fields' values in header order (``COUNT`` values for a
  field with ``COUNT`` > 1).
- ``DATA binary``: ``WIDTH * HEIGHT`` packed little-endian records, fields in header order.
- ``DATA binary_compressed``: ``uint32 compressed_size``, ``uint32 uncompressed_size``, then an
  LZF block (liblzf's format) that holds the fields one after the other (all ``x``, then all
  ``y``, ...), padding fields named ``_`` left out. It is decompressed here in pure Python
  (:func:`lzf_decompress`), the whole block at once: about 0.5 s per 10 MB.

Size limits (:mod:`octolgp.io.limits`), checked from the header before the data are read:
``WIDTH * HEIGHT`` at most :data:`~octolgp.io.limits.MAX_SCAN_POINTS`; binary data no longer
than what follows the header; a compressed block no larger than what follows, inflating to
at most :data:`~octolgp.io.limits.MAX_DECOMPRESSED_BYTES` and at most
:data:`~octolgp.io.limits.LZF_MAX_RATIO` times its size.

Only the fields ``x``, ``y`` and ``z`` are read (any ``TYPE``/``SIZE``, ``COUNT`` 1); the others
are skipped. The points are in the sensor frame; ``VIEWPOINT tx ty tz qw qx qy qz`` (default
``0 0 0 1 0 0 0``) is the sensor pose in the world frame, so each point becomes
``R(q) p + t`` and the scan's origin is ``t`` (metres).

Invalid points: in an organised cloud (``HEIGHT`` > 1) a point with a NaN coordinate marks a
pixel without a return; it is dropped and counted in :attr:`PcdReader.dropped_nan`. Anywhere
else a NaN or inf coordinate is a malformed point (raised, or skipped with ``skip_bad``).
ASCII data is parsed a chunk of lines at a time and binary data a chunk of records at a time.
"""

from __future__ import annotations

import io
import math
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import IO

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.geometry.rotations import quaternion_to_matrix
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

__all__ = [
    "PcdHeader",
    "PcdReader",
    "looks_like_pcd",
    "lzf_decompress",
    "read_pcd",
    "read_pcd_header",
]

_KEYWORDS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
_TYPES = MappingProxyType(
    {("F", 4): "f4", ("F", 8): "f8"}
    | {(t, s): f"{t.lower()}{s}" for t in "IU" for s in (1, 2, 4, 8)}
)
_MAX_HEADER_LINES = 256
_MAX_LINE = 1 << 16


@dataclass(frozen=True)
class PcdHeader:
    """A parsed PCD header.

    Attributes
    ----------
    fields, sizes, types, counts : tuple
        ``FIELDS``, ``SIZE`` (bytes), ``TYPE`` (``F``/``I``/``U``) and ``COUNT``, in file order.
    width, height : int
        ``HEIGHT`` > 1 means an organised cloud.
    viewpoint : tuple of 7 float
        ``tx ty tz qw qx qy qz``: the sensor pose in the world frame (metres, quaternion).
    data : str
        ``ascii``, ``binary`` or ``binary_compressed``.
    data_offset : int
        Byte offset of the data; ``header_lines``: lines up to and including ``DATA``.
    """

    fields: tuple[str, ...]
    sizes: tuple[int, ...]
    types: tuple[str, ...]
    counts: tuple[int, ...]
    width: int
    height: int
    viewpoint: tuple[float, ...]
    data: str
    data_offset: int
    header_lines: int

    @property
    def points(self) -> int:
        """``WIDTH * HEIGHT``."""
        return self.width * self.height

    def dtype(self, skip_padding: bool = False) -> np.dtype[np.void]:
        """The packed little-endian record of one point (``_`` fields left out if asked)."""
        names, formats = [], []
        for i, (name, t, s, c) in enumerate(
            zip(self.fields, self.types, self.sizes, self.counts, strict=True)
        ):
            if skip_padding and name == "_":
                continue
            names.append(f"f{i}")
            formats.append((np.dtype("<" + _TYPES[t, s]), (c,)) if c > 1 else "<" + _TYPES[t, s])
        return np.dtype({"names": names, "formats": formats})

    def xyz_columns(self) -> list[int]:
        """Indices of ``x``, ``y``, ``z`` among the ASCII columns (fields expanded by COUNT)."""
        starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]])
        return [int(starts[self.fields.index(a)]) for a in "xyz"]


def _ints(tokens: list[str], key: str, lo: int) -> tuple[int, ...]:
    try:
        values = tuple(int(t) for t in tokens)
    except ValueError:
        raise OctolgpError(f"{key} must be integers, got {' '.join(tokens)!r}") from None
    if any(v < lo for v in values):
        raise OctolgpError(f"{key} values must be >= {lo}, got {' '.join(tokens)!r}")
    return values


def _parse_header(fh: IO[bytes]) -> PcdHeader:
    """Parse a header from the start of ``fh``; errors name the line, without the file."""
    entries, data, line_no, where = _header_entries(fh)
    try:
        for key in ("FIELDS", "SIZE", "TYPE", "WIDTH"):
            if key not in entries:
                raise OctolgpError(f"no {key} line")
        fields, sizes, types, counts = _field_layout(entries)
    except OctolgpError as exc:
        raise OctolgpError(f"{line_no}: {exc}") from None
    size_line = max(where.get(k, 0) for k in ("WIDTH", "HEIGHT", "POINTS"))
    try:
        width, height = _cloud_size(entries)
    except OctolgpError as exc:
        raise OctolgpError(f"{size_line}: {exc}") from None
    try:
        viewpoint = _viewpoint(entries)
    except OctolgpError as exc:
        raise OctolgpError(f"{where.get('VIEWPOINT', line_no)}: {exc}") from None
    return PcdHeader(
        fields, sizes, types, counts, width, height, viewpoint, data, fh.tell(), line_no
    )


def _header_entries(fh: IO[bytes]) -> tuple[dict[str, list[str]], str, int, dict[str, int]]:
    """Read the header lines up to ``DATA``: values, data kind, its line, each keyword's line.

    Comments and blank lines are skipped; an unknown or repeated keyword, binary bytes,
    an overlong line or a header without a valid ``DATA`` line raise with the line number.
    """
    entries: dict[str, list[str]] = {}
    where: dict[str, int] = {}
    line_no = 0
    while True:
        raw = fh.readline(_MAX_LINE)
        line_no += 1
        if not raw:
            raise OctolgpError(f"{line_no}: no DATA line (empty or truncated header)")
        if line_no > _MAX_HEADER_LINES or (not raw.endswith(b"\n") and len(raw) >= _MAX_LINE):
            raise OctolgpError(f"{line_no}: not a PCD header")
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            raise OctolgpError(f"{line_no}: not a PCD header (binary bytes)") from None
        tokens = text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        key = tokens[0].upper()
        if key == "DATA":
            break
        if key not in _KEYWORDS:
            raise OctolgpError(f"{line_no}: unknown PCD header keyword {tokens[0][:40]!r}")
        if key in entries:
            raise OctolgpError(f"{line_no}: repeated {key}")
        entries[key] = tokens[1:]
        where[key] = line_no
    data = tokens[1].lower() if len(tokens) == 2 else ""
    if data not in _DATA_KINDS:
        raise OctolgpError(f"{line_no}: DATA must be one of {_DATA_KINDS}, got {text.strip()!r}")
    return entries, data, line_no, where


def _field_layout(
    entries: dict[str, list[str]],
) -> tuple[tuple[str, ...], tuple[int, ...], tuple[str, ...], tuple[int, ...]]:
    """The ``FIELDS``, ``SIZE``, ``TYPE`` and ``COUNT`` of a point, checked against each other.

    Every field needs a supported type and size, and ``x``, ``y``, ``z`` must each appear
    once with ``COUNT 1``; ``COUNT`` defaults to 1 per field.
    """
    fields = tuple(entries["FIELDS"])
    n = len(fields)
    sizes = _ints(entries["SIZE"], "SIZE", 1)
    types = tuple(t.upper() for t in entries["TYPE"])
    counts = _ints(entries.get("COUNT", ["1"] * n), "COUNT", 1)
    if not n or not len(sizes) == len(types) == len(counts) == n:
        raise OctolgpError(f"FIELDS, SIZE, TYPE and COUNT need {n} entries each")
    for name, t, s in zip(fields, types, sizes, strict=True):
        if (t, s) not in _TYPES:
            raise OctolgpError(f"field {name!r}: unsupported TYPE {t} SIZE {s}")
    for axis in "xyz":
        if fields.count(axis) != 1 or counts[fields.index(axis)] != 1:
            raise OctolgpError(f"needs exactly one field {axis!r} with COUNT 1")
    return fields, sizes, types, counts


def _cloud_size(entries: dict[str, list[str]]) -> tuple[int, int]:
    """``WIDTH`` and ``HEIGHT`` (default 1), which ``POINTS``, when given, must multiply to.

    Neither may claim more than :data:`~octolgp.io.limits.MAX_SCAN_POINTS` points.
    """
    (width,) = _ints(entries["WIDTH"], "WIDTH", 0)
    (height,) = _ints(entries.get("HEIGHT", ["1"]), "HEIGHT", 1)
    if "POINTS" in entries:
        (points,) = _ints(entries["POINTS"], "POINTS", 0)
        limits.check_points(points, "POINTS")
        if points != width * height:
            raise OctolgpError(f"POINTS {points} != WIDTH * HEIGHT = {width * height}")
    limits.check_points(width * height, f"WIDTH * HEIGHT = {width} * {height}")
    return width, height


def _viewpoint(entries: dict[str, list[str]]) -> tuple[float, ...]:
    """``VIEWPOINT``: 7 finite numbers with a non-zero quaternion; the identity pose if absent."""
    vp = entries.get("VIEWPOINT", ["0", "0", "0", "1", "0", "0", "0"])
    try:
        viewpoint = tuple(float(v) for v in vp)
    except ValueError:
        raise OctolgpError(f"VIEWPOINT is not numeric: {' '.join(vp)!r}") from None
    if len(viewpoint) != 7 or not all(map(math.isfinite, viewpoint)):
        raise OctolgpError(f"VIEWPOINT needs 7 finite numbers, got {' '.join(vp)!r}")
    if not np.linalg.norm(viewpoint[3:]) > 0:
        raise OctolgpError("VIEWPOINT quaternion is zero")
    return viewpoint


def read_pcd_header(path: str | Path) -> PcdHeader:
    """Read and validate the header of a PCD file.

    Raises
    ------
    OctolgpError
        On a malformed header (``PCD path: header...: why``) or an unreadable file.
    """
    return read_header(path, _parse_header, "PCD")


def looks_like_pcd(path: str | Path) -> bool:
    """Tell whether ``path`` is a PCD file (a valid header) or a directory of ``*.pcd`` files."""
    p = Path(path)
    if p.is_dir():
        return has_cloud_files(p, ".pcd")
    if not p.is_file():
        return False
    try:
        read_pcd_header(p)
    except OctolgpError:
        return False
    return True


class _LzfError(Exception):
    """Corrupt LZF data; the reader adds the file and offset."""


def lzf_decompress(data: bytes, size: int) -> bytes:
    """Decompress liblzf data (``lzf_decompress``) that must expand to exactly ``size`` bytes.

    Raises
    ------
    OctolgpError
        On corrupt data: a run past the input, a back-reference before the start, or the
        wrong output length.
    """
    try:
        return bytes(_lzf(data, size))
    except _LzfError as exc:
        raise OctolgpError(f"corrupt LZF data: {exc}") from None


def _remaining(fh: IO[bytes]) -> int:
    """Bytes from the position of ``fh`` to the end of its file."""
    here = fh.tell()
    end = fh.seek(0, io.SEEK_END)
    fh.seek(here)
    return end - here


def _lzf(data: bytes, size: int) -> bytearray:
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            run = ctrl + 1
            if i + run > n:
                raise _LzfError(f"literal run past the end at byte {i - 1}")
            out += data[i : i + run]
            i += run
        else:  # back-reference: length code (3 bits), offset (13 bits)
            length = ctrl >> 5
            if length == 7:
                if i >= n:
                    raise _LzfError(f"truncated back-reference at byte {i - 1}")
                length += data[i]
                i += 1
            if i >= n:
                raise _LzfError(f"truncated back-reference at byte {i - 1}")
            dist = ((ctrl & 0x1F) << 8) + data[i] + 1
            i += 1
            length += 2
            ref = len(out) - dist
            if ref < 0:
                raise _LzfError(f"back-reference before the start at byte {i - 2}")
            if dist >= length:
                out += out[ref : ref + length]
            else:  # overlapping copy: repeat the last `dist` bytes
                pattern = bytes(out[ref:])
                out += (pattern * (length // dist + 1))[:length]
        if len(out) > size:
            raise _LzfError(f"expands past the stated {size} bytes")
    if len(out) != size:
        raise _LzfError(f"expands to {len(out)} bytes, not the stated {size}")
    return out


class PcdReader(CloudReader):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over PCD files, one scan per file.

    Parameters
    ----------
    path : str or Path
        A ``.pcd`` file, or a directory whose ``*.pcd`` files are read in name order.
    skip_bad : bool
        Skip and count malformed points (lines or records) and unreadable files (bad header,
        truncated data, no valid point) instead of raising.
    max_range : float, optional
        Passed to each :class:`~octolgp.scan.Scan`, metres.

    Attributes
    ----------
    files : tuple of Path
        The files, in order.
    dropped_nan : int
        Points of organised clouds dropped so far for a NaN coordinate (no return).
    skipped, bad_lines, bad_scans
        See :class:`~octolgp.io.pointcloud.CloudReader`.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, for a directory without ``.pcd`` files; while iterating, on a malformed
        file, naming it and the line (ASCII), point index (``path:point i``) or byte offset.
    """

    kind = "PCD"

    def __init__(
        self, path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
    ) -> None:
        self.dropped_nan = 0
        super().__init__(path, skip_bad=skip_bad, max_range=max_range)
        self.files = list_cloud_files(self.path, ".pcd", "PCD")

    def _generate(self) -> Generator[Scan, None, None]:
        yield from self._read_files(self.files)

    def _read_file(self, path: Path) -> Scan:
        header = read_pcd_header(path)
        organised = header.height > 1
        try:
            with open(path, "rb") as fh:
                fh.seek(header.data_offset)
                if header.data == "ascii":
                    blocks = self._read_ascii(fh, path, header, organised)
                elif header.data == "binary":
                    blocks = self._read_binary(fh, path, header, organised)
                else:
                    blocks = self._read_compressed(fh, path, header, organised)
        except READ_ERRORS as exc:
            raise OctolgpError(f"PCD {path}: unreadable: {exc}") from None
        kept = []
        for block in blocks:
            if organised:
                nan = np.isnan(block).any(axis=1)
                self.dropped_nan += int(np.count_nonzero(nan))
                block = block[~nan]
            kept.append(block)
        vp = header.viewpoint
        R = quaternion_to_matrix(vp[3:], order="wxyz")
        return self.make_scan(path, "", np.array(vp[:3]), kept, R)

    def _read_ascii(
        self, fh: IO[bytes], path: Path, header: PcdHeader, organised: bool
    ) -> list[FloatArray]:
        text = io.TextIOWrapper(fh, encoding="utf-8", errors="replace")
        try:
            return self._parse_text(text, path, header, organised)
        finally:
            text.detach()  # the caller closes fh

    def _parse_text(
        self, text: IO[str], path: Path, header: PcdHeader, organised: bool
    ) -> list[FloatArray]:
        ncols = sum(header.counts)
        blocks: list[FloatArray] = []
        start = header.header_lines + 1
        for chunk, line_no in read_exact_lines(text, header.points, path, start, "PCD"):
            blocks += parse_ascii(
                self,
                chunk,
                path,
                line_no,
                ncols=ncols,
                xyz=header.xyz_columns(),
                allow_nan=organised,
            )
        # Values are what the declared type holds: F 4 text becomes float32, as in PCL.
        f4 = [
            i
            for i, a in enumerate("xyz")
            if _TYPES[header.types[header.fields.index(a)], header.sizes[header.fields.index(a)]]
            == "f4"
        ]
        for block in blocks:
            block[:, f4] = block[:, f4].astype(np.float32)
        return blocks

    def _check_records(
        self, path: Path, xyz: FloatArray, first: int, organised: bool
    ) -> FloatArray:
        """Route non-finite binary points (NaN allowed when organised) to :meth:`bad_line`."""
        bad = np.isinf(xyz) if organised else ~np.isfinite(xyz)
        rows = np.flatnonzero(bad.any(axis=1))
        for r in rows:
            self.bad_line(path, first + int(r), "NaN or inf in x/y/z", unit="point ")
        return np.delete(xyz, rows, axis=0) if rows.size else xyz

    def _xyz(self, records: np.ndarray, header: PcdHeader) -> FloatArray:
        with np.errstate(invalid="ignore"):  # a signalling NaN in the file; caught as NaN
            cols = [records[f"f{header.fields.index(a)}"].astype(np.float64) for a in "xyz"]
        return np.stack(cols, axis=1)

    def _read_binary(
        self, fh: IO[bytes], path: Path, header: PcdHeader, organised: bool
    ) -> list[FloatArray]:
        dtype = header.dtype()
        need = header.points * dtype.itemsize
        follow = _remaining(fh)
        if need > follow:
            raise OctolgpError(
                f"PCD {path}: byte {header.data_offset}: truncated binary data: {header.points} "
                f"points need {need} bytes, {follow} follow the header"
            )
        blocks: list[FloatArray] = []
        done = 0
        while done < header.points:
            k = min(CHUNK_POINTS, header.points - done)
            buf = fh.read(k * dtype.itemsize)
            if len(buf) < k * dtype.itemsize:
                got = done + len(buf) // dtype.itemsize
                raise OctolgpError(
                    f"PCD {path}: byte {header.data_offset + done * dtype.itemsize + len(buf)}: "
                    f"truncated binary data: {got} of {header.points} points"
                )
            xyz = self._xyz(np.frombuffer(buf, dtype=dtype), header)
            blocks.append(self._check_records(path, xyz, done, organised))
            done += k
        return blocks

    def _read_compressed(
        self, fh: IO[bytes], path: Path, header: PcdHeader, organised: bool
    ) -> list[FloatArray]:
        sizes = fh.read(8)
        offset = header.data_offset
        if len(sizes) < 8:
            raise OctolgpError(f"PCD {path}: byte {offset}: truncated binary_compressed sizes")
        compressed, uncompressed = np.frombuffer(sizes, dtype="<u4").tolist()
        dtype = header.dtype(skip_padding=True)
        if uncompressed != header.points * dtype.itemsize:
            raise OctolgpError(
                f"PCD {path}: byte {offset + 4}: uncompressed size {uncompressed} != "
                f"{header.points} points x {dtype.itemsize} bytes"
            )
        follow = _remaining(fh)
        try:
            limits.check_bytes(uncompressed, "the LZF block")
        except OctolgpError as exc:
            raise OctolgpError(f"PCD {path}: byte {offset + 4}: {exc}") from None
        if compressed > follow:
            raise OctolgpError(
                f"PCD {path}: byte {offset}: truncated LZF block: its {compressed} bytes "
                f"are stated, {follow} follow"
            )
        if uncompressed > limits.LZF_MAX_RATIO * compressed:
            raise OctolgpError(
                f"PCD {path}: byte {offset}: corrupt LZF sizes: {compressed} bytes cannot "
                f"inflate to {uncompressed} (LZF inflates at most {limits.LZF_MAX_RATIO}-fold)"
            )
        data = fh.read(compressed)
        if len(data) < compressed:
            raise OctolgpError(
                f"PCD {path}: byte {offset + 8 + len(data)}: truncated LZF block "
                f"({len(data)} of {compressed} bytes)"
            )
        try:
            raw = _lzf(data, uncompressed)
        except _LzfError as exc:
            raise OctolgpError(f"PCD {path}: byte {offset + 8}: corrupt LZF data: {exc}") from None
        # The block holds each field for all points, one field after the other.
        n = header.points
        xyz = np.empty((n, 3))
        pos = 0
        for name, t, s, c in zip(
            header.fields, header.types, header.sizes, header.counts, strict=True
        ):
            if name == "_":
                continue
            if name in ("x", "y", "z"):
                values = np.frombuffer(raw, dtype="<" + _TYPES[t, s], count=n, offset=pos)
                with np.errstate(invalid="ignore"):  # a signalling NaN; caught as NaN
                    xyz[:, "xyz".index(name)] = values
            pos += s * c * n
        return [self._check_records(path, xyz, 0, organised)]


def read_pcd(
    path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
) -> PcdReader:
    """Open PCD files as a stream of scans in the world frame; see :class:`PcdReader`."""
    return PcdReader(path, skip_bad=skip_bad, max_range=max_range)
