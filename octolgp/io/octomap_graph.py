"""Streaming readers for OctoMap's scan files: ``scan.dat`` text and ``.graph`` binary scan graphs.

``scan.dat`` (text; plain, gzip, bzip2 or xz by magic bytes) in one of two forms, as
OctoMap's ``ScanGraph::readPlainASCII`` and ``octovis`` read it:

- plain ``x y z`` lines: one scan, sensor at the origin with the identity orientation
  (``octovis ViewerGui::openPointcloud`` uses ``pose6d(0, 0, 0, 0, 0, 0)``); points in metres,
  world frame;
- graph text: ``NODE x y z roll pitch yaw`` starts a new scan whose following ``x y z`` lines are
  in the sensor frame. The sensor pose is OctoMap's ``pose6d``: translation ``(x, y, z)``,
  rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` (radians; ``octomath::Quaternion(roll, pitch, yaw)``),
  so a point becomes ``R p + t`` and the scan's origin is ``t``. Points before the first
  ``NODE`` form a scan at the identity pose.

Blank lines and ``#`` comments are skipped. OctoMap also skips lines that start with a space;
here such lines are parsed, so no point is lost silently. A ``NODE`` without points is an
empty scan (an error, or skipped with ``skip_bad``).

``.graph`` (``ScanGraph::writeBinary``, little-endian)::

    uint32 n_nodes, then per node:
        Pointcloud: uint32 n_points, then per point: int32 3, float64 x, y, z   (28 bytes)
        pose6d:     int32 3, float64 x, y, z; int32 4, float64 qw, qx, qy, qz   (64 bytes)
        uint32 id
    uint32 n_edges, then the edges (ignored here)

The points are in the sensor frame; the node pose maps them to the world frame. Nodes are read
one at a time and their points a chunk of records at a time.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Generator, Iterable, Sequence
from pathlib import Path
from typing import IO

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.geometry.rotations import matrix_to_quaternion, quaternion_to_matrix, rpy_to_matrix
from octolgp.io import limits
from octolgp.io.limits import LineTooLongError, read_line, skip_line_rest
from octolgp.io.pointcloud import (
    CHUNK_LINES,
    CHUNK_POINTS,
    READ_ERRORS,
    CloudReader,
    open_text,
    parse_ascii,
)
from octolgp.scan import FloatArray, Scan

__all__ = [
    "GraphReader",
    "ScanDatReader",
    "looks_like_graph",
    "looks_like_scan_dat",
    "read_graph",
    "read_scan_dat",
    "write_graph",
]

_DAT_NAME = re.compile(r".+\.dat(?:\.(?:gz|bz2|xz))?", re.IGNORECASE)
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_POINT_LINE = re.compile(rf"\s*{_NUMBER}\s+{_NUMBER}\s+{_NUMBER}\s*")
_NODE_LINE = re.compile(rf"NODE(?:\s+{_NUMBER}){{6}}\s*")
_POINT = np.dtype([("n", "<i4"), ("p", "<f8", (3,))])  # 28 bytes, packed
_POSE = struct.Struct("<i3di4d")  # 64 bytes
_U32 = struct.Struct("<I")
_SNIFF_LINES = 100


def looks_like_scan_dat(path: str | Path) -> bool:
    """Tell whether ``path`` reads as an OctoMap ``scan.dat``.

    True if its first data line (after blanks and ``#`` comments) is ``NODE`` with 6 numbers,
    or if it is named ``*.dat[.gz|.bz2|.xz]`` and that line is 3 numbers.
    """
    p = Path(path)
    if not p.is_file():
        return False
    try:
        with open_text(p) as fh:
            for _, line in zip(range(_SNIFF_LINES), fh, strict=False):
                text = line.split("#", 1)[0]
                if not text.strip():
                    continue
                if _NODE_LINE.fullmatch(text.rstrip()):
                    return True
                return bool(_DAT_NAME.fullmatch(p.name) and _POINT_LINE.fullmatch(text))
    except (*READ_ERRORS, UnicodeError):
        return False
    return False


def looks_like_graph(path: str | Path) -> bool:
    """Tell whether ``path`` is an OctoMap binary scan graph.

    A ``.graph`` file of at least 8 bytes, or any file whose first node is laid out as
    ``ScanGraph::writeBinary`` writes it (the pose's ``int32 3`` where it must be).
    """
    p = Path(path)
    try:
        if not p.is_file():
            return False
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(12)
            if len(head) < 8:
                return False
            n_nodes, n_points = struct.unpack("<II", head[:8])
            if n_nodes == 0:
                return p.suffix.lower() == ".graph" and size >= 8
            if size < 8 + 28 * n_points + 68:
                return False
            fh.seek(8 + 28 * n_points)
            marker = fh.read(4)
    except OSError:
        return False
    return marker == b"\x03\x00\x00\x00" and (n_points == 0 or head[8:12] == marker)


class ScanDatReader(CloudReader):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over an OctoMap ``scan.dat``.

    Parameters
    ----------
    path : str or Path
        The text file (plain, ``.gz``, ``.bz2`` or ``.xz``).
    skip_bad : bool
        Skip and count malformed point lines, bad ``NODE`` lines (with the points that follow
        them) and empty scans instead of raising.
    max_range : float, optional
        Passed to each :class:`~octolgp.scan.Scan`, metres.

    Attributes
    ----------
    skipped, bad_lines, bad_scans
        See :class:`~octolgp.io.pointcloud.CloudReader`.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, if ``path`` is not a file; while iterating, on an unreadable stream, a
        malformed line (``path:line: why``) or a scan without points.
    """

    kind = "OctoMap scan.dat"
    single_file = True

    def __init__(
        self, path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
    ) -> None:
        super().__init__(path, skip_bad=skip_bad, max_range=max_range)

    def _node(self, line: str, line_no: int) -> tuple[FloatArray, FloatArray] | None:
        """The ``(t, R)`` of a NODE line, or ``None`` if malformed and skipped."""
        tokens = line.split("#", 1)[0].split()
        try:
            values = [float(t) for t in tokens[1:]]
        except ValueError:
            values = []
        if len(values) != 6 or not all(map(math.isfinite, values)):
            self.bad_line(self.path, line_no, f"expected 'NODE x y z roll pitch yaw': {line!r}")
            return None
        return np.array(values[:3]), rpy_to_matrix(*values[3:])

    def _generate(self) -> Generator[Scan, None, None]:
        pose: tuple[FloatArray, FloatArray] | None = (np.zeros(3), np.eye(3))
        where = ""  # the current scan's NODE line, for messages
        blocks: list[FloatArray] = []
        pending: list[str] = []  # point lines not parsed yet; the first is line `start`
        start = 1
        line_no = 0

        def flush() -> None:
            if pending and pose is not None:
                blocks.extend(
                    parse_ascii(
                        self, pending, self.path, start, ncols=3, xyz=[0, 1, 2], comments="#"
                    )
                )
                held = sum(len(b) for b in blocks)
                limits.check_points(
                    held, f"{self.kind} {self.path}:{line_no}: the scan", claimed=False
                )
            pending.clear()

        def finish() -> Scan | None:
            flush()
            if pose is None:  # a malformed NODE, skipped with its points
                return None
            try:
                return self.make_scan(self.path, where, pose[0], blocks, pose[1])
            except OctolgpError as exc:
                self.bad_scan(exc)
                return None

        try:
            with open_text(self.path) as fh:
                while True:
                    line_no += 1
                    try:
                        line = read_line(fh)
                    except LineTooLongError as exc:
                        flush()  # the pending lines run up to the one before
                        self.bad_line(self.path, line_no, str(exc))  # raises without skip_bad
                        if not exc.ended:
                            skip_line_rest(fh)
                        continue
                    if not line:
                        line_no -= 1  # the last line read
                        break
                    if line.startswith("NODE"):
                        flush()
                        if where or blocks:  # a NODE scan, or plain points before the first
                            scan = finish()
                            if scan is not None:
                                yield scan
                        blocks = []
                        where = f":{line_no}: NODE"
                        pose = self._node(line, line_no)
                        continue
                    if not pending:
                        start = line_no
                    pending.append(line)
                    if len(pending) >= CHUNK_LINES:
                        flush()
        except READ_ERRORS as exc:
            where = f"{self.path}:{line_no}"
            raise OctolgpError(f"{self.kind} {where}: unreadable: {exc}") from None
        scan = finish()
        if scan is not None:
            yield scan


class _GraphBrokenError(OctolgpError):
    """A truncated or garbled node: the rest of the graph cannot be found."""


class GraphReader(CloudReader):
    """A one-pass iterator of :class:`~octolgp.scan.Scan` over an OctoMap binary ``.graph``.

    Parameters
    ----------
    path : str or Path
        The ``.graph`` file (``ScanGraph::writeBinary``).
    skip_bad : bool
        Skip and count points with a NaN/inf coordinate, and a truncated or garbled node (which
        ends the reading: the rest of the file cannot be found) instead of raising.
    max_range : float, optional
        Passed to each :class:`~octolgp.scan.Scan`, metres.

    Attributes
    ----------
    node_ids : list of int
        The OctoMap ids of the nodes read so far.
    skipped, bad_lines, bad_scans
        See :class:`~octolgp.io.pointcloud.CloudReader`; ``bad_lines`` holds ``(path, point
        index within its node)``.

    Raises
    ------
    MapFileNotFound
        At construction, if ``path`` does not exist.
    OctolgpError
        At construction, if ``path`` is not a file; while iterating, on a truncated or garbled
        file (naming the node and byte offset), a non-finite point or an empty graph or node.
    """

    kind = "OctoMap graph"
    single_file = True

    def __init__(
        self, path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
    ) -> None:
        super().__init__(path, skip_bad=skip_bad, max_range=max_range)
        self.node_ids: list[int] = []

    def _fail(self, fh: IO[bytes], why: str) -> _GraphBrokenError:
        return _GraphBrokenError(f"{self.kind} {self.path}: byte {fh.tell()}: {why}")

    def _read_node(self, fh: IO[bytes], index: int, size: int) -> Scan:
        raw = fh.read(4)
        if len(raw) < 4:
            raise self._fail(fh, f"node {index}: truncated point count")
        (n,) = _U32.unpack(raw)
        try:
            limits.check_points(n, f"node {index}")
        except OctolgpError as exc:
            raise self._fail(fh, str(exc)) from None
        if fh.tell() + 28 * n + _POSE.size + 4 > size:
            raise self._fail(fh, f"node {index}: {n} points do not fit in the file (truncated)")
        blocks: list[FloatArray] = []
        done = 0
        while done < n:
            k = min(CHUNK_POINTS, n - done)
            rec = np.frombuffer(fh.read(28 * k), dtype=_POINT)
            if (rec["n"] != 3).any():
                bad = done + int(np.flatnonzero(rec["n"] != 3)[0])
                raise self._fail(fh, f"node {index}: point {bad} is garbled (no Vector3 marker)")
            with np.errstate(invalid="ignore"):  # a signalling NaN; caught as NaN below
                pts = rec["p"].astype(np.float64)
            rows = np.flatnonzero(~np.isfinite(pts).all(axis=1))
            for r in rows:
                self.bad_line(self.path, done + int(r), f"node {index}: NaN or inf", unit="point ")
            blocks.append(np.delete(pts, rows, axis=0) if rows.size else pts)
            done += k
        m3, x, y, z, m4, qw, qx, qy, qz = _POSE.unpack(fh.read(_POSE.size))
        (node_id,) = _U32.unpack(fh.read(4))
        if (m3, m4) != (3, 4):
            raise self._fail(fh, f"node {index}: garbled pose (markers {m3}, {m4})")
        q = (qw, qx, qy, qz)
        if not all(map(math.isfinite, (x, y, z, *q))) or abs(math.hypot(*q) - 1) > 1e-3:
            raise self._fail(fh, f"node {index}: pose is not finite or not a unit quaternion")
        self.node_ids.append(node_id)
        R = quaternion_to_matrix(q, order="wxyz")
        return self.make_scan(self.path, f": node {index}", np.array([x, y, z]), blocks, R)

    def _generate(self) -> Generator[Scan, None, None]:
        try:
            size = self.path.stat().st_size
            with open(self.path, "rb") as fh:
                raw = fh.read(4)
                if len(raw) < 4:
                    self.bad_scan(self._fail(fh, "empty or truncated file (no node count)"))
                    return
                (n_nodes,) = _U32.unpack(raw)
                if n_nodes == 0:
                    self.bad_scan(self._fail(fh, "the graph has no nodes"))
                for i in range(n_nodes):
                    try:
                        scan = self._read_node(fh, i, size)
                    except OctolgpError as exc:
                        self.bad_scan(exc)
                        if isinstance(exc, _GraphBrokenError):
                            return
                        continue
                    yield scan
        except READ_ERRORS as exc:
            raise OctolgpError(f"{self.kind} {self.path}: unreadable: {exc}") from None


def write_graph(
    path: str | Path, scans: Iterable[Scan], poses: Sequence[np.ndarray] | None = None
) -> None:
    """Write 3D scans as an OctoMap binary scan graph (``ScanGraph::writeBinary``), no edges.

    Parameters
    ----------
    path : str or Path
        Output file (``.graph`` by convention).
    scans : iterable of Scan
        3D scans in the world frame.
    poses : sequence of ndarray of shape (4, 4), optional
        ``T_world_sensor`` per scan: points are stored in that sensor frame and the node pose is
        ``T``. By default the pose is the scan's origin with the identity rotation.

    Raises
    ------
    OctolgpError
        On a 2D scan, a pose count or shape mismatch, or a non-rotation pose.
    """
    scans = list(scans)
    if poses is not None and len(poses) != len(scans):
        raise OctolgpError(f"write_graph: {len(poses)} poses for {len(scans)} scans")
    with open(path, "wb") as fh:
        fh.write(_U32.pack(len(scans)))
        for i, scan in enumerate(scans):
            if scan.dim != 3:
                raise OctolgpError(f"write_graph: scan {i} is {scan.dim}D, not 3D")
            T = np.eye(4) if poses is None else np.asarray(poses[i], dtype=np.float64)
            if poses is None:
                T[:3, 3] = scan.origin
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise OctolgpError(f"write_graph: pose {i} must be a finite 4x4 transform")
            R = T[:3, :3]
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise OctolgpError(f"write_graph: pose {i} has no rotation matrix")
            rec = np.empty(len(scan), dtype=_POINT)
            rec["n"] = 3
            rec["p"] = (scan.points - T[:3, 3]) @ R
            fh.write(_U32.pack(len(scan)))
            fh.write(rec.tobytes())
            q = matrix_to_quaternion(R, order="wxyz")
            fh.write(_POSE.pack(3, *T[:3, 3].tolist(), 4, *q.tolist()))
            fh.write(_U32.pack(i))
        fh.write(_U32.pack(0))


def read_scan_dat(
    path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
) -> ScanDatReader:
    """Open an OctoMap ``scan.dat`` as a stream of scans; see :class:`ScanDatReader`."""
    return ScanDatReader(path, skip_bad=skip_bad, max_range=max_range)


def read_graph(
    path: str | Path, *, skip_bad: bool = False, max_range: float | None = None
) -> GraphReader:
    """Open an OctoMap binary ``.graph`` as a stream of scans; see :class:`GraphReader`."""
    return GraphReader(path, skip_bad=skip_bad, max_range=max_range)
