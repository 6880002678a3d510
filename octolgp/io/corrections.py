"""Pose corrections from a text file, for ``octolgp correct`` (:meth:`OnlineMap.correct_scans`).

One correction per line: the scan's number (from 1, as ``octolgp run`` counts them),
then the rigid transform that moves that scan's world-frame origin and points, as

- ``(d+1)²`` numbers, the homogeneous matrix row by row (9 in 2D, 16 in 3D); or
- a pose: ``x y yaw`` in 2D (metres, radians), ``tx ty tz qx qy qz qw`` in 3D (TUM's
  order; the quaternion is normalised).

Blank lines and ``#`` comments are ignored. Numbers are separated by spaces or commas.
Example (2D, scan 12 moved 5 cm in x and turned by 0.01 rad; scan 13 as a matrix)::

    # scan  x     y    yaw
    12      0.05  0.0  0.01
    13      1 0 0.05  0 1 0  0 0 1
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.mapping.correction import check_transform
from octolgp.scan import FloatArray

__all__ = ["pose_matrix", "read_corrections"]


def pose_matrix(values: FloatArray, dim: int) -> FloatArray:
    """A homogeneous matrix from a pose: ``x y yaw`` (2D) or ``tx ty tz qx qy qz qw`` (3D).

    Raises
    ------
    ValueError
        On a zero quaternion or the wrong number of values.
    """
    T = np.eye(dim + 1)
    if dim == 2 and values.size == 3:
        c, s = np.cos(values[2]), np.sin(values[2])
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 2] = values[:2]
        return T
    if dim == 3 and values.size == 7:
        q = values[3:]
        norm = float(np.linalg.norm(q))
        if norm == 0.0:
            raise ValueError("the quaternion is zero")
        x, y, z, w = q / norm
        T[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        T[:3, 3] = values[:3]
        return T
    raise ValueError(f"a {dim}D pose has {3 if dim == 2 else 7} values, got {values.size}")


def read_corrections(path: str | Path, dim: int) -> dict[int, FloatArray]:
    """Read a corrections file (module docstring) for a map of dimension ``dim``.

    Returns
    -------
    dict of int to ndarray of shape (d+1, d+1)

    Raises
    ------
    OctolgpError
        Naming the file and line: an unreadable number, a scan number that is not a
        positive integer or repeats, a wrong count of values, a matrix that is not
        rigid or not finite. A missing file names the path.
    """
    p = Path(path)
    if not p.is_file():
        raise OctolgpError(f"corrections file {str(p)!r} does not exist")
    out: dict[int, FloatArray] = {}
    matrix = (dim + 1) ** 2
    pose = 3 if dim == 2 else 7
    with p.open(encoding="utf-8") as fh:
        for n, raw in enumerate(fh, start=1):  # one correction per line
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            where = f"{p}:{n}"
            fields = [f for f in re.split(r"[\s,]+", line) if f]
            if not re.fullmatch(r"\d+", fields[0]) or int(fields[0]) < 1:
                raise OctolgpError(f"{where}: scan number {fields[0]!r} is not a positive integer")
            scan = int(fields[0])
            if scan in out:
                raise OctolgpError(f"{where}: scan {scan} is corrected twice")
            try:
                values = np.array([float(f) for f in fields[1:]])
            except ValueError:
                raise OctolgpError(f"{where}: a value is not a number: {line!r}") from None
            if values.size == matrix:
                T = values.reshape(dim + 1, dim + 1)
            elif values.size == pose:
                try:
                    T = pose_matrix(values, dim)
                except ValueError as exc:
                    raise OctolgpError(f"{where}: {exc}") from None
            else:
                raise OctolgpError(
                    f"{where}: expected the scan number and {matrix} matrix entries or a "
                    f"{pose}-value pose, got {values.size} values"
                )
            out[scan] = check_transform(T, dim, f"{where}: scan {scan}")
    return out
