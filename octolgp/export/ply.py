"""PLY point clouds of voxel centres and their occupancy probability."""

from __future__ import annotations

from collections.abc import Iterable

from numpy.typing import ArrayLike

from octolgp.export.common import PathLike, write_xyz_prob_stream


def write_ply(path: PathLike, centres: ArrayLike, prob: ArrayLike, *, binary: bool = True) -> None:
    """Write voxel centres and their occupancy probability as a PLY point cloud.

    Parameters
    ----------
    path : str or os.PathLike
        Output file.
    centres : array_like of float, shape (k, 3) or (k, 2)
        Voxel centres in the world frame, metres; 2D centres get ``z = 0``.
    prob : array_like of float, shape (k,)
        P(occupied) per centre, in [0, 1].
    binary : bool, optional
        ``binary_little_endian`` (default) or ``ascii`` PLY. Either way the vertex
        has float32 properties ``x y z prob``.

    Raises
    ------
    OctolgpError
        On a bad shape or non-finite value in ``centres`` or ``prob``, ``prob``
        outside [0, 1], or a ``path`` that cannot be written.
    """
    write_ply_chunks(path, [(centres, prob)], binary=binary)


def write_ply_chunks(
    path: PathLike, chunks: Iterable[tuple[ArrayLike, ArrayLike]], *, binary: bool = True
) -> int:
    """:func:`write_ply` of ``(centres, prob)`` chunks, one in memory at a time (the same bytes).

    Returns the number of points written.
    """
    fmt = "binary_little_endian" if binary else "ascii"

    def header(n: int) -> bytes:
        return (
            f"ply\nformat {fmt} 1.0\ncomment octolgp occupancy\nelement vertex {n}\n"
            "property float x\nproperty float y\nproperty float z\nproperty float prob\n"
            "end_header\n"
        ).encode("ascii")

    return write_xyz_prob_stream(path, header, chunks, binary=binary)
