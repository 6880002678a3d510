"""Corrected poses: validate rigid transforms, move scans, find what a correction touches.

The pure half of :meth:`octolgp.mapping.online.OnlineMap.correct_scans`. A correction
maps a scan's number (from 1, as in ``ScanUpdate.scan``) to a rigid transform, a
``(d+1, d+1)`` homogeneous matrix ``T = [[R, t], [0, 1]]`` applied to the scan's
world-frame origin and points (``p' = R p + t``). The map then rebuilds exactly the
leaves that either version of a corrected scan touches, from every journaled scan
whose extent reaches them (:func:`scan_extents`, :func:`overlapping_scans`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from octolgp.errors import OctolgpError
from octolgp.mapping.grid import LeafGrid
from octolgp.scan import FloatArray, Scan

RIGID_TOLERANCE = 1e-6
"""Largest ``|RᵀR - I|`` entry and ``|det R - 1|`` accepted as a rotation."""

IntArray = NDArray[np.int64]


def check_corrections(corrections: object, n_scans: int, dim: int) -> dict[int, FloatArray]:
    """Validate corrections: scan numbers in ``1..n_scans``, rigid ``(d+1, d+1)`` matrices.

    Parameters
    ----------
    corrections : mapping of int to array_like
        Scan number → homogeneous transform.
    n_scans : int
        Scans in the map's journal.
    dim : int
        The map's dimension ``d``.

    Returns
    -------
    dict of int to ndarray of shape (d+1, d+1)
        In ascending scan order, as float64.

    Raises
    ------
    OctolgpError
        Naming the scan number and what is wrong: not a mapping, an unknown number, a
        matrix of the wrong shape, non-finite, not rigid (a reflection, a scale, a
        shear) or without the last row ``[0, …, 0, 1]``.
    """
    if not isinstance(corrections, Mapping):
        raise OctolgpError(
            f"corrections must be a mapping of scan number to transform, "
            f"got {type(corrections).__name__}"
        )
    out: dict[int, FloatArray] = {}
    for key in sorted(corrections, key=lambda k: (not isinstance(k, int), str(k))):
        if not isinstance(key, int | np.integer) or isinstance(key, bool):
            raise OctolgpError(f"corrections: scan number {key!r} is not an integer")
        index = int(key)
        if not 1 <= index <= n_scans:
            raise OctolgpError(f"corrections: scan {index} is not in the map (scans 1..{n_scans})")
        out[index] = check_transform(corrections[key], dim, f"corrections[{index}]")
    return dict(sorted(out.items()))


def check_transform(value: object, dim: int, name: str) -> FloatArray:
    """Validate one rigid homogeneous transform of dimension ``dim``.

    Raises
    ------
    OctolgpError
        Naming ``name`` and the problem.
    """
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise OctolgpError(f"{name} is not a numeric matrix: {exc}") from None
    if T.shape != (dim + 1, dim + 1):
        raise OctolgpError(f"{name} must have shape ({dim + 1}, {dim + 1}), got {T.shape}")
    if not np.isfinite(T).all():
        raise OctolgpError(f"{name} contains NaN or inf")
    bottom = np.r_[np.zeros(dim), 1.0]
    if np.abs(T[dim] - bottom).max() > RIGID_TOLERANCE:
        raise OctolgpError(f"{name} must end with the row {bottom.tolist()}, got {T[dim].tolist()}")
    R = T[:dim, :dim]
    off = np.abs(R.T @ R - np.eye(dim)).max()
    det = float(np.linalg.det(R))
    if off > RIGID_TOLERANCE or abs(det - 1.0) > RIGID_TOLERANCE:
        raise OctolgpError(
            f"{name} is not rigid: its rotation block has |RᵀR - I| = {off:.2g} and "
            f"det = {det:.6g} (a rotation has 0 and 1)"
        )
    return T


def transform_scan(scan: Scan, T: FloatArray) -> Scan:
    """The scan with its origin and points moved by the rigid transform ``T``.

    Ranges are kept, so no-returns stay no-returns; ``max_range`` and ``stamp`` are kept.
    """
    d = scan.dim
    R, t = T[:d, :d], T[:d, d]
    return Scan(
        origin=R @ scan.origin + t,
        points=scan.points @ R.T + t,
        max_range=scan.max_range,
        stamp=scan.stamp,
    )


def scan_extents(scans: list[Scan], grid: LeafGrid) -> IntArray:
    """Each scan's extent in voxel keys: the box of its origin and points, one voxel wider.

    Every voxel a scan observes (returns, free segments, no-returns up to
    ``max_range``) lies in the box of its origin and points, so the extent holds them.

    Returns
    -------
    ndarray of int64, shape (n, 2, d)
        Lowest and highest key per axis.
    """
    out = np.zeros((len(scans), 2, grid.dim), dtype=np.int64)
    offset = 1 << (grid.tree_depth - 1)
    for i, scan in enumerate(scans):  # one iteration per scan
        pts = np.vstack([scan.origin[None, :], scan.points])
        keys = np.floor(pts / grid.resolution).astype(np.int64) + offset
        out[i, 0] = keys.min(axis=0) - 1
        out[i, 1] = keys.max(axis=0) + 1
    return out


def overlapping_scans(extents: IntArray, leaves: IntArray, grid: LeafGrid) -> NDArray[np.bool_]:
    """Which scans' extents reach any of the leaves' halo boxes.

    Parameters
    ----------
    extents : ndarray of int64, shape (n, 2, d)
        From :func:`scan_extents`.
    leaves : ndarray of int64, shape (m, d)
        Leaf indices.
    grid : LeafGrid

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    hit = np.zeros(extents.shape[0], dtype=bool)
    if not leaves.size or not extents.size:
        return hit
    lo = leaves * grid.side - grid.halo_voxels  # (m, d) halo boxes in voxel keys
    hi = (leaves + 1) * grid.side + grid.halo_voxels - 1
    step = max(1, (1 << 22) // max(1, leaves.shape[0]))
    for a in range(0, extents.shape[0], step):  # blocks of scans: bounded transients
        e = extents[a : a + step]
        meets = np.logical_and(e[:, None, 0] <= hi[None], e[:, None, 1] >= lo[None])
        hit[a : a + step] = np.any(np.all(meets, axis=2), axis=1)
    return hit
