"""Training data → leaves: which leaves a step touches and the evidence each gains.

:func:`gather_evidence` assigns a step's hits and free segments to the leaves
(:func:`octolgp.mapping.grid.assign_points`, :func:`~octolgp.mapping.grid.assign_segments`)
and returns *new* leaves holding the old evidence plus the new, under the bounded
evidence rule of :meth:`octolgp.mapping.store.Leaf.with_evidence`. It reads the store
through a lookup function and never writes it: the map applies the result later.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments
from octolgp.mapping.store import Leaf
from octolgp.scan import Scan, check_scan_size
from octolgp.training import IntArray, TrainingData, make_training_data


def group_keys(packed: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Sort order, unique values and run bounds of packed keys.

    Returns
    -------
    order : ndarray of shape (n,)
        Stable sort order of ``packed``.
    keys : ndarray of shape (u,)
        The distinct keys, ascending.
    bounds : ndarray of shape (u + 1,)
        Key ``keys[j]`` holds ``order[bounds[j]:bounds[j + 1]]``.
    """
    order = np.argsort(packed, kind="stable")
    s = packed[order]
    starts = np.flatnonzero(np.r_[True, s[1:] != s[:-1]]) if s.size else np.zeros(0, np.int64)
    return order, s[starts], np.append(starts, s.size).astype(np.int64)


def check_scan(scan: object, config: MapConfig, grid: LeafGrid) -> Scan:
    """Validate a scan for a map: type, size, dimension and addressable range.

    The halo of a leaf at the edge of the tree must stay addressable too, so the
    usable range is the addressable range less two leaf edges on each side.

    Raises
    ------
    OctolgpError
        Naming the field and the first offending row.
    """
    if not isinstance(scan, Scan):
        raise OctolgpError(f"scan must be a Scan, got {type(scan).__name__}")
    check_scan_size(scan, config.online.max_scan_points)
    if scan.dim != config.dim:
        raise OctolgpError(f"scan is {scan.dim}D but MapConfig.dim is {config.dim}")
    low, high = addressable_range(config.resolution, config.tree_depth)
    margin = 2 * grid.edge
    for name, pts in (("scan.origin", scan.origin[None, :]), ("scan.points", scan.points)):
        bad = (pts < low + margin) | (pts >= high - margin)
        if bad.any():
            row = int(np.flatnonzero(bad.any(axis=1))[0])
            raise OctolgpError(
                f"{name} row {row} ({pts[row].tolist()}) is outside the addressable range "
                f"[{low + margin:g}, {high - margin:g}) m of this map"
            )
    return scan


@dataclass(frozen=True)
class Evidence:
    """The evidence one step brings to the leaves.

    Attributes
    ----------
    changed : list of (int, Leaf)
        Leaves that gained items, as new leaves (packed key, leaf), in key order.
    touched : list of int
        Packed keys of every leaf the step's evidence reached, ascending.
    new_items : int
        Items added over all leaves.
    """

    changed: list[tuple[int, Leaf]]
    touched: list[int]
    new_items: int


def gather_evidence(
    data: TrainingData,
    grid: LeafGrid,
    config: MapConfig,
    lookup: Callable[[int], Leaf | None],
) -> Evidence:
    """Assign training data to leaves and return the leaves that gain evidence.

    Parameters
    ----------
    data : TrainingData
        Hits and free segments of the step, in time order.
    grid : LeafGrid
    config : MapConfig
        Uses ``resolution`` (free pieces stop half a voxel short) and
        ``online.free_voxels``.
    lookup : callable
        The current leaf of a packed key, or ``None``; only read.

    Returns
    -------
    Evidence
    """
    h_idx, h_leaf = assign_points(grid, data.hits)
    _, s_leaf, a, b = assign_segments(grid, data.seg_start, data.seg_end, 0.5 * config.resolution)
    hits = data.hits[h_idx]
    hit_keys = grid.voxel_keys(hits)
    free_keys = grid.voxel_keys(b, config.online.free_voxels)
    h_order, h_keys, h_bounds = group_keys(grid.pack(h_leaf))
    s_order, s_keys, s_bounds = group_keys(grid.pack(s_leaf))
    touched = np.union1d(h_keys, s_keys)
    changed: list[tuple[int, Leaf]] = []
    new_items = 0
    hi = np.searchsorted(h_keys, touched)
    si = np.searchsorted(s_keys, touched)
    for j, key in enumerate(touched.tolist()):  # one iteration per touched leaf
        hsel = np.zeros(0, dtype=np.int64)
        ssel = np.zeros(0, dtype=np.int64)
        if hi[j] < h_keys.size and h_keys[hi[j]] == key:
            hsel = h_order[h_bounds[hi[j]] : h_bounds[hi[j] + 1]]
        if si[j] < s_keys.size and s_keys[si[j]] == key:
            ssel = s_order[s_bounds[si[j]] : s_bounds[si[j] + 1]]
        old = lookup(key)
        if old is None:
            old = Leaf.empty(h_leaf[hsel[0]] if hsel.size else s_leaf[ssel[0]])
        leaf, added = old.with_evidence(
            hits[hsel], hit_keys[hsel], a[ssel], b[ssel], free_keys[ssel]
        )
        if added:
            new_items += added
            changed.append((key, leaf))
    return Evidence(changed, touched.tolist(), new_items)


def scan_chunks(scans: list[Scan], beams: int) -> Iterator[list[Scan]]:
    """Consecutive runs of scans holding about ``beams`` beams each (at least one scan)."""
    chunk: list[Scan] = []
    total = 0
    for s in scans:  # one iteration per scan
        chunk.append(s)
        total += len(s)
        if total >= beams:
            yield chunk
            chunk, total = [], 0
    if chunk:
        yield chunk


def gather_batch(
    scans: list[Scan],
    grid: LeafGrid,
    config: MapConfig,
    lookup: Callable[[int], Leaf | None],
    chunk_beams: int,
    stats: dict[str, float],
) -> tuple[dict[int, Leaf], int]:
    """Every scan's evidence, chunk by chunk in time order, as new leaves by key.

    Chunks in time order give exactly the leaves of all scans at once (the first item
    per voxel wins) while bounding the transient arrays of the assignment by the
    chunk, not the log.

    Parameters
    ----------
    scans : list of Scan
        Checked scans, in time order.
    grid : LeafGrid
    config : MapConfig
        The map's config (training data as the map makes it).
    lookup : callable
        The map's current leaf of a packed key, or ``None``; only read.
    chunk_beams : int
        Beams per chunk.
    stats : dict of str to float
        ``training`` and ``assign`` seconds are written here.

    Returns
    -------
    leaves : dict of int to Leaf
        The leaves that gained evidence, new objects, in first-touch order.
    new_items : int
    """
    gathered: dict[int, Leaf] = {}
    new_items = 0
    stats["training"] = stats["assign"] = 0.0

    def current(key: int) -> Leaf | None:
        leaf = gathered.get(key)
        return leaf if leaf is not None else lookup(key)

    for chunk in scan_chunks(scans, chunk_beams):  # a few hundred thousand beams each
        t = time.perf_counter()
        data = make_training_data(chunk, config)
        stats["training"] += time.perf_counter() - t
        t = time.perf_counter()
        evidence = gather_evidence(data, grid, config, current)
        del data
        new_items += evidence.new_items
        for key, leaf in evidence.changed:  # one iteration per leaf that gained evidence
            gathered[key] = leaf
        stats["assign"] += time.perf_counter() - t
    return gathered, new_items
