"""Pose files for ``octolgp correct``: corrections (``--poses``) or absolute poses (``--absolute``).

One scan per line: its number (from 1, as ``octolgp run`` counts them), then a rigid
transform, as

- a pose: ``x y yaw`` in 2D (metres, radians), ``x y z qx qy qz qw`` in 3D (TUM's
  order, the timestamp replaced by the scan number; the quaternion within
  :data:`~octolgp.scan.ROTATION_TOLERANCE` of unit length, then normalised);
- the top ``d`` rows of the homogeneous matrix, row by row (6 numbers in 2D; 12 in 3D,
  a KITTI poses line); or
- the whole ``(d+1) x (d+1)`` matrix row by row (9 in 2D, 16 in 3D).

A matrix's rotation block within :data:`~octolgp.scan.ROTATION_TOLERANCE` of a rotation
(files print a few digits) is taken as the nearest rotation. Blank lines and ``#``
comments are ignored; numbers are separated by spaces or commas.

- :func:`read_corrections` (``--poses``): the transform moves that scan's world-frame
  origin and points (:meth:`octolgp.OnlineMap.correct_scans`).
- :func:`read_poses` (``--absolute``): the transform is the sensor's new pose in the
  world frame, as a pose graph writes it (:meth:`octolgp.OnlineMap.correct_poses`).

Example (2D, scan 12 moved 5 cm in x and turned by 0.01 rad; scan 13 as a matrix)::

    # scan  x     y    yaw
    12      0.05  0.0  0.01
    13      1 0 0.05  0 1 0
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from octolgp.errors import OctolgpError
from octolgp.mapping.correction import RIGID_TOLERANCE, check_transform
from octolgp.scan import ROTATION_TOLERANCE, FloatArray, nearest_rotation

__all__ = ["pose_matrix", "read_corrections", "read_poses"]


def pose_matrix(values: FloatArray, dim: int) -> FloatArray:
    """A homogeneous matrix from a pose: ``x y yaw`` (2D) or ``x y z qx qy qz qw`` (3D).

    Raises
    ------
    ValueError
        On a quaternion further than :data:`~octolgp.scan.ROTATION_TOLERANCE` from unit
        length, or the wrong number of values.
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
        if abs(norm - 1.0) > ROTATION_TOLERANCE:
            raise ValueError(
                f"the quaternion (qx qy qz qw) has norm {norm:.6g}, not 1 "
                f"(to {ROTATION_TOLERANCE:g})"
            )
        x, y, z, w = q / norm
        T[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
        T[:3, 3] = values[:3]
        return T
    raise ValueError(f"a {dim}D pose has {3 if dim == 2 else 7} values, got {values.size}")


def read_corrections(
    path: str | Path, dim: int, scans: range | None = None
) -> dict[int, FloatArray]:
    """Read a corrections file (module docstring) for a map of dimension ``dim``.

    Parameters
    ----------
    path : str or Path
    dim : int
        The map's dimension, 2 or 3.
    scans : range, optional
        The scan numbers a correction can reach (the map's journal); a line naming
        another is refused with its line.

    Returns
    -------
    dict of int to ndarray of shape (d+1, d+1)

    Raises
    ------
    OctolgpError
        Naming the file and line: an unreadable number, NaN or inf, a scan number that
        is not a positive integer, repeats or is outside ``scans``, a wrong count of
        values, a matrix that is not rigid, a quaternion that is not of unit length. A
        missing file names the path.
    """
    return _read(path, dim, scans, "corrections", "is corrected twice")


def read_poses(path: str | Path, dim: int, scans: range | None = None) -> dict[int, FloatArray]:
    """Read a file of absolute sensor poses (module docstring), as :func:`read_corrections`.

    Returns
    -------
    dict of int to ndarray of shape (d+1, d+1)
        Scan number → the sensor's new pose, sensor to world frame.
    """
    return _read(path, dim, scans, "poses", "has two poses")


def _read(
    path: str | Path, dim: int, scans: range | None, kind: str, twice: str
) -> dict[int, FloatArray]:
    """One transform per line, checked (module docstring); ``kind`` names the file."""
    p = Path(path)
    if not p.is_file():
        raise OctolgpError(f"{kind} file {str(p)!r} does not exist")
    out: dict[int, FloatArray] = {}
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise OctolgpError(f"{kind} file {str(p)!r} cannot be read: {exc}") from None
    for n, raw in enumerate(text.splitlines(), start=1):  # one transform per line
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"{p}:{n}"
        fields = [f for f in re.split(r"[\s,]+", line) if f]
        if not re.fullmatch(r"\d+", fields[0]) or int(fields[0]) < 1:
            raise OctolgpError(f"{where}: scan number {fields[0]!r} is not a positive integer")
        scan = int(fields[0])
        if scan in out:
            raise OctolgpError(f"{where}: scan {scan} {twice}")
        if scans is not None and scan not in scans:
            raise OctolgpError(f"{where}: {_outside(scan, scans)}")
        try:
            values = np.array([float(f) for f in fields[1:]])
        except ValueError:
            raise OctolgpError(f"{where}: a value is not a number: {line!r}") from None
        if not np.isfinite(values).all():
            raise OctolgpError(f"{where}: scan {scan} has a NaN or inf value")
        out[scan] = _transform(values, dim, f"{where}: scan {scan}")
    return out


def _outside(scan: int, scans: range) -> str:
    """Why a scan number is outside the journal ``scans``."""
    if scans and scan < scans.start:
        return (
            f"scan {scan} is older than the map's journal, which keeps scans {scans.start} to "
            f"{scans.stop - 1} (OnlineConfig.journal_scans); its evidence is folded into the map"
        )
    last = scans.stop - 1
    return f"scan {scan} is not in the map (scans 1..{last})"


def _transform(values: FloatArray, dim: int, name: str) -> FloatArray:
    """The rigid ``(d+1, d+1)`` transform a line's values give (module docstring)."""
    full, top, pose = (dim + 1) ** 2, dim * (dim + 1), 3 if dim == 2 else 7
    if values.size == pose:
        try:
            return pose_matrix(values, dim)
        except ValueError as exc:
            raise OctolgpError(f"{name}: {exc}") from None
    if values.size not in (full, top):
        raise OctolgpError(
            f"{name}: expected {pose} values (a pose), {top} or {full} (a matrix's top {dim} "
            f"rows or all of it, row by row), got {values.size}"
        )
    T = np.eye(dim + 1)
    T[: values.size // (dim + 1)] = values.reshape(-1, dim + 1)
    bottom = np.r_[np.zeros(dim), 1.0]
    if np.abs(T[dim] - bottom).max() > RIGID_TOLERANCE:
        raise OctolgpError(f"{name} must end with the row {bottom.tolist()}, got {T[dim].tolist()}")
    try:
        T[:dim, :dim] = nearest_rotation(T[:dim, :dim], dim, "its rotation block")
    except OctolgpError as exc:
        raise OctolgpError(f"{name} is not rigid: {exc}") from None
    return check_transform(T, dim, name)
