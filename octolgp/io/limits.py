"""Stated limits on what one input file may make a reader allocate, checked before reading.

A file's header says how much data follows: a PCD ``POINTS`` line and the sizes of its
compressed block, a PLY element count, the shape in each ``.npy`` member header of an npz
archive. The readers check those claims against the limits below *before* they read or
decompress the data, so a small malicious file (a decompression bomb, or a header that
claims 10¹² points) is refused at once with an :class:`~octolgp.errors.OctolgpError` that
names the file, the claim and the limit, instead of exhausting memory. Text readers read
lines of bounded length (:func:`read_line`), so one enormous line (a gzip stream of zeros
inflates a thousandfold) is refused as soon as the limit is passed.

The limits are read at each check: assign to raise one, for example
``octolgp.io.limits.MAX_SCAN_POINTS = 1 << 26``.
"""

from __future__ import annotations

from typing import IO

from octolgp.errors import OctolgpError

__all__ = [
    "LZF_MAX_RATIO",
    "MAX_DECOMPRESSED_BYTES",
    "MAX_LINE_LENGTH",
    "MAX_SCAN_POINTS",
    "LineTooLongError",
    "check_bytes",
    "check_points",
    "read_line",
    "read_lines",
    "skip_line_rest",
]

MAX_SCAN_POINTS = 1 << 24
"""Most points one scan read from a file may hold: 16,777,216, 64 revolutions of a 128-beam,
2048-column lidar (262,144 points each). A header that claims more is refused before the
points are read; a text file is refused as soon as it holds more. ``insert_scan`` accepts
fewer still by default (``OnlineConfig.max_scan_points``); downsample after loading."""

MAX_DECOMPRESSED_BYTES = 1 << 30
"""Most bytes (1 GiB) that one file's arrays or compressed blocks may claim to hold once
inflated: a PCD ``binary_compressed`` block, or the arrays of an npz scan log together
(its ``.npy`` member headers give their shapes). Checked from the headers, before anything
is decompressed."""

MAX_LINE_LENGTH = 1 << 22
"""Longest text line, in characters (4 MiB): room for a CARMEN laser line of some 500,000
readings. Lines are read at most this much at a time, so a longer one costs no more memory
than this before it is refused."""

LZF_MAX_RATIO = 88
"""Most bytes that LZF can inflate one byte to: a 3-byte back-reference copies at most 264
bytes. A PCD block that claims a larger ratio is corrupt (a format bound, not a setting)."""


class LineTooLongError(OctolgpError):
    """A text line longer than :data:`MAX_LINE_LENGTH`; the reader adds the file and line.

    Attributes
    ----------
    ended : bool
        Whether the part read holds the line's end (its newline); if not, the rest of the
        line is still to be read (:func:`skip_line_rest`).
    before : list of str
        With :func:`read_lines`: the whole lines read before it in the same call.
    """

    def __init__(self, message: str, ended: bool) -> None:
        super().__init__(message)
        self.ended = ended
        self.before: list[str] = []


def check_points(count: int, what: str, *, claimed: bool = True) -> None:
    """Refuse a scan that claims (or holds) more than :data:`MAX_SCAN_POINTS` points.

    Parameters
    ----------
    count : int
        Points claimed (a header's count) or read so far.
    what : str
        What claims or holds them, for the message (``"POINTS"``, ``"element vertex"``).
    claimed : bool
        Whether ``count`` is a header's claim rather than points read.

    Raises
    ------
    OctolgpError
        If ``count > MAX_SCAN_POINTS``.
    """
    if count > MAX_SCAN_POINTS:
        verb = "claims" if claimed else "holds"
        raise OctolgpError(
            f"{what} {verb} {count} points, more than octolgp.io.limits.MAX_SCAN_POINTS "
            f"({MAX_SCAN_POINTS}) for one scan"
        )


def check_bytes(nbytes: int, what: str) -> None:
    """Refuse data that claim to inflate to more than :data:`MAX_DECOMPRESSED_BYTES`.

    Parameters
    ----------
    nbytes : int
        Bytes claimed once decompressed.
    what : str
        What claims them, for the message.

    Raises
    ------
    OctolgpError
        If ``nbytes > MAX_DECOMPRESSED_BYTES``.
    """
    if nbytes > MAX_DECOMPRESSED_BYTES:
        raise OctolgpError(
            f"{what} claims {nbytes} bytes once decompressed, more than "
            f"octolgp.io.limits.MAX_DECOMPRESSED_BYTES ({MAX_DECOMPRESSED_BYTES})"
        )


def read_line(fh: IO[str]) -> str:
    """Read one line of at most :data:`MAX_LINE_LENGTH` characters (``""`` at the end).

    Raises
    ------
    LineTooLongError
        If the line is longer; at most ``MAX_LINE_LENGTH + 1`` characters have been read.
    """
    limit = MAX_LINE_LENGTH
    line = fh.readline(limit + 1)
    if len(line) > limit:
        raise LineTooLongError(
            f"line longer than octolgp.io.limits.MAX_LINE_LENGTH ({limit} characters)",
            ended=line.endswith("\n"),
        )
    return line


def read_lines(fh: IO[str], hint: int) -> list[str]:
    """Read whole lines, each checked by :func:`read_line`, until ``hint`` characters or the end.

    Like ``fh.readlines(hint)`` but no line may exceed :data:`MAX_LINE_LENGTH`, so one call
    holds at most ``hint + MAX_LINE_LENGTH`` characters.

    Raises
    ------
    LineTooLongError
        At an overlong line, with the lines read before it in ``before``.
    """
    lines: list[str] = []
    size = 0
    while size < hint:
        try:
            line = read_line(fh)
        except LineTooLongError as exc:
            exc.before = lines
            raise
        if not line:
            break
        lines.append(line)
        size += len(line)
    return lines


def skip_line_rest(fh: IO[str]) -> None:
    """Read and drop the rest of an overlong line, :data:`MAX_LINE_LENGTH` at a time."""
    while True:
        part = fh.readline(MAX_LINE_LENGTH)
        if not part or part.endswith("\n"):
            return
