"""Corrected poses: validate rigid transforms, move scans, find what a correction touches.

What :meth:`octolgp.mapping.online.OnlineMap.correct_scans` computes before it writes.
A correction maps a scan's number (from 1, as in ``ScanUpdate.scan``) to a rigid transform, a
``(d+1, d+1)`` homogeneous matrix ``T = [[R, t], [0, 1]]`` applied to the scan's
world-frame origin and points (``p' = R p + t``). A pose graph's new absolute pose
``T_new`` of a scan taken from ``T_old`` is the correction ``T_new · T_old⁻¹``
(:func:`pose_corrections`). The map then rebuilds exactly the
leaves that either version of a corrected scan touches, from every journaled scan
whose extent reaches them (:func:`scan_extents`, :func:`overlapping_scans`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from octolgp.engines.base import LeafEngine
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import unpack_keys
from octolgp.mapping.grid import LeafGrid
from octolgp.mapping.store import ScanJournal
from octolgp.scan import FloatArray, Scan

RIGID_TOLERANCE = 1e-6
"""Largest ``|RᵀR - I|`` entry and ``|det R - 1|`` accepted as a rotation."""

IntArray = NDArray[np.int64]


def check_corrections(
    corrections: object, n_scans: int, dim: int, name: str = "corrections"
) -> dict[int, FloatArray]:
    """Validate corrections: scan numbers in ``1..n_scans``, rigid ``(d+1, d+1)`` matrices.

    Parameters
    ----------
    corrections : mapping of int to array_like
        Scan number → homogeneous transform (a correction, or a sensor pose).
    n_scans : int
        Scans in the map's journal.
    dim : int
        The map's dimension ``d``.
    name : str
        The argument's name in messages (``corrections``, ``poses``).

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
            f"{name} must be a mapping of scan number to transform, "
            f"got {type(corrections).__name__}"
        )
    out: dict[int, FloatArray] = {}
    for key in sorted(corrections, key=lambda k: (not isinstance(k, int), str(k))):
        if not isinstance(key, int | np.integer) or isinstance(key, bool):
            raise OctolgpError(f"{name}: scan number {key!r} is not an integer")
        index = int(key)
        if not 1 <= index <= n_scans:
            raise OctolgpError(f"{name}: scan {index} is not in the map (scans 1..{n_scans})")
        out[index] = check_transform(corrections[key], dim, f"{name}[{index}]")
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

    Ranges are kept, so no-returns stay no-returns; ``max_range`` and ``stamp`` are kept,
    and the sensor's ``rotation``, when the scan has one, turns with it (``R · rotation``).
    """
    d = scan.dim
    R, t = T[:d, :d], T[:d, d]
    return Scan(
        origin=R @ scan.origin + t,
        points=scan.points @ R.T + t,
        max_range=scan.max_range,
        stamp=scan.stamp,
        rotation=None if scan.rotation is None else R @ scan.rotation,
    )


def pose_corrections(
    old: Mapping[int, Scan], poses: Mapping[int, FloatArray], name: str = "poses"
) -> dict[int, FloatArray]:
    """The corrections that move scans to new absolute sensor poses: ``T_new · T_old⁻¹``.

    Parameters
    ----------
    old : mapping of int to Scan
        The scans as journaled, by number; each must have its sensor rotation
        (:attr:`octolgp.Scan.rotation`), so ``T_old`` is :attr:`octolgp.Scan.pose`.
    poses : mapping of int to ndarray of shape (d+1, d+1)
        The new sensor poses (sensor to world frame, rigid), by the same numbers.
    name : str
        The argument's name in messages.

    Returns
    -------
    dict of int to ndarray of shape (d+1, d+1)
        The rigid corrections, by number: ``R = R_new R_oldᵀ``, ``t = t_new - R t_old``.

    Raises
    ------
    OctolgpError
        Naming the first scan journaled without its rotation.
    """
    out: dict[int, FloatArray] = {}
    for i, T_new in poses.items():  # one small matrix product per scan
        scan = old[i]
        if scan.rotation is None:
            raise OctolgpError(
                f"{name}[{i}]: scan {i} was journaled without its sensor rotation (Scan.rotation: "
                "a scan made from points alone, or a map file written before the journal kept "
                "rotations), so the pose it was inserted with is unknown; give correction "
                "transforms instead (correct_scans, octolgp correct --poses)"
            )
        d = scan.dim
        R = T_new[:d, :d] @ scan.rotation.T
        T = np.eye(d + 1)
        T[:d, :d], T[:d, d] = R, T_new[:d, d] - R @ scan.origin
        out[i] = T
    return out


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


class JournalExtents:
    """Each journaled scan's extent in voxel keys, (journaled scans, 2, d), kept up to date.

    Read from the journal on the first correction, then extended as scans are journaled,
    so a later correction reads only the scans that reach what it moves. Row ``j`` is
    scan ``start + j + 1``, ``start`` the journal's (``ScanJournal.journal_start``).
    """

    def __init__(self, grid: LeafGrid) -> None:
        self.grid = grid
        self._boxes: IntArray | None = None
        self._start = 0

    def read(self, storage: ScanJournal, n_scans: int) -> tuple[int, IntArray]:
        """The journal's start and the extents of its scans (read once, a copy)."""
        start = storage.journal_start
        if self._boxes is None or self._start != start or self._boxes.shape[0] != n_scans - start:
            boxes = [scan_extents([s], self.grid) for s in storage.scans(start)]
            d = self.grid.dim
            self._boxes = np.concatenate(boxes) if boxes else np.zeros((0, 2, d), np.int64)
            self._start = start
        return start, self._boxes.copy()

    def journaled(self, scans: list[Scan]) -> None:
        """Add the extents of newly journaled scans (once the extents have been read)."""
        if self._boxes is not None and scans:
            self._boxes = np.concatenate([self._boxes, scan_extents(scans, self.grid)])

    def replace(self, extents: IntArray) -> None:
        """The extents after a correction."""
        self._boxes = extents


