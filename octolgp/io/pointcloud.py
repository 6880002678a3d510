"""Shared machinery of the point-cloud scan readers: PCD, PLY, OctoMap ``scan.dat`` and ``.graph``.

The readers themselves are in :mod:`octolgp.io.pcd`, :mod:`octolgp.io.ply` and
:mod:`octolgp.io.octomap_graph`; this module holds what they share:

- :class:`CloudReader`, the base of every reader: a one-pass iterator of
  :class:`~octolgp.scan.Scan` with the ``skip_bad`` policy. A malformed line or binary record is
  skipped and counted (``skipped``, ``bad_lines``); a malformed whole scan (bad header, truncated
  binary data, no points) is skipped and counted too (``skipped``, ``bad_scans``, with the
  message that would have been raised). Without ``skip_bad`` both raise :class:`OctolgpError`
  naming the file and the line, point or byte offset.
- :func:`parse_ascii`, which parses ``x y z``-style lines with one :func:`numpy.loadtxt` call per
  chunk and bisects a failing chunk down to its malformed lines.

The readers' rotations (quaternions, OctoMap's roll/pitch/yaw) are in
:mod:`octolgp.geometry.rotations`.
"""

from __future__ import annotations

import bz2
import gzip
import itertools
import logging
import lzma
import math
import warnings
import zlib
from collections.abc import Callable, Generator, Iterable, Iterator
from pathlib import Path
from typing import IO, ClassVar, TypeVar

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io.base import ScanStream
from octolgp.scan import FloatArray, Scan

__all__ = [
    "CloudReader",
    "has_cloud_files",
    "list_cloud_files",
    "open_text",
    "parse_ascii",
    "read_exact_lines",
    "read_header",
]

logger = logging.getLogger(__name__)

H = TypeVar("H")

CHUNK_LINES = 1 << 16
"""Text lines parsed per :func:`numpy.loadtxt` call."""
CHUNK_POINTS = 1 << 16
"""Binary records decoded per read."""
READ_ERRORS = (OSError, EOFError, lzma.LZMAError, zlib.error)
_DIAGNOSE_LINES = 32  # a failing block this small is checked line by line


