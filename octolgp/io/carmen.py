"""Streaming reader for CARMEN text logs (``.log``/``.clf``, plain or gzip).

Two laser messages are read, every other message type is ignored:

- ``FLASER n r_0 .. r_{n-1} x y theta odom_x odom_y odom_theta timestamp host logger_ts``.
  ``x y theta`` is the laser pose in the world frame (metres, radians CCW). Beam
  ``i`` points at ``theta - pi/2 + i * pi / n`` for ``n`` in {180, 360} (1° or
  0.5° steps, -90° included, +90° not: verified on the Intel and FR079 logs) and
  at ``theta - pi/2 + i * pi / (n - 1)`` for every other ``n`` (a 180° fan that
  includes both ends, as for 181 or 361 beams).
- ``ROBOTLASER1 type start_angle fov angular_res max_range accuracy remission_mode
  n r_0 .. r_{n-1} m rem_0 .. rem_{m-1} laser_x laser_y laser_theta robot_x robot_y
  robot_theta tv rv forward_safety side_safety turn_axis timestamp host logger_ts``.
  Beam ``i`` points at ``laser_theta + start_angle + i * angular_res``.

No-return: a reading at the log's maximum value means the beam hit nothing. That
value comes from, in order: the ``max_range`` argument; for ``ROBOTLASER1`` its own
``max_range`` field; a ``PARAM robot_front_laser_max`` line; otherwise it is
detected as the largest reading of the first 200 laser scans when that value occurs
in at least 5 beams (81.83 in the Intel log, 81.91 in FR079), else there is none.
:attr:`Scan.max_range` is set :data:`NO_RETURN_MARGIN` below it so that round-off
never turns a no-return into a hit.

The file is read line by line, each line at most
:data:`~octolgp.io.limits.MAX_LINE_LENGTH` characters (a longer one is malformed: raised
naming the file and line, or skipped with ``skip_bad``, never held whole); only the first
200 scans are held while the no-return value is detected.
"""

from __future__ import annotations

import functools
import gzip
import logging
import re
import zlib
from collections.abc import Generator
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import IO

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io import limits
from octolgp.io.base import ScanStream
from octolgp.io.limits import LineTooLongError, read_line, skip_line_rest
from octolgp.scan import FloatArray, Scan

__all__ = ["NO_RETURN_MARGIN", "CarmenReader", "beam_angles", "looks_like_carmen", "read_carmen"]

logger = logging.getLogger(__name__)

NO_RETURN_MARGIN = 1e-3
"""Metres that :attr:`Scan.max_range` is set below a log's no-return reading."""

DETECT_SCANS = 200
DETECT_MIN_REPEATS = 5
_MAX_RANGE_PARAMS = frozenset({"robot_front_laser_max"})
_MESSAGE_NAME = re.compile(r"[A-Z][A-Z0-9_]*")
_SNIFF_LINES = 1000
_READ_ERRORS = (OSError, EOFError, zlib.error)


class _BadLineError(Exception):
    """A malformed laser line; the reader adds the file name and line number."""


@functools.lru_cache(maxsize=16)
def beam_angles(n: int) -> FloatArray:
    """Return the FLASER beam angles in the laser frame, radians CCW, shape (n,).

    ``-pi/2 + i*pi/n`` for ``n`` in {180, 360}, else ``-pi/2 + i*pi/(n-1)``
    (both fan ends included; a single beam points straight ahead).
    """
    angles: FloatArray = np.zeros(1)
    if n > 1:
        step = np.pi / n if n in (180, 360) else np.pi / (n - 1)
        angles = -np.pi / 2 + step * np.arange(n, dtype=np.float64)
    angles.setflags(write=False)
    return angles


@dataclass(frozen=True, slots=True)
class _Record:
    """One parsed laser line, before the no-return value is known."""

    pose: FloatArray  # (3,) laser x, y, theta in the world frame
    ranges: FloatArray  # (n,) metres
    angles: FloatArray  # (n,) laser frame, radians
    stamp: float
    inline_max: float | None  # ROBOTLASER1's own maximum range


def _floats(tokens: list[str], what: str) -> FloatArray:
    """Parse tokens as finite floats or raise :class:`_BadLineError`."""
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError as exc:
        raise _BadLineError(f"non-numeric {what}: {exc}") from None
    if not np.isfinite(values).all():
        raise _BadLineError(f"NaN or inf in {what}")
    return values


def _count(token: str, what: str) -> int:
    """Parse a reading count (an integer >= 1, or >= 0 for remissions)."""
    try:
        n = int(token)
    except ValueError:
        raise _BadLineError(f"{what} {token!r} is not an integer") from None
    if n < (0 if what == "remission count" else 1):
        raise _BadLineError(f"{what} must be positive, got {n}")
    return n


