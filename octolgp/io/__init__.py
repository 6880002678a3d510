"""Scan log readers and writers; :func:`load_scans` picks the reader from the file.

Supported formats (``format=`` names):

- ``"npz"``: the npz scan log of ``API.md`` (:mod:`octolgp.io.npz`), read and
  validated at the call.
- ``"carmen"``: CARMEN text logs ``.log``/``.clf``, optionally ``.gz``
  (:mod:`octolgp.io.carmen`), streamed line by line.
- ``"3dtk"``: a directory of 3DTK ``scanNNN.3d[.xz]`` files with ``.frames``/``.pose`` poses, or
  one such file (:mod:`octolgp.io.threedtk`), streamed scan by scan.
- ``"rrd"``: a Rerun recording ``.rrd`` (:mod:`octolgp.io.rrd`), streamed chunk by chunk: the
  exact scans that :func:`~octolgp.io.rrd.log_scan` wrote, else the ``Points3D``/``Points2D``
  rows of any recording posed by its ``Transform3D``. :func:`~octolgp.io.rrd.read_rrd` takes
  the options (points entity, pose entity, timeline, ``max_range``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

from numpy.typing import ArrayLike

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io.carmen import CarmenReader, looks_like_carmen, read_carmen
from octolgp.io.npz import read_npz, read_truth, write_npz
from octolgp.io.rrd import RrdScanReader, log_scan, looks_like_rrd, read_rrd
from octolgp.io.threedtk import ThreeDTKReader, looks_like_3dtk, read_3dtk
from octolgp.scan import Scan

__all__ = [
    "SCAN_FORMATS",
    "CarmenReader",
    "RrdScanReader",
    "ThreeDTKReader",
    "detect_format",
    "load_scans",
    "log_scan",
    "read_3dtk",
    "read_carmen",
    "read_npz",
    "read_rrd",
    "read_truth",
    "save_scan_log",
    "write_npz",
]

SCAN_FORMATS = ("npz", "carmen", "3dtk", "rrd")
"""Names accepted by ``load_scans(..., format=...)``."""

_CARMEN_SUFFIXES = (".log", ".clf")
_ZIP_MAGIC = b"PK\x03\x04"
_GZIP_MAGIC = b"\x1f\x8b"


def detect_format(path: str | Path) -> str:
    """Name the scan-log format of a file, from its suffix, else its first bytes.

    Parameters
    ----------
    path : str or Path
        An existing file, or a directory of 3DTK scans.

    Returns
    -------
    str
        One of :data:`SCAN_FORMATS`.

    Raises
    ------
    MapFileNotFound
        If ``path`` does not exist.
    OctolgpError
        If ``path`` is not a file or its format is not recognised.
    """
    p = Path(path)
    if not p.exists():
        raise MapFileNotFound(f"scan log {str(p)!r} does not exist")
    if looks_like_3dtk(p):
        return "3dtk"
    if not p.is_file():
        raise OctolgpError(f"scan log {str(p)!r} is not a file")
    # Suffix first: x.npz, x.log, x.clf, x.log.gz, x.clf.gz.
    suffixes = [s.lower() for s in p.suffixes[-2:]]
    if suffixes and suffixes[-1] == ".gz":
        suffixes.pop()
    if suffixes and suffixes[-1] == ".npz":
        return "npz"
    if suffixes and suffixes[-1] in _CARMEN_SUFFIXES:
        return "carmen"
    if suffixes and suffixes[-1] == ".rrd":
        return "rrd"
    # Then the magic bytes: a zip archive is an npz, RRF2 a Rerun recording, text (or gzipped
    # text) may be CARMEN.
    try:
        with open(p, "rb") as fh:
            magic = fh.read(4)
    except OSError as exc:
        raise OctolgpError(f"scan log {str(p)!r} cannot be read: {exc}") from None
    if magic == _ZIP_MAGIC:
        return "npz"
    if looks_like_rrd(p):
        return "rrd"
    if (magic[:2] == _GZIP_MAGIC or magic.isascii()) and magic and looks_like_carmen(p):
        return "carmen"
    raise OctolgpError(
        f"scan log {str(p)!r}: unknown format (supported: {', '.join(SCAN_FORMATS)})"
    )


def load_scans(
    path: str | Path, format: str | None = None, *, skip_bad: bool = False
) -> Iterator[Scan]:
    """Read a scan log as a stream of scans in the world frame.

    Parameters
    ----------
    path : str or Path
        The log file (or 3DTK scan directory).
    format : str, optional
        One of :data:`SCAN_FORMATS`; chosen by :func:`detect_format` when omitted.
    skip_bad : bool
        CARMEN and 3DTK: skip malformed laser or point lines and count them (the returned
        :class:`~octolgp.io.carmen.CarmenReader` or
        :class:`~octolgp.io.threedtk.ThreeDTKReader` has ``skipped``) instead of raising.
        Rerun: skip invalid scans (:class:`~octolgp.io.rrd.RrdScanReader` has ``skipped`` and
        ``notes``); a cut-off tail is always skipped and reported there.

    Returns
    -------
    Iterator of Scan
        In file order (a Rerun recording: timeline order). CARMEN logs and Rerun recordings
        stream; an npz log is validated at the call.

    Raises
    ------
    MapFileNotFound
        At the call, if ``path`` does not exist.
    OctolgpError
        At the call for an unknown format name or a foreign/unreadable file; while
        iterating for a corrupt part (CARMEN, 3DTK), naming the file and line.
    """
    p = Path(path)
    if not p.exists():
        raise MapFileNotFound(f"scan log {str(p)!r} does not exist")
    if format is None:
        format = detect_format(p)
    if format == "npz":
        return read_npz(p)
    if format == "carmen":
        return CarmenReader(p, skip_bad=skip_bad)
    if format == "3dtk":
        return ThreeDTKReader(p, skip_bad=skip_bad)
    if format == "rrd":
        return RrdScanReader(p, skip_bad=skip_bad)
    raise OctolgpError(f"load_scans: unknown format {format!r} (supported: {SCAN_FORMATS})")


def save_scan_log(
    path: str | Path,
    scans: Iterable[Scan],
    truth_points: ArrayLike | None = None,
    truth_labels: ArrayLike | None = None,
) -> None:
    """Write scans, and optionally ground truth, as an npz scan log (``.npz``).

    Parameters
    ----------
    path : str or Path
        Output file; its suffix must be ``.npz``.
    scans : iterable of Scan
        The scans, all of one dimension.
    truth_points : array_like of shape (M, d), optional
        Ground-truth test positions, world frame, metres.
    truth_labels : array_like of shape (M,), optional
        1 occupied, 0 free.

    Raises
    ------
    OctolgpError
        On another suffix, or on invalid scans or ground truth (see
        :func:`~octolgp.io.npz.write_npz`).
    """
    if Path(path).suffix.lower() != ".npz":
        raise OctolgpError(f"save_scan_log: {str(path)!r} must end in .npz")
    write_npz(path, scans, truth_points, truth_labels)
