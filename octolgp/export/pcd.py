"""PCD point clouds (Point Cloud Library) of voxel centres and their occupancy probability."""

from __future__ import annotations

from collections.abc import Iterable

from numpy.typing import ArrayLike

from octolgp.export.common import PathLike, write_xyz_prob_stream

__all__ = ["write_pcd", "write_pcd_chunks"]


def write_pcd(path: PathLike, centres: ArrayLike, prob: ArrayLike, *, binary: bool = True) -> None:
    """Write voxel centres and their occupancy probability as a PCD v0.7 point cloud.

    The cloud is unorganised (``HEIGHT 1``) with ``VIEWPOINT 0 0 0 1 0 0 0``, so the points are
    in the world frame; each point has float32 fields ``x y z prob``. PCL's ``pcl::io::loadPCDFile``
    (as ``PointXYZ``, or a custom point type for ``prob``), CloudCompare and octolgp's own
    :func:`~octolgp.io.pcd.read_pcd` read it.

    Parameters
    ----------
    path : str or os.PathLike
        Output file (``.pcd``).
    centres : array_like of float, shape (k, 3) or (k, 2)
        Voxel centres in the world frame, metres; 2D centres get ``z = 0``.
    prob : array_like of float, shape (k,)
        P(occupied) per centre, in [0, 1].
    binary : bool, optional
        ``DATA binary`` (packed little-endian records, default) or ``DATA ascii`` (9
        significant digits, which round-trip float32).

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value in ``centres`` or ``prob``, ``prob`` outside
        [0, 1], or a ``path`` that cannot be written.
    """
    write_pcd_chunks(path, [(centres, prob)], binary=binary)


def write_pcd_chunks(
    path: PathLike, chunks: Iterable[tuple[ArrayLike, ArrayLike]], *, binary: bool = True
) -> int:
    """:func:`write_pcd` of ``(centres, prob)`` chunks, one in memory at a time (the same bytes).

    Returns the number of points written.
    """

    def header(n: int) -> bytes:
        return (
            "# .PCD v0.7 - Point Cloud Data file format\n"
            "# octolgp occupied voxel centres, P(occupied) in prob\n"
            "VERSION 0.7\nFIELDS x y z prob\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
            f"DATA {'binary' if binary else 'ascii'}\n"
        ).encode("ascii")

    return write_xyz_prob_stream(path, header, chunks, binary=binary)
