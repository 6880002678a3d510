"""3DTK poses: the ``.pose`` and ``.frames`` files, and 3DTK's frame to octolgp's world frame.

3DTK's frame is **left-handed**, x right, y up, z forward, in **centimetres** (3DTK
``doc/high_level_doc/documentation.tex``, "File Formats and Units"). A pose maps scan to world
coordinates, ``p_world = R p_scan + t``:

- ``scanNNN.pose``: ``tx ty tz`` (cm), then ``θx θy θz`` (degrees), with
  ``R = Rx(θx) Ry(θy) Rz(θz)`` (3DTK ``EulerToMatrix4``; the usual right-hand-rule matrices,
  applied to left-handed coordinates: :func:`octolgp.geometry.rotations.euler_xyz_to_matrix`).
- ``scanNNN.frames``: one line per ICP step, a 4x4 matrix stored column-major (OpenGL) followed by
  a colour code; the **last line** is the final registered pose.

octolgp's world frame is right-handed, in metres, x forward, y left, z up::

    p_rh = C p_lh / 100,  C = [[0, 0, 1], [-1, 0, 0], [0, 1, 0]]   (det C = -1)
    R_rh = C R Cᵀ,        t_rh = C t / 100

Checked on the 3DTK example scans (``data/3dtk_example_scans/README.md``): the first
``scan002.frames`` line equals ``scan002.pose`` to 5e-7, and registered scans overlap to a median
nearest-neighbour distance of 2.9 cm (scan001 to scan000) and 3.1 cm (scan002 to scan001).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from octolgp.errors import MapFileNotFound, OctolgpError
from octolgp.geometry.rotations import euler_xyz_to_matrix
from octolgp.scan import FloatArray

__all__ = ["CM", "LH_TO_RH", "from_3dtk_pose", "read_frames", "read_pose"]

CM = 0.01
"""Metres per centimetre, 3DTK's unit."""

LH_TO_RH: FloatArray = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""``C``: 3DTK axes (x right, y up, z forward) to octolgp axes (x forward, y left, z up)."""
LH_TO_RH.setflags(write=False)

_ORTHO_TOL = 1e-3  # the files keep 6 significant digits


def from_3dtk_pose(T: FloatArray) -> FloatArray:
    """Convert 3DTK poses (left-handed, cm) to octolgp's world frame (right-handed, metres).

    Parameters
    ----------
    T : ndarray of shape (..., 4, 4)
        ``p_world = T[:3, :3] p + T[:3, 3]`` in 3DTK coordinates.

    Returns
    -------
    ndarray of shape (..., 4, 4)
        ``[[C R Cᵀ, C t / 100], [0, 1]]`` with ``C`` = :data:`LH_TO_RH`.
    """
    out = np.zeros(T.shape)
    out[..., :3, :3] = LH_TO_RH @ T[..., :3, :3] @ LH_TO_RH.T
    out[..., :3, 3] = (T[..., :3, 3] @ LH_TO_RH.T) * CM
    out[..., 3, 3] = 1.0
    return out


def _numeric_lines(path: Path, what: str) -> list[tuple[int, FloatArray]]:
    """Read a small text file as ``(line_number, numbers)`` for each non-blank line."""
    if not path.is_file():
        raise MapFileNotFound(f"3DTK {what} file {str(path)!r} does not exist")
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise OctolgpError(f"3DTK {what} file {path}: unreadable: {exc}") from None
    rows = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            values = np.array(line.split(), dtype=np.float64)
        except ValueError as exc:
            raise OctolgpError(f"3DTK {what} file {path}:{line_no}: {exc}") from None
        if not np.isfinite(values).all():
            raise OctolgpError(f"3DTK {what} file {path}:{line_no}: NaN or inf")
        rows.append((line_no, values))
    if not rows:
        raise OctolgpError(f"3DTK {what} file {path} is empty")
    return rows


def read_pose(path: str | Path) -> FloatArray:
    """Read a ``.pose`` file as ``T_world_scan`` in octolgp's frame, shape (4, 4).

    Raises
    ------
    MapFileNotFound
        If the file does not exist.
    OctolgpError
        Unless it holds exactly two lines of three finite numbers (names file and line).
    """
    p = Path(path)
    rows = _numeric_lines(p, "pose")
    for line_no, values in rows:
        if values.shape != (3,):
            raise OctolgpError(f"3DTK pose file {p}:{line_no}: expected 3 numbers")
    if len(rows) != 2:
        raise OctolgpError(f"3DTK pose file {p}: expected 2 lines (t in cm, angles in degrees)")
    T = np.eye(4)
    T[:3, :3] = euler_xyz_to_matrix(rows[1][1], degrees=True)
    T[:3, 3] = rows[0][1]
    return from_3dtk_pose(T)


def read_frames(path: str | Path) -> FloatArray:
    """Read a ``.frames`` file: one ``T_world_scan`` per ICP step, shape (k, 4, 4).

    In octolgp's frame; the last one is the final registration. The files keep 6 significant
    digits, so each rotation is replaced by the nearest orthonormal one (this moves a point
    30 m away by under 0.1 mm).

    Raises
    ------
    MapFileNotFound
        If the file does not exist.
    OctolgpError
        On a line that is not 16 numbers (plus an optional colour code) of a rigid transform,
        naming file and line.
    """
    p = Path(path)
    frames = []
    for line_no, values in _numeric_lines(p, "frames"):
        if values.size not in (16, 17):
            raise OctolgpError(f"3DTK frames file {p}:{line_no}: expected 17 numbers")
        T = values[:16].reshape(4, 4).T  # column-major (OpenGL)
        R = T[:3, :3]
        rigid = np.abs(R.T @ R - np.eye(3)).max() < _ORTHO_TOL and np.linalg.det(R) > 0
        if not rigid or not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
            raise OctolgpError(f"3DTK frames file {p}:{line_no}: not a rigid transform")
        # Nearest rotation (polar decomposition), so that beam lengths are kept exactly.
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
        frames.append(T)
    return from_3dtk_pose(np.stack(frames))
