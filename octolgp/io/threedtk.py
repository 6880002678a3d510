"""Streaming reader for 3DTK scans: ``scanNNN.3d`` points with their ``.pose``/``.frames``.

The format is 3DTK's "uos" format; the frames and poses are in :mod:`octolgp.io.threedtk_pose`.

- ``scanNNN.3d``: one point ``x y z`` per line, centimetres, in the scanner's left-handed frame
  (x right, y up, z forward); the sensor is at the origin. Files written before 2019 start with a
  ``W x H`` header line (``360 x 225``), which is skipped. Plain, xz, gzip or bzip2, chosen by
  the magic bytes (``scanNNN.3d.xz`` etc.).
- Each scan becomes a :class:`~octolgp.scan.Scan` in octolgp's world frame (right-handed,
  metres): points ``C (R p + t) / 100``, origin ``C t / 100``, ``C`` =
  :data:`~octolgp.io.threedtk_pose.LH_TO_RH`.
- Invalid points, as ``data/3dtk_example_scans/README.md`` defines them: a point nearer than
  ``min_range`` (0.20 m) is near-field noise and is dropped; a point at ``max_range`` (32.70 m)
  or beyond is a no-return (the example scans write them at 32.76-32.77 m) and is kept, with
  :attr:`Scan.max_range` set.

Points are parsed with :func:`numpy.loadtxt` a chunk of lines at a time; a chunk that fails is
bisected down to a few lines to name the malformed one, so only bad input is parsed line by line.
"""

from __future__ import annotations

import logging
import math
import re
import warnings
from collections.abc import Generator
from pathlib import Path
from typing import IO

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import limits
from octolgp.io.base import ScanStream
from octolgp.io.limits import LineTooLongError, read_lines, skip_line_rest
from octolgp.io.pointcloud import READ_ERRORS, open_text
from octolgp.io.threedtk_pose import CM, LH_TO_RH, read_frames, read_pose
from octolgp.scan import FloatArray, Scan

__all__ = ["MIN_RANGE", "NO_RETURN_RANGE", "ThreeDTKReader", "looks_like_3dtk", "read_3dtk"]

logger = logging.getLogger(__name__)

MIN_RANGE = 0.20
"""Metres; nearer points are near-field noise (data README)."""

NO_RETURN_RANGE = 32.70
"""Metres; points at least this far are no-returns (data README: 32.76-32.77 m readings)."""

_SCAN_NAME = re.compile(r"scan(\d+)\.3d(?:\.(?:xz|gz|bz2))?")
_POINT_FILE = re.compile(r"(.+)\.3d(?:\.(?:xz|gz|bz2))?", re.IGNORECASE)
_LEGACY_HEADER = re.compile(r"\s*\d+\s*x\s*\d+\s*")
_CHUNK_BYTES = 1 << 22  # about this many bytes of lines per np.loadtxt call
_DIAGNOSE_LINES = 32  # a failing block this small is checked line by line


def looks_like_3dtk(path: str | Path) -> bool:
    """Tell whether ``path`` is a ``*.3d[.xz|.gz|.bz2]`` file or a directory of ``scanNNN.3d*``."""
    p = Path(path)
    if p.is_dir():
        return any(_SCAN_NAME.fullmatch(f.name) and f.is_file() for f in p.iterdir())
    return p.is_file() and _POINT_FILE.fullmatch(p.name) is not None


def _stem(path: Path) -> str:
    """``scan001`` for ``scan001.3d.xz``: the name its ``.pose``/``.frames`` share."""
    match = _POINT_FILE.fullmatch(path.name)
    return match[1] if match else path.name


def _parse_block(lines: list[str]) -> FloatArray | None:
    """Parse lines of ``x y z`` in one vectorised call; ``None`` if any line is malformed."""
    if not "".join(lines).strip():
        return np.empty((0, 3))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data"
            xyz = np.loadtxt(lines, dtype=np.float64, comments=None, ndmin=2)
    except ValueError:
        return None
    if xyz.shape[1] != 3 or not np.isfinite(xyz).all():
        return None
    return xyz


def _line_error(line: str) -> str:
    """Say what is wrong with a point line that :func:`_parse_block` rejects."""
    tokens = line.split()
    if len(tokens) != 3:
        return f"expected 3 numbers 'x y z', got {len(tokens)} fields"
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        return f"non-numeric value in {line.strip()!r}"
    return f"cannot parse {line.strip()!r}" if all(map(math.isfinite, values)) else "NaN or inf"


