"""Training data → leaves: which leaves a step touches and the evidence each gains.

:func:`gather_evidence` assigns a step's hits and free segments to the leaves
(:func:`octolgp.mapping.grid.assign_points`, :func:`~octolgp.mapping.grid.assign_segments`)
and returns *new* leaves holding the old evidence plus the new, under the bounded
evidence rule of :meth:`octolgp.mapping.store.Leaf.with_evidence`.
:func:`gather_observations` does the same for the lattice engine: a step's voxel
observation counts (:func:`octolgp.observations.observe`) are added to the count
arrays of every leaf whose halo box holds the voxel. Both read the store through a
lookup function and never write it: the map applies the result later.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError
from octolgp.geometry.keys import addressable_range, pack_keys
from octolgp.mapping.grid import LeafGrid, assign_points, assign_segments
from octolgp.mapping.store import Leaf
from octolgp.observations import VoxelObservations, advance, effective_counts, observe
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
        Items added over all leaves (lattice engine: (voxel, class) inputs of the leaf
        GPs that changed, added or forgotten).
    kept : list of (int, Leaf)
        Lattice engine: leaves whose counts moved without changing what their GP sees
        (a free count on its way to ``clear_scans``); stored as they are, not refitted.
    """

    changed: list[tuple[int, Leaf]]
    touched: list[int]
    new_items: int
    kept: list[tuple[int, Leaf]] = field(default_factory=list)


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


def gather_observations(
    obs: VoxelObservations,
    grid: LeafGrid,
    config: MapConfig,
    lookup: Callable[[int], Leaf | None],
) -> Evidence:
    """Add voxel observation counts to the leaves whose halo boxes hold the voxels.

    A leaf's counts per halo-box voxel and class saturate at
    ``online.evidence_cap``; a leaf is *changed* when any of its counts moved.

    Parameters
    ----------
    obs : VoxelObservations
        The step's observations.
    grid : LeafGrid
    config : MapConfig
        Uses ``online.evidence_cap``.
    lookup : callable
        The current leaf of a packed key, or ``None``; only read.

    Returns
    -------
    Evidence
        ``new_items`` is the total increase of the counts.
    """
    side, halo, d = grid.side, grid.halo_voxels, grid.dim
    box = side + 2 * halo
    keys = obs.keys
    lo = (keys - halo) // side
    hi = (keys + halo) // side
    vox_parts, leaf_parts = [], []
    for offset in itertools.product((0, 1), repeat=d):  # 4 or 8 neighbours
        cand = lo + np.asarray(offset, dtype=np.int64)
        ok = (cand <= hi).all(axis=1) & (cand >= 0).all(axis=1)
        ok &= (cand < (1 << grid.leaf_depth)).all(axis=1)
        vox_parts.append(np.flatnonzero(ok))
        leaf_parts.append(cand[ok])
    voxel = np.concatenate(vox_parts)
    leaf_index = np.concatenate(leaf_parts)
    local = keys[voxel] - (leaf_index * side - halo)
    flat = local @ (box ** np.arange(d, dtype=np.int64))
    touched, first, inverse = np.unique(
        pack_keys(leaf_index), return_index=True, return_inverse=True
    )
    n_halo = box**d
    old = np.zeros((touched.size, 2, n_halo), dtype=np.uint8)
    current: list[Leaf | None] = []
    for j, key in enumerate(touched.tolist()):  # one iteration per touched leaf
        leaf = lookup(key)
        current.append(leaf)
        if leaf is not None and leaf.counts.shape[1] == n_halo:
            old[j] = leaf.counts
    cap = config.online.evidence_cap
    before_h = old[inverse, 0, flat].astype(np.int64)
    before_f = old[inverse, 1, flat].astype(np.int64)
    state = advance(before_h, before_f, obs, voxel, cap)
    new = old.copy()
    new[inverse, 0, flat] = state.hits
    new[inverse, 1, flat] = state.frees
    # what the leaf GP sees: its effective counts, and the kept returns
    eh0, ef0 = effective_counts(before_h, before_f, cap, obs.clear_scans)
    eh1, ef1 = effective_counts(state.hits, state.frees, cap, obs.clear_scans)
    d_h, d_f = eh1 != eh0, ef1 != ef0
    moves = state.replace | state.drop
    effective = d_h | d_f | moves
    stored = effective | (state.hits != before_h) | (state.frees != before_f)
    # a leaf keeps one return per voxel it sees occupied; the pairs whose return is
    # new or forgotten, grouped by leaf
    with_move = np.flatnonzero(moves)
    with_move = with_move[np.argsort(inverse[with_move], kind="stable")]
    move_bounds = np.searchsorted(inverse[with_move], np.arange(touched.size + 1))
    refit = np.zeros(touched.size, dtype=bool)
    refit[inverse[effective]] = True
    packed_voxels = pack_keys(keys)
    changed: list[tuple[int, Leaf]] = []
    kept: list[tuple[int, Leaf]] = []
    for j in np.unique(inverse[stored]).tolist():  # one iteration per leaf with new counts
        leaf = current[j]
        if leaf is None:
            leaf = Leaf.empty(leaf_index[first[j]])
        leaf = leaf.evolve(counts=new[j].copy())
        pairs = with_move[move_bounds[j] : move_bounds[j + 1]]
        if pairs.size:  # kept in voxel-key order, however the scans were grouped
            gone = np.isin(leaf.hit_keys, packed_voxels[voxel[pairs[state.drop[pairs]]]])
            add = pairs[state.replace[pairs]]
            hit_keys = np.concatenate([leaf.hit_keys[~gone], packed_voxels[voxel[add]]])
            order = np.argsort(hit_keys, kind="stable")
            leaf.hits = np.concatenate([leaf.hits[~gone], state.position[add]])[order]
            leaf.hit_keys = hit_keys[order]
        (changed if refit[j] else kept).append((int(touched[j]), leaf))
    gained = int(d_h.sum() + d_f.sum())
    return Evidence(changed, touched.tolist(), gained, kept)