@dataclass(frozen=True)
class Replay:
    """What a correction rebuilds.

    Attributes
    ----------
    affected : list of int
        Packed keys of the leaves either version of a corrected scan reaches, ascending.
    numbers : list of int
        The numbers of ``scans`` (from 1), ascending.
    scans : list of Scan
        Every journaled scan whose extent reaches them, corrected, in time order.
    extents : ndarray of int64, shape (n_scans, 2, d)
        The journal's extents after the correction.
    """

    affected: list[int]
    numbers: list[int]
    scans: list[Scan]
    extents: IntArray


def plan_replay(
    storage: ScanJournal,
    start: int,
    extents: IntArray,
    old: Mapping[int, Scan],
    new: Mapping[int, Scan],
    engine: LeafEngine,
    stats: dict[str, float],
) -> Replay:
    """The leaves a correction reaches and the scans to rebuild them from (reads only).

    Parameters
    ----------
    storage : ScanJournal
        The map's journal: its file, or RAM.
    start : int
        The journal holds the scans after this one.
    extents : ndarray of int64, shape (journaled scans, 2, d)
        The journal's extents before the correction (:class:`JournalExtents`).
    old, new : mapping of int to Scan
        The corrected scans before and after, by number.
    engine : LeafEngine
        The map's engine (which leaves a scan's evidence reaches).
    stats : dict of str to float
        Stage seconds, accumulated.
    """
    grid = engine.grid
    reach = engine.evidence([*old.values(), *new.values()], lambda _: None, stats)
    affected = sorted(reach.touched)
    corrected = moved_extents(extents, start, new, grid)
    index = unpack_keys(np.asarray(affected, dtype=np.int64), grid.dim)
    near = (np.flatnonzero(overlapping_scans(corrected, index, grid)) + start + 1).tolist()
    journal = storage.read_scans(near)
    return Replay(affected, near, [new.get(i, journal[i]) for i in near], corrected)


def moved_extents(
    extents: IntArray, start: int, new: Mapping[int, Scan], grid: LeafGrid
) -> IntArray:
    """The journal's extents (scans after ``start``) with the scans ``new`` in their place."""
    out = extents.copy()
    out[np.array(list(new), dtype=np.int64) - start - 1] = scan_extents(list(new.values()), grid)
    return out
