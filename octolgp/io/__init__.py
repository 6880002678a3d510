"""Scan log readers and writers; :func:`load_scans` picks the reader from the file.

Supported formats (``format=`` names):

- ``"npz"``: the npz scan log of ``docs/npz-format.md`` (:mod:`octolgp.io.npz`), read and
  validated at the call.
- ``"carmen"``: CARMEN text logs ``.log``/``.clf``, optionally ``.gz``
  (:mod:`octolgp.io.carmen`), streamed line by line.
- ``"3dtk"``: a directory of 3DTK ``scanNNN.3d[.xz]`` files with ``.frames``/``.pose`` poses, or
  one such file (:mod:`octolgp.io.threedtk`), streamed scan by scan.
- ``"rrd"``: a Rerun recording ``.rrd`` (:mod:`octolgp.io.rrd_read`), streamed chunk by chunk: the
  exact scans that :func:`~octolgp.io.rrd_write.log_scan` wrote (checksums verified; a scan whose
  exact copy is lost is never replayed from its float32 display copy), else the
  ``Points3D``/``Points2D`` rows of any recording posed by its ``Transform3D``.
  :func:`~octolgp.io.rrd_read.read_rrd` takes the options (points entity, pose entity, timeline,
  ``max_range``).
- ``"rosbag"``: a ROS 1 ``.bag`` or a ROS 2 bag (directory with ``metadata.yaml``, or its
  ``.db3``/``.mcap``) read with ``rosbags`` (:mod:`octolgp.io.rosbag`): ``LaserScan`` or
  ``PointCloud2``, posed by ``/tf`` or a ``PoseStamped``/``Odometry`` topic; streamed.
  :func:`~octolgp.io.rosbag.read_rosbag` takes the options (topics, fixed frame).
- ``"pcd"``: PCL point clouds (ascii, binary, binary_compressed), one file or a directory of
  ``.pcd`` files, one scan each, posed by ``VIEWPOINT`` (:mod:`octolgp.io.pcd`).
- ``"ply"``: PLY point clouds (ascii or binary), one file or a directory of ``.ply``
  (:mod:`octolgp.io.ply`); origin from a ``comment origin x y z`` line, else (0, 0, 0).
- ``"scandat"``: OctoMap's plain ``scan.dat`` (``x y z`` lines, sensor at the origin) and its
  ``NODE x y z roll pitch yaw`` scan-graph text form, optionally ``.gz``/``.bz2``.
- ``"graph"``: OctoMap's binary scan graph ``.graph`` (:mod:`octolgp.io.octomap_graph`).
- ``"kitti"``: a KITTI odometry sequence directory ``sequences/NN`` (``velodyne/*.bin``,
  ``calib.txt``) posed by ``poses/NN.txt`` beside ``sequences/`` (:mod:`octolgp.io.kitti`);
  streamed. :func:`~octolgp.io.kitti.read_kitti` takes the options (poses file, world frame).

Every reader streams and takes ``skip_bad``: malformed lines, messages or files are then
skipped and counted (the reader's ``skipped``) instead of raising an error that names the
file and line. Each skip is also logged at INFO (file, line or message, reason) on the
reader's ``octolgp.io.*`` logger; a Rerun recording that was not closed or is cut off is
logged at WARNING.

What one file may make a reader allocate is bounded by the stated limits of
:mod:`octolgp.io.limits` (points per scan, bytes once decompressed, line length), checked
from the file's headers before its data are read or decompressed.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from types import MappingProxyType

from numpy.typing import ArrayLike

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.io.carmen import CarmenReader, looks_like_carmen, read_carmen
from octolgp.io.kitti import KittiReader, looks_like_kitti, read_kitti
from octolgp.io.npz import read_npz, read_truth, write_npz
from octolgp.io.octomap_graph import (
    GraphReader,
    ScanDatReader,
    looks_like_graph,
    looks_like_scan_dat,
    read_graph,
    read_scan_dat,
    write_graph,
)
from octolgp.io.pcd import PcdReader, looks_like_pcd, read_pcd
from octolgp.io.ply import PlyReader, looks_like_ply, read_ply
from octolgp.io.rosbag import RosbagReader, looks_like_rosbag, read_rosbag
from octolgp.io.rrd_format import looks_like_rrd
from octolgp.io.rrd_read import RrdScanReader, read_rrd
from octolgp.io.rrd_write import log_scan
from octolgp.io.threedtk import ThreeDTKReader, looks_like_3dtk, read_3dtk
from octolgp.scan import Scan

__all__ = [
    "SCAN_FORMATS",
    "CarmenReader",
    "GraphReader",
    "KittiReader",
    "PcdReader",
    "PlyReader",
    "RosbagReader",
    "RrdScanReader",
    "ScanDatReader",
    "ThreeDTKReader",
    "detect_format",
    "load_scans",
    "log_scan",
    "read_3dtk",
    "read_carmen",
    "read_graph",
    "read_kitti",
    "read_npz",
    "read_pcd",
    "read_ply",
    "read_rosbag",
    "read_rrd",
    "read_scan_dat",
    "read_truth",
    "save_scan_log",
    "write_graph",
    "write_npz",
]

SCAN_FORMATS = (
    "npz",
    "carmen",
    "3dtk",
    "rrd",
    "rosbag",
    "pcd",
    "ply",
    "scandat",
    "graph",
    "kitti",
)
"""Names accepted by ``load_scans(..., format=...)``."""

_CARMEN_SUFFIXES = (".log", ".clf")
_OTHER_SUFFIXES = MappingProxyType(
    {".pcd": "pcd", ".ply": "ply", ".bag": "rosbag", ".graph": "graph"}
)
_ZIP_MAGIC = b"PK\x03\x04"
_GZIP_MAGIC = b"\x1f\x8b"


def detect_format(path: str | Path) -> str:
    """Name the scan-log format of a file, from its suffix, else its first bytes.

    Parameters
    ----------
    path : str or Path
        An existing file, or a directory of 3DTK, PCD or PLY scans, a ROS 2 bag or a
        KITTI sequence.

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
    if looks_like_rosbag(p):
        return "rosbag"
    if p.is_dir() and looks_like_kitti(p):
        return "kitti"
    if looks_like_3dtk(p):
        return "3dtk"
    if p.is_dir() and looks_like_pcd(p):
        return "pcd"
    if p.is_dir() and looks_like_ply(p):
        return "ply"
    if not p.is_file():
        raise OctolgpError(f"scan log {str(p)!r} is not a file")
    # Suffix first: x.npz, x.log, x.clf, x.log.gz, x.clf.gz.
    suffixes = [s.lower() for s in p.suffixes[-2:]]
    compressed = bool(suffixes) and suffixes[-1] == ".gz"
    if compressed:
        suffixes.pop()
    if suffixes and suffixes[-1] == ".npz":
        return "npz"
    if suffixes and suffixes[-1] in _CARMEN_SUFFIXES:
        return "carmen"
    if suffixes and suffixes[-1] == ".rrd":
        return "rrd"
    # Unambiguous suffixes of the other formats: a damaged x.pcd gets the PCD reader's
    # message (which part is wrong) rather than "unknown format".
    if suffixes and suffixes[-1] in _OTHER_SUFFIXES and not compressed:
        return _OTHER_SUFFIXES[suffixes[-1]]
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
    for name, sniff in (
        ("pcd", looks_like_pcd),
        ("ply", looks_like_ply),
        ("graph", looks_like_graph),
        ("scandat", looks_like_scan_dat),
    ):
        if sniff(p):
            return name
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
        The log file (or 3DTK scan directory, KITTI sequence ``sequences/NN``...).
    format : str, optional
        One of :data:`SCAN_FORMATS`; chosen by :func:`detect_format` when omitted.
    skip_bad : bool
        Skip malformed lines, messages or files and count them (the returned reader's
        ``skipped``) instead of raising; every format but npz, which is validated whole.
        Rerun: skip invalid scans (:class:`~octolgp.io.rrd_read.RrdScanReader` has ``skipped`` and
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
    if format == "rosbag":
        return RosbagReader(p, skip_bad=skip_bad)
    if format == "pcd":
        return PcdReader(p, skip_bad=skip_bad)
    if format == "ply":
        return PlyReader(p, skip_bad=skip_bad)
    if format == "scandat":
        return ScanDatReader(p, skip_bad=skip_bad)
    if format == "graph":
        return GraphReader(p, skip_bad=skip_bad)
    if format == "kitti":
        return KittiReader(p, skip_bad=skip_bad)
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