def _parse_flaser(tokens: list[str]) -> _Record:
    """Parse the tokens of a FLASER line."""
    if len(tokens) < 2:
        raise _BadLineError("FLASER line has no beam count")
    n = _count(tokens[1], "beam count")
    if len(tokens) != n + 11:
        raise _BadLineError(f"FLASER with {n} beams needs {n + 11} tokens, got {len(tokens)}")
    values = _floats(tokens[2 : n + 9], "FLASER ranges/pose/timestamp")
    ranges = values[:n]
    if (ranges < 0).any():
        raise _BadLineError("negative range")
    return _Record(values[n : n + 3], ranges, beam_angles(n), float(values[n + 6]), None)


def _parse_robotlaser(tokens: list[str]) -> _Record:
    """Parse the tokens of a ROBOTLASER1 line."""
    if len(tokens) < 10:
        raise _BadLineError(f"ROBOTLASER1 line is truncated ({len(tokens)} tokens)")
    n = _count(tokens[8], "beam count")
    if len(tokens) < n + 10:
        raise _BadLineError(f"ROBOTLASER1 with {n} beams is truncated ({len(tokens)} tokens)")
    m = _count(tokens[n + 9], "remission count")
    if len(tokens) != n + m + 24:
        raise _BadLineError(f"ROBOTLASER1 with {n}+{m} readings needs {n + m + 24} tokens")
    head = _floats(tokens[2:6], "ROBOTLASER1 header")
    ranges = _floats(tokens[9 : 9 + n], "ROBOTLASER1 ranges")
    tail = _floats(tokens[n + m + 10 : n + m + 22], "ROBOTLASER1 poses/timestamp")
    if (ranges < 0).any():
        raise _BadLineError("negative range")
    angles = head[0] + head[2] * np.arange(n)
    inline_max = float(head[3]) if head[3] > 0 else None
    return _Record(tail[0:3], ranges, angles, float(tail[11]), inline_max)


_PARSERS = MappingProxyType({"FLASER": _parse_flaser, "ROBOTLASER1": _parse_robotlaser})


def count_laser_lines(path: str | Path) -> int:
    """Laser lines (``FLASER``, ``ROBOTLASER1``) of a CARMEN log: its scans, read or not.

    A quick pass over the text (for a progress total); the reader yields one scan per
    such line, but for malformed ones it skips or refuses.
    """
    with _open_text(Path(path)) as fh:
        return sum(1 for line in fh if line.split(maxsplit=1)[:1] in (["FLASER"], ["ROBOTLASER1"]))


def _open_text(path: Path) -> IO[str]:
    """Open a log as text, gunzipping when it starts with the gzip magic bytes."""
    with open(path, "rb") as fh:
        magic = fh.read(2)
    if magic == b"\x1f\x8b":
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


def looks_like_carmen(path: str | Path) -> bool:
    """Tell whether a file reads as a CARMEN log: its first message is an upper-case name.

    Comment lines (``#``) and blank lines are skipped; a file of only those passes.
    Unreadable files (a corrupt gzip stream, say) do not pass.
    """
    try:
        with _open_text(Path(path)) as fh:
            for _ in range(_SNIFF_LINES):
                line = fh.readline(limits.MAX_LINE_LENGTH + 1)  # an overlong line: its head
                if not line:
                    break
                tokens = line.split(maxsplit=1)
                if tokens and not tokens[0].startswith("#"):
                    return _MESSAGE_NAME.fullmatch(tokens[0]) is not None
                if not line.endswith("\n"):
                    skip_line_rest(fh)
    except _READ_ERRORS:
        return False
    return True


