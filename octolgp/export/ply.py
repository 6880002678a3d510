"""PLY point clouds of voxel centres and their occupancy probability."""

from __future__ import annotations

import io

import numpy as np
from numpy.typing import ArrayLike

from octolgp.export.common import PathLike, as_centres, as_prob, write_bytes


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
    c = as_centres(centres, (2, 3))
    p = as_prob(prob, c.shape[0])
    if c.shape[1] == 2:
        c = np.column_stack([c, np.zeros(c.shape[0])])
    vertex = np.empty(c.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("prob", "<f4")])
    for axis, name in enumerate("xyz"):
        vertex[name] = c[:, axis]
    vertex["prob"] = p
    fmt = "binary_little_endian" if binary else "ascii"
    header = (
        f"ply\nformat {fmt} 1.0\ncomment octolgp occupancy\nelement vertex {c.shape[0]}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float prob\nend_header\n"
    ).encode("ascii")
    if binary:
        body = vertex.tobytes()
    else:
        text = io.StringIO()
        rows = np.column_stack([vertex[name] for name in ("x", "y", "z", "prob")])
        np.savetxt(text, rows, fmt="%.9g")  # 9 significant digits round-trip float32
        body = text.getvalue().encode("ascii")
    write_bytes(path, [header, body])