def step_evidence(
    scans: list[Scan],
    grid: LeafGrid,
    config: MapConfig,
    lookup: Callable[[int], Leaf | None],
    stats: dict[str, float],
) -> Evidence:
    """Scans → training data → the leaves they change, for the map's engine.

    ``stats["training"]`` and ``stats["assign"]`` accumulate the seconds of the two
    stages. ``config`` is the map's raw config (training data not deduplicated).
    """
    t = time.perf_counter()
    lattice = config.online.engine == "lattice"
    data = observe(scans, config) if lattice else make_training_data(scans, config)
    stats["training"] = stats.get("training", 0.0) + time.perf_counter() - t
    t = time.perf_counter()
    if isinstance(data, VoxelObservations):
        evidence = gather_observations(data, grid, config, lookup)
    else:
        evidence = gather_evidence(data, grid, config, lookup)
    stats["assign"] = stats.get("assign", 0.0) + time.perf_counter() - t
    return evidence


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
) -> tuple[dict[int, Leaf], set[int], int]:
    """Every scan's evidence, chunk by chunk in time order, as new leaves by key.

    Chunks in time order give exactly the leaves of all scans at once (the evidence
    rules are applied in time order) while bounding the transient arrays of the
    assignment by the chunk, not the log.

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
        The leaves with new evidence, new objects, in first-touch order.
    refit : set of int
        The keys among them whose GP inputs changed (the others are only stored).
    new_items : int
    """
    gathered: dict[int, Leaf] = {}
    refit: set[int] = set()
    new_items = 0
    stats["training"] = stats["assign"] = 0.0

    def current(key: int) -> Leaf | None:
        leaf = gathered.get(key)
        return leaf if leaf is not None else lookup(key)

    for chunk in scan_chunks(scans, chunk_beams):  # a few hundred thousand beams each
        evidence = step_evidence(chunk, grid, config, current, stats)
        new_items += evidence.new_items
        for key, leaf in evidence.changed:  # one iteration per leaf that gained evidence
            gathered[key] = leaf
            refit.add(key)
        for key, leaf in evidence.kept:  # one iteration per leaf with new counts only
            gathered[key] = leaf
    return gathered, refit, new_items
