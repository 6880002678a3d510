"""What octolgp puts in a Rerun recording, and how an ``.rrd`` file is framed.

Names
-----
:func:`octolgp.io.rrd_write.log_scan` writes, and :mod:`octolgp.io.rrd_read` reads, one scan
per row on the :data:`SCAN_TIMELINE` sequence timeline (and on :data:`TIME_TIMELINE` when the
scan has a stamp), with an exact float64 copy at :data:`SCAN_ENTITY` as the dynamic archetype
:data:`SCAN_ARCHETYPE`. The copy carries a CRC-32 (:data:`CHECKSUM_COMPONENT`, computed by
:func:`scan_checksum`) that the reader verifies, and each row of the float32 display copy
(the ``Points3D``/``Points2D`` a viewer shows) carries :data:`DISPLAY_MARK`, so a reader knows
that a scan whose exact copy is missing had one: it never replays such a scan from its display
copy, which has no ``max_range`` (its no-return beams would become hits).

Framing
-------
An RRD file is a 12-byte stream header (``RRF2``, version, options) then messages framed as
``kind: u64, len: u64, payload`` (0 End, 1 SetStoreInfo, 2 ArrowMsg, 3
BlueprintActivationCommand, little-endian). A closed file ends with an End message holding the
chunk manifest and a 32-byte ``RRF2FOOT`` trailer. A killed writer leaves no End message, and a
file cut at any byte may end inside a message; :func:`scan_framing` walks the message headers
(16 bytes read per message) to find where the complete messages end.

Nothing here imports rerun.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "CHECKSUM_COMPONENT",
    "DISPLAY_ARCHETYPE",
    "DISPLAY_MARK",
    "LEGACY_MAGICS",
    "RRD_MAGIC",
    "SCAN_ARCHETYPE",
    "SCAN_ENTITY",
    "SCAN_TIMELINE",
    "TIME_TIMELINE",
    "Framing",
    "looks_like_rrd",
    "scan_checksum",
    "scan_framing",
]

SCAN_ENTITY = "octolgp/scan"
"""Entity of the exact float64 copy of each scan."""
SCAN_ARCHETYPE = "octolgp.Scan"
"""Archetype name of that copy; its components are ``octolgp.Scan:origin`` and so on."""
CHECKSUM_COMPONENT = "crc32"
"""Component of the exact copy holding its CRC-32 (uint32, :func:`scan_checksum`).
Recordings written before it existed have none and are read unchecked."""
DISPLAY_ARCHETYPE = "octolgp.ScanDisplay"
"""Archetype logged on each row of a scan's display copy, beside its ``Points3D``/``Points2D``."""
DISPLAY_MARK = f"{DISPLAY_ARCHETYPE}:exact"
"""Component of a display row (int64, 1): this scan's exact copy is logged at
:data:`SCAN_ENTITY` at the same :data:`SCAN_TIMELINE` value."""
SCAN_TIMELINE = "scan"
"""Sequence timeline of the scans: the scan's index."""
TIME_TIMELINE = "time"
"""Timestamp timeline of the scans that have a stamp."""
RRD_MAGIC = b"RRF2"
"""First bytes of an RRD file that rerun 0.41 reads."""
LEGACY_MAGICS = (b"RRF0", b"RRF1")
"""First bytes of older RRD files, which rerun 0.41 cannot read."""
_STREAM_HEADER = 12
_MESSAGE_HEADER = struct.Struct("<QQ")
_END, _KINDS = 0, frozenset({0, 1, 2, 3})


def scan_checksum(
    index: int,
    dim: ArrayLike,
    origin: ArrayLike,
    points: ArrayLike,
    max_range: ArrayLike,
    stamp: ArrayLike,
) -> int:
    """CRC-32 of one exact scan record, over its components' little-endian bytes.

    Covers, in order: the :data:`SCAN_TIMELINE` value ``index`` and ``dim`` (int64), then
    ``origin``, ``points``, ``max_range`` and ``stamp`` (float64; NaN where absent), exactly as
    :func:`octolgp.io.rrd_write.log_scan` logs them, so flipped bytes in any of them, or in the
    row's scan number, change it.

    Parameters
    ----------
    index : int
        The row's value on the :data:`SCAN_TIMELINE` timeline.
    dim, origin, points, max_range, stamp : array_like
        The record's components as logged (``points`` flattened row-major).

    Returns
    -------
    int
        The CRC-32, in ``[0, 2**32)``.
    """
    crc = zlib.crc32(np.array([index], dtype="<i8").tobytes())
    crc = zlib.crc32(np.ascontiguousarray(dim, dtype="<i8").tobytes(), crc)
    for part in (origin, points, max_range, stamp):
        crc = zlib.crc32(np.ascontiguousarray(part, dtype="<f8").reshape(-1).data, crc)
    return crc


def looks_like_rrd(path: str | Path) -> bool:
    """Tell whether a file starts with an RRD stream header (any version)."""
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError:
        return False
    return magic == RRD_MAGIC or magic in LEGACY_MAGICS


@dataclass(frozen=True, slots=True)
class Framing:
    """Where the complete messages of an RRD file end.

    Attributes
    ----------
    size : int
        File size, bytes.
    data_end : int
        End of the last complete data (non-End) message; 0 if there is none.
    closed : bool
        Whether the last stream ends with an End message: the writer closed the file.
    problem : str or None
        Why the bytes after ``data_end`` cannot be read, if they cannot.
    corrupt : bool
        Whether the problem is an unrecognised message rather than a cut-off tail.
    """

    size: int
    data_end: int
    closed: bool
    problem: str | None
    corrupt: bool


def scan_framing(path: Path) -> Framing:
    """Walk the message headers of an RRD file (16 bytes read per message).

    Parameters
    ----------
    path : Path
        A file starting with :data:`RRD_MAGIC`.

    Returns
    -------
    Framing
        Where its complete messages end and why the rest, if any, cannot be read.
    """
    size = path.stat().st_size
    off = data_end = 0
    closed, problem, corrupt = False, None, False
    with open(path, "rb") as fh:
        while off < size:
            fh.seek(off)
            head = fh.read(_MESSAGE_HEADER.size)
            if head[:4] == RRD_MAGIC and head[4:8] != b"FOOT":  # a (concatenated) stream
                if len(head) < _STREAM_HEADER:
                    problem = f"cut inside a stream header at byte {off}"
                    break
                off, closed = off + _STREAM_HEADER, False
                continue
            if closed:  # footer trailer (or padding) after an End message
                break
            if len(head) < _MESSAGE_HEADER.size:
                problem = f"an incomplete message header at byte {off}"
                break
            kind, length = _MESSAGE_HEADER.unpack(head)
            if kind not in _KINDS:
                problem, corrupt = f"unrecognised message kind {kind} at byte {off}", True
                break
            if off + _MESSAGE_HEADER.size + length > size:
                what = "the footer" if kind == _END else "last message"
                problem = f"{what} (byte {off}, {length} bytes) is incomplete"
                closed = kind == _END  # all data was written; only the manifest is cut
                break
            off += _MESSAGE_HEADER.size + length
            if kind == _END:
                closed = True
            else:
                data_end = off
    return Framing(size, data_end, closed, problem, corrupt)
