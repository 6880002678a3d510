"""Scan → voxel observations: which voxels each scan saw occupied and which it saw free.

The training data of the lattice leaf engine (:mod:`octolgp.gp.lattice`), the
voxel-level form of :mod:`octolgp.training`'s rule: a beam's hit is an observation
"occupied" of the voxel holding it; its free segment (stopping ``free_margin`` short of
the hit, or at ``max_range`` for a no-return) is an observation "free" of every voxel
it passes through, sampled every half voxel along the segment and at its end.

Within one scan each voxel counts once per class, and a voxel holding a return of
the scan is not also free in that scan (OctoMap's discretised insertion). Across
scans the counts add: ``hits[v]`` is the number of scans with a return in ``v``,
``frees[v]`` the number whose free segments cross ``v`` without a return there. The
counts of a set of scans are therefore the sums of the counts of its parts, in any
order: this is what makes inserting scans one by one equal to inserting them at once.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from octolgp.config import MapConfig
from octolgp.geometry.keys import KEY_BITS, pack_keys, unpack_keys
from octolgp.scan import Scan
from octolgp.training import IntArray, check_scans, split_beams, stack_beams

SAMPLES_PER_VOXEL = 2
"""Points sampled per voxel edge along a free segment."""

BLOCK_SAMPLES = 1 << 21
"""Free-segment sample points handled at once (bounds the transient arrays)."""

MAX_SCANS = 1 << 12
"""Scans whose observations are deduplicated in one pass (the scan number shares an
int64 with the packed voxel key)."""


@dataclass(frozen=True)
class VoxelObservations:
    """Observation counts per voxel.

    Attributes
    ----------
    keys : ndarray of int64, shape (n, d)
        OctoMap keys of the observed voxels, unique, ascending by packed key.
    hits : ndarray of int64, shape (n,)
        Scans with a return in the voxel.
    frees : ndarray of int64, shape (n,)
        Scans whose free segments cross the voxel and hold no return in it.
    first_hit : ndarray of shape (n, d)
        The first return in the voxel (scan order, then beam order), metres, world
        frame; NaN where ``hits`` is 0.
    """

    keys: IntArray
    hits: IntArray
    frees: IntArray
    first_hit: np.ndarray

    @property
    def n_voxels(self) -> int:
        """Observed voxels."""
        return int(self.hits.size)


def sorted_unique(values: IntArray) -> IntArray:
    """``np.unique`` of an int64 array by one sort (numpy's hash-based unique is slower here)."""
    a = np.sort(values, kind="stable" if values.size < 64 else "quicksort")
    if a.size == 0:
        return a
    keep = np.empty(a.size, dtype=bool)
    keep[0] = True
    np.not_equal(a[1:], a[:-1], out=keep[1:])
    out: IntArray = a[keep]
    return out


def _unique_counts(values: IntArray) -> tuple[IntArray, IntArray]:
    """Sorted unique values and how often each occurs."""
    a = np.sort(values)
    if a.size == 0:
        return a, np.zeros(0, dtype=np.int64)
    starts = np.flatnonzero(np.r_[True, a[1:] != a[:-1]])
    return a[starts], np.diff(np.r_[starts, a.size]).astype(np.int64)


def _voxel_keys(points: np.ndarray, resolution: float, tree_depth: int) -> IntArray:
    """OctoMap keys of points known to be addressable (no range check), (n, d)."""
    keys: IntArray = np.floor(points / resolution).astype(np.int64) + (1 << (tree_depth - 1))
    return keys


def _scan_codes(packed: IntArray, scan: IntArray, dim: int) -> IntArray:
    """One int64 per (scan, voxel): the scan number above the packed key's bits."""
    out: IntArray = packed | (scan << (KEY_BITS * dim))
    return out


def _free_codes(
    origins: np.ndarray,
    free_end: np.ndarray,
    scan: IntArray,
    resolution: float,
    tree_depth: int,
) -> IntArray:
    """Unique (scan, voxel) codes of the voxels the free segments pass through."""
    dim = origins.shape[1]
    step = resolution / SAMPLES_PER_VOXEL
    seg_len = np.linalg.norm(free_end - origins, axis=1)
    n_samples = np.floor(seg_len / step).astype(np.int64) + 2  # every step, and the end
    # per axis, in voxels: start and change per metre along the segment
    start = origins / resolution
    slope = (free_end - origins) / (resolution * np.maximum(seg_len, 1e-300))[:, None]
    offset = 1 << (tree_depth - 1)
    parts: list[IntArray] = []
    ends = np.cumsum(n_samples)
    lo = 0
    while lo < seg_len.size:  # blocks of about BLOCK_SAMPLES samples
        hi = int(np.searchsorted(ends, ends[lo] - n_samples[lo] + BLOCK_SAMPLES, side="right"))
        hi = max(hi, lo + 1)
        counts = n_samples[lo:hi]
        beam = np.repeat(np.arange(lo, hi), counts)
        first = np.cumsum(counts) - counts
        j = np.arange(beam.size) - np.repeat(first, counts)
        dist = np.minimum(j * step, seg_len[beam])  # metres along the segment
        codes = scan[beam] << (KEY_BITS * dim)
        for axis in range(dim):  # per axis: floor of the coordinate in voxels, packed
            u = start[beam, axis] + slope[beam, axis] * dist
            codes |= (np.floor(u).astype(np.int64) + offset) << (KEY_BITS * axis)
        keep = np.empty(codes.size, dtype=bool)  # consecutive samples in one voxel
        keep[0] = True
        np.not_equal(codes[1:], codes[:-1], out=keep[1:])
        parts.append(sorted_unique(codes[keep]))
        lo = hi
    if not parts:
        return np.zeros(0, dtype=np.int64)
    return sorted_unique(np.concatenate(parts))


def observe(scans: Iterable[Scan], config: MapConfig) -> VoxelObservations:
    """Count, per voxel, the scans that saw it occupied and the scans that saw it free.

    Parameters
    ----------
    scans : iterable of Scan
        World-frame scans of dimension ``config.dim`` (points addressable).
    config : MapConfig
        Uses ``resolution``, ``tree_depth`` and ``free_margin``.

    Returns
    -------
    VoxelObservations

    Raises
    ------
    OctolgpError
        On an empty sequence or a dimension mismatch.
    """
    scan_list = check_scans(scans, config.dim)
    if len(scan_list) > MAX_SCANS:
        parts = [
            observe(scan_list[lo : lo + MAX_SCANS], config)
            for lo in range(0, len(scan_list), MAX_SCANS)
        ]
        return merge_observations(parts, config.dim)
    dim, res, depth = config.dim, config.resolution, config.tree_depth
    origins, ends, max_range = stack_beams(scan_list)
    scan = np.repeat(np.arange(len(scan_list), dtype=np.int64), [len(s) for s in scan_list])
    beams = split_beams(origins, ends, max_range, config.free_margin)
    hit_points = ends[beams.is_hit]
    hit_packed = pack_keys(_voxel_keys(hit_points, res, depth))
    hit_codes = sorted_unique(_scan_codes(hit_packed, scan[beams.is_hit], dim))
    seg = beams.has_seg
    free_codes = _free_codes(origins[seg], beams.free_end[seg], scan[seg], res, depth)
    free_codes = free_codes[~np.isin(free_codes, hit_codes, assume_unique=True)]
    mask = (1 << (KEY_BITS * dim)) - 1
    hit_vox, hit_n = _unique_counts(hit_codes & mask)
    free_vox, free_n = _unique_counts(free_codes & mask)
    # the first return per voxel: a stable sort keeps scan, then beam order
    order = np.argsort(hit_packed, kind="stable")
    ordered = hit_packed[order]
    first = order[np.r_[True, ordered[1:] != ordered[:-1]]] if order.size else order
    first_points = hit_points[first]
    return _combine(hit_vox, hit_n, free_vox, free_n, first_points, dim)


def _combine(
    hit_vox: IntArray,
    hit_n: IntArray,
    free_vox: IntArray,
    free_n: IntArray,
    hit_points: np.ndarray,
    dim: int,
) -> VoxelObservations:
    """Observations from sorted unique packed voxels with their counts and first returns."""
    packed = sorted_unique(np.concatenate([hit_vox, free_vox]))
    hits = np.zeros(packed.size, dtype=np.int64)
    frees = np.zeros(packed.size, dtype=np.int64)
    first_hit = np.full((packed.size, dim), np.nan)
    at = np.searchsorted(packed, hit_vox)
    hits[at] = hit_n
    first_hit[at] = hit_points
    frees[np.searchsorted(packed, free_vox)] = free_n
    return VoxelObservations(unpack_keys(packed, dim), hits, frees, first_hit)


def merge_observations(parts: list[VoxelObservations], dim: int) -> VoxelObservations:
    """The observations of several disjoint sets of scans: counts add per voxel."""
    packed = np.concatenate([pack_keys(p.keys) for p in parts]) if parts else np.zeros(0)
    hits = np.concatenate([p.hits for p in parts]) if parts else np.zeros(0, np.int64)
    frees = np.concatenate([p.frees for p in parts]) if parts else np.zeros(0, np.int64)
    points = np.concatenate([p.first_hit for p in parts]) if parts else np.zeros((0, dim))
    uniq, inverse = np.unique(packed.astype(np.int64), return_inverse=True)
    h = np.bincount(inverse, weights=hits, minlength=uniq.size).astype(np.int64)
    f = np.bincount(inverse, weights=frees, minlength=uniq.size).astype(np.int64)
    # the first part (in time order) with a return in the voxel gives its first return
    has = np.flatnonzero(hits > 0)
    first_hit = np.full((uniq.size, dim), np.nan)
    _, pick = np.unique(inverse[has], return_index=True)
    first_hit[inverse[has[pick]]] = points[has[pick]]
    return VoxelObservations(unpack_keys(uniq, dim), h, f, first_hit)