def open_text(path: Path) -> IO[str]:
    """Open a text file, decompressing xz, gzip or bzip2 by its magic bytes."""
    with open(path, "rb") as fh:
        magic = fh.read(6)
    if magic.startswith(b"\xfd7zXZ\x00"):
        return lzma.open(path, "rt", encoding="utf-8", errors="replace")
    if magic.startswith(b"\x1f\x8b"):
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    if magic.startswith(b"BZh"):
        return bz2.open(path, "rt", encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def has_cloud_files(path: Path, suffix: str) -> bool:
    """Whether ``path`` is a directory holding at least one ``*suffix`` file (any case)."""
    return path.is_dir() and any(f.suffix.lower() == suffix and f.is_file() for f in path.iterdir())


def read_header(path: str | Path, parse: Callable[[IO[bytes]], H], what: str) -> H:
    """Parse a file's header with ``parse``; errors name the format ``what`` and the file.

    Raises
    ------
    OctolgpError
        On an unreadable file (``what path: unreadable: ...``) or a malformed header
        (``what path:<where parse says>``).
    """
    try:
        with open(path, "rb") as fh:
            return parse(fh)
    except OSError as exc:
        raise OctolgpError(f"{what} {path}: unreadable: {exc}") from None
    except OctolgpError as exc:
        raise OctolgpError(f"{what} {path}:{exc}") from None


def list_cloud_files(path: Path, suffix: str, what: str) -> tuple[Path, ...]:
    """One file, or a directory's ``*suffix`` files (case-insensitive) sorted by name."""
    if path.is_file():
        return (path,)
    if path.is_dir():
        files = sorted(
            (f for f in path.iterdir() if f.is_file() and f.suffix.lower() == suffix),
            key=lambda f: f.name,
        )
        if not files:
            raise OctolgpError(f"{what} scans: no {suffix} files in {str(path)!r}")
        return tuple(files)
    raise OctolgpError(f"{what} scans: {str(path)!r} is neither a file nor a directory")


def _parse_block(
    lines: list[str], ncols: int, xyz: list[int], allow_nan: bool, comments: str | None
) -> FloatArray | None:
    """Parse lines in one call, keep the ``xyz`` columns; ``None`` if any line is malformed."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            arr = np.loadtxt(lines, dtype=np.float64, comments=comments, ndmin=2)
    except ValueError:
        return None
    if arr.size == 0:
        return np.empty((0, 3))
    if arr.shape[1] != ncols:
        return None
    pts = arr[:, xyz]
    if (np.isinf(pts) if allow_nan else ~np.isfinite(pts)).any():
        return None
    return pts


def _line_error(line: str, ncols: int, allow_nan: bool, comments: str | None) -> str:
    """Say what is wrong with a line that :func:`_parse_block` rejects."""
    text = line.split(comments, 1)[0] if comments else line
    tokens = text.split()
    if len(tokens) != ncols:
        return f"expected {ncols} numbers, got {len(tokens)} fields in {line.strip()[:80]!r}"
    try:
        [float(t) for t in tokens]
    except ValueError:
        return f"non-numeric value in {line.strip()[:80]!r}"
    return "inf in x/y/z" if allow_nan else "NaN or inf in x/y/z"


def parse_ascii(
    reader: CloudReader,
    lines: list[str],
    path: Path,
    start: int,
    *,
    ncols: int,
    xyz: list[int],
    allow_nan: bool = False,
    comments: str | None = None,
) -> list[FloatArray]:
    """Parse data lines whose first is line ``start`` (1-based) into ``(k, 3)`` x/y/z blocks.

    A malformed line (wrong field count, non-numeric, non-finite x/y/z; NaN is allowed with
    ``allow_nan``) goes to :meth:`CloudReader.bad_line`: raised, or skipped and counted. Blank
    lines, and comment lines with ``comments``, yield nothing. Chunks that fail are bisected, so
    only bad input is parsed line by line.
    """
    out: list[FloatArray] = []
    stack = [(0, len(lines))]
    while stack:  # in order: the first malformed line is the first one found
        lo, hi = stack.pop()
        pts = _parse_block(lines[lo:hi], ncols, xyz, allow_nan, comments)
        if pts is not None:
            if len(pts):
                out.append(pts)
        elif hi - lo > _DIAGNOSE_LINES:
            mid = (lo + hi) // 2
            stack += [(mid, hi), (lo, mid)]
        else:
            for i in range(lo, hi):
                pts = _parse_block(lines[i : i + 1], ncols, xyz, allow_nan, comments)
                if pts is not None:
                    if len(pts):
                        out.append(pts)
                else:
                    why = _line_error(lines[i], ncols, allow_nan, comments)
                    reader.bad_line(path, start + i, why)
    return out


def read_exact_lines(
    fh: IO[str], n: int, path: Path, start: int, what: str
) -> Iterator[tuple[list[str], int]]:
    """Yield ``(chunk, first_line_number)`` holding exactly ``n`` non-blank lines in all.

    Raises
    ------
    OctolgpError
        If the file ends first (message: ``what path:line: truncated``).
    """
    found = 0
    line_no = start
    while found < n:
        chunk = list(itertools.islice(fh, min(n - found, CHUNK_LINES)))
        if not chunk:
            raise OctolgpError(
                f"{what} {path}:{line_no}: truncated: expected {n} data lines, found {found}"
            )
        yield chunk, line_no
        found += sum(1 for line in chunk if line.strip())
        line_no += len(chunk)


class CloudReader(ScanStream):
    """Base of the point-cloud readers: a one-pass iterator of :class:`~octolgp.scan.Scan`.

    Parameters
    ----------
    path : str or Path
        The file or directory to read.
    skip_bad : bool
        Skip and count malformed lines, records and scans instead of raising.
    max_range : float, optional
        Passed to every :class:`~octolgp.scan.Scan` (metres; a beam at least this long is a
        no-return); ``None`` when the cloud holds hits only.

    Attributes
    ----------
    skipped : int
        Malformed lines, binary records and whole scans skipped so far (``skip_bad=True``).
    bad_lines : list of (Path, int)
        The skipped lines and records: 1-based line number in text data, 0-based point index in
        binary data.
    bad_scans : list of str
        One message per skipped whole scan (bad header, truncated data, no points...).
    """

    kind: ClassVar[str] = "point cloud"
    single_file: ClassVar[bool] = False
    """Readers of one file (not a directory) set this: a directory is then refused."""

    def __init__(self, path: str | Path, *, skip_bad: bool, max_range: float | None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise MapFileNotFound(f"{self.kind} {str(self.path)!r} does not exist")
        if self.single_file and not self.path.is_file():
            raise OctolgpError(f"{self.kind} {str(self.path)!r} is not a file")
        if max_range is not None and (
            isinstance(max_range, bool)
            or not isinstance(max_range, int | float | np.floating | np.integer)
            or not (math.isfinite(max_range) and max_range > 0)
        ):
            raise OctolgpError(
                f"{type(self).__name__}.max_range must be finite and > 0, got {max_range!r}"
            )
        self.max_range = None if max_range is None else float(max_range)
        self.skip_bad = skip_bad
        self.skipped = 0
        self.bad_lines: list[tuple[Path, int]] = []
        self.bad_scans: list[str] = []
        self._scans = self._generate()

    def _generate(self) -> Generator[Scan, None, None]:  # pragma: no cover - abstract
        raise NotImplementedError
        yield

    def bad_line(self, path: Path, where: int, why: str, unit: str = "") -> None:
        """Raise, or count and skip (``skip_bad``), a malformed line or record at ``where``."""
        if not self.skip_bad:
            raise OctolgpError(f"{self.kind} {path}:{unit}{where}: {why}")
        self.skipped += 1
        self.bad_lines.append((path, where))
        logger.info("%s %s:%s%d: skipped: %s", self.kind, path, unit, where, why)

    def bad_scan(self, exc: OctolgpError) -> None:
        """Raise, or count and skip (``skip_bad``), a whole malformed scan."""
        if not self.skip_bad:
            raise exc
        self.skipped += 1
        self.bad_scans.append(str(exc))
        logger.info("skipped a scan: %s", exc)

    def _read_files(self, files: Iterable[Path]) -> Generator[Scan, None, None]:
        """One scan per file (:meth:`_read_file`); a file that fails goes to :meth:`bad_scan`."""
        for path in files:  # one iteration per file
            try:
                scan = self._read_file(path)
            except OctolgpError as exc:
                self.bad_scan(exc)
                continue
            yield scan

    def _read_file(self, path: Path) -> Scan:  # pragma: no cover - per-file readers override
        """Read one file as one scan (readers of one scan per file override this)."""
        raise NotImplementedError

    def make_scan(
        self,
        path: Path,
        where: str,
        origin: FloatArray,
        blocks: list[FloatArray],
        rotation: FloatArray | None = None,
    ) -> Scan:
        """Join point blocks into a scan; with ``rotation``, they are in the sensor frame.

        Sensor-frame points become ``rotation @ p + origin``; without ``rotation`` the points
        are already in the world frame.

        Raises
        ------
        OctolgpError
            If there is no point (``path: where: no points``).
        """
        if len(blocks) == 1:
            points = blocks[0]  # the scan copies it; no second copy here
        else:
            points = np.concatenate(blocks) if blocks else np.empty((0, 3))
        if not points.shape[0]:
            raise OctolgpError(f"{self.kind} {path}{where}: no points")
        if rotation is not None:
            if not np.array_equal(rotation, np.eye(3)):
                points = points @ rotation.T
            if origin.any():
                points = points + origin
        return Scan(origin.copy(), points, self.max_range, rotation=rotation)