class ThreeDTKReader(ScanStream):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over 3DTK scans, in scan-number order.

    Parameters
    ----------
    path : str or Path
        A directory of ``scanNNN.3d`` files (``.xz``/``.gz``/``.bz2`` too) with their
        ``scanNNN.pose``/``scanNNN.frames``, or one such point file.
    first, last : int, optional
        Read only scans numbered ``first..last`` (inclusive, as 3DTK's ``-s``/``-e``).
    pose : {"frames", "pose"}
        Take each pose from the last line of ``.frames`` (the registered pose) or from ``.pose``.
    skip_bad : bool
        Skip and count malformed point lines instead of raising. Pose files are always strict.
    max_range : float, optional
        No-return range, metres; :data:`NO_RETURN_RANGE` when ``None``; ``math.inf`` for none.
    min_range : float
        Points nearer to the sensor than this (metres) are dropped.

    Attributes
    ----------
    files : tuple of Path
        The point files, in order.
    transforms : ndarray of shape (n, 4, 4)
        ``T_world_scan`` per file in octolgp's frame (metres); the origin is ``T[:3, 3]``.
    skipped : int
        Malformed point lines skipped so far; ``bad_lines`` holds their ``(file, line)``.
    near_field : int
        Points dropped so far as nearer than ``min_range``.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` or a needed pose file does not exist.
    OctolgpError
        At construction, on bad arguments, no matching scans or a malformed pose file; while
        iterating, on an unreadable stream or a malformed point line (``file:line: why``), or a
        scan with no point beyond ``min_range``.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        first: int | None = None,
        last: int | None = None,
        pose: str = "frames",
        skip_bad: bool = False,
        max_range: float | None = None,
        min_range: float = MIN_RANGE,
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise MapFileNotFound(f"3DTK scans {str(self.path)!r} do not exist")
        if pose not in ("frames", "pose"):
            raise OctolgpError(f"read_3dtk: pose must be 'frames' or 'pose', got {pose!r}")
        for name, value in (("first", first), ("last", last)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
                raise OctolgpError(f"read_3dtk: {name} must be an int, got {value!r}")
        self.max_range = NO_RETURN_RANGE if max_range is None else float(max_range)
        if not (self.max_range > 0 and 0 <= min_range < self.max_range):
            raise OctolgpError(
                f"read_3dtk: need 0 <= min_range < max_range, got {min_range!r}, {max_range!r}"
            )
        self.min_range = float(min_range)
        self.skip_bad = skip_bad
        self.skipped = 0
        self.bad_lines: list[tuple[Path, int]] = []
        self.near_field = 0
        self.files = self._discover(first, last)
        stems = [f.with_name(_stem(f)) for f in self.files]
        if pose == "frames":
            transforms = [read_frames(s.with_name(s.name + ".frames"))[-1] for s in stems]
        else:
            transforms = [read_pose(s.with_name(s.name + ".pose")) for s in stems]
        self.transforms: FloatArray = np.stack(transforms)
        self._scans = self._generate()

    def _discover(self, first: int | None, last: int | None) -> tuple[Path, ...]:
        """List the point files numbered ``first..last`` (inclusive), in scan-number order."""
        lo = -math.inf if first is None else first
        hi = math.inf if last is None else last
        if self.path.is_file():
            if not _POINT_FILE.fullmatch(self.path.name):
                raise OctolgpError(
                    f"3DTK scans: {str(self.path)!r} is not a .3d[.xz|.gz|.bz2] file"
                )
            match = _SCAN_NAME.fullmatch(self.path.name)
            if match and not lo <= int(match[1]) <= hi:
                raise OctolgpError(f"3DTK scans: {str(self.path)!r} is not in {first}..{last}")
            return (self.path,)
        found: dict[int, Path] = {}
        for f in self.path.iterdir():
            match = _SCAN_NAME.fullmatch(f.name)
            if match and f.is_file():
                n = int(match[1])
                if n in found:
                    raise OctolgpError(f"3DTK scans: both {found[n]} and {f} are scan {n}")
                found[n] = f
        files = tuple(found[n] for n in sorted(found) if lo <= n <= hi)
        if not files:
            raise OctolgpError(
                f"3DTK scans: no scanNNN.3d files numbered {first}..{last} in {str(self.path)!r}"
            )
        return files

    def _parse(self, lines: list[str], path: Path, start: int) -> list[FloatArray]:
        """Parse a chunk whose first line is number ``start``; bisect to find malformed lines."""
        out: list[FloatArray] = []
        stack = [(0, len(lines))]
        while stack:  # in-order: the first malformed line is the first one found
            lo, hi = stack.pop()
            xyz = _parse_block(lines[lo:hi])
            if xyz is not None:
                out.append(xyz)
            elif hi - lo > _DIAGNOSE_LINES:
                mid = (lo + hi) // 2
                stack += [(mid, hi), (lo, mid)]
            else:  # a small block: find the malformed lines one by one
                for i in range(lo, hi):
                    xyz = _parse_block(lines[i : i + 1])
                    if xyz is not None:
                        out.append(xyz)
                    elif not self.skip_bad:
                        raise OctolgpError(f"3DTK scan {path}:{start + i}: {_line_error(lines[i])}")
                    else:
                        self.skipped += 1
                        self.bad_lines.append((path, start + i))
                        logger.info(
                            "3DTK scan %s:%d: skipped: %s", path, start + i, _line_error(lines[i])
                        )
        return out

    def _read_points(self, path: Path) -> FloatArray:
        """Read a point file in the scanner frame, centimetres, shape (n, 3).

        Lines are at most :data:`~octolgp.io.limits.MAX_LINE_LENGTH` characters (a longer one
        is malformed) and the file at most :data:`~octolgp.io.limits.MAX_SCAN_POINTS`
        points, checked as it is read, so a small compressed file cannot inflate without
        bound.
        """
        blocks: list[FloatArray] = []
        line_no = total = 0
        try:
            with open_text(path) as fh:
                while True:
                    long_line: LineTooLongError | None = None
                    try:
                        chunk = read_lines(fh, _CHUNK_BYTES)
                    except LineTooLongError as exc:
                        chunk, long_line = exc.before, exc
                    if not chunk and long_line is None:
                        break
                    if chunk:
                        if line_no == 0 and _LEGACY_HEADER.fullmatch(chunk[0]):
                            chunk[0] = "\n"  # pre-2019 "360 x 225" header
                        new = self._parse(chunk, path, line_no + 1)
                        blocks += new
                        line_no += len(chunk)
                        total += sum(len(b) for b in new)
                        limits.check_points(total, f"3DTK scan {path}:{line_no}:", claimed=False)
                    if long_line is not None:
                        line_no += 1
                        self._long_line(fh, path, line_no, long_line)
        except READ_ERRORS as exc:
            raise OctolgpError(f"3DTK scan {path}:{line_no + 1}: unreadable: {exc}") from None
        return np.concatenate(blocks) if blocks else np.empty((0, 3))

    def _long_line(self, fh: IO[str], path: Path, line_no: int, exc: LineTooLongError) -> None:
        """Raise at an overlong line, or skip the rest of it and count it with ``skip_bad``."""
        if not self.skip_bad:
            raise OctolgpError(f"3DTK scan {path}:{line_no}: {exc}")
        self.skipped += 1
        self.bad_lines.append((path, line_no))
        logger.info("3DTK scan %s:%d: skipped: %s", path, line_no, exc)
        if not exc.ended:
            skip_line_rest(fh)

    def _generate(self) -> Generator[Scan, None, None]:
        """Read, filter and transform one scan at a time."""
        for path, T in zip(self.files, self.transforms, strict=True):
            xyz = self._read_points(path)
            if not xyz.size:
                raise OctolgpError(f"3DTK scan {path}: no points")
            r = np.linalg.norm(xyz, axis=1) * CM
            keep = r >= self.min_range
            self.near_field += int(keep.size - np.count_nonzero(keep))
            if not keep.any():
                raise OctolgpError(f"3DTK scan {path}: no point at or beyond {self.min_range} m")
            # world = C (R p + t) / 100 = R_rh (C p / 100) + t_rh
            M = T[:3, :3] @ LH_TO_RH * CM
            points = xyz[keep] @ M.T + T[:3, 3]
            max_range = self.max_range if math.isfinite(self.max_range) else None
            yield Scan(T[:3, 3].copy(), points, max_range, rotation=T[:3, :3])


def read_3dtk(
    path: str | Path,
    *,
    first: int | None = None,
    last: int | None = None,
    pose: str = "frames",
    skip_bad: bool = False,
    max_range: float | None = None,
    min_range: float = MIN_RANGE,
) -> ThreeDTKReader:
    """Open 3DTK scans as a stream of scans in the world frame; see :class:`ThreeDTKReader`."""
    return ThreeDTKReader(
        path,
        first=first,
        last=last,
        pose=pose,
        skip_bad=skip_bad,
        max_range=max_range,
        min_range=min_range,
    )