class CarmenReader(ScanStream):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over a CARMEN log.

    Parameters
    ----------
    path : str or Path
        ``.log``/``.clf`` file, plain or gzip-compressed.
    max_range : float, optional
        The log's no-return reading, metres; detected when ``None`` (see the module
        docstring). :attr:`Scan.max_range` is set :data:`NO_RETURN_MARGIN` below it.
    skip_bad : bool
        Skip and count malformed laser lines instead of raising.

    Attributes
    ----------
    skipped : int
        Malformed laser lines skipped so far (``skip_bad=True``).
    bad_lines : list of int
        Their 1-based line numbers.
    no_return : float or None
        The no-return reading in use, once known (after the first scan).

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, if the file is not a CARMEN log; while iterating, on an
        unreadable stream or a malformed laser line (message: ``file:line: why``).
    """

    def __init__(
        self, path: str | Path, *, max_range: float | None = None, skip_bad: bool = False
    ) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise MapFileNotFound(f"CARMEN log {str(self.path)!r} does not exist")
        if not self.path.is_file() or not looks_like_carmen(self.path):
            raise OctolgpError(f"{str(self.path)!r} is not a readable CARMEN log")
        if max_range is not None and not (np.isfinite(max_range) and max_range > 0):
            raise OctolgpError(f"CarmenReader.max_range must be finite and > 0, got {max_range!r}")
        self.max_range = max_range
        self.skip_bad = skip_bad
        self.skipped = 0
        self.bad_lines: list[int] = []
        self.no_return: float | None = max_range
        self._scans = self._generate()

    def _lines(self) -> Generator[tuple[int, str], None, None]:
        """Yield ``(line_number, line)``; a read error becomes :class:`OctolgpError`.

        A line longer than :data:`~octolgp.io.limits.MAX_LINE_LENGTH` raises naming the file
        and line, or with ``skip_bad`` is read to its end in bounded parts and skipped.
        """
        line_no = 0
        try:
            with _open_text(self.path) as fh:
                while True:
                    line_no += 1
                    try:
                        line = read_line(fh)
                    except LineTooLongError as exc:
                        if not self.skip_bad:
                            raise OctolgpError(f"CARMEN log {self.path}:{line_no}: {exc}") from None
                        self.skipped += 1
                        self.bad_lines.append(line_no)
                        logger.info("CARMEN log %s:%d: skipped: %s", self.path, line_no, exc)
                        if not exc.ended:
                            skip_line_rest(fh)
                        continue
                    if not line:
                        return
                    yield line_no, line
        except _READ_ERRORS as exc:
            where = f"{self.path}:{line_no}"
            raise OctolgpError(f"CARMEN log {where}: unreadable: {exc}") from None

    def _to_scan(self, record: _Record) -> Scan:
        """Project a record to the world frame with the no-return value in force."""
        value = self.no_return
        if self.max_range is None and record.inline_max is not None:
            value = record.inline_max
        threshold = None if value is None else value - NO_RETURN_MARGIN
        if threshold is not None and threshold <= 0:
            threshold = None
        return Scan.from_ranges(record.pose, record.ranges, record.angles, threshold, record.stamp)

    def _detect(self, pending: list[_Record]) -> None:
        """Detect the no-return reading: the largest reading, if repeated in several beams."""
        ranges = [r.ranges for r in pending if r.inline_max is None]
        if not ranges:
            return
        readings = np.concatenate(ranges)
        top = float(readings.max())
        if int(np.count_nonzero(readings == top)) >= DETECT_MIN_REPEATS:
            self.no_return = top

    def _generate(self) -> Generator[Scan, None, None]:
        """Stream scans; hold the first :data:`DETECT_SCANS` while detecting the no-return."""
        resolved = self.max_range is not None
        pending: list[_Record] = []
        lasers = 0  # laser lines seen, good or bad
        for line_no, line in self._lines():
            tokens = line.split()
            if not tokens:
                continue
            if tokens[0] == "PARAM" and not resolved and len(tokens) >= 3:
                # A declared maximum beats detection.
                if tokens[1] in _MAX_RANGE_PARAMS:
                    try:
                        value = float(tokens[2])
                    except ValueError:
                        continue
                    if np.isfinite(value) and value > 0:
                        self.no_return, resolved = value, True
                        yield from (self._to_scan(r) for r in pending)
                        pending = []
                continue
            parser = _PARSERS.get(tokens[0])
            if parser is None:
                continue
            lasers += 1
            try:
                record = parser(tokens)
            except _BadLineError as exc:
                if not self.skip_bad:
                    raise OctolgpError(f"CARMEN log {self.path}:{line_no}: {exc}") from None
                self.skipped += 1
                self.bad_lines.append(line_no)
                logger.info("CARMEN log %s:%d: skipped: %s", self.path, line_no, exc)
                continue
            if resolved:
                yield self._to_scan(record)
                continue
            pending.append(record)
            if len(pending) >= DETECT_SCANS:
                self._detect(pending)
                resolved = True
                yield from (self._to_scan(r) for r in pending)
                pending = []
        if pending:
            self._detect(pending)
            yield from (self._to_scan(r) for r in pending)
        if lasers == 0:
            raise OctolgpError(
                f"CARMEN log {str(self.path)!r} holds no laser message "
                f"({', '.join(sorted(_PARSERS))})"
            )


def read_carmen(
    path: str | Path, *, max_range: float | None = None, skip_bad: bool = False
) -> CarmenReader:
    """Open a CARMEN log as a stream of scans; see :class:`CarmenReader`."""
    return CarmenReader(path, max_range=max_range, skip_bad=skip_bad)
